"""Many environments behind gymnasium's vector-env interface, with auto-reset.

``latentdrive.make_vec("merge", 64, backend="fast")`` steps 64 merges per call;
``make_vec(["roundabout", "intersection", "merge", "exit"], 64)`` cycles the scenarios
over the 64 environments (mixed-scenario batches, for mixed training). Environment ``i``
reset with seed ``s + i`` behaves exactly like ``make_env(scenario_i).reset(seed=s + i)``
followed by the same actions, whatever the batch size: seeds are per environment, and
the backend's environments do not interact.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode
from gymnasium.vector.utils import batch_space

from latentdrive.actions import N_ACTIONS
from latentdrive.config import ConfigError
from latentdrive.env import AgentStep, Episode, make_env_config
from latentdrive.scenarios import ScenarioSpec
from latentdrive.sim import BatchBackend, make_batch

__all__ = ["DrivingVecEnv", "make_vec"]


class DrivingVecEnv(gym.vector.VectorEnv[np.ndarray, np.ndarray, np.ndarray]):
    """``num_envs`` driving environments stepped together.

    Observations ``(num_envs, n_av, 4, T, H, W)``; actions ``(num_envs, n_av)``; rewards
    ``(num_envs,)`` (each the mean over that environment's agents).

    Auto-reset follows gymnasium 1.x's same-step mode. When environment i ends, the
    returned observation is the first of its next episode, ``info`` describes that new
    episode, ``info["final_obs"][i]`` is the ended episode's last observation and
    ``info["final_info"]`` holds the ended episodes' infos as a dict of arrays (entry i
    valid where ``info["final_info"]["_<key>"][i]``; masks ``_final_obs`` /
    ``_final_info``). Like ``rewards``, ``terminations`` and ``truncations``,
    ``info["agents"]`` (an :class:`~latentdrive.env.AgentStep` of ``(num_envs, n_av)``
    arrays) describes the transition just taken, so for an ended environment it is the
    ended episode's last step; its AVs all act on the next step. ``info`` also holds
    ``agent_rewards``, ``crashed``, ``arrived`` ``(num_envs, n_av)``, ``episode_seed``,
    ``scenario`` and ``scene`` (object arrays) of the current episodes.

    ``reset(seed=s)`` gives environment i the seed ``s + i``; ``reset()`` without a seed
    continues each environment's seeded sequence (entropy only before the first seeded
    reset), as a single env does.

    Args:
        scenarios: one scenario (name or spec) per environment.
        backend: ``"fast"`` (one compiled call per step) or ``"highway"``.
        **overrides: as for :func:`latentdrive.env.make_env_config`, applied to every
            environment.
    """

    metadata: ClassVar[dict[str, Any]] = {"autoreset_mode": AutoresetMode.SAME_STEP}  # type: ignore[misc]

    def __init__(self, scenarios: Sequence[str | ScenarioSpec], backend: str = "fast", **overrides: Any) -> None:
        if not scenarios:
            raise ConfigError("make_vec needs at least one environment")
        configs = [make_env_config(s, backend=backend, **overrides) for s in scenarios]
        n_av = {c.scenario.n_av for c in configs}
        obs_cfgs = {c.observation for c in configs}
        if len(n_av) > 1 or len(obs_cfgs) > 1:
            raise ConfigError("a vector env's scenarios must share n_av and the observation config "
                              f"(got n_av {sorted(n_av)}); set them with overrides")
        self.configs = configs
        self.num_envs = len(configs)
        self.n_av = configs[0].scenario.n_av
        self.single_observation_space = gym.spaces.Box(0.0, 1.0, (self.n_av, *configs[0].observation.shape), np.float32)
        self.single_action_space = gym.spaces.MultiDiscrete(np.full(self.n_av, N_ACTIONS, dtype=np.int64))
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self._batch = make_batch([c.scenario for c in configs], backend)
        # Every environment's stacks live in one array, copied once per step.
        shape = (self.num_envs, self.n_av, *configs[0].observation.shape)
        self._obs = np.zeros(shape, dtype=np.float32)
        self._clean = np.zeros(shape, dtype=np.float32) if configs[0].clean_observation else None
        self._episodes = [Episode(c, self._obs[i], None if self._clean is None else self._clean[i])
                          for i, c in enumerate(configs)]
        self._rngs: list[np.random.Generator] | None = None
        #: Seconds spent in the simulator and in building observations (rewards included) by
        #: step() since construction; resets excluded. For benchmarks.
        self.timings = {"simulate": 0.0, "observe": 0.0}

    @property
    def simulator(self) -> BatchBackend:
        """The backend stepping these environments (read-only use: planners branch it)."""
        return self._batch

    def reset(self, *, seed: int | Sequence[int | None] | None = None,
              options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """Start every environment; ``seed`` s gives environment i the seed s + i."""
        if seed is None or isinstance(seed, int | np.integer):
            seeds: list[int | None] = [None if seed is None else int(seed) + i for i in range(self.num_envs)]
        else:
            seeds = list(seed)
            if len(seeds) != self.num_envs:
                raise ValueError(f"got {len(seeds)} seeds for {self.num_envs} environments")
        # Each environment owns the generator its episode seeds come from, seeded like
        # DrivingEnv's np_random, so environment i matches a single env seeded s + i. A
        # missing seed keeps the environment's generator, as gymnasium's Env.reset does.
        old = self._rngs
        self._rngs = [np.random.default_rng(s) if s is not None or old is None else old[i]
                      for i, s in enumerate(seeds)]
        episode_seeds = [self._next_seed(i) for i in range(self.num_envs)]
        scenes = self._batch.reset(episode_seeds)
        for ep, sc, es in zip(self._episodes, scenes, episode_seeds, strict=True):
            ep.begin(sc, es)
        results = self._observe(list(range(self.num_envs)))
        info = self._merge([info for _, info in results])
        info["agents"] = AgentStep(*(np.stack(f) for f in zip(*(i["agents"] for _, i in results), strict=True)))
        return self._obs.copy(), info

    def _observe(self, env_ids: list[int]) -> list[tuple[np.ndarray, dict[str, Any]]]:
        """Render the frames the episodes ``env_ids`` need (one batch call, noisy and, if
        asked, clean) and hand them over; each episode's ``(obs, info)``."""
        eps = [self._episodes[i] for i in env_ids]
        observing = np.zeros((len(eps), self.n_av), dtype=bool)
        for k, ep in enumerate(eps):
            observing[k] = ep.observing
        # Each environment's draws come from its own stream, as in a single env.
        noise = [ep.draw_noise(ep.scene.n_vehicles) for ep in eps]  # type: ignore[union-attr]
        cfg = self.configs[0].observation
        frames = self._batch.render(env_ids, cfg, noise, observing)
        clean = self._batch.render(env_ids, cfg, None, observing) if self.configs[0].clean_observation else None
        # The stacks are views of self._obs: read them before the next call.
        return [ep.observe(frames[k], None if clean is None else clean[k], copy=False) for k, ep in enumerate(eps)]

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        acts = np.asarray(actions)
        if acts.shape[:1] != (self.num_envs,):
            raise ValueError(f"actions must be ({self.num_envs}, {self.n_av}), got shape {acts.shape}")
        checked = [ep.check_actions(a) for ep, a in zip(self._episodes, acts, strict=True)]
        t0 = time.perf_counter()
        scenes = self._batch.step(checked)
        t1 = time.perf_counter()
        rewards, terms, truncs = zip(*(ep.account(sc) for ep, sc in zip(self._episodes, scenes, strict=True)), strict=True)
        _, infos = zip(*self._observe(list(range(self.num_envs))), strict=True)
        self.timings["simulate"] += t1 - t0
        self.timings["observe"] += time.perf_counter() - t1
        info_list = list(infos)
        agents = AgentStep(*(np.stack(f) for f in zip(*(inf["agents"] for inf in infos), strict=True)))
        done = [i for i in range(self.num_envs) if terms[i] or truncs[i]]
        final_obs = np.full(self.num_envs, None, dtype=object)
        final_info: dict[str, Any] = {}
        if done:
            seeds = [self._next_seed(i) for i in done]
            for i, scene, s in zip(done, self._batch.reset(seeds, env_ids=done), seeds, strict=True):
                final_obs[i] = self._obs[i].copy()  # before the next episode's stack replaces it
                # gymnasium's own dict-of-arrays merge, with its ``_key`` masks.
                final_info = self._add_info(final_info, info_list[i], i)
                self._episodes[i].begin(scene, s)
            for i, (_, inf) in zip(done, self._observe(done), strict=True):
                info_list[i] = inf
        info = self._merge(info_list)
        info["agents"] = agents
        mask = np.zeros(self.num_envs, dtype=bool)
        mask[done] = True
        info.update(final_obs=final_obs, _final_obs=mask, final_info=final_info, _final_info=mask.copy())
        return (self._obs.copy(), np.asarray(rewards, dtype=np.float64), np.asarray(terms, dtype=bool),
                np.asarray(truncs, dtype=bool), info)

    def _next_seed(self, i: int) -> int:
        if self._rngs is None:
            raise RuntimeError("call reset() first")
        return int(self._rngs[i].integers(2**63 - 1))

    def _merge(self, infos: list[dict[str, Any]]) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for key in ("agent_rewards", "crashed", "arrived", "episode_seed"):
            out[key] = np.stack([np.asarray(info[key]) for info in infos])
        for key in ("scenario", "scene"):
            out[key] = np.empty(self.num_envs, dtype=object)
            out[key][:] = [info[key] for info in infos]
        if "clean_observation" in infos[0]:
            out["clean_observation"] = np.stack([info["clean_observation"] for info in infos])
        return out


def make_vec(scenario: str | ScenarioSpec | Sequence[str | ScenarioSpec], num_envs: int,
             backend: str = "fast", **overrides: Any) -> DrivingVecEnv:
    """``num_envs`` environments of one scenario, or of several cycled over the batch."""
    if num_envs < 1:
        raise ConfigError(f"num_envs must be at least 1, got {num_envs}")
    names = [scenario] if isinstance(scenario, str | ScenarioSpec) else list(scenario)
    if not names:
        raise ConfigError("make_vec needs at least one scenario")
    return DrivingVecEnv([names[i % len(names)] for i in range(num_envs)], backend=backend, **overrides)
