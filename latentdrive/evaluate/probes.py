"""Linear probes on frozen features: what a linear read-out recovers from each representation.

The VFAN can be fed the raw stacked VelocityMap, the frozen BNN's latents, or the latents
of the same encoder with random weights (:mod:`latentdrive.models.vfan`). A probe asks of
each representation how much driving-relevant information (the targets of
:mod:`latentdrive.evaluate.probe_targets`: gap and relative speed to the vehicle ahead,
free adjacent lanes, distance to the goal) a *linear* function of it recovers on episodes
it was not fitted on (:mod:`latentdrive.evaluate.probe_fit`).

1. :func:`collect_probe_data` drives reference policies through the one episode loop
   (:func:`latentdrive.rollout.rollout`) on the fast backend, from reset seeds no training
   or evaluation run uses (:func:`latentdrive.seeds.probe_reset_seed`), and records every
   active AV's observation with the targets at the instant it observed;
2. :func:`probe_features` turns observations into each representation, through
   :meth:`QNetwork.features <latentdrive.models.vfan.QNetwork.features>`, the VFAN's own
   definition of what it is fed;
3. :func:`fit_probes` fits and scores the probes; :func:`run_probes` runs all three steps
   from a :class:`ProbeConfig` and returns a JSON-safe summary.

A high score says the information is linearly available, not that the policy uses it; a
low one says a linear read-out misses it, not that the features lack it (a nonlinear one
may find it).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Literal, NamedTuple, cast

import numpy as np
import torch
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, ValidationError, field_validator

from latentdrive.bnn.checkpoint import CheckpointError
from latentdrive.bnn.resume import CHECKPOINT_NAME, saved_configs
from latentdrive.bnn.train import load_trained_bottleneck
from latentdrive.config import (
    Config,
    ConfigError,
    ObservationConfig,
    describe_validation_error,
    validate,
)
from latentdrive.evaluate.policies import reference_policy
from latentdrive.evaluate.probe_fit import ProbeScore, fit_probes, split_by_episode
from latentdrive.evaluate.probe_targets import (
    BOOLEAN_TARGETS,
    TARGETS,
    forward_range,
    scene_targets,
)
from latentdrive.evaluate.run import quotas
from latentdrive.fileio import MAX_JSON_BYTES, read_json
from latentdrive.models.bottleneck import BottleneckConfig, BottleneckNetwork
from latentdrive.models.vfan import Mode, QNetwork, VFANConfig
from latentdrive.rollout import Policy, PolicyInput, rollout
from latentdrive.runtime import resolve_device
from latentdrive.scenarios import SCENARIOS, ScenarioSpec, check_scenario_names
from latentdrive.seeds import MAX_ENVS, PROBE_SETS, probe_reset_seed
from latentdrive.sim.fast import FastBatch
from latentdrive.sim.fast.network import Network, get_network
from latentdrive.vec import make_vec

__all__ = [
    "PROBE_KINDS",
    "RANDOM_ENCODER_SEED",
    "ProbeConfig",
    "ProbeData",
    "ProbeScore",
    "collect_probe_data",
    "fit_probes",
    "probe_features",
    "read_probe_results",
    "run_probes",
    "split_by_episode",
]

PROBE_KINDS: tuple[str, ...] = ("raw", "latent", "latent-random")
#: Seed of the untrained encoder's weights in kind ``latent-random``.
RANDOM_ENCODER_SEED = 0


class ProbeData(NamedTuple):
    """One sample per active AV per policy step."""

    #: ``(n, 4, T, H, W)`` float32: the stacked VelocityMap the AV acted on.
    obs: NDArray[np.float32]
    #: ``{target: (n,)}`` in :data:`~latentdrive.evaluate.probe_targets.TARGETS` order:
    #: float64 metres or m/s (``goal_distance`` NaN where no goal is reachable), bool flags.
    targets: dict[str, NDArray[np.generic]]
    #: ``(n,)`` scenario name of each sample.
    scenario: NDArray[np.object_]
    #: ``(n,)`` episode id, unique across scenarios: splits keep episodes whole.
    episode: NDArray[np.int64]


#: Per environment of one decision: the active agents and their targets.
StepTargets = list[tuple[NDArray[np.int64], dict[str, NDArray[np.generic]]]]


def _step_targets(inp: PolicyInput, net: Network, spec: ScenarioSpec, reach: float) -> StepTargets:
    """Per environment: the active agents and their targets at this decision."""
    sim = inp.simulator
    if not isinstance(sim, FastBatch):
        raise TypeError("probe targets read the fast backend's lanes: collect with backend='fast'")
    out = []
    for e, scene in enumerate(inp.scenes):
        agents = np.flatnonzero(inp.active[e]).astype(np.int64)
        keys = sim.lane_keys(e)[: scene.n_agents]
        lanes = [net.lane(key) for key in keys]
        out.append((agents, scene_targets(scene, net, lanes, sim.goal_nodes(e), spec.goal.longitudinal, reach, agents)))
    return out


def _recording(act: Policy, net: Network, spec: ScenarioSpec, reach: float) -> tuple[Policy, list[StepTargets]]:
    """``act``, noting every decision's targets in the list returned beside it."""
    pending: list[StepTargets] = []

    def policy(inp: PolicyInput) -> NDArray[np.int64]:
        # Targets are read at the decision, when the simulator is at the observed instant.
        pending.append(_step_targets(inp, net, spec, reach))
        return act(inp)

    return policy, pending


def collect_probe_data(scenarios: Sequence[str], episodes: int, seed: int, observation: ObservationConfig | None = None,
                       policy: str = "rule", envs: int = 8) -> ProbeData:
    """Observations and targets of every active AV at every step of ``episodes`` episodes
    per scenario, driven by the reference ``policy``.

    Each scenario runs in a vector env of ``min(envs, episodes)`` environments reset with
    :func:`latentdrive.seeds.probe_reset_seed` ``(seed)``; slot ``i`` contributes its first
    episodes (the quotas of :func:`latentdrive.evaluate.run.quotas`), so the data set is
    fixed by ``(scenarios, episodes, seed, observation, policy, envs)``.
    """
    if episodes < 1:
        raise ValueError(f"episodes must be at least 1, got {episodes}")
    obs_cfg = observation if observation is not None else ObservationConfig()
    reach = forward_range(obs_cfg)
    reset = probe_reset_seed(seed)
    obs: list[NDArray[np.float32]] = []
    targets: dict[str, list[NDArray[np.generic]]] = {t: [] for t in TARGETS}
    names: list[str] = []
    ids: list[NDArray[np.int64]] = []
    first_id = 0
    for name in scenarios:
        k = max(1, min(envs, episodes))
        want = np.asarray(quotas(episodes, k))
        vec = make_vec(name, k, backend="fast", observation=obs_cfg.model_dump())
        spec = vec.configs[0].scenario
        net = get_network(spec.layout, spec.lanes_count)
        recording, pending = _recording(reference_policy(policy, seed)(), net, spec, reach)
        slot_start = first_id + np.concatenate([[0], np.cumsum(want)[:-1]])
        done = np.zeros(k, dtype=np.int64)
        for rec in rollout(vec, recording, seed=reset):
            for e, (agents, tg) in enumerate(pending.pop()):
                if done[e] >= want[e] or agents.size == 0:
                    continue
                obs.append(rec.obs[e, agents].copy())
                for t in TARGETS:
                    targets[t].append(tg[t])
                names += [name] * agents.size
                ids.append(np.full(agents.size, slot_start[e] + done[e], dtype=np.int64))
            done += rec.ended
            if (done >= want).all():
                break
        vec.close()
        first_id += int(want.sum())
    shape = (0, *obs_cfg.shape)
    return ProbeData(
        obs=np.concatenate(obs) if obs else np.zeros(shape, dtype=np.float32),
        targets={t: np.concatenate(v) if v else np.zeros(0, dtype=bool if t in BOOLEAN_TARGETS else np.float64)
                 for t, v in targets.items()},
        scenario=np.asarray(names, dtype=object),
        episode=np.concatenate(ids) if ids else np.zeros(0, dtype=np.int64),
    )


def _encoder_config(bnn_run: str | Path) -> BottleneckConfig:
    """The architecture saved in a BNN run's checkpoint."""
    saved = saved_configs(Path(bnn_run))
    if saved is None or not isinstance(saved, dict) or "model" not in saved:
        raise CheckpointError(f"{Path(bnn_run) / CHECKPOINT_NAME}: no BNN checkpoint with a model config")
    return validate(BottleneckConfig, saved["model"])


def _encoder(kind: str, shape: tuple[int, int, int, int], bnn_run: str | Path | None,
             seed: int) -> BottleneckNetwork | None:
    """The frozen encoder of ``kind`` (None for ``raw``), checked against ``shape``."""
    if kind == "raw":
        return None
    if kind == "latent":
        if bnn_run is None:
            raise ConfigError("probe kind 'latent' needs a trained BNN run")
        encoder = load_trained_bottleneck(bnn_run)
    elif kind == "latent-random":
        cfg = _encoder_config(bnn_run) if bnn_run is not None else BottleneckConfig(input_shape=shape[1:])
        with torch.random.fork_rng(devices=[]):
            # Fixed weights, and the caller's random stream untouched.
            torch.manual_seed(seed)
            encoder = BottleneckNetwork(cfg)
    else:
        raise ConfigError(f"unknown probe kind {kind!r}: choose one of {', '.join(PROBE_KINDS)}")
    if encoder.cfg.observation_shape != shape:
        raise ConfigError(f"the BNN takes observations {encoder.cfg.observation_shape} but the probe data has {shape}")
    return encoder


def _network(kind: str, shape: tuple[int, int, int, int], bnn_run: str | Path | None, seed: int) -> QNetwork:
    encoder = _encoder(kind, shape, bnn_run, seed)
    with torch.random.fork_rng(devices=[]):
        # The VFAN body is built (and randomly initialized) beside the encoder; only its
        # feature map is used here.
        return QNetwork(VFANConfig(), cast(Mode, kind), shape, encoder).eval()


def probe_features(kind: str, obs: NDArray[np.floating], bnn_run: str | Path | None = None, device: str = "cpu",
                   batch_size: int = 256, seed: int = RANDOM_ENCODER_SEED) -> NDArray[np.float32]:
    """The representation of kind ``kind`` of observations ``(n, 4, T, H, W)``, flattened.

    - ``raw``: the stacked VelocityMap itself, ``F = 4·T·H·W``;
    - ``latent``: the frozen encoder of the BNN run ``bnn_run`` (loaded as policy training
      loads it), ``F = 3·d``;
    - ``latent-random``: the same architecture (``bnn_run``'s when given, else the default
      for the observation) with untrained weights drawn from ``seed``, ``F = 3·d``.

    Returns:
        ``(n, F)`` float32.
    """
    x = np.ascontiguousarray(obs, dtype=np.float32)
    if x.ndim != 5 or x.shape[1] != 4:
        raise ValueError(f"observations must be (n, 4, T, H, W), got {x.shape}")
    shape = (4, int(x.shape[2]), int(x.shape[3]), int(x.shape[4]))
    dev = resolve_device(device)
    net = _network(kind, shape, bnn_run, seed).to(dev)
    parts = [net.features(torch.from_numpy(x[i:i + batch_size]).to(dev)).reshape(min(batch_size, len(x) - i), -1)
             .cpu().numpy().astype(np.float32, copy=True) for i in range(0, len(x), batch_size)]
    width = int(np.prod(net.stored_shape))
    return np.concatenate(parts) if parts else np.zeros((0, width), dtype=np.float32)


class ProbeConfig(Config):
    """The data linear probes are fitted and scored on (:func:`run_probes`)."""

    scenarios: tuple[str, ...] = Field(SCENARIOS, min_length=1, description="Scenarios to collect probe data on; their samples are pooled, as the BNN's training data is.")
    episodes: int = Field(20, ge=2, le=100_000, description="Episodes collected per scenario (each gives one sample per active AV per policy step).")
    test_fraction: float = Field(0.25, gt=0.0, lt=1.0, description="Share of each scenario's episodes held out to score the probes; whole episodes, never single samples.")
    seed: int = Field(0, ge=0, lt=PROBE_SETS, description="Probe data set: the environments' reset seeds (a range no training or evaluation run uses) and the episode split.")
    observation: ObservationConfig = Field(default_factory=ObservationConfig, description="VelocityMap settings; must match the BNN's input.")
    policy: Literal["random", "idle", "stop", "rule", "plan"] = Field("rule", description="Reference policy that drives the AVs while data is collected.")
    envs: int = Field(8, ge=1, le=MAX_ENVS, description="Environments stepped together per scenario; part of the data set's definition.")

    @field_validator("scenarios")
    @classmethod
    def _known(cls, v: tuple[str, ...]) -> tuple[str, ...]:
        return check_scenario_names(v)


def _finite(x: float) -> float | None:
    return None if math.isnan(x) else float(x)


def run_probes(cfg: ProbeConfig, kinds: Sequence[str], bnn_run: str | Path | None = None,
               device: str = "cpu") -> dict[str, Any]:
    """Collect probe data, fit every kind's probes, score them on held-out episodes.

    Returns:
        ``{kind: {target: {"metric", "value", "baseline", "penalty", "n_train", "n_test"}},
        "samples": {"train", "test", "train_episodes", "test_episodes"}}``: plain JSON
        types; an unscorable value (a target constant on the test split) is None.
    """
    kinds = tuple(kinds)
    for kind in kinds:
        if kind not in PROBE_KINDS:
            raise ConfigError(f"unknown probe kind {kind!r}: choose one of {', '.join(PROBE_KINDS)}")
        # Refuse a missing or mismatched BNN before spending time on the data.
        _encoder(kind, cfg.observation.shape, bnn_run, RANDOM_ENCODER_SEED)
    data = collect_probe_data(cfg.scenarios, cfg.episodes, cfg.seed, cfg.observation, cfg.policy, cfg.envs)
    test = split_by_episode(data.episode, data.scenario, cfg.test_fraction, cfg.seed)
    train = ~test
    out: dict[str, Any] = {}
    for kind in kinds:
        x = probe_features(kind, data.obs, bnn_run, device)
        scores = fit_probes(x[train], {t: v[train] for t, v in data.targets.items()},
                            x[test], {t: v[test] for t, v in data.targets.items()}, groups=data.episode[train])
        out[kind] = {t: {"metric": s.metric, "value": _finite(s.value), "baseline": _finite(s.baseline),
                         "penalty": float(s.penalty), "n_train": int(s.n_train), "n_test": int(s.n_test)}
                     for t, s in scores.items()}
    out["samples"] = {"train": int(train.sum()), "test": int(test.sum()),
                      "train_episodes": int(np.unique(data.episode[train]).size),
                      "test_episodes": int(np.unique(data.episode[test]).size)}
    return out


class _Loose(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)


class _ScoreShape(_Loose):
    """One target's entry of :func:`run_probes`'s result (further keys allowed)."""

    metric: str
    value: float | None
    baseline: float | None


class _SamplesShape(_Loose):
    """The ``samples`` entry of :func:`run_probes`'s result (further keys allowed)."""

    train: int
    test: int


def _checked(path: Path, data: Any, shape: Any, what: str) -> None:
    try:
        TypeAdapter(shape).validate_python(data)
    except ValidationError as exc:
        raise ConfigError(f"{path}: not a {what} ({describe_validation_error(exc, first=True)})") from None


def read_probe_results(path: Path) -> dict[str, Any]:
    """What :func:`run_probes` returned, as a study step saved it (JSON at ``path``), checked
    against the shape it writes: a damaged file is a one-line :class:`ConfigError` naming it."""
    data = read_json(path, limit=MAX_JSON_BYTES, what="probe results", error=ConfigError)
    _checked(path, data, dict[str, Any], "probe result")
    _checked(path, data.get("samples"), _SamplesShape, "probe result (samples)")
    _checked(path, {k: v for k, v in data.items() if k != "samples"}, dict[str, dict[str, _ScoreShape]], "probe result")
    out: dict[str, Any] = data
    return out
