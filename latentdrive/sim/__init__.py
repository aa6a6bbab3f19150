"""Simulator backends. Each turns a ScenarioSpec into a running simulation whose only output
is the :class:`~latentdrive.scene.Scene`; nothing downstream imports a simulator."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from latentdrive.config import ConfigError, ObservationConfig
from latentdrive.observe import SensorNoise, render_agents
from latentdrive.scenarios.spec import ScenarioSpec
from latentdrive.scene import Scene

__all__ = ["BACKENDS", "Backend", "BatchBackend", "SerialBatch", "make_backend", "make_batch"]

BACKENDS = ("highway", "fast")


class Backend(Protocol):
    """What the env needs of a simulator."""

    spec: ScenarioSpec

    def reset(self, seed: int) -> Scene:
        """Start an episode, deterministically for ``seed``."""
        ...

    def step(self, actions: np.ndarray) -> Scene:
        """Apply one meta-action index per AV, ``(n_av,)``, and simulate one policy period."""
        ...


class BatchBackend(Protocol):
    """Several environments stepped together (what the vector env needs)."""

    specs: list[ScenarioSpec]

    def reset(self, seeds: Sequence[int], env_ids: Sequence[int] | None = None) -> list[Scene]:
        """Start episodes in ``env_ids`` (all by default) from ``seeds``; their initial Scenes."""
        ...

    def step(self, actions: Sequence[np.ndarray]) -> list[Scene]:
        """One ``(n_av_i,)`` action array per environment; every environment's next Scene."""
        ...

    def render(self, env_ids: Sequence[int], cfg: ObservationConfig, noise: Sequence[SensorNoise] | None,
               observing: NDArray[np.bool_]) -> NDArray[np.float32]:
        """VelocityMap frames ``(K, A, 4, H, W)`` of the current instant of ``env_ids``: AV
        ``a`` of environment ``env_ids[k]`` where ``observing[k, a]`` (``(K, A)``, ``A``
        the largest AV count), zeros elsewhere. ``noise`` holds each environment's draws
        ``(n_av, n_veh)`` (:func:`~latentdrive.observe.draw_noise`); None renders clean."""
        ...


class SerialBatch:
    """A batch of single-environment backends stepped one after the other."""

    def __init__(self, specs: Sequence[ScenarioSpec], backend: str) -> None:
        self.specs = list(specs)
        self.envs = [make_backend(spec, backend) for spec in self.specs]
        self._scenes: list[Scene | None] = [None] * len(self.envs)

    def reset(self, seeds: Sequence[int], env_ids: Sequence[int] | None = None) -> list[Scene]:
        ids = range(len(self.envs)) if env_ids is None else env_ids
        scenes = [self.envs[i].reset(int(s)) for i, s in zip(ids, seeds, strict=True)]
        for i, scene in zip(ids, scenes, strict=True):
            self._scenes[i] = scene
        return scenes

    def step(self, actions: Sequence[np.ndarray]) -> list[Scene]:
        self._scenes = [env.step(a) for env, a in zip(self.envs, actions, strict=True)]
        return list(self._scenes)  # type: ignore[arg-type]

    def render(self, env_ids: Sequence[int], cfg: ObservationConfig, noise: Sequence[SensorNoise] | None,
               observing: NDArray[np.bool_]) -> NDArray[np.float32]:
        """As :meth:`BatchBackend.render`, with the reference renderer, one scene at a time."""
        width = max(s.n_av for s in self.specs)
        out = np.zeros((len(env_ids), width, 4, cfg.height, cfg.width), dtype=np.float32)
        for k, i in enumerate(env_ids):
            scene = self._scenes[i]
            if scene is None:
                raise RuntimeError("reset() the environments before rendering them")
            n_av = scene.n_agents
            out[k, :n_av] = render_agents(scene, cfg, None if noise is None else noise[k], observing[k, :n_av])
        return out


def make_backend(spec: ScenarioSpec, backend: str = "highway") -> Backend:
    """A backend instance for ``spec`` (imported lazily: highway-env and numba are heavy)."""
    if backend == "highway":
        from latentdrive.sim.highway import HighwayBackend

        return HighwayBackend(spec)
    if backend == "fast":
        from latentdrive.sim.fast import FastBackend

        return FastBackend(spec)
    raise ConfigError(f"unknown backend {backend!r}: choose one of {', '.join(BACKENDS)}")


def make_batch(specs: Sequence[ScenarioSpec], backend: str = "fast") -> BatchBackend:
    """Many environments of a backend: the fast backend steps them in one call."""
    if backend == "fast":
        from latentdrive.sim.fast import FastBatch

        return FastBatch(specs)
    if backend in BACKENDS:
        return SerialBatch(specs, backend)
    raise ConfigError(f"unknown backend {backend!r}: choose one of {', '.join(BACKENDS)}")
