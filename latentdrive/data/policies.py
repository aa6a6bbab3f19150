"""Behaviour policies that drive the AVs while observation datasets are collected.

A policy is a small pure function ``policy(scene, rng) -> actions`` returning one
meta-action index per AV, ``(n_av,)`` int64 in ``[0, N_ACTIONS)`` (indices into
:data:`latentdrive.actions.ACTION_NAMES`: Left, Idle, Right, Accelerate, Decelerate). It
reads only the :class:`~latentdrive.scene.Scene` and draws only from ``rng``, so an
episode's actions are reproducible from its seed.

The bottleneck network must see the states a learned policy will visit: cruising,
following, braking behind slower traffic and crashing. Uniformly random actions alone
crash early and rarely follow a leader; the rule-based driver alone never explores. The
``mixed`` behaviour picks one of them per episode.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from functools import partial
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from latentdrive.actions import FASTER, IDLE, LEFT, N_ACTIONS, RIGHT, SLOWER
from latentdrive.scene import Scene

__all__ = [
    "BEHAVIOURS",
    "Behaviour",
    "Policy",
    "episode_policy",
    "random_policy",
    "rule_policy",
]

IntArray = NDArray[np.int64]
Policy = Callable[[Scene, np.random.Generator], IntArray]
Behaviour = Literal["mixed", "random", "rule"]
BEHAVIOURS: tuple[str, ...] = ("mixed", "random", "rule")


def random_policy(scene: Scene, rng: np.random.Generator) -> IntArray:
    """Uniformly random meta-actions, ``(n_av,)`` int64."""
    return rng.integers(0, N_ACTIONS, size=scene.n_agents, dtype=np.int64)


def rule_policy(
    scene: Scene,
    rng: np.random.Generator,
    *,
    cruise_speed: float = 25.0,
    speed_tolerance: float = 1.0,
    standstill_gap: float = 8.0,
    time_headway: float = 1.5,
    cone_half_angle: float = 0.35,
    lateral_reach: float = 3.0,
    lane_change_prob: float = 0.05,
) -> IntArray:
    """A simple car-following driver, vectorized over the AVs; ``(n_av,)`` int64.

    For every AV it looks for the nearest other vehicle ahead, inside a cone of half-angle
    ``cone_half_angle`` (radians) around its heading and at most ``lateral_reach`` metres
    to either side of its heading line (the cone alone would catch cars two lanes over
    at long range). If that vehicle's bumper-to-bumper gap is below the safe distance
    ``standstill_gap + time_headway · speed`` (metres, with speed in m/s) the AV
    decelerates. Otherwise it accelerates or decelerates towards ``cruise_speed`` (m/s),
    idling within ``speed_tolerance`` m/s of it, and with probability
    ``lane_change_prob`` per step changes lane left or right at random (a lane change
    where there is no lane is a no-op in every layout).

    Args:
        scene: the current Scene; only positions, headings, speeds, lengths, the
            validity mask and the agent indices are read.
        rng: source of the random lane changes.
    """
    ag = scene.agents
    n_av = ag.shape[0]
    pos = scene.position
    heading = scene.heading[ag]
    cos_h, sin_h = np.cos(heading), np.sin(heading)
    # Every other vehicle in each AV's frame: x along its heading, y across it.
    d = pos[None, :, :] - pos[ag][:, None, :]  # (n_av, N, 2) metres
    along = d[..., 0] * cos_h[:, None] + d[..., 1] * sin_h[:, None]
    across = -d[..., 0] * sin_h[:, None] + d[..., 1] * cos_h[:, None]
    candidate = scene.mask[None, :] & (along > 0.0)
    candidate &= np.abs(across) <= np.minimum(along * np.tan(cone_half_angle), lateral_reach)
    candidate[np.arange(n_av), ag] = False  # an AV is never its own leader
    gap = along - 0.5 * (scene.length[ag][:, None] + scene.length[None, :])
    nearest_gap = np.where(candidate, gap, np.inf).min(axis=1)  # (n_av,) metres
    speed = scene.speed[ag]
    too_close = nearest_gap < standstill_gap + time_headway * np.maximum(speed, 0.0)

    actions = np.full(n_av, IDLE, dtype=np.int64)
    actions[speed < cruise_speed - speed_tolerance] = FASTER
    actions[speed > cruise_speed + speed_tolerance] = SLOWER
    # Draw for every AV on every step, so the random stream does not depend on which
    # AVs happen to be braking.
    change = rng.random(n_av) < lane_change_prob
    side = np.where(rng.random(n_av) < 0.5, LEFT, RIGHT)
    actions = np.where(change, side, actions)
    actions[too_close] = SLOWER
    return actions


def episode_policy(
    behaviour: Behaviour,
    rng: np.random.Generator,
    *,
    rule_fraction: float = 0.5,
    cruise_speeds: Sequence[float] = (25.0,),
) -> tuple[str, Policy]:
    """Choose the policy of one episode: ``(name, policy)`` with name ``"random"`` or ``"rule"``.

    ``"mixed"`` picks the rule-based driver with probability ``rule_fraction`` and the
    random policy otherwise. A rule-based episode cruises at a speed drawn uniformly from
    ``cruise_speeds`` (m/s; pass the scenario's AV target speeds), so the data holds slow
    and fast traffic alike.
    """
    if behaviour not in BEHAVIOURS:
        raise ValueError(f"unknown behaviour {behaviour!r}: choose one of {', '.join(BEHAVIOURS)}")
    if not 0.0 <= rule_fraction <= 1.0:
        raise ValueError(f"rule_fraction must be in [0, 1], got {rule_fraction}")
    # Always the same two draws, so a given seed yields the same choice and cruise speed
    # under every behaviour and rule_fraction only moves the threshold.
    u = rng.random()
    cruise = float(rng.choice(np.asarray(cruise_speeds, dtype=np.float64)))
    use_rule = behaviour == "rule" or (behaviour == "mixed" and u < rule_fraction)
    if use_rule:
        return "rule", partial(rule_policy, cruise_speed=cruise)
    return "random", random_policy
