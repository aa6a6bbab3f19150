"""The gymnasium environment: scenario spec + backend + VelocityMap observation + reward.

One env holds ``n_av`` agents that share a policy. Observations are stacked VelocityMaps
of every agent, ``(n_av, 4, T, H, W)`` float32 in [0, 1]; actions are one meta-action
index per agent (``MultiDiscrete([5] * n_av)``); the scalar reward is the mean of the
per-agent rewards.

Per-agent episodes (``info["agents"]``, an :class:`AgentStep`):

- an AV *terminates* on the step it crashes or completes its mission. Its transition of
  that step has no bootstrap; it earns nothing afterwards and stores no more transitions,
  its observation stays the last one it saw (no more frames are rendered for it), and the
  env drives it with Idle whatever action it is given;
- the *episode* ends when any AV has crashed or every AV has completed its mission
  (terminated), or when time runs out (truncated). AVs still driving then are *cut off*
  (``AgentStep.truncated``): their last transition bootstraps from the next observation,
  because nothing about their own state ended;
- ``step()`` after the episode ended raises; call ``reset()``.
"""

from __future__ import annotations

from typing import Any, ClassVar, Literal, NamedTuple

import gymnasium as gym
import numpy as np
from numpy.typing import NDArray
from pydantic import Field

from latentdrive.actions import N_ACTIONS, idle_when_done
from latentdrive.config import Config, ConfigError, ObservationConfig, merge_overrides, validate
from latentdrive.observe import FrameStack, SensorNoise, draw_noise, render_agents
from latentdrive.reward import agent_rewards, episode_end
from latentdrive.scenarios import RewardConfig, ScenarioSpec, get_spec
from latentdrive.scene import Scene
from latentdrive.sim import make_backend

__all__ = ["AgentStep", "DrivingEnv", "EnvConfig", "Episode", "EpisodeEnded", "make_env", "make_env_config",
           "resolve_config"]



class EpisodeEnded(RuntimeError):
    """``step()`` was called after the episode ended; call ``reset()`` first."""


class AgentStep(NamedTuple):
    """Per-agent account of one policy step; every field ``(n_av,)`` (vector env: ``(num_envs, n_av)``).

    ``acting`` agents chose this step's action: each has a transition. Of those, exactly one
    of ``terminated`` (crashed or completed its mission on this step, or, with a nonzero
    ``reward.failure``, was still driving when the episode ended as a failure: do not
    bootstrap), ``truncated`` (the episode ended for another reason: bootstrap from the
    next observation) and ``active`` (drives on) is true. After ``reset()``: all ``active``,
    none acting.
    """

    reward: NDArray[np.float64]
    acting: NDArray[np.bool_]
    terminated: NDArray[np.bool_]
    truncated: NDArray[np.bool_]
    active: NDArray[np.bool_]

    @classmethod
    def start(cls, n_av: int) -> AgentStep:
        """The account after a reset: nobody acted yet, everybody is active."""
        no = np.zeros(n_av, dtype=bool)
        return cls(np.zeros(n_av), no, no.copy(), no.copy(), np.ones(n_av, dtype=bool))


class EnvConfig(Config):
    """Everything that defines an environment."""

    scenario: ScenarioSpec = Field(description="The scenario to simulate.")
    observation: ObservationConfig = Field(default_factory=ObservationConfig, description="VelocityMap settings.")
    reward: RewardConfig = Field(default_factory=RewardConfig, description="Per-agent reward weights.")
    backend: Literal["highway", "fast"] = Field("highway", description="Simulator backend: 'highway' (highway-env, the reference) or 'fast' (compiled, batched, same simulation).")
    clean_observation: bool = Field(False, description="Also return the noise-free stack in info['clean_observation'] (for denoising datasets).")


_ENV_KEYS = set(EnvConfig.model_fields) - {"scenario"}


def make_env_config(scenario: str | ScenarioSpec, **overrides: Any) -> EnvConfig:
    """Resolve a scenario name (or spec) and overrides into an :class:`EnvConfig`.

    Overrides named ``observation``, ``reward``, ``backend`` or ``clean_observation`` (or
    dotted into them, ``observation.frames=2``) configure the env; every other key
    overrides a scenario field (``n_av=3``, ``duration=20``).
    """
    env_part = {k: v for k, v in overrides.items() if k.partition(".")[0] in _ENV_KEYS}
    spec_part = {k: v for k, v in overrides.items() if k.partition(".")[0] not in _ENV_KEYS}
    spec = get_spec(scenario, **spec_part)
    return validate(EnvConfig, merge_overrides({"scenario": spec}, env_part))


class Episode:
    """The bookkeeping of one environment's episode, shared by the single and vector envs.

    Turns the backend's Scenes into stacked observations, per-agent rewards, the end of
    the episode and ``info``. Backend-neutral: it only reads Scenes.
    """

    def __init__(self, config: EnvConfig, storage: np.ndarray | None = None,
                 clean_storage: np.ndarray | None = None) -> None:
        """``storage`` (and ``clean_storage``): where to keep the stacks, ``(n_av, 4, T, H,
        W)`` float32 (a vector env's rows); by default arrays of their own."""
        self.config = config
        self.spec = config.scenario
        self._stack = FrameStack(config.observation.frames, storage)
        self._clean_stack = FrameStack(config.observation.frames, clean_storage)
        self._noise_rng = np.random.default_rng(0)
        self.scene: Scene | None = None
        self.steps = 0
        self.seed = 0
        self.active: NDArray[np.bool_] = np.zeros(config.scenario.n_av, dtype=bool)
        #: ``(n_av,)`` the AVs whose frame the current step needs: all after a reset, then
        #: those that acted on the step.
        self.observing: NDArray[np.bool_] = np.zeros(config.scenario.n_av, dtype=bool)
        self.ended = False
        self._agents = AgentStep.start(config.scenario.n_av)
        self._fresh = True

    def start(self, scene: Scene, episode_seed: int) -> tuple[np.ndarray, dict[str, Any]]:
        """Begin an episode at ``scene``, the backend's reset for ``episode_seed``."""
        self.begin(scene, episode_seed)
        return self.observe(*self._render(scene))

    def begin(self, scene: Scene, episode_seed: int) -> None:
        """:meth:`start` up to its observation (give it to :meth:`observe`)."""
        self.seed, self.scene, self.steps = episode_seed, scene, 0
        self.active = np.ones(self.spec.n_av, dtype=bool)
        self.ended = False
        # Sensor noise has its own stream, derived from the episode seed.
        self._noise_rng = np.random.default_rng([episode_seed, 2])
        self._agents = AgentStep.start(self.spec.n_av)
        self.observing = np.ones(self.spec.n_av, dtype=bool)
        self._fresh = True

    def draw_noise(self, n_vehicles: int) -> SensorNoise:
        """The next frame's sensor noise, for every AV (whether observing or not, so the
        stream does not depend on who is still driving) and ``n_vehicles`` vehicles."""
        return draw_noise(self._noise_rng, self.spec.n_av, n_vehicles, self.config.observation.noise)

    def observe(self, frame: np.ndarray, clean_frame: np.ndarray | None,
                copy: bool = True) -> tuple[np.ndarray, dict[str, Any]]:
        """Stack the frames ``(n_av, 4, H, W)`` of the AVs in :attr:`observing` (the other
        rows are not read; those AVs keep their last observation) and return the
        observation and ``info`` of the current step; ``clean_frame`` is needed exactly
        when the config asks for clean observations. ``copy=False`` returns the stack
        itself, which changes on the next call."""
        if self.scene is None:
            raise RuntimeError("call reset() first")
        if (clean_frame is None) == self.config.clean_observation:
            raise ValueError("a clean frame is needed exactly when clean_observation is on")
        stacks = [(self._stack, frame)]
        if clean_frame is not None:
            stacks.append((self._clean_stack, clean_frame))
        for stack, f in stacks:
            if self._fresh:
                stack.reset(f)
            else:
                stack.push(f, rows=self.observing)
        self._fresh = False
        return self._stack.stack if copy else self._stack.view, self._info(self.scene, self._agents)

    def check_actions(self, action: np.ndarray) -> np.ndarray:
        """``action`` as ``(n_av,)`` int64 with inactive AVs set to Idle; ValueError or EpisodeEnded."""
        if self.scene is None:
            raise RuntimeError("call reset() first")
        if self.ended:
            raise EpisodeEnded("the episode has ended; call reset() before step()")
        actions = np.asarray(action, dtype=np.int64).reshape(-1)
        if actions.shape != (self.spec.n_av,) or actions.min() < 0 or actions.max() >= N_ACTIONS:
            raise ValueError(f"action must be {self.spec.n_av} integers in [0, {N_ACTIONS}), got {action!r}")
        return idle_when_done(actions, ~self.active)

    def advance(self, scene: Scene) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Account for one policy step that led to ``scene``."""
        reward, terminated, truncated = self.account(scene)
        obs, info = self.observe(*self._render(scene))
        return obs, reward, terminated, truncated, info

    def account(self, scene: Scene) -> tuple[float, bool, bool]:
        """:meth:`advance` up to its observation (give it to :meth:`observe`): the mean
        reward and whether the episode terminated or was truncated.

        The AVs that acted on this step (:attr:`observing` afterwards) get a frame: their
        transitions lead to it. AVs done on an earlier step get none.
        """
        before = self.scene
        if before is None:
            raise RuntimeError("call reset() first")
        self.scene = scene
        self.steps += 1
        ag, prev = scene.agents, before.agents
        acting = self.active
        rewards = agent_rewards(
            scene.speed[ag], scene.crashed[ag], scene.arrived[ag],  # type: ignore[index]
            before.crashed[prev], before.arrived[prev],  # type: ignore[index]
            self.spec.reward_speed_range, self.config.reward,
        )
        # A crashed or arrived AV earns nothing after its terminal step.
        rewards = np.where(acting, rewards, 0.0)
        terminated, truncated = episode_end(scene, self.steps, self.spec)
        self.ended = terminated or truncated
        own_end: NDArray[np.bool_] = acting & (scene.crashed[ag] | scene.arrived[ag])  # type: ignore[index]
        cut_off = acting & ~own_end & self.ended
        # The episode failed unless it ended because every AV arrived unharmed.
        if self.config.reward.failure != 0.0 and self.ended and (truncated or scene.crashed[ag].any()):
            # The team's failure is the end of these agents' episode too: paid and not
            # bootstrapped, so that neither a time-out nor a partner's crash is free.
            rewards = rewards + self.config.reward.failure * cut_off
            own_end, cut_off = own_end | cut_off, np.zeros_like(cut_off)
        self.active = acting & ~own_end & (not self.ended)
        self._agents = AgentStep(rewards, acting.copy(), own_end, cut_off, self.active.copy())
        self.observing = acting.copy()
        return float(rewards.mean()), terminated, truncated

    def _render(self, scene: Scene) -> tuple[np.ndarray, np.ndarray | None]:
        """The reference renderer's frames of :attr:`observing` (noisy, and clean if asked)."""
        cfg = self.config.observation
        frame = render_agents(scene, cfg, self.draw_noise(scene.n_vehicles), self.observing)
        clean = render_agents(scene, cfg, None, self.observing) if self.config.clean_observation else None
        return frame, clean

    def _info(self, scene: Scene, agents: AgentStep) -> dict[str, Any]:
        info: dict[str, Any] = {
            "scene": scene,
            "agents": agents,
            "agent_rewards": agents.reward,
            "crashed": scene.crashed[scene.agents].copy(),
            "arrived": scene.arrived[scene.agents].copy(),  # type: ignore[index]
            "scenario": self.spec.name,
            "episode_seed": self.seed,
        }
        if self.config.clean_observation:
            info["clean_observation"] = self._clean_stack.stack
        return info


def resolve_config(scenario: str | ScenarioSpec | None, config: EnvConfig | None, overrides: dict[str, Any]) -> EnvConfig:
    """The EnvConfig named by a scenario and/or a config, with overrides applied on top."""
    if config is None:
        if scenario is None:
            raise ConfigError("an env needs a scenario or a config")
        return make_env_config(scenario, **overrides)
    if overrides or scenario is not None:
        return make_env_config(scenario or config.scenario, **merge_overrides(
            {k: v for k, v in config.model_dump().items() if k != "scenario"}, overrides))
    return config


class DrivingEnv(gym.Env[np.ndarray, np.ndarray]):
    """A mixed-autonomy driving scenario as a gymnasium Env.

    Args:
        scenario: a scenario name, a spec, or None when ``config`` is given.
        config: a complete config (overrides then apply on top of it).
        **overrides: see :func:`make_env_config`.

    ``info`` after reset and step holds ``scene`` (the :class:`Scene`), ``agents`` (the
    :class:`AgentStep` of this step: per-agent reward and terminated / cut-off / active
    flags; see the module docstring), ``agent_rewards`` (``agents.reward``), ``crashed``
    and ``arrived`` ``(n_av,)`` bool, ``scenario`` and ``episode_seed``. The episode
    ``terminated`` when any AV crashed or every AV completed its mission, and is
    ``truncated`` when time ran out; ``step()`` after either raises :class:`EpisodeEnded`.
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": []}  # type: ignore[misc]

    def __init__(self, scenario: str | ScenarioSpec | None = None, config: EnvConfig | None = None, **overrides: Any) -> None:
        super().__init__()
        self.config = resolve_config(scenario, config, overrides)
        self.spec_ = self.config.scenario
        n_av = self.spec_.n_av
        self.observation_space = gym.spaces.Box(0.0, 1.0, (n_av, *self.config.observation.shape), np.float32)
        self.action_space = gym.spaces.MultiDiscrete(np.full(n_av, N_ACTIONS, dtype=np.int64))
        self._backend = make_backend(self.spec_, self.config.backend)
        self._episode = Episode(self.config)

    @property
    def scene(self) -> Scene:
        """The current Scene (after :meth:`reset`)."""
        if self._episode.scene is None:
            raise RuntimeError("call reset() first")
        return self._episode.scene

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        # Episode seeds come from the env's generator: reset(seed=s) fixes the whole
        # sequence of episodes that follows, as gymnasium specifies.
        episode_seed = int(self.np_random.integers(2**63 - 1))
        return self._episode.start(self._backend.reset(episode_seed), episode_seed)

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        actions = self._episode.check_actions(action)
        return self._episode.advance(self._backend.step(actions))


def make_env(scenario: str | ScenarioSpec, **overrides: Any) -> DrivingEnv:
    """Create the env of a scenario: ``make_env("merge", n_av=3, observation={"frames": 2})``."""
    return DrivingEnv(scenario, **overrides)
