"""Evaluating trained policies beside the reference policies, comparing two runs, drawing an episode."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch

from latentdrive.config import ConfigError
from latentdrive.evaluate.gif import save_episode_gif, save_side_by_side_gif
from latentdrive.evaluate.planner import PlannerConfig
from latentdrive.evaluate.policies import SIMULATOR_POLICIES, reference_policy
from latentdrive.evaluate.report import PolicyReport, policy_report
from latentdrive.evaluate.run import evaluate_policy
from latentdrive.fileio import atomic_write_text
from latentdrive.models.bottleneck import PAIR_CHANNELS
from latentdrive.models.vfan import QNetwork
from latentdrive.outcome import EpisodeOutcome
from latentdrive.rl.policy import greedy_policy, load_policy_network
from latentdrive.rollout import Policy, rollout
from latentdrive.scenarios import RewardConfig, ScenarioSpec, resolve_specs
from latentdrive.seeds import eval_reset_seed
from latentdrive.vec import make_vec

__all__ = [
    "EvaluationSet",
    "PlayedEpisode",
    "evaluate_many",
    "outcome_label",
    "pairs_to_channels",
    "play_episode",
    "policy_makers",
    "save_policies_gif",
    "save_policy_gif",
]


class EvaluationSet:
    """The definition of an evaluation: which episodes, on which backend."""

    def __init__(self, scenarios: Sequence[str], episodes: int, envs: int, backend: str, seed_offset: int,
                 observation: dict[str, Any] | None = None, reward: dict[str, Any] | None = None,
                 planner: PlannerConfig | None = None, specs: Mapping[str, ScenarioSpec] | None = None,
                 observations: Mapping[str, dict[str, Any]] | None = None) -> None:
        self.scenarios, self.episodes, self.envs = list(scenarios), episodes, min(envs, episodes)
        #: The spec each scenario name stands for (a run's stored copies, else the preset or
        #: spec file the name gives), resolved once so that every policy meets the same ones.
        self.specs = resolve_specs(self.scenarios, specs)
        self.backend, self.seed_offset = backend, seed_offset
        self.observation = observation or {}
        #: Policies (by name) that observe another map than ``observation``, e.g. runs
        #: trained with and without an observation option. They play the same episodes:
        #: sensor noise and traffic come from each episode's own streams, which no
        #: observation setting but the noise levels changes.
        self.observations: dict[str, dict[str, Any]] = dict(observations or {})
        #: The runs' reward weights (returns are reported under them; rates do not depend on them).
        self.reward = reward or {}
        #: Settings of the ``plan`` reference (None when it is not evaluated).
        self.planner = planner

    def as_dict(self) -> dict[str, Any]:
        return {"scenarios": self.scenarios, "episodes_per_scenario": self.episodes, "envs": self.envs,
                "backend": self.backend, "reset_seed": eval_reset_seed(self.seed_offset),
                "seed_offset": self.seed_offset,
                **({"planner": self.planner.model_dump()} if self.planner is not None else {})}

    def env_overrides(self, name: str | None = None) -> dict[str, Any]:
        """Env settings for policy ``name`` (its own observation where it has one)."""
        observation = self.observations.get(name, self.observation) if name is not None else self.observation
        return {k: v for k, v in (("observation", observation), ("reward", self.reward)) if v}

    def run(self, make_policy: Callable[[], Policy], progress: Callable[[int], None] | None = None,
            name: str | None = None) -> list[EpisodeOutcome]:
        kw = self.env_overrides(name)
        return evaluate_policy(make_policy, [self.specs[n] for n in self.scenarios], self.episodes, envs=self.envs, backend=self.backend,
                               seed_offset=self.seed_offset, progress=progress, **kw)


def policy_makers(runs: Mapping[str, str], references: Sequence[str], eval_set: EvaluationSet,
                  device: torch.device) -> dict[str, Callable[[], Policy]]:
    """Load every run (failing early, with a one-line error) and name every policy to evaluate.

    ``runs`` maps each run's name (a label, or its folder) to its folder; the result and
    ``eval_set.observations`` are keyed by those names, so no run and reference share one.
    """
    makers: dict[str, Callable[[], Policy]] = {}
    for name, run in runs.items():
        net, cfg = load_policy_network(run, device)
        if eval_set.observation and cfg.observation.model_dump() != eval_set.observations.get(name, eval_set.observation):
            raise ConfigError(f"{run}: trained on another observation config than the evaluation's")
        makers[name] = greedy_policy(net, device)
    reward = RewardConfig(**eval_set.reward)
    for name in references:
        if name in makers:
            raise ConfigError(f"{name!r} names both a run and a reference policy")
        if name in SIMULATOR_POLICIES and eval_set.backend != "fast":
            raise ConfigError(f"the {name!r} reference needs the fast backend (it branches the simulation "
                              f"state, which the {eval_set.backend} backend cannot copy cheaply)")
        makers[name] = reference_policy(name, planner=eval_set.planner, reward=reward)
    return makers


def evaluate_many(makers: dict[str, Callable[[], Policy]], eval_set: EvaluationSet,
                  progress: Callable[[int], None] | None = None,
                  ) -> tuple[dict[str, PolicyReport], dict[str, list[EpisodeOutcome]]]:
    """Reports and raw outcomes of every policy on the same episodes."""
    outcomes = {name: eval_set.run(make, progress, name) for name, make in makers.items()}
    return {name: policy_report(o) for name, o in outcomes.items()}, outcomes


def write_json(path: str | Path, data: dict[str, Any]) -> Path:
    import json

    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    return atomic_write_text(p, json.dumps(data, indent=1, allow_nan=False) + "\n")


def pairs_to_channels(pairs: torch.Tensor) -> np.ndarray:
    """Reconstructed pairs ``(3, 2, T, H, W)`` → channels ``(4, T, H, W)`` (HV, AV, RL, MV).

    AV appears in all three pairs; the mean of its three reconstructions is shown.
    """
    p = pairs.detach().cpu().numpy()
    out = np.zeros((4, *p.shape[2:]), dtype=np.float32)
    for k, (first, _) in enumerate(PAIR_CHANNELS):
        out[first] = p[k, 0]
    out[PAIR_CHANNELS[0][1]] = p[:, 1].mean(axis=0)
    return out


class PlayedEpisode(NamedTuple):
    """One episode of one environment, step by step."""

    #: The Scene after each step, and the observations ``(n_av, 4, T, H, W)`` the agents see then.
    scenes: list[Any]
    observations: list[np.ndarray]
    outcome: EpisodeOutcome
    #: The environment's observation settings (to draw the observed window).
    observation: Any


def play_episode(make_policy: Callable[[], Policy], scenario: str, eval_set: EvaluationSet, name: str | None = None,
                 episode: int = 0) -> PlayedEpisode:
    """Episode ``episode`` (0: the first) that one environment plays from the evaluation's
    reset seed, under policy ``name``. Every policy meets the same episode
    (:func:`latentdrive.rollout.rollout`)."""
    if episode < 0:
        raise ConfigError(f"the episode to draw must be 0 or more, got {episode}")
    vec = make_vec(eval_set.specs[scenario], 1, backend=eval_set.backend, **eval_set.env_overrides(name))
    scenes: list[Any] = []
    observations: list[np.ndarray] = []
    played = 0
    try:
        for rec in rollout(vec, make_policy(), seed=eval_reset_seed(eval_set.seed_offset)):
            if played == episode:
                scenes.append(rec.scenes[0])
                observations.append(rec.next_obs[0])
            if rec.ended[0]:
                if played == episode:
                    return PlayedEpisode(scenes, observations, rec.outcomes[0], vec.configs[0].observation)
                played += 1
    finally:
        vec.close()
    raise AssertionError("rollout ended")  # it never does: it drives until told to stop


def outcome_label(outcome: EpisodeOutcome) -> str:
    """How an episode ended, in a few words."""
    crashed, arrived = int(outcome.agent_crashed.sum()), int(outcome.agent_arrived.sum())
    n = len(outcome.agent_crashed)
    wreck = ", HVs crashed among themselves" if outcome.traffic_crashed else ""
    if crashed:
        return f"failed: {crashed} of {n} AVs crashed{wreck}"
    if arrived < n:
        return f"failed: time ran out ({arrived} of {n} AVs arrived{wreck})"
    return f"success: all {n} AVs arrived{wreck}"


def save_policy_gif(path: str | Path, net: QNetwork | None, make_policy: Callable[[], Policy], scenario: str,
                    eval_set: EvaluationSet, title: str, device: torch.device, episode: int = 0) -> Path:
    """One evaluation episode of ``scenario`` as a GIF, seen by agent 0; with the BNN's
    reconstruction when ``net`` has a trained encoder (latent modes)."""
    scenes, observations, outcome, cfg = play_episode(make_policy, scenario, eval_set, episode=episode)
    recon = None
    if net is not None and net.mode == "latent" and net.encoder is not None:
        with torch.no_grad():
            x = torch.from_numpy(np.stack([o[0] for o in observations])).to(device)
            pairs = net.encoder.decode(net.encoder.encode(x))
        recon = [pairs_to_channels(p) for p in pairs]
    return save_episode_gif(path, scenes, observations, cfg, agent=0, reconstructions=recon,
                            title=f"{title}, episode seed {outcome.seed}: {outcome_label(outcome)}")


def save_policies_gif(path: str | Path, makers: Mapping[str, Callable[[], Policy]], scenario: str,
                      eval_set: EvaluationSet, episode: int = 0) -> Path:
    """The same evaluation episode of ``scenario`` under every policy, side by side, each
    panel named with how the episode ended for it."""
    played = {name: play_episode(make, scenario, eval_set, name, episode) for name, make in makers.items()}
    seeds = {p.outcome.seed for p in played.values()}
    if len(seeds) != 1:  # rollout's promise, checked: the title names one episode for all
        raise AssertionError(f"the policies met different episodes (seeds {sorted(seeds)})")
    panels = [(f"{name}: {outcome_label(p.outcome)}", p.scenes, p.observation) for name, p in played.items()]
    return save_side_by_side_gif(path, panels, agent=0, title=f"{scenario}, episode seed {seeds.pop()}")
