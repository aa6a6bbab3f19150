"""The per-agent reward and episode end rule shared by every scenario and backend."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from latentdrive.scenarios.spec import RewardConfig, ScenarioSpec
from latentdrive.scene import Scene

__all__ = ["agent_rewards", "episode_end"]


def episode_end(scene: Scene, steps: int, spec: ScenarioSpec) -> tuple[bool, bool]:
    """``(terminated, truncated)`` of an episode at ``scene``, after ``steps`` policy steps.

    Terminated when any AV has crashed or every AV has completed its mission; otherwise
    truncated once ``steps`` reaches the scenario's ``max_steps``. Every consumer (env,
    benchmarks, backend validation) ends episodes with this one rule.
    """
    ag = scene.agents
    assert scene.arrived is not None
    terminated = bool(scene.crashed[ag].any() or scene.arrived[ag].all())
    return terminated, (not terminated) and steps >= spec.max_steps


def agent_rewards(
    speed: NDArray[np.float64],
    crashed: NDArray[np.bool_],
    arrived: NDArray[np.bool_],
    was_crashed: NDArray[np.bool_],
    was_arrived: NDArray[np.bool_],
    speed_range: tuple[float, float],
    cfg: RewardConfig,
) -> NDArray[np.float64]:
    """Reward of each agent for one policy step (see :class:`RewardConfig` for the formula).

    Args:
        speed: ``(n_av,)`` agent speeds after the step, m/s.
        crashed, arrived: ``(n_av,)`` flags after the step.
        was_crashed, was_arrived: ``(n_av,)`` the same flags before the step; the collision
            and mission terms pay once, on the step the flag turns on.
        speed_range: ``(v_lo, v_hi)`` m/s mapped to 0 and 1 in the speed term.
    Returns:
        ``(n_av,)`` rewards.
    """
    lo, hi = speed_range
    speed_term = np.clip((np.asarray(speed, dtype=np.float64) - lo) / (hi - lo), 0.0, 1.0)
    # A crashed car is not rewarded for the speed it had when it hit something.
    speed_term = np.where(crashed, 0.0, speed_term)
    # A crash on the step of arrival fails the episode: it must not pay the mission
    # (collision + mission was +4 at the default weights, a reward for a failure).
    return (
        cfg.collision * (crashed & ~was_crashed)
        + cfg.speed * speed_term
        + cfg.mission * (arrived & ~was_arrived & ~crashed)
    )
