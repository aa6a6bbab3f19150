import json
import subprocess
import sys

import pytest
import yaml

from latentdrive.cli import main
from latentdrive.scenarios import get_spec


def run_cli(*args):
    """Run the console entry point in a subprocess, as a user would."""
    return subprocess.run([sys.executable, "-m", "latentdrive.cli", *args], capture_output=True, text=True)


def test_scenarios_lists_all_five(capsys):
    assert main(["scenarios"]) == 0
    out = capsys.readouterr().out
    for name in ("roundabout", "intersection", "merge", "exit", "highway"):
        assert name in out


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["show", "lake", "--out", "x.png"], "unknown scenario 'lake'"),
        (["show", "merge", "--out", "x.png", "--set", "n_av=99"], "scenario.n_av"),
        (["show", "merge", "--out", "x.png", "--set", "observation.frames=0"], "observation.frames"),
        (["show", "merge", "--out", "x.png", "--set", "colour=red"], "scenario.colour: unknown key"),
        (["show", "merge", "--out", "x.png", "--set", "n_av"], "expected key=value"),
        (["bench", "--scenarios", "merge,lake"], "unknown scenario 'lake'"),
    ],
)
def test_bad_input_is_one_line_and_nonzero(args, needle, tmp_path):
    proc = subprocess.run([sys.executable, "-m", "latentdrive.cli", *args], capture_output=True,
                          text=True, cwd=tmp_path)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("latentdrive: error:") and needle in lines[0]
    assert not (tmp_path / "x.png").exists()


def test_show_writes_a_png(tmp_path):
    out = tmp_path / "fig" / "merge.png"
    assert main(["show", "merge", "--out", str(out), "--steps", "2",
                 "--set", "observation.height=16", "--set", "observation.width=32"]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_bench_prints_ratio_and_json(tmp_path, capsys):
    path = tmp_path / "bench.json"
    assert main(["bench", "--scenarios", "merge", "--steps", "3", "--json", str(path)]) == 0
    out = capsys.readouterr().out
    assert "grid/obs" in out and "merge" in out
    (row,) = json.loads(path.read_text())
    assert row["scenario"] == "merge" and row["steps"] == 3
    assert row["grid_over_obs"] == pytest.approx(row["grid_ms_per_agent_frame"] / row["obs_ms_per_agent_frame"])
    assert row["sim_steps_per_s"] > 0


def test_bench_fast_prints_both_backends_and_speedup(tmp_path, capsys):
    path = tmp_path / "fast.json"
    assert main(["bench", "--backend", "fast", "--scenarios", "exit", "--steps", "3", "--batch-size", "4",
                 "--repeat", "3", "--json", str(path)]) == 0
    out = capsys.readouterr().out
    assert "speed-up" in out and "resets included" in out
    rows = json.loads(path.read_text())
    assert [r["velocity_maps"] for r in rows] == [False, True]
    for r in rows:
        assert r["speedup"] == pytest.approx(r["fast_steps_per_s"] / r["highway_steps_per_s"])
        # The reported run is the median of three timed runs (distinct in practice): neither end.
        assert r["runs"] == 3 and r["speedup_min"] < r["speedup"] < r["speedup_max"]


def test_validate_backend_small(tmp_path, capsys):
    path = tmp_path / "val.json"
    code = main(["validate-backend", "--scenarios", "intersection", "--episodes", "3", "--policies", "idle",
                 "--json", str(path)])
    rows = json.loads(path.read_text())
    assert {r["statistic"] for r in rows} == {"crash_rate", "length", "speed", "lane_change_rate"}
    assert code == (0 if all(r["ok"] for r in rows) else 1)
    assert "intersection" in capsys.readouterr().out


def test_scenarios_prints_how_far_each_mission_is(capsys):
    assert main(["scenarios", "merge"]) == 0
    out = capsys.readouterr().out
    assert "300 m, 67%" in out and "roundabout" not in out


def test_scenarios_keeps_a_long_name_apart_from_its_layout(tmp_path, capsys):
    # Regression: names longer than the presets' ran into the layout column
    # ("intersection-1avintersection").
    spec = tmp_path / "long.yaml"
    spec.write_text(yaml.safe_dump({**get_spec("intersection").model_dump(mode="json"), "name": "intersection-one-av"}))
    assert main(["scenarios", str(spec), "merge"]) == 0
    rows = [line.split() for line in capsys.readouterr().out.splitlines()[1:3]]
    assert rows[0][:2] == ["intersection-one-av", "intersection"]
    assert rows[1][:2] == ["merge", "merge"]


def test_a_path_in_the_way_is_one_line(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    # Regression: a file where a folder goes (or the reverse) ended commands in a traceback.
    import latentdrive.cli as cli

    def blocked(args: object) -> int:
        raise IsADirectoryError(21, "Is a directory", "study/report.md\nx")

    monkeypatch.setattr(cli, "_cmd_scenarios", blocked)  # build_parser binds it when main runs
    assert cli.main(["scenarios"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["latentdrive: error: Is a directory: study/report.md\\nx"]


def test_a_terminate_stops_the_command_like_an_interrupt(monkeypatch, capsys):
    """SIGTERM (a scheduler's stop) raises in the command, so that its clean-ups run; the
    CLI says so on one line, exits 143 and restores the handler it found."""
    import os
    import signal
    import time

    from latentdrive import cli

    def terminated_midway(args):
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(30)
        return 0

    before = signal.getsignal(signal.SIGTERM)
    monkeypatch.setattr(cli, "_cmd_scenarios", terminated_midway)
    t0 = time.monotonic()
    assert main(["scenarios"]) == 143
    assert time.monotonic() - t0 < 10
    assert capsys.readouterr().err.strip() == "latentdrive: terminated"
    assert signal.getsignal(signal.SIGTERM) is before


def test_no_help_text_shows_an_escaped_percent_sign():
    """Regression: argparse %-formats argument help but not descriptions, so a description's
    ``%%`` was printed as is."""
    import argparse

    from latentdrive.cli import build_parser

    parser = build_parser()
    subs = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    assert len(subs.choices) > 10
    for name, sub in subs.choices.items():
        assert "%%" not in sub.format_help(), name


def test_a_reader_that_goes_away_ends_the_command_quietly(monkeypatch, capsys):
    # `latentdrive status OUT | head -1`: the rest of the output has nowhere to go.
    from latentdrive.experiments import reproduce_cli

    def closed_pipe(_args):
        raise BrokenPipeError(32, "Broken pipe")

    monkeypatch.setattr(reproduce_cli, "_cmd_status", closed_pipe)
    assert main(["status", "anywhere"]) == 141  # as a shell reports SIGPIPE
    assert capsys.readouterr().err == ""
