"""What one finished episode amounts to: the record evaluation and training logs share."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

__all__ = ["EpisodeOutcome"]


class EpisodeOutcome(NamedTuple):
    """One finished episode of one environment.

    ``failed`` is the paper's "crashed or failed episode": an AV crashed, or time ran out
    before every AV completed its mission. ``success`` is its complement. A policy that
    always brakes rarely crashes but always fails, so the failure rate is the headline.
    """

    scenario: str
    #: Index of the environment slot in its vector env, and of the episode within that slot.
    env_index: int
    episode_index: int
    #: The episode seed the backend was reset with.
    seed: int
    #: Policy steps the episode lasted.
    steps: int
    #: ``(n_av,)`` bool: which AVs crashed, which completed their mission.
    agent_crashed: NDArray[np.bool_]
    agent_arrived: NDArray[np.bool_]
    #: ``(n_av,)`` undiscounted sum of each AV's rewards.
    agent_return: NDArray[np.float64]
    #: Mean AV speed over the agent-steps in which an AV was acting, m/s.
    mean_speed: float
    #: Human drivers crashed among themselves (or into the road's obstacles) while no AV
    #: had crashed. A wreck can block a lane for good: a failure no AV could avoid.
    traffic_crashed: bool = False

    @property
    def crashed(self) -> bool:
        """Any AV crashed."""
        return bool(self.agent_crashed.any())

    @property
    def success(self) -> bool:
        """Every AV completed its mission and none crashed."""
        return bool(self.agent_arrived.all() and not self.agent_crashed.any())

    @property
    def failed(self) -> bool:
        """Crashed, or time ran out before every AV completed its mission."""
        return not self.success

    @property
    def timed_out(self) -> bool:
        """Failed without a crash: the mission was not completed in time."""
        return self.failed and not self.crashed
