"""The reference policies every evaluation table shows beside a learned one.

- ``random``: uniform meta-actions;
- ``idle``: always Idle (keep the target speed and lane);
- ``stop``: always Decelerate. It rarely crashes and never completes a mission, which is
  why the failure rate, not the crash rate, is the headline;
- ``rule``: the rule-based car follower of :func:`latentdrive.data.policies.rule_policy`,
  cruising at the scenario's top AV target speed, without lane changes;
- ``plan``: the lookahead planner of :mod:`latentdrive.evaluate.planner`, which tries
  action sequences on copies of the simulation (fast backend only). It bounds how many
  failures are avoidable: read a policy's failure rate against the planner's.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

import numpy as np
from numpy.typing import NDArray

from latentdrive.actions import IDLE, N_ACTIONS, SLOWER
from latentdrive.config import ConfigError
from latentdrive.data.policies import rule_policy
from latentdrive.evaluate.planner import PlannerConfig, planner_policy
from latentdrive.rollout import Policy, PolicyInput
from latentdrive.scenarios import RewardConfig, get_spec

__all__ = ["REFERENCE_POLICIES", "SIMULATOR_POLICIES", "check_references", "reference_policy"]

REFERENCE_POLICIES: tuple[str, ...] = ("random", "idle", "stop", "rule", "plan")
#: The references that need the fast backend (they branch its state).
SIMULATOR_POLICIES: tuple[str, ...] = ("plan",)


def _constant(action: int) -> Policy:
    def policy(inp: PolicyInput) -> NDArray[np.int64]:
        return np.full(inp.active.shape, action, dtype=np.int64)

    return policy


def _random(seed: int) -> Policy:
    rng = np.random.default_rng(seed)

    def policy(inp: PolicyInput) -> NDArray[np.int64]:
        return rng.integers(0, N_ACTIONS, size=inp.active.shape, dtype=np.int64)

    return policy


def _rule(seed: int) -> Policy:
    rng = np.random.default_rng(seed)

    def policy(inp: PolicyInput) -> NDArray[np.int64]:
        # The specs the envs run (a spec file's name is not a preset name).
        specs = inp.simulator.specs if inp.simulator is not None else [get_spec(n) for n in inp.scenarios]
        return np.stack([rule_policy(scene, rng, cruise_speed=max(spec.av_target_speeds), lane_change_prob=0.0)
                         for scene, spec in zip(inp.scenes, specs, strict=True)])

    return policy


def reference_policy(name: str, seed: int = 0, *, planner: PlannerConfig | None = None,
                     reward: RewardConfig | None = None) -> Callable[[], Policy]:
    """A factory of the named reference policy (fresh random stream per call).

    ``planner`` and ``reward`` configure ``plan`` (its settings, and the reward it plans
    under: the evaluated runs' own); the other references ignore them.
    """
    makers: dict[str, Callable[[], Policy]] = {
        "random": lambda: _random(seed),
        "idle": lambda: _constant(IDLE),
        "stop": lambda: _constant(SLOWER),
        "rule": lambda: _rule(seed),
        "plan": lambda: planner_policy(planner, reward),
    }
    check_references([name])
    return makers[name]


def check_references(names: Iterable[str]) -> None:
    """A one-line error for the first name that is not a reference policy."""
    for name in names:
        if name not in REFERENCE_POLICIES:
            raise ConfigError(f"unknown reference policy {name!r}: choose one of {', '.join(REFERENCE_POLICIES)}")
