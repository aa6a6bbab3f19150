"""``FastBackend``: the fast simulator behind the one-environment Backend protocol."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from latentdrive.scenarios.spec import ScenarioSpec
from latentdrive.scene import Scene
from latentdrive.sim.fast.batch import FastBatch

__all__ = ["FastBackend"]


class FastBackend:
    """One scenario on the fast simulator, reported as a :class:`Scene` per instant.

    The same simulation as a row of :class:`FastBatch`; use the batch directly to step
    many environments per call.

    Args:
        spec: the scenario.
    """

    name = "fast"

    def __init__(self, spec: ScenarioSpec) -> None:
        self.spec = spec
        self.batch = FastBatch([spec])

    def reset(self, seed: int) -> Scene:
        """Place every vehicle, deterministically for ``seed``."""
        return self.batch.reset([seed])[0]

    def step(self, actions: NDArray[np.integer]) -> Scene:
        """Apply one meta-action per AV, ``(n_av,)``, then simulate one policy period."""
        return self.batch.step([np.asarray(actions).reshape(-1)])[0]

    def lane_keys(self) -> list[tuple[str, str, int]]:
        """highway-env lane index ``(from, to, id)`` of each vehicle (Scene order)."""
        return self.batch.lane_keys(0)
