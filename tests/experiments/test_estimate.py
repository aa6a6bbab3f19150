"""`latentdrive estimate`: measured seconds per unit, scaled to another study and list-scheduled."""

from __future__ import annotations

from pathlib import Path

import pytest

from latentdrive.cli import main
from latentdrive.config import ConfigError
from latentdrive.experiments.estimate import estimate_study, measured_rates, step_size
from latentdrive.experiments.graph import Graph, Step, StepRecord
from latentdrive.experiments.reproduce import estimate_from
from latentdrive.experiments.study import build_graph, load_reproduce_config


def _evals(*chain: tuple[str, int, str | None]) -> Graph:
    """Evaluation steps of ``episodes`` episodes on one scenario, ``name`` after ``needs``."""
    ev = {"backend": "fast", "scenarios": ["merge"]}
    return Graph([Step(n, "evaluate", {"eval": {**ev, "episodes": e}}, {"a": d} if d else {}) for n, e, d in chain])


def test_a_list_schedule_of_literal_step_times() -> None:
    # a (10 episodes) then b (20) in one chain; c (30) alone; 1 s per episode.
    g = _evals(("a", 10, None), ("b", 20, "a"), ("c", 30, None))
    rates = {"evaluate:fast:policy": 1.0}
    one, two = estimate_study(g, rates, 1), estimate_study(g, rates, 2)
    assert one.step_hours * 3600 == pytest.approx(60) and one.wall_hours * 3600 == pytest.approx(60)
    # Two workers: the chain a→b (30 s) beside c (30 s).
    assert two.wall_hours * 3600 == pytest.approx(30)
    # Three workers cannot beat the longest chain.
    assert estimate_study(g, rates, 3).wall_hours * 3600 == pytest.approx(30)


def test_rates_are_seconds_per_unit_of_each_class() -> None:
    g = _evals(("a", 10, None), ("b", 30, None))
    recs = {n: StepRecord(name=n, kind="evaluate", key=g.keys[n], summary={}, wall_s=w, peak_rss_mb=1.0)
            for n, w in (("a", 5.0), ("b", 15.0))}
    assert measured_rates(g, recs) == {"evaluate:fast:policy": pytest.approx(0.5)}
    # A step resumed after an interruption costs its earlier attempts' seconds too.
    recs["b"] = StepRecord(name="b", kind="evaluate", key=g.keys["b"], summary={}, wall_s=5.0, peak_rss_mb=1.0,
                           resumed_s=10.0)
    assert measured_rates(g, recs) == {"evaluate:fast:policy": pytest.approx(0.5)}


def test_a_speedup_divides_its_classes_time(tiny_study: Path) -> None:
    # Long policies, so that each class's hours (rounded to 0.01 h) carry the factor.
    cfg = load_reproduce_config("tiny", {"policy": {"steps": 10**8}})
    base = estimate_from(tiny_study, cfg, [1])[0]
    fast = estimate_from(tiny_study, cfg, [1], {"policy": 4.0})[0]
    for cls, hours in base.by_class.items():
        if cls.startswith("policy:"):
            assert hours > 1 and fast.by_class[cls] == pytest.approx(hours / 4, rel=0.01)
        else:
            assert fast.by_class[cls] == hours
    assert fast.step_hours < base.step_hours
    with pytest.raises(ConfigError, match="no such step class"):
        estimate_from(tiny_study, cfg, [1], {"gpu": 2.0})
    with pytest.raises(ConfigError, match=r"other observations \(height 16 there, 24 here\)"):
        estimate_from(tiny_study, load_reproduce_config("tiny", {"observation": {"height": 24}}), [1])


def test_bad_speedups_are_one_line(tiny_study: Path, capsys: pytest.CaptureFixture[str]) -> None:
    for bad in ("bnn", "bnn=fast", "bnn=0", "bnn=inf"):
        assert main(["estimate", str(tiny_study), "--preset", "tiny", "--speedup", bad]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 4 and all("--speedup" in line for line in err)


def _bnn(name: str, epoch_steps: int) -> Step:
    train = {"pretrain_epochs": 1, "mixed_epochs": 1, "epoch_steps": epoch_steps, "batch_size": 4}
    return Step(name, "bnn", {"train": train, "channels": [4], "latent_dim": 8})


def test_a_bnn_step_is_sized_in_the_training_samples_it_processes() -> None:
    # Two epochs of 10 batches of 4: 80 samples, whatever the dataset, unless it is smaller.
    capped = Graph([_bnn("capped", 10)])
    assert step_size(capped.steps["capped"]) == ("bnn:batch4:channels4", 80.0)
    assert step_size(capped.steps["capped"], epoch_samples=30.0)[1] == 60.0
    # Uncapped: two epochs of the training episodes' samples, which the caller gives.
    uncapped = Graph([_bnn("uncapped", 0)])
    assert step_size(uncapped.steps["uncapped"], epoch_samples=100.0)[1] == 200.0
    with pytest.raises(ConfigError, match="uncapped: an uncapped BNN epoch's size needs its dataset's sample count"):
        step_size(uncapped.steps["uncapped"])
    # So a capped study measures an uncapped one: 8 s for 80 samples, 20 s for 200.
    rec = StepRecord(name="capped", kind="bnn", key=capped.keys["capped"], summary={}, wall_s=8.0, peak_rss_mb=1.0)
    rates = measured_rates(capped, {"capped": rec})
    assert rates == {"bnn:batch4:channels4": pytest.approx(0.1)}
    assert estimate_study(uncapped, rates, 1, epoch_samples=100.0).step_hours * 3600 == pytest.approx(20.0)


def _report(score_samples: int) -> Step:
    study = {"score_samples": score_samples, "val_fraction": 0.2}
    return Step("report", "bnn-report", {"study": study, "runs": {"d8": [8, 0.0], "d16": [16, 0.0]}})


def test_the_bnn_report_is_sized_in_the_held_out_samples_it_scores() -> None:
    # Two runs and the noisy input; 400 training samples at a fifth held out: 100 held out.
    every, capped = Graph([_report(0)]).steps["report"], Graph([_report(30)]).steps["report"]
    assert step_size(every, epoch_samples=400.0) == ("bnn-report", 300.0)
    assert step_size(capped, epoch_samples=400.0) == ("bnn-report", 90.0)
    assert step_size(capped, epoch_samples=40.0)[1] == 30.0  # 10 held out: fewer than the cap
    assert step_size(capped)[1] == 90.0
    with pytest.raises(ConfigError, match="report: a report that scores every held-out sample needs"):
        step_size(every)


def test_capped_and_uncapped_bnn_epochs_estimate_alike(tiny_study: Path) -> None:
    # Long BNNs, so that their hours (rounded to 0.01 h) carry the ratios.
    def bnn_hours(train: dict[str, int]) -> float:
        cfg = load_reproduce_config("tiny", {"bnn": {"train": {"mixed_epochs": 100_000, **train}}})
        est = estimate_from(tiny_study, cfg, [1])[0]
        return sum(h for c, h in est.by_class.items() if c.startswith("bnn:"))

    one_step, two_steps = bnn_hours({"epoch_steps": 1}), bnn_hours({"epoch_steps": 2})
    assert one_step > 1 and two_steps == pytest.approx(2 * one_step, rel=0.01)
    # A cap above the epoch changes nothing.
    assert bnn_hours({"epoch_steps": 10**6}) == pytest.approx(bnn_hours({}), rel=0.01)


def test_a_bnn_of_another_batch_size_or_architecture_is_not_measured_by_this_one(tiny_study: Path) -> None:
    # A BNN's time per sample depends on its batch size and structure: a study that trained
    # other BNNs does not measure them, and says so rather than borrowing their rate.
    same = estimate_from(tiny_study, load_reproduce_config("tiny"), [1])[0]
    assert not [c for c in same.unmeasured if c.startswith("bnn:")]
    assert [c for c in same.by_class if c.startswith("bnn:batch")]
    tiny = load_reproduce_config("tiny")
    for change in ({"train": {"batch_size": tiny.bnn.train.batch_size * 2}}, {"model": {"head_hidden": 0}},
                   {"channels": [4]}):
        other = estimate_from(tiny_study, load_reproduce_config("tiny", {"bnn": change}), [1])[0]
        assert [c for c in other.unmeasured if c.startswith("bnn:")], change
        assert not [c for c in other.by_class if c.startswith("bnn:")], change


def test_a_bnn_speedup_reaches_the_bnn_classes(tiny_study: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # Long BNNs, so that their hours (rounded to 0.01 h) carry the factor.
    cfg = load_reproduce_config("tiny", {"bnn": {"train": {"mixed_epochs": 100_000}}})
    base = estimate_from(tiny_study, cfg, [1])[0]
    fast = estimate_from(tiny_study, cfg, [1], {"bnn": 4.0})[0]
    bnn = [c for c in base.by_class if c.startswith("bnn:")]
    assert bnn and all(base.by_class[c] > 1 and fast.by_class[c] == pytest.approx(base.by_class[c] / 4, rel=0.01)
                       for c in bnn)
    # A class named in full keeps every '=' of its name; the factor is what follows the last.
    assert main(["estimate", str(tiny_study), "--preset", "tiny", "--speedup", "bnn:batch8:head_hidden=0=2"]) == 2
    assert "--speedup bnn:batch8:head_hidden=0: no such step class" in capsys.readouterr().err


def test_an_estimate_with_unmeasured_steps_is_a_lower_bound(tiny_study: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["estimate", str(tiny_study), "--preset", "tiny", "--set", "bnn.train.batch_size=64"]) == 0
    out = capsys.readouterr().out
    assert "wall time with   1 worker(s): at least " in out and "not measured there (counted as 0): bnn:batch64" in out


def test_the_rates_preset_measures_every_step_class_of_the_paper_preset() -> None:
    def classes(preset: str) -> set[str]:
        graph = build_graph(load_reproduce_config(preset))
        return {step_size(step, epoch_samples=1e5)[0] for step in graph.steps.values()}

    paper, rates = classes("paper"), classes("rates")
    assert "bnn:batch64:channels16-32" in paper  # the paper's BNNs, no model section
    assert paper <= rates, f"not measured by the rates preset: {sorted(paper - rates)}"
    # The quick preset's BNNs are another class: an estimate from it leaves the paper's out.
    assert not paper <= classes("quick")
    # What a class leaves out but a unit's cost depends on matches too.
    p, r = load_reproduce_config("paper"), load_reproduce_config("rates")
    assert r.bnn.model == p.bnn.model and r.bnn.train.batch_size == p.bnn.train.batch_size
    assert r.evaluate.planner == p.evaluate.planner and r.evaluate.envs == p.evaluate.envs
    for cfg in (p, r):  # held-out episodes during training, per 1,000 agent-transitions: 2
        t = cfg.policy.train
        assert t["eval_episodes"] * 1000 / t["segment"] == 2
        assert cfg.policy.finetune_steps % t["segment"] == 0  # fine-tuning evaluates as often


def test_policy_classes_part_where_the_time_per_transition_does() -> None:
    g = build_graph(load_reproduce_config("tiny", {"policy": {"by_kind": {
        "raw": {"vfan": {"reader": "objects"}, "dqn": {"updates_per_transition": 1, "batch_size": 64}},
        "latent": {"dqn": {"updates_per_transition": 0.125}}}}}))
    classes = {n: step_size(s)[0] for n, s in g.steps.items() if s.kind == "policy"}
    assert classes["policy/raw/mixed/s0"] == "policy:raw:objects:upt1:batch64"
    # The tiny preset's 0.25 updates per transition and batch of 8 differ from the defaults;
    # latent's own 0.125 is the default's.
    assert classes["policy/latent/mixed/s0"] == "policy:latent:batch8"
    assert classes["policy/end-to-end/mixed/s0"] == "policy:end-to-end:upt0.25:batch8"
    assert classes["policy/imitation/mixed/s0"] == "policy:raw:dagger:upt0.25:batch8"
    # A precision set apart from auto's choice is a class of its own.
    g = build_graph(load_reproduce_config("tiny", {"policy": {"train": {"precision": "fp32"}}}))
    assert step_size(g.steps["policy/latent/mixed/s0"])[0] == "policy:latent:upt0.25:batch8:fp32"
