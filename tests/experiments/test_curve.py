"""``latentdrive curve``: learning curves read from run folders, references on the same episodes."""

import csv
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from latentdrive.cli import main
from latentdrive.config import ConfigError, merge_overrides
from latentdrive.evaluate.report import policy_report
from latentdrive.experiments.curve import (
    common_evaluation,
    curve_table,
    group_curves,
    read_curve,
    reference_rates,
)
from latentdrive.rl.config import PolicyTrainConfig
from latentdrive.rl.policy import greedy_policy, load_policy_network
from latentdrive.rl.train import periodic_evaluation, train_policy

pytestmark = pytest.mark.usefixtures("one_torch_thread")

#: Three evaluations of 3 episodes in a run of a few seconds.
TINY: dict[str, Any] = {
    "mode": "raw", "scenarios": ["intersection"], "steps": 240, "envs": 4, "segment": 80, "eval_every": 1,
    "eval_episodes": 3, "observation": {"height": 16, "width": 32, "frames": 2},
    "vfan": {"hidden": 32, "channels": [8, 16, 16]},
    "dqn": {"learning_starts": 40, "buffer_size": 1000, "batch_size": 16, "updates_per_transition": 0.25},
}


def _train(path: Path, **changes: Any) -> Path:
    cfg = PolicyTrainConfig.model_validate(merge_overrides(TINY, changes))
    train_policy(cfg, path, progress=False, say=lambda _line: None)
    return path


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    root = tmp_path_factory.mktemp("curve")
    return [_train(root / f"seed-{s}", seed=s) for s in (0, 1)]


def _rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def test_a_curve_is_the_runs_evaluations_with_their_elapsed_minutes(runs):
    curve = read_curve(runs[0])
    evals = [r for r in _rows(runs[0] / "eval.csv") if r["scenario"] == "mixed"]
    metrics = {int(r["transitions"]): float(r["elapsed_s"]) for r in _rows(runs[0] / "metrics.csv")}
    assert len(evals) == 3
    np.testing.assert_array_equal(curve.transitions, [int(r["transitions"]) for r in evals])
    np.testing.assert_allclose(curve.failure, [float(r["failure_rate"]) for r in evals])
    np.testing.assert_allclose(curve.minutes, [metrics[int(r["transitions"])] / 60 for r in evals])
    assert np.all(np.diff(curve.minutes) > 0) and curve.episodes == 3 and curve.label == "raw"
    one = read_curve(runs[0], scenario="intersection")
    np.testing.assert_allclose(one.failure, curve.failure)  # one scenario: the mix is that scenario


def test_references_play_the_episodes_of_the_runs_evaluations(runs):
    """The run's final evaluation, replayed by periodic_evaluation with the final network,
    gives the failure count eval.csv logged: the episodes are the same."""
    curve = read_curve(runs[1])
    net, cfg = load_policy_network(runs[1])
    replayed = policy_report(periodic_evaluation(cfg, greedy_policy(net, torch.device("cpu")))).mixed
    logged = [r for r in _rows(runs[1] / "eval.csv") if r["scenario"] == "mixed"][-1]
    assert replayed.failure_rate.n == curve.episodes
    assert replayed.failure_rate.rate == pytest.approx(curve.failure[-1])
    # The mean return pins the episodes down far more finely than 3 pass/fail outcomes.
    assert replayed.mean_return.mean == pytest.approx(float(logged["mean_return"]), rel=1e-9)
    rates = reference_rates(common_evaluation([curve, read_curve(runs[0])]), ["idle", "stop"])
    assert set(rates) == {"idle", "stop"} and all(r.n == 3 for r in rates.values())


def test_the_table_averages_seeds_at_each_evaluation(runs):
    label = "a setting with a label longer than the columns"
    curves = [read_curve(r, label) for r in runs]
    header, *lines = curve_table(group_curves(curves), {}).splitlines()
    assert len(lines) == 3
    for i, line in enumerate(lines):
        mean = 100 * np.mean([c.failure[i] for c in curves])
        rest = line[len(label):].split()
        assert line.startswith(label) and rest[:2] == ["2", str(i + 1)]
        # The seeds column lines up with its header, whatever the label's length.
        assert line.index(" 2 ") + 1 == header.index("seeds") + len("seeds") - 1
        assert float(rest[4]) == pytest.approx(mean, abs=0.051)


def test_the_command_draws_and_prints(runs, tmp_path, capsys):
    out = tmp_path / "curves.png"
    assert main(["curve", str(out), f"tiny={runs[0]}", f"tiny={runs[1]}", "--references", "idle"]) == 0
    text = capsys.readouterr().out
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "tiny" in text and "idle" in text and f"wrote {out}" in text


def test_bad_input_is_one_line_and_writes_nothing(runs, tmp_path, capsys):
    silent = tmp_path / "silent"
    shutil.copytree(runs[0], silent)
    (silent / "eval.csv").unlink()
    other = _train(tmp_path / "other", eval_episodes=2, steps=80)
    damaged = tmp_path / "damaged"
    shutil.copytree(runs[0], damaged)
    text = (damaged / "metrics.csv").read_text().splitlines()
    text[1] = ",".join([*text[1].split(",")[:-1], "soon"])
    (damaged / "metrics.csv").write_text("\n".join(text) + "\n")
    out = tmp_path / "c.png"
    cases = [
        ([str(out), str(damaged)], "no number in column 'elapsed_s'"),
        ([str(out), str(silent)], "no periodic evaluations"),
        ([str(out), str(runs[0]), "--scenario", "merge"], "no evaluation of 'merge'"),
        ([str(out), str(runs[0]), "--references", "oracle"], "unknown reference policy 'oracle'"),
        ([str(tmp_path / "c.svg"), str(runs[0])], "the figure is a PNG"),
        ([str(out), str(runs[0]), f"other={other}"], "evaluated on different episodes"),
        ([str(out), str(tmp_path / "nowhere")], "nowhere"),
        ([str(out), str(runs[0]), "--set", "planner.depth=3"], "the planner ('plan') is not a reference"),
    ]
    for argv, message in cases:
        assert main(["curve", *argv]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and message in err[0], (argv, err)
    assert not out.exists() and not (tmp_path / "c.svg").exists()
    # Without references, runs evaluated on different episodes may share a figure.
    assert main(["curve", str(out), str(runs[0]), f"other={other}", "--references", "none"]) == 0


def test_minutes_add_up_over_a_resumed_run(tmp_path):
    cfg = PolicyTrainConfig.model_validate(merge_overrides(TINY, {"steps": 160}))
    train_policy(cfg, tmp_path / "run", progress=False, say=lambda _line: None)
    before = read_curve(tmp_path / "run")
    train_policy(cfg.model_copy(update={"steps": 240}), tmp_path / "run", resume=True, progress=False,
                 say=lambda _line: None)
    after = read_curve(tmp_path / "run")
    assert len(after.minutes) == 3
    np.testing.assert_array_equal(after.minutes[:2], before.minutes)
    assert after.minutes[2] > after.minutes[1]  # the second session's clock starts where the first stopped


def test_a_label_groups_seeds_of_one_setting_only(runs, tmp_path, capsys):
    other = _train(tmp_path / "lr", steps=80, dqn={"lr": 1e-3})
    with pytest.raises(ConfigError, match=r"share the label 'raw' but differ in dqn"):
        group_curves([read_curve(runs[0]), read_curve(other)])
    assert main(["curve", str(tmp_path / "c.png"), str(runs[0]), str(other), "--references", "none"]) == 2
    assert "LABEL=RUN" in capsys.readouterr().err
    assert main(["curve", str(tmp_path / "c.png"), f"=x{runs[0]}"]) == 2
    assert "an empty label" in capsys.readouterr().err
    assert set(group_curves([read_curve(runs[0]), read_curve(other, "lr")])) == {"raw", "lr"}
    assert not (tmp_path / "c.png").exists()


def test_a_dagger_run_is_labelled_by_its_expert(tmp_path):
    run = _train(tmp_path / "dagger", steps=80, learner="dagger", imitation={"expert": "rule"})
    assert read_curve(run).label == "raw, imitating rule"


def test_common_evaluation_names_the_run_that_differs(runs, tmp_path):
    other = _train(tmp_path / "other", observation={"height": 16, "width": 32, "frames": 3}, steps=80)
    with pytest.raises(ConfigError, match="other"):
        common_evaluation([read_curve(runs[0]), read_curve(other)])
