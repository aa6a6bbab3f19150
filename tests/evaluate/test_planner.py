"""The lookahead planner: its candidates, determinism, competence and refusals."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from latentdrive.actions import ACTION_NAMES
from latentdrive.config import ConfigError
from latentdrive.evaluate.planner import Plan, PlannerConfig, candidate_sequences, planner_policy
from latentdrive.evaluate.policies import reference_policy
from latentdrive.evaluate.run import evaluate_policy
from latentdrive.rollout import rollout
from latentdrive.sim.fast import FastBatch
from latentdrive.vec import make_vec

IDLE, LEFT, SLOWER = (ACTION_NAMES.index(a) for a in ("Idle", "Left", "Decelerate"))
FAST = PlannerConfig(depth=4, tail=1)


def test_candidates_hold_a_first_action_then_a_second() -> None:
    seq = candidate_sequences(depth=4, switch=1)
    assert seq.shape == (25, 4)
    np.testing.assert_array_equal(seq[0], [IDLE] * 4)  # ties go to Idle
    assert len({tuple(s) for s in seq}) == 25
    assert [LEFT, SLOWER, SLOWER, SLOWER] in seq.tolist()
    assert all(len(set(s[1:])) == 1 for s in seq.tolist())
    two = candidate_sequences(depth=4, switch=2)
    assert all(s[0] == s[1] and len(set(s[2:])) == 1 for s in two.tolist())
    # When the switch is at or past the horizon only constant sequences remain.
    np.testing.assert_array_equal(candidate_sequences(depth=3, switch=3)[:, 0], [IDLE, 0, 2, 3, 4])


def test_same_seed_same_decisions() -> None:
    def actions() -> list[np.ndarray]:
        vec = make_vec("merge", 2)
        out = []
        for k, rec in enumerate(rollout(vec, planner_policy(FAST), seed=123)):
            out.append(rec.actions)
            if k == 5:
                return out
        raise AssertionError

    for a, b in zip(actions(), actions(), strict=True):
        np.testing.assert_array_equal(a, b)


def test_the_adopted_action_is_the_best_valued_one() -> None:
    decisions: list[Plan] = []
    vec = make_vec("merge", 2)
    taken = []
    for k, rec in enumerate(rollout(vec, planner_policy(FAST, record=decisions.append), seed=123)):
        taken.append(rec.actions)
        if k == 5:
            break
    assert len(decisions) == len(taken) == 6
    for d, acted in zip(decisions, taken, strict=True):
        np.testing.assert_array_equal(d.actions, acted)
        assert d.values.shape == (2, 2, len(ACTION_NAMES)) and np.isfinite(d.values).all()
        best = np.take_along_axis(d.values, d.actions[..., None], axis=-1)[..., 0]
        np.testing.assert_array_equal(best, d.values.max(axis=-1))
    # Values rank the actions: somewhere a first action is worth less than the best one.
    assert any((d.values < d.values.max(axis=-1, keepdims=True)).any() for d in decisions)


def test_the_planner_completes_merges_the_rule_driver_crashes_in() -> None:
    plan = evaluate_policy(reference_policy("plan", planner=FAST), ["merge"], 8, envs=8)
    rule = evaluate_policy(reference_policy("rule"), ["merge"], 8, envs=8)
    assert sorted(o.seed for o in plan) == sorted(o.seed for o in rule)  # the same episodes
    plan_fail = sum(not (o.agent_arrived.all() and not o.agent_crashed.any()) for o in plan)
    rule_fail = sum(not (o.agent_arrived.all() and not o.agent_crashed.any()) for o in rule)
    assert plan_fail <= 2
    assert rule_fail - plan_fail >= 4


def test_the_planner_refuses_a_backend_it_cannot_branch() -> None:
    vec = make_vec("merge", 1, backend="highway")
    with pytest.raises(ConfigError, match="fast backend"):
        next(rollout(vec, planner_policy(FAST), seed=0))


@pytest.mark.parametrize("bad", [{"depth": 0}, {"rounds": 0}, {"crash_penalty": 1.0}, {"discount": 0.0},
                                 {"horizon": 3}, {"human_routes": "guess"}])
def test_bad_planner_settings_are_refused(bad: dict[str, object]) -> None:
    from latentdrive.evaluate.planner import planner_config

    with pytest.raises(ConfigError, match="planner"):
        planner_config(bad)


@pytest.mark.parametrize("overrides", [{}, {"duration": 4}])
def test_a_plan_scores_what_the_env_would_pay(overrides: dict[str, Any]) -> None:
    """With no discount, penalty or tail, a plan's score is the env's summed reward for
    the same actions: per-AV rewards, nothing after an AV finished or the episode ended,
    and nothing past the time limit (``duration=4`` cuts the 6-step horizon)."""
    from latentdrive.evaluate.planner import _scores
    from latentdrive.scenarios import RewardConfig

    cfg = PlannerConfig(depth=6, discount=1.0, crash_penalty=0.0, tail=0)
    scenarios = ["merge", "roundabout", "highway"]
    vec = make_vec(scenarios, 3, **overrides)
    vec.reset(seed=7)
    sim = vec.simulator
    assert isinstance(sim, FastBatch)
    plans = np.repeat(candidate_sequences(6, 6)[None, :, None, :], 2, axis=2)  # both AVs, constant
    plans = np.repeat(plans, 3, axis=0)  # (E, C, A, D)
    left = np.array([s.max_steps for s in sim.specs])
    scores = _scores(sim, np.arange(3), plans, left, cfg, RewardConfig())
    for c, action in enumerate(plans[0, :, 0, 0]):
        env = make_vec(scenarios, 3, **overrides)
        env.reset(seed=7)
        paid = np.zeros(3)
        over = np.zeros(3, dtype=bool)
        for _ in range(6):
            _, _, term, trunc, info = env.step(np.full((3, 2), action))
            paid += np.where(over, 0.0, info["agents"].reward.sum(axis=1))
            over |= term | trunc
        np.testing.assert_allclose(scores[:, c], paid, atol=1e-9)


def test_the_rule_reference_runs_on_a_spec_file(tmp_path) -> None:
    from pathlib import Path

    # Regression: the rule driver looked its cruise speed up by the scenario's name,
    # which only presets have.
    spec = Path(__file__).parents[2] / "docs" / "calibration" / "merge-2-ramp-hvs.yaml"
    outcomes = evaluate_policy(reference_policy("rule"), [str(spec)], 2, envs=2)
    assert [o.scenario for o in outcomes] == ["merge-2-ramp-hvs"] * 2
