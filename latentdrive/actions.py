"""The five meta-actions every scenario shares (paper section V-A)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = ["ACTION_NAMES", "FASTER", "IDLE", "LEFT", "META_ACTIONS", "N_ACTIONS", "RIGHT", "SLOWER", "idle_when_done"]

#: Human-readable names, in action-index order.
ACTION_NAMES: tuple[str, ...] = ("Left", "Idle", "Right", "Accelerate", "Decelerate")
#: The same actions in the vocabulary of highway-env's MDPVehicle. A lane change where
#: there is no lane keeps the current lane (a no-op), so all five exist in every layout.
META_ACTIONS: tuple[str, ...] = ("LANE_LEFT", "IDLE", "LANE_RIGHT", "FASTER", "SLOWER")
N_ACTIONS = len(ACTION_NAMES)
#: Action indices by name. Idle is what an AV that has finished is driven with.
LEFT, IDLE, RIGHT, FASTER, SLOWER = range(N_ACTIONS)
assert ACTION_NAMES[IDLE] == "Idle" and ACTION_NAMES[SLOWER] == "Decelerate"


def idle_when_done(actions: NDArray[np.integer], done: NDArray[np.bool_]) -> NDArray[np.int64]:
    """``actions`` with Idle wherever ``done`` (same shape, e.g. ``(n_av,)`` or ``(n_env, n_av)``).

    An AV that has crashed or completed its mission is driven with Idle whatever it is
    told, so that what a policy says to a finished AV cannot change the simulation. The
    env and the planner's simulation branches both apply this one rule.
    """
    return np.where(done, IDLE, actions).astype(np.int64)
