"""The five meta-actions every scenario shares (paper section V-A)."""

from __future__ import annotations

__all__ = ["ACTION_NAMES", "FASTER", "IDLE", "LEFT", "META_ACTIONS", "N_ACTIONS", "RIGHT", "SLOWER"]

#: Human-readable names, in action-index order.
ACTION_NAMES: tuple[str, ...] = ("Left", "Idle", "Right", "Accelerate", "Decelerate")
#: The same actions in the vocabulary of highway-env's MDPVehicle. A lane change where
#: there is no lane keeps the current lane (a no-op), so all five exist in every layout.
META_ACTIONS: tuple[str, ...] = ("LANE_LEFT", "IDLE", "LANE_RIGHT", "FASTER", "SLOWER")
N_ACTIONS = len(ACTION_NAMES)
#: Action indices by name. Idle is what an AV that has finished is driven with.
LEFT, IDLE, RIGHT, FASTER, SLOWER = range(N_ACTIONS)
assert ACTION_NAMES[IDLE] == "Idle" and ACTION_NAMES[SLOWER] == "Decelerate"
