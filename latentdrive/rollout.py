"""The one episode loop: a vector env and a policy → per-step records and episode outcomes.

Collection, evaluation and training all drive environments through :func:`rollout`. It
yields one :class:`StepRecord` per vector step, holding what a learner needs (the
observation each agent acted on, its action, reward, next observation and per-agent end
flags; for an env built with ``clean_observation=True`` also the noise-free observations,
which dataset collection records) and the :class:`~latentdrive.outcome.EpisodeOutcome`
of every episode that ended on that step. The caller decides when to stop (a transition
budget, an episode quota) by breaking out of the loop.

A policy is any callable ``policy(PolicyInput) -> actions (num_envs, n_av)`` int.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from latentdrive.env import AgentStep
from latentdrive.outcome import EpisodeOutcome, failure_cause
from latentdrive.scene import Kind, Scene
from latentdrive.sim import BatchBackend
from latentdrive.vec import DrivingVecEnv

__all__ = ["Policy", "PolicyInput", "StepRecord", "rollout", "scene_policy"]


class PolicyInput(NamedTuple):
    """What a policy sees at one vector step."""

    #: ``(num_envs, n_av, 4, T, H, W)`` float32 stacked VelocityMaps.
    obs: NDArray[np.float32]
    #: ``(num_envs,)`` object array of the current Scenes (reference policies read them).
    scenes: NDArray[np.object_]
    #: ``(num_envs, n_av)`` bool: which AVs act on this step (the others are driven Idle).
    active: NDArray[np.bool_]
    #: ``(num_envs,)`` scenario names.
    scenarios: NDArray[np.object_]
    #: The vector env's simulator, for references with privileged access (the lookahead
    #: planner branches its state); learned policies never read it.
    simulator: BatchBackend | None = None


Policy = Callable[[PolicyInput], NDArray[np.int64]]


class StepRecord(NamedTuple):
    """One vector step.

    ``agents.acting[e, a]`` marks the agents with a transition on this step:
    ``obs[e, a] --actions[e, a]--> next_obs[e, a]`` with reward ``agents.reward[e, a]``,
    bootstrapped unless ``agents.terminated[e, a]``.

    ``clean_obs`` and ``clean_next_obs`` are the noise-free counterparts of ``obs`` and
    ``next_obs`` when the env was built with ``clean_observation=True``, else None.
    """

    #: The observations the policy acted on, ``(num_envs, n_av, 4, T, H, W)``.
    obs: NDArray[np.float32]
    actions: NDArray[np.int64]
    agents: AgentStep
    #: The observation each transition leads to: the same episode's next observation,
    #: or, for an environment whose episode ended on this step, its final observation.
    next_obs: NDArray[np.float32]
    #: ``(num_envs,)`` bool: the episode ended on this step (the env auto-reset).
    ended: NDArray[np.bool_]
    #: The observations the policy sees next (new episodes where ``ended``); this is
    #: ``next_obs`` wherever ``ended`` is False.
    obs_after: NDArray[np.float32]
    #: Episodes that ended on this step, in environment order.
    outcomes: list[EpisodeOutcome]
    #: ``(num_envs,)`` the Scenes the step led to (the ended episode's last where ``ended``).
    scenes: NDArray[np.object_]
    #: The noise-free ``obs`` (env built with ``clean_observation=True``), else None.
    clean_obs: NDArray[np.float32] | None = None
    #: The noise-free ``next_obs`` (the ended episode's final one where ``ended``), else None.
    clean_next_obs: NDArray[np.float32] | None = None
    #: ``(num_envs,)`` the Scenes ``obs`` shows (those the policy acted on).
    acted_scenes: NDArray[np.object_] | None = None
    #: ``(num_envs,)`` the Scenes ``obs_after`` shows (new episodes' first where ``ended``).
    scenes_after: NDArray[np.object_] | None = None


class _Tally:
    """Running per-episode sums of every environment slot."""

    def __init__(self, num_envs: int, n_av: int) -> None:
        self.steps = np.zeros(num_envs, dtype=np.int64)
        self.returns = np.zeros((num_envs, n_av))
        self.speed_sum = np.zeros(num_envs)
        self.speed_n = np.zeros(num_envs, dtype=np.int64)
        self.crashed = np.zeros((num_envs, n_av), dtype=bool)
        self.arrived = np.zeros((num_envs, n_av), dtype=bool)
        self.traffic_crashed = np.zeros(num_envs, dtype=bool)
        self.episode_index = np.zeros(num_envs, dtype=np.int64)

    def add(self, agents: AgentStep, speeds: NDArray[np.float64], crashed: NDArray[np.bool_],
            arrived: NDArray[np.bool_], hv_crashed: NDArray[np.bool_]) -> None:
        self.steps += 1
        self.returns += agents.reward
        self.speed_sum += np.where(agents.acting, speeds, 0.0).sum(axis=1)
        self.speed_n += agents.acting.sum(axis=1)
        self.crashed |= crashed
        self.arrived |= arrived
        # An HV that crashed on the step an AV did most likely hit that AV: not a wreck
        # among the traffic.
        self.traffic_crashed |= hv_crashed & ~crashed.any(axis=1)

    def close(self, e: int, scenario: str, seed: int, cause: str) -> EpisodeOutcome:
        out = EpisodeOutcome(
            scenario=scenario, env_index=e, episode_index=int(self.episode_index[e]), seed=seed,
            steps=int(self.steps[e]), agent_crashed=self.crashed[e].copy(), agent_arrived=self.arrived[e].copy(),
            agent_return=self.returns[e].copy(),
            mean_speed=float(self.speed_sum[e] / max(int(self.speed_n[e]), 1)),
            traffic_crashed=bool(self.traffic_crashed[e]), cause=cause,
        )
        self.steps[e] = 0
        self.returns[e] = 0.0
        self.speed_sum[e] = 0.0
        self.speed_n[e] = 0
        self.crashed[e] = False
        self.arrived[e] = False
        self.traffic_crashed[e] = False
        self.episode_index[e] += 1
        return out


def _agent_values(scenes: NDArray[np.object_], field: str) -> NDArray[np.generic]:
    return np.stack([getattr(s, field)[s.agents] for s in scenes])


def _hv_crashed(scenes: NDArray[np.object_]) -> NDArray[np.bool_]:
    return np.array([bool(s.crashed[s.kind == Kind.HV].any()) for s in scenes])


def rollout(env: DrivingVecEnv, policy: Policy, seed: int | None) -> Iterator[StepRecord]:
    """Drive ``env`` with ``policy`` forever, from ``env.reset(seed=seed)``; break to stop.

    Episode ``k`` of environment slot ``i`` is the same episode (same seed, same traffic)
    whatever the policy, so two policies run from the same ``seed`` meet identical
    episodes as long as they are compared slot by slot and episode by episode.
    """
    obs, info = env.reset(seed=seed)
    clean = info.get("clean_observation")
    active = info["agents"].active
    tally = _Tally(env.num_envs, env.n_av)
    while True:
        scenes = info["scene"]
        seeds = info["episode_seed"]
        scenarios = info["scenario"]
        actions = np.asarray(policy(PolicyInput(obs, scenes, active, scenarios, env.simulator)), dtype=np.int64)
        obs_after, _, term, trunc, info = env.step(actions)
        agents: AgentStep = info["agents"]
        ended = term | trunc
        fin = info["final_info"]
        # The transition's scene is the ended episode's last one where the env reset.
        last_scenes = np.where(ended, fin["scene"], info["scene"]) if ended.any() else info["scene"]
        tally.add(agents, _agent_values(last_scenes, "speed").astype(np.float64),
                  _agent_values(last_scenes, "crashed").astype(bool),
                  _agent_values(last_scenes, "arrived").astype(bool), _hv_crashed(last_scenes))
        next_obs = obs_after
        clean_after = info.get("clean_observation")
        clean_next = clean_after
        outcomes: list[EpisodeOutcome] = []
        if ended.any():
            next_obs = obs_after.copy()
            if clean_after is not None:
                clean_next = clean_after.copy()
            for e in np.flatnonzero(ended):
                next_obs[e] = info["final_obs"][e]
                if clean_next is not None:
                    clean_next[e] = fin["clean_observation"][e]
                before = scenes[e].arrived[scenes[e].agents] if scenes[e].arrived is not None else None
                cause = failure_cause(last_scenes[e], before)
                outcomes.append(tally.close(int(e), str(scenarios[e]), int(seeds[e]), cause))
        yield StepRecord(obs, actions, agents, next_obs, ended, obs_after, outcomes, last_scenes,
                         clean, clean_next, scenes, info["scene"])
        obs, clean = obs_after, clean_after
        active = np.where(ended[:, None], True, agents.active)


def scene_policy(fn: Callable[[Scene, np.random.Generator], NDArray[np.int64]],
                 rng: np.random.Generator) -> Policy:
    """Adapt a per-Scene driver ``fn(scene, rng) -> (n_av,)`` (see :mod:`latentdrive.data.policies`)."""

    def policy(inp: PolicyInput) -> NDArray[np.int64]:
        return np.stack([fn(s, rng) for s in inp.scenes])

    return policy
