"""Building a Q-network for a run, acting with it, and loading a trained one.

A policy run directory holds ``config.json`` (the resolved :class:`PolicyTrainConfig` with
the spec of every scenario it trains on, the encoder's architecture and the parameter
counts) and ``checkpoint.safetensors``, whose model tensors include the encoder: a run is
self-contained once trained, and evaluates and resumes wherever its folder lies.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from numpy.typing import NDArray

from latentdrive.actions import N_ACTIONS
from latentdrive.bnn.checkpoint import CheckpointError, load_checkpoint, read_checkpoint, section
from latentdrive.bnn.resume import changed_fields
from latentdrive.bnn.train import load_trained_bottleneck
from latentdrive.config import ConfigError, config_hash, validate
from latentdrive.fileio import read_json
from latentdrive.models.bottleneck import BottleneckConfig, BottleneckNetwork
from latentdrive.models.vfan import QNetwork
from latentdrive.rl.config import PolicyTrainConfig
from latentdrive.rollout import Policy, PolicyInput
from latentdrive.runtime import autocast
from latentdrive.scenarios import ScenarioSpec, get_spec

__all__ = [
    "CHECKPOINT",
    "CONFIG",
    "FeatureCache",
    "build_network",
    "changed_scenarios",
    "encoder_config",
    "greedy_actions",
    "greedy_policy",
    "load_policy_network",
    "read_run_config",
    "scenario_hashes",
]

CHECKPOINT = "checkpoint.safetensors"
CONFIG = "config.json"


def encoder_config(cfg: PolicyTrainConfig) -> BottleneckConfig | None:
    """The encoder architecture a run uses (None in raw mode)."""
    if cfg.mode == "raw":
        return None
    if cfg.bnn:
        ckpt = Path(cfg.bnn) / CHECKPOINT
        if not ckpt.exists():
            raise ConfigError(f"--bnn {cfg.bnn}: no BNN checkpoint there ({ckpt} is missing)")
        saved = read_checkpoint(ckpt)[1]["config"]
        if not isinstance(saved, dict) or "model" not in saved:
            raise CheckpointError(f"{ckpt}: not a BNN checkpoint (no model config)")
        enc = validate(BottleneckConfig, saved["model"])
        if cfg.mode == "latent" and isinstance(saved.get("observation"), dict):
            _check_bnn_maps(cfg, saved["observation"])
    else:
        enc = BottleneckConfig.for_observation(cfg.observation)
    want = cfg.observation.shape
    if enc.observation_shape != want:
        raise ConfigError(f"the BNN takes observations {enc.observation_shape} but the env gives {want}: "
                          "train-policy --set observation.KEY=VALUE to match it, or another BNN")
    return enc


def _check_bnn_maps(cfg: PolicyTrainConfig, drawn: dict[str, Any]) -> None:
    """Refuse a frozen encoder whose training maps were drawn otherwise than this run's.

    The shape check alone passes a BNN trained without the route (``observation.route``)
    for a run that draws it, or with other eq. 13 coefficients: the same tensor, other
    content, which the frozen code was never trained on. The noise may differ (a policy
    can be tested on noisier sensors than its encoder saw); every other field must match.
    A BNN run that predates this record (no ``observation`` in its config) is checked by
    shape only.
    """
    # A field the record lacks counts as its default; one this version lacks is not compared.
    changed = changed_fields(drawn, cfg.observation, ignore=frozenset({"noise"}))
    if changed:
        raise ConfigError(f"--bnn {cfg.bnn}: its maps were drawn with other observation settings than this "
                          f"run's (the BNN's → this run's): observation.{', observation.'.join(changed)}; "
                          "set observation.KEY=VALUE to match them, or use another BNN")


def build_network(cfg: PolicyTrainConfig, encoder_cfg: BottleneckConfig | None,
                  load_bnn_weights: bool = True) -> QNetwork:
    """A freshly initialized network for ``cfg`` (seeded), with the BNN's trained weights in
    mode ``latent`` when ``load_bnn_weights``."""
    torch.manual_seed(cfg.seed)
    encoder: BottleneckNetwork | None = None
    if encoder_cfg is not None:
        if cfg.mode == "latent" and load_bnn_weights:
            assert cfg.bnn is not None
            encoder = load_trained_bottleneck(cfg.bnn)
        else:
            encoder = BottleneckNetwork(encoder_cfg)
    return QNetwork(cfg.vfan, cfg.mode, cfg.observation.shape, encoder, dueling=cfg.dqn.dueling,
                    geometry=(cfg.observation.resolution, cfg.observation.behind))


class FeatureCache:
    """What replay stores for the latest observations, computed once.

    Latent modes encode each observation with the frozen encoder once, and the objects
    reader finds its vehicles once (``QNetwork.stores_features``); the learner and the
    acting policy both read the cached result for the same array. Callers say which
    agents they need: an AV that has finished its mission or crashed stays in the arrays
    until its episode ends, and its observations need no encoding (its rows hold zeros
    until some caller needs them).
    """

    def __init__(self, net: QNetwork, device: torch.device, dtype: torch.dtype = torch.float32) -> None:
        self.net, self.device, self.dtype = net, device, dtype
        self._key: NDArray[np.float32] | None = None
        self._value: torch.Tensor | None = None
        self._have: NDArray[np.bool_] | None = None
        self.seconds = 0.0  # wall time spent computing features (for the benchmark)

    def __call__(self, obs: NDArray[np.float32], need: NDArray[np.bool_] | None = None) -> torch.Tensor:
        """Features ``(num_envs, n_av, *stored_shape)`` of ``obs`` ``(num_envs, n_av, 4, T, H, W)``,
        exact wherever ``need`` ``(num_envs, n_av)`` is True (everywhere when None)."""
        if not self.net.stores_features:
            # Raw observations are their own features: no copy on the acting path.
            return torch.from_numpy(obs).to(self.device)
        lead = obs.shape[:2]
        if obs is not self._key:
            self._key, self._have = obs, np.zeros(lead, dtype=bool)
            self._value = torch.zeros(*lead, *self.net.stored_shape, device=self.device)
        assert self._value is not None and self._have is not None
        missing = ~self._have if need is None else need & ~self._have
        if missing.any():
            t0 = time.perf_counter()
            ei, ai = np.nonzero(missing)
            self._value[ei, ai] = self._features(obs[ei, ai])
            self._have |= missing
            self.seconds += time.perf_counter() - t0
        return self._value

    def encode(self, obs: NDArray[np.float32]) -> torch.Tensor:
        """Features of observations ``(k, 4, T, H, W)`` outside the cache."""
        t0 = time.perf_counter()
        out = self._features(obs)
        self.seconds += time.perf_counter() - t0
        return out

    def _features(self, obs: NDArray[np.float32]) -> torch.Tensor:
        """The network's features of ``obs`` in the cache's precision, returned as fp32."""
        with autocast(self.dtype, self.device):
            return self.net.features(torch.from_numpy(obs).to(self.device)).float()


def q_values(net: QNetwork, feats: torch.Tensor, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Q-values ``(num_envs, n_av, n_actions)`` fp32 of features ``(num_envs, n_av, ...)``,
    computed in ``dtype`` (bf16 autocast or fp32)."""
    with torch.no_grad(), autocast(dtype, feats.device):
        flat = feats.reshape(-1, *feats.shape[2:])
        return net(flat).float().reshape(*feats.shape[:2], -1)


def greedy_actions(net: QNetwork, cache: FeatureCache, inp: PolicyInput) -> NDArray[np.int64]:
    """The network's greedy actions ``(num_envs, n_av)`` on ``inp``, features from ``cache``
    (exact for the active AVs)."""
    return q_values(net, cache(inp.obs, inp.active), cache.dtype).argmax(dim=-1).cpu().numpy().astype(np.int64)


def epsilon_greedy(net: QNetwork, cache: FeatureCache, rng: np.random.Generator,
                   eps: Callable[[], float], guide: Policy | None = None, guide_share: float = 0.0) -> Policy:
    """ε-greedy over the cached features. Draws the same random numbers every step,
    whoever is active, so the stream does not depend on the episodes' course.

    With a ``guide`` (a reference policy), each exploratory action is the guide's with
    probability ``guide_share``, else uniform. One-step Q-learning is off-policy: the greedy
    policy's values are learned from whatever behaviour filled the replay, so a guide
    changes which states are visited. n-step returns (``n_step`` > 1) carry no off-policy
    correction: their rewards follow the behaviour's later actions, the guide's among them.
    Without a guide no extra numbers are drawn, so runs configured before the option keep
    their stream."""

    def policy(inp: PolicyInput) -> NDArray[np.int64]:
        greedy = greedy_actions(net, cache, inp)
        explore = rng.random(greedy.shape) < eps()
        random = rng.integers(0, N_ACTIONS, size=greedy.shape)
        if guide is not None:
            guided = rng.random(greedy.shape) < guide_share
            # The guide is asked only on steps where some agent takes its action: late in
            # training few do, and the rule driver reads every scene.
            if (explore & guided).any():
                random = np.where(guided, np.asarray(guide(inp), dtype=np.int64), random)
        return np.where(explore, random, greedy).astype(np.int64)

    return policy


def greedy_policy(net: QNetwork, device: torch.device, dtype: torch.dtype = torch.float32) -> Callable[[], Policy]:
    """A factory of the network's greedy policy (for evaluation), computed in ``dtype``."""

    def make() -> Policy:
        cache = FeatureCache(net, device, dtype)

        def policy(inp: PolicyInput) -> NDArray[np.int64]:
            return greedy_actions(net, cache, inp)

        return policy

    return make


def read_run_config(run_dir: str | Path) -> dict[str, Any]:
    """A policy run's config.json, or a one-line error when it is not a policy run.

    Its ``train`` section is validated (and completed with the defaults of fields it
    predates), so callers may index it without meeting a hand-edited or damaged file's
    missing keys. A run that predates stored scenario specs gets today's, and
    ``specs_stored`` False.
    """
    path = Path(run_dir) / CONFIG
    try:
        data = read_json(path, what="run config", error=ConfigError)
    except FileNotFoundError:
        raise ConfigError(f"{run_dir}: not a policy run (no {CONFIG})") from None
    if not isinstance(data, dict) or data.get("kind") != "policy" or not isinstance(data.get("train"), dict):
        raise ConfigError(f"{path}: not a policy run's config")
    try:
        train = validate(PolicyTrainConfig, data["train"])
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None
    return {**data, "train": train.model_dump(mode="json"), "specs_stored": "specs" in data["train"]}


def scenario_hashes(scenarios: Sequence[str] | dict[str, ScenarioSpec]) -> dict[str, str]:
    """The hash of each scenario's spec: of the given specs, or of today's spec of each name."""
    specs = scenarios if isinstance(scenarios, dict) else {name: get_spec(name) for name in scenarios}
    return {name: config_hash(spec) for name, spec in specs.items()}


def changed_scenarios(run_config: dict[str, Any]) -> list[str]:
    """The training scenarios of a run (its config.json, as :func:`read_run_config` gives
    it) whose spec changed since it was trained. Empty for a run that stores its specs (it
    trains and evaluates on those) and for one that predates the record of their hashes."""
    old = run_config.get("scenario_hashes")
    if run_config.get("specs_stored", True) or not isinstance(old, dict):
        return []
    now = scenario_hashes(run_config["train"]["scenarios"])
    return sorted(n for n, h in now.items() if old.get(n) != h)


def load_policy_network(run_dir: str | Path, device: torch.device | str = "cpu") -> tuple[QNetwork, PolicyTrainConfig]:
    """The trained network of a policy run (eval mode) and the run's config: its last
    weights, or with ``keep: best`` those that failed least at a periodic evaluation."""
    data = read_run_config(run_dir)
    cfg = validate(PolicyTrainConfig, data["train"])
    ckpt = Path(run_dir) / CHECKPOINT
    if not ckpt.exists():
        raise CheckpointError(f"{run_dir}: no checkpoint yet ({CHECKPOINT} is missing); train it first")
    enc = validate(BottleneckConfig, data["encoder"]) if data.get("encoder") else None
    net = build_network(cfg, enc, load_bnn_weights=False)
    info = load_checkpoint(ckpt, net)
    if cfg.keep == "best":
        best = section(info.extra_tensors, "best/")
        if not best:
            raise CheckpointError(f"{ckpt}: no evaluated weights yet (the run keeps its best evaluated weights, "
                                  "and none has been evaluated)")
        try:
            net.load_state_dict(best, strict=True)
        except RuntimeError:
            raise CheckpointError(f"{ckpt}: its best weights do not match the model") from None
    return net.to(device).eval(), cfg
