"""`latentdrive reproduce` end to end on the tiny preset: every experiment's table and
figure, resumption without rework, the same numbers when steps are re-run, and a report
rebuilt from the finished steps alone."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from helpers import study_numbers as _numbers

from latentdrive.cli import main
from latentdrive.experiments.study import build_graph, load_reproduce_config
from latentdrive.experiments.study_runs import read_runs


def test_the_tiny_study_reports_every_experiment(tiny_study: Path) -> None:
    res = json.loads((tiny_study / "results.json").read_text())
    assert {"headline", "matrix", "domain_adaptation", "transfer", "leave_one_out", "ablations", "per_seed",
            "references", "bnn", "probes", "steps", "meta"} <= set(res)
    scen = ["roundabout", "intersection", "merge"]
    assert [r["test"] for r in res["headline"]] == [*scen, "mixed"]
    assert set(res["matrix"]["latent"]) == {*scen, "mixed"}
    assert set(res["ablations"]) == {"raw", "latent", "latent-random", "end-to-end", "latent-lam"}
    for row in res["headline"]:
        for rep in ("raw", "latent"):
            assert 0 <= row[rep]["failure"]["mean"] <= 1 and row[rep]["failure"]["seeds"] == 1
        assert row["paired"]["failure"]["n"] == 2 * (len(scen) if row["test"] == "mixed" else 1)
    assert all(s["peak_rss_mb"] > 0 for s in res["steps"].values())
    # The imitation reference: a DAgger run, evaluated on every test set and paired with raw.
    im = res["imitation"]
    assert set(im["policy"]) == {*scen, "mixed"} and 0 <= im["policy"]["mixed"]["failure"]["mean"] <= 1
    assert im["vs_raw"]["n"] == 2 * len(scen)
    run_cfg = json.loads(next(tiny_study.glob("steps/policy-imitation-mixed-s0-*/run/config.json")).read_text())
    assert run_cfg["train"]["learner"] == "dagger" and run_cfg["train"]["mode"] == "raw"
    assert run_cfg["train"]["imitation"]["planner"]["depth"] == 2  # the study's planner is the expert
    # Finished policies keep their checkpoint, not the replay that only resuming needs.
    assert list(tiny_study.glob("steps/policy-*/run/checkpoint.safetensors"))
    assert not list(tiny_study.glob("steps/policy-*/run/replay-*"))
    report = (tiny_study / "report.md").read_text()
    for section in ("Bottleneck vs baseline", "Train × test", "Domain adaptation", "Transfer learning",
                    "Leave one scenario out", "Ablations", "Bottleneck network", "linear probes", "What this run can and cannot show",
                    "The imitation reference"):
        assert section in report
    # The BNN table scores vehicles both ways, beside the noisy input's own scores.
    bnn_rows = report[report.index("## 9. Bottleneck network"):].splitlines()
    assert "| run | d | λ | held-out recon | vehicle recall | precision | mean scenario MMD² |" in bnn_rows
    assert any(row.startswith("| noisy input (reference) |") for row in bnn_rows)
    for fig in ("headline", "matrix", "transfer", "leave_one_out", "ablations", "bnn_loss", "bnn_distance"):
        assert (tiny_study / "figures" / f"{fig}.png").stat().st_size > 1000
    # Every figure the report shows is there.
    for line in report.splitlines():
        if line.startswith("!["):
            assert (tiny_study / line[line.index("(") + 1:-1]).is_file(), line


def test_rerunning_skips_finished_steps_and_rebuilding_the_report_changes_no_number(tiny_study: Path) -> None:
    before = _numbers(tiny_study)
    graph = build_graph(load_reproduce_config("tiny"))
    stamps = {n: (graph.folder(tiny_study, n) / "done.json").stat().st_mtime_ns for n in graph.order}
    assert main(["reproduce", str(tiny_study), "--preset", "tiny", "-q"]) == 0
    assert stamps == {n: (graph.folder(tiny_study, n) / "done.json").stat().st_mtime_ns for n in graph.order}
    (tiny_study / "report.md").unlink()
    (tiny_study / "results.json").write_text("{ damaged")  # what `report` exists to rebuild
    assert main(["report", str(tiny_study)]) == 0
    assert (tiny_study / "report.md").is_file() and _numbers(tiny_study) == before


def test_re_running_steps_gives_the_same_numbers(tiny_study: Path) -> None:
    before = _numbers(tiny_study)
    graph = build_graph(load_reproduce_config("tiny"))
    # A policy and the evaluations that read it, run again in one worker instead of two.
    for name in ("policy/latent/mixed/s0", "evaluate/policy/latent/mixed/s0", "evaluate/ref/random"):
        shutil.rmtree(graph.folder(tiny_study, name))
    assert main(["reproduce", str(tiny_study), "--preset", "tiny", "--workers", "1", "-q"]) == 0
    assert _numbers(tiny_study) == before


def test_report_of_a_folder_that_holds_no_study_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["report", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not a study folder" in err[0]


def test_an_unknown_preset_or_key_is_refused_before_anything_is_written(tmp_path: Path,
                                                                         capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "o"
    assert main(["reproduce", str(out), "--preset", "huge"]) == 2
    assert main(["reproduce", str(out), "--preset", "tiny", "--set", "policy.train.bogus=1"]) == 2
    assert main(["reproduce", str(out), "--preset", "tiny", "--set", "policy_bnn=5"]) == 2
    assert main(["reproduce", str(out), "--preset", "tiny", "--workers", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 4 and all(line.startswith("latentdrive: error:") for line in err)
    assert "unknown preset 'huge'" in err[0] and "bogus" in err[1] and "policy_bnn 5" in err[2] and "--workers" in err[3]
    assert not out.exists()


def test_a_killed_study_loses_only_the_steps_in_progress(tiny_study: Path, tmp_path: Path) -> None:
    import os
    import signal
    import subprocess
    import sys
    import time

    before = _numbers(tiny_study)
    out = tmp_path / "copy"
    shutil.copytree(tiny_study, out)
    graph = build_graph(load_reproduce_config("tiny"))
    redo = [n for n in graph.order if "/latent/" in n]
    for name in redo:
        shutil.rmtree(graph.folder(out, name))
    proc = subprocess.Popen([sys.executable, "-m", "latentdrive", "reproduce", str(out), "--preset", "tiny",
                             "--workers", "2", "-q"], start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    logged = len(read_runs(out) or [])
    # Killed once a step has finished and the run has logged it (a moment the log must survive).
    while len(read_runs(out) or []) == logged:
        assert proc.poll() is None and time.monotonic() < deadline
        time.sleep(0.2)
    os.killpg(proc.pid, signal.SIGKILL)  # the whole study, workers included, at an arbitrary moment
    proc.wait()
    finished = {n: (graph.folder(out, n) / "done.json").stat().st_mtime_ns for n in graph.order
                if (graph.folder(out, n) / "done.json").exists()}
    assert 0 < len(finished) < len(graph.order)
    assert main(["reproduce", str(out), "--preset", "tiny", "--workers", "2", "-q"]) == 0
    assert all((graph.folder(out, n) / "done.json").stat().st_mtime_ns == t for n, t in finished.items())
    assert _numbers(out) == before
    # The runs log keeps the killed run, whose end was never written, beside the one that finished.
    runs = json.loads((out / "runs.json").read_text())
    assert len(runs) == logged + 2
    killed, rerun = runs[-2:]
    assert killed["wall_s"] is None and "ended" not in killed and killed["steps"] >= 1
    assert killed["command"].startswith("latentdrive reproduce")
    assert rerun["ended"] == "finished" and rerun["finished_before"] == len(finished)
    report = (out / "report.md").read_text()
    assert f"- Runs of this folder: {len(runs)}," in report and "1 of them not to their end (1 cut off" in report
    # A damaged results.json loses nothing the report needs: the log knows the last run's command.
    (out / "results.json").write_text("{")
    assert main(["report", str(out)]) == 0
    assert f"- Command of the last run: `{rerun['command']}`." in (out / "report.md").read_text().splitlines()


def test_running_another_config_into_a_study_folder_says_so(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import latentdrive.experiments.reproduce as rep

    # Only the bookkeeping around the steps is under test here: no step runs.
    monkeypatch.setattr(rep, "run_local", lambda *a, **k: {})
    monkeypatch.setattr(rep, "_report", lambda *a, **k: {})
    said: list[str] = []
    rep.run_study(load_reproduce_config("tiny"), tmp_path, preset="tiny", say=said.append)
    rep.run_study(load_reproduce_config("tiny"), tmp_path, preset="tiny", say=said.append)
    assert not any(s.startswith("note:") for s in said)  # the same study again: nothing to say
    rep.run_study(load_reproduce_config("tiny", {"seeds": 2}), tmp_path, preset="tiny", say=said.append)
    assert said[-1].startswith(f"note: {tmp_path} held a study of preset tiny")
    assert rep.read_study(tmp_path)[0].seeds == 2


@pytest.mark.parametrize(("step", "file", "content", "needle"), [
    ("bnn/report", "report.json", "{}", "not a BNN study report"),
    ("bnn/report", "report.json", "[]", "not an object"),
    ("probes", "probes.json", '{"raw": 1, "samples": {"train": 1, "test": 1}}', "raw"),
    ("probes", "probes.json", '{"raw": {}}', "samples"),
    ("evaluate/ref/random", "outcomes.json", "[]", "0 episodes of roundabout"),
    ("policy/raw/roundabout-finetuned/s0", "run/eval.csv", "a,b\n1,2\n", "evaluation log"),
    ("evaluate/ref/random", "outcomes.json", None, "missing, though its step is recorded as finished"),
])
def test_a_damaged_step_result_is_a_one_line_error_and_the_report_is_kept(
        tiny_study: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str],
        step: str, file: str, content: str | None, needle: str) -> None:
    out = tmp_path / "copy"
    shutil.copytree(tiny_study, out)
    graph = build_graph(load_reproduce_config("tiny"))
    if content is None:
        (graph.folder(out, step) / file).unlink()
    else:
        (graph.folder(out, step) / file).write_text(content)
    report = (out / "report.md").read_bytes()
    capsys.readouterr()
    assert main(["report", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and file in err[0] and needle in err[0], err
    assert (out / "report.md").read_bytes() == report


def test_a_moved_study_reports_resumes_and_evaluates_from_another_directory(
        tiny_study: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from latentdrive.experiments.reproduce import read_study_specs
    from latentdrive.scenarios import get_spec

    before = _numbers(tiny_study)
    moved = tmp_path / "moved" / "study"
    shutil.copytree(tiny_study, moved)
    stored = read_study_specs(moved)
    assert stored == {n: get_spec(n) for n in ("roundabout", "intersection", "merge")}
    (tmp_path / "elsewhere").mkdir()
    monkeypatch.chdir(tmp_path / "elsewhere")
    graph = build_graph(load_reproduce_config("tiny"), stored)
    stamps = {n: (graph.folder(moved, n) / "done.json").stat().st_mtime_ns for n in graph.order}
    assert main(["reproduce", str(moved), "--preset", "tiny", "-q"]) == 0  # nothing left to run
    assert stamps == {n: (graph.folder(moved, n) / "done.json").stat().st_mtime_ns for n in graph.order}
    (moved / "report.md").unlink()
    assert main(["report", str(moved)]) == 0 and _numbers(moved) == before
    # A latent policy of the moved study evaluates from here: its run stores its specs and
    # its encoder, so neither the study's former path nor its BNN folder is needed.
    run = graph.folder(moved, "policy/latent/mixed/s0") / "run"
    assert set(json.loads((run / "config.json").read_text())["train"]["specs"]) == set(stored)
    shutil.rmtree(graph.folder(moved, graph.steps["policy/latent/mixed/s0"].inputs["bnn"]))
    assert main(["evaluate", str(run), "--policy", "none", "--episodes", "1", "-q"]) == 0


def test_a_study_reports_from_the_specs_it_stored_not_todays_presets(
        tiny_study: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import latentdrive.scenarios as scenarios

    before = _numbers(tiny_study)
    copy = tmp_path / "study"
    shutil.copytree(tiny_study, copy)
    # As if a later version changed a preset: the steps it keys are not this study's.
    real = scenarios._preset

    def later(name: str) -> dict:
        data = dict(real(name))
        return {**data, "n_hv": data["n_hv"] + 1} if name == "merge" else data

    monkeypatch.setattr(scenarios, "_preset", later)
    today = build_graph(load_reproduce_config("tiny"))
    assert today.record(copy, "evaluate/ref/random") is None
    (copy / "report.md").unlink()
    assert main(["report", str(copy)]) == 0 and _numbers(copy) == before


def test_the_report_names_the_settings_of_one_kind(tiny_study: Path, tmp_path: Path) -> None:
    from latentdrive.experiments.study_report import write_report

    res = json.loads((tiny_study / "results.json").read_text())
    write_report(res, tmp_path)
    report = (tmp_path / "report.md").read_text()
    assert "policies only:" not in report and "against the same network on the raw maps (`raw`)." in report
    res["meta"]["config"]["policy"]["by_kind"] = {"raw": {"vfan": {"reader": "objects", "objects_k": 8}}, "latent": {}}
    write_report(res, tmp_path)
    lines = (tmp_path / "report.md").read_text().splitlines()
    assert "- `raw` policies only: `vfan.reader=objects`, `vfan.objects_k=8`." in lines
    assert any("(`raw`: `vfan.reader=objects`, `vfan.objects_k=8`), so not the paper's raw baseline." in line
               for line in lines)
    assert not any(line.startswith("- `latent` policies only") for line in lines)


def test_the_report_names_the_command_and_the_commits_the_steps_ran_from(tiny_study: Path, tmp_path: Path) -> None:
    from latentdrive.experiments.study_report import write_report
    from latentdrive.provenance import source_revision

    # A run of the finished study: every step skipped, the report written with this command.
    assert main(["reproduce", str(tiny_study), "--preset", "tiny", "--workers", "1", "-q"]) == 0
    res = json.loads((tiny_study / "results.json").read_text())
    # The fixture's steps ran from this checkout (or from no checkout: unknown).
    assert {s["source"] for s in res["steps"].values()} <= {source_revision(), None}
    lines = (tiny_study / "report.md").read_text().splitlines()
    assert f"- Command of the last run: `latentdrive reproduce {tiny_study} --preset tiny --workers 1`." in lines
    assert any(line.startswith("- Code: every step ran from commit `") or line.startswith("- Code: the commit")
               for line in lines)
    # Steps from two commits, and records from before commits were kept, are told apart.
    names = sorted(res["steps"])
    for i, name in enumerate(names):
        res["steps"][name]["source"] = ("aaaaaaaaaaaa", "bbbbbbbbbbbb+changes.0123abcd", None)[i % 3]
    write_report(res, tmp_path)
    code = next(line for line in (tmp_path / "report.md").read_text().splitlines() if line.startswith("- Code:"))
    assert "more than one commit" in code and "`aaaaaaaaaaaa`" in code and "`bbbbbbbbbbbb+changes.0123abcd`" in code
    assert f"; {len(names) // 3} steps' commit unknown" in code
    # One commit beside records from before commits were kept: not "more than one commit".
    for i, name in enumerate(names):
        res["steps"][name]["source"] = "aaaaaaaaaaaa" if i else None
    write_report(res, tmp_path)
    code = next(line for line in (tmp_path / "report.md").read_text().splitlines() if line.startswith("- Code:"))
    assert code.startswith(f"- Code: {len(names) - 1} steps ran from commit `aaaaaaaaaaaa`; 1 steps' commit unknown")


def test_the_reports_cost_counts_what_interrupted_attempts_did(tiny_study: Path, tmp_path: Path) -> None:
    from latentdrive.experiments.study_report import write_report

    res = json.loads((tiny_study / "results.json").read_text())
    assert all(s["resumed_s"] == 0 for s in res["steps"].values())  # the fixture ran in one go
    write_report(res, tmp_path)
    before = next(line for line in (tmp_path / "report.md").read_text().splitlines() if line.startswith("- Last run:"))
    assert "resumed" not in before
    total = sum(s["wall_s"] for s in res["steps"].values())
    assert f"{total:.0f} s of step time in all" in before
    name = next(n for n, s in res["steps"].items() if s["kind"] == "policy")
    res["steps"][name]["resumed_s"] = 1000.0
    write_report(res, tmp_path)
    lines = (tmp_path / "report.md").read_text().splitlines()
    after = next(line for line in lines if line.startswith("- Last run:"))
    assert f"{total + 1000:.0f} s of step time in all" in after
    assert "1 step(s) resumed after an interruption, with the 1000 s their earlier attempts spent" in after
    table = lines.index(next(line for line in lines if line.startswith("| step kind |")))
    policy_row = next(line for line in lines[table:] if line.startswith("| policy |"))
    assert float(policy_row.split("|")[3]) >= 1000


def test_the_reported_command_holds_what_defines_the_run() -> None:
    import argparse

    from latentdrive.experiments.reproduce_cli import add_reproduce_parsers, reproduce_command

    parser = argparse.ArgumentParser()
    add_reproduce_parsers(parser.add_subparsers())

    def command(*argv: str) -> str:
        return reproduce_command(parser.parse_args(["reproduce", "out dir", *argv]))

    assert command("-q") == "latentdrive reproduce 'out dir' --preset quick --workers 1"
    assert command("--seeds", "2", "--set", "policy.steps=9", "--workers", "2") == (
        "latentdrive reproduce 'out dir' --preset quick --seeds 2 --set policy.steps=9 --workers 2")
    assert command("--ray", "auto", "--gpu-fraction", "0.25").endswith("--ray auto --gpu-fraction 0.25")
    # Without Ray the share asks for nothing, and at its default it says nothing.
    assert "--gpu-fraction" not in command("--gpu-fraction", "0.25") + command("--ray", "auto")


def test_the_report_tests_every_seed_against_the_rule_driver_and_latent_against_raw(tiny_study: Path,
                                                                                      tmp_path: Path) -> None:
    from latentdrive.experiments.study_report import write_report

    res = json.loads((tiny_study / "results.json").read_text())
    per = res["per_seed"]
    # One entry per seed, each of the same episodes (the mixed test set) on both sides.
    mixed = res["evaluation"]["episodes_per_scenario"] * len(res["scenarios"])
    assert set(per) == {"latent_vs_raw", "vs_random", "vs_rule"}
    assert all(len(per[k][rep]) == res["seeds"] for k in ("vs_random", "vs_rule") for rep in ("raw", "latent"))
    assert len(per["latent_vs_raw"]) == res["seeds"] and all(t["n"] == mixed for t in per["latent_vs_raw"])
    assert per["vs_rule"]["raw"][0]["rate_b"] == res["references"]["rule"]["mixed"]["failure"]["rate"]
    # Two seeds: one significantly below the rule driver, one below it but not significantly.
    test = {"n": 400, "rate_a": 0.3, "rate_b": 0.6, "difference": -0.3, "lo": -0.36, "hi": -0.24, "p_value": 1e-6}
    per["vs_rule"] = {"raw": [test, {**test, "p_value": 0.2}], "latent": [{**test, "rate_a": 0.7}, test]}
    per["vs_random"] = {rep: [{**test, "rate_b": 0.9}] * 2 for rep in ("raw", "latent")}
    per["latent_vs_raw"] = [test, {**test, "difference": None, "lo": None, "hi": None, "p_value": None}]
    write_report(res, tmp_path)
    lines = (tmp_path / "report.md").read_text().splitlines()
    assert ("Seeds that fail significantly less often than the rule driver (McNemar p < 0.05 for each seed, no "
            "correction over seeds): `raw` 1 of 2, `latent` 1 of 2; significantly more often: `raw` 0, `latent` 1.") in lines
    assert "| raw | 1 | 30.0 | 90.0 | <0.001 | 60.0 | 0.200 |" in lines
    assert "| 0 | 60.0 | 30.0 | -30.0 [-36.0, -24.0] | <0.001 |" in lines and "| 1 | 60.0 | 30.0 | – | – |" in lines
    # Without the rule driver the report says no seed was tested against it.
    del per["vs_rule"]
    write_report(res, tmp_path)
    lines = (tmp_path / "report.md").read_text().splitlines()
    assert "The rule driver was not evaluated (`evaluate.references`): no seed is tested against it." in lines
    assert "| raw | 1 | 30.0 | 90.0 | <0.001 |" in lines
