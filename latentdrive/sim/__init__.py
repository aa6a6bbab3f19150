"""Simulator backends. Each turns a ScenarioSpec into a running simulation whose only output
is the :class:`~latentdrive.scene.Scene`; nothing downstream imports a simulator."""

from __future__ import annotations

from typing import Protocol

import numpy as np

from latentdrive.config import ConfigError
from latentdrive.scenarios.spec import ScenarioSpec
from latentdrive.scene import Scene

__all__ = ["BACKENDS", "Backend", "make_backend"]

BACKENDS = ("highway",)


class Backend(Protocol):
    """What the env needs of a simulator."""

    spec: ScenarioSpec

    def reset(self, seed: int) -> Scene:
        """Start an episode, deterministically for ``seed``."""
        ...

    def step(self, actions: np.ndarray) -> Scene:
        """Apply one meta-action index per AV, ``(n_av,)``, and simulate one policy period."""
        ...


def make_backend(spec: ScenarioSpec, backend: str = "highway") -> Backend:
    """A backend instance for ``spec`` (imported lazily: highway-env is heavy)."""
    if backend == "highway":
        from latentdrive.sim.highway import HighwayBackend

        return HighwayBackend(spec)
    raise ConfigError(f"unknown backend {backend!r}: choose one of {', '.join(BACKENDS)}")
