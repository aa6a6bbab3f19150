"""Summaries, tables and paired comparisons over hand-made episode outcomes."""

from __future__ import annotations

import json

import numpy as np
import pytest

from latentdrive.evaluate.report import (
    cause_counts,
    compare,
    format_causes,
    format_compare,
    format_table,
    policy_report,
    summarize,
)
from latentdrive.outcome import EpisodeOutcome


def outcome(
    kind: str,
    scenario: str = "merge",
    seed: int = 0,
    *,
    env_index: int = 0,
    episode_index: int = 0,
    steps: int = 10,
    speed: float = 20.0,
) -> EpisodeOutcome:
    """A two-AV episode: "crash" (AV 0 crashed, AV 1 arrived), "timeout" (AV 0 arrived
    only) or "success" (both arrived)."""
    crashed = {"crash": [True, False], "timeout": [False, False], "success": [False, False]}
    arrived = {"crash": [False, True], "timeout": [True, False], "success": [True, True]}
    cause = {"crash": "HV ahead", "timeout": "time-out", "success": ""}
    return EpisodeOutcome(
        scenario, env_index, episode_index, seed, steps,
        np.array(crashed[kind]), np.array(arrived[kind]),
        np.array([1.0, 3.0]), speed, cause=cause[kind],
    )


def three() -> list[EpisodeOutcome]:
    return [
        outcome("crash", seed=0, steps=5, speed=10.0),
        outcome("timeout", seed=1, steps=40, speed=2.0),
        outcome("success", seed=2, steps=15, speed=12.0),
    ]


def test_summarize_a_crash_a_timeout_a_success() -> None:
    s = summarize(three())
    assert s.episodes == 3
    for r in (s.crash_rate, s.timeout_rate, s.success_rate):
        assert (r.k, r.n) == (1, 3) and r.rate == pytest.approx(1 / 3)
    assert (s.failure_rate.k, s.failure_rate.n) == (2, 3)
    # Six AV-episodes: one crashed; arrived 1 + 1 + 2.
    assert (s.agent_crash_rate.k, s.agent_crash_rate.n) == (1, 6)
    assert (s.agent_arrival_rate.k, s.agent_arrival_rate.n) == (4, 6)
    assert s.mean_speed.mean == pytest.approx(8.0)
    assert s.mean_return.mean == pytest.approx(2.0)
    assert s.mean_steps.mean == pytest.approx(20.0)
    assert s.mean_steps.n == 3


def test_summary_dict_is_json_safe_even_when_empty() -> None:
    d = summarize(three()).as_dict()
    assert d["episodes"] == 3
    assert set(d["crash_rate"]) == {"rate", "lo", "hi", "k", "n"}
    json.dumps(d, allow_nan=False)
    empty = summarize([]).as_dict()
    assert empty["episodes"] == 0 and empty["failure_rate"]["rate"] is None
    json.dumps(empty, allow_nan=False)


def test_policy_report_groups_and_pools() -> None:
    outs = [*three(), outcome("crash", "exit", 0), outcome("success", "exit", 1)]
    rep = policy_report(outs)
    assert list(rep.scenarios) == ["exit", "merge"]
    assert rep.scenarios["exit"].episodes == 2 and rep.mixed.episodes == 5
    assert rep.mixed.failure_rate.k == 3
    d = rep.as_dict()
    assert d["scenarios"]["merge"]["failure_rate"]["k"] == 2
    assert d["mixed"]["episodes"] == 5
    json.dumps(d, allow_nan=False)


def test_format_table_rows_and_headline_first() -> None:
    reports = {"brake": policy_report(three()), "dqn": policy_report([outcome("success")])}
    text = format_table(reports)
    lines = text.splitlines()
    header = lines[0]
    assert header.index("failure %") < header.index("crash %") < header.index("success %")
    assert len(lines) == 2 + 4  # header, rule, (merge, mixed) per policy
    merge_row = lines[2].split()
    assert merge_row[:3] == ["brake", "merge", "3"] and merge_row[3] == "66.7"
    assert any(line.split()[:2] == ["dqn", "mixed"] for line in lines)


def test_compare_pairs_by_episode() -> None:
    a = [outcome("success", "merge", s) for s in range(6)] + [outcome("crash", "exit", 0)]
    b = [outcome("timeout", "merge", s) for s in range(6)] + [outcome("crash", "exit", 0)]
    res = compare(list(reversed(a)), b)  # order does not matter, keys do
    assert list(res) == ["exit", "merge", "mixed"]
    merge = res["merge"]["failed"]
    assert (merge.a_only, merge.b_only) == (0, 6)
    assert merge.p_value == pytest.approx(0.03125)
    assert res["merge"]["crashed"].p_value == 1.0
    assert res["exit"]["failed"].p_value == 1.0
    assert res["mixed"]["failed"].n == 7
    text = format_compare(res, names=("dqn", "brake"))
    assert "0.0312" in text and "dqn-brake pp" in text


def test_compare_refuses_different_episodes() -> None:
    a = [outcome("success", seed=s) for s in range(3)]
    b = [outcome("success", seed=s) for s in (0, 1, 5)]
    with pytest.raises(ValueError, match="not the same evaluation episodes") as err:
        compare(a, b)
    assert "\n" not in str(err.value)
    with pytest.raises(ValueError, match="twice"):
        compare([*a, a[0]], [*a, a[0]])


def test_cause_counts_per_scenario_and_pooled_and_their_table() -> None:
    outs = [*three(), outcome("crash", "roundabout", seed=5), outcome("success", "roundabout", seed=6)]
    counts = cause_counts(outs)
    assert counts == {
        "merge": {"episodes": 3, "success": 1, "time-out": 1, "HV ahead": 1},
        "roundabout": {"episodes": 2, "success": 1, "time-out": 0, "HV ahead": 1},
        "mixed": {"episodes": 5, "success": 2, "time-out": 1, "HV ahead": 2},
    }
    lines = format_causes({"p": outs}).splitlines()
    assert lines[0].split() == ["policy", "scenario", "episodes", "success", "%", "time-out", "%", "HV", "ahead", "%"]
    assert lines[2].split() == ["p", "merge", "3", "33.3", "33.3", "33.3"]
    assert lines[-1].split() == ["p", "mixed", "5", "40.0", "20.0", "40.0"]
