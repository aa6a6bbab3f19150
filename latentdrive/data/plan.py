"""What a dataset collection does: its config, its work units and every episode's seeds.

The unit list and every episode's seeds follow from the :class:`CollectConfig` alone
(see :mod:`latentdrive.data.collect`), so workers are independent and the result does not
depend on how many there are.
"""

from __future__ import annotations

import re
import zlib
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from pydantic import Field, ValidationInfo, field_validator

from latentdrive.config import Config, ConfigError, config_hash, merge_overrides
from latentdrive.data.policies import Behaviour
from latentdrive.env import EnvConfig, make_env_config
from latentdrive.scenarios import SCENARIOS, ScenarioSpec, resolve_specs

__all__ = ["CollectConfig", "WorkUnit", "dataset_hash", "episode_seeds", "plan_units", "resolve_env_configs"]


class CollectConfig(Config):
    """What to collect. Everything except ``workers`` defines the dataset's content."""

    scenarios: list[str] = Field(
        default_factory=lambda: list(SCENARIOS), min_length=1,
        description="Scenario names (or spec .yaml files); a sample's scenario label is its index in this list.")
    episodes: int = Field(200, ge=1, le=1_000_000, description="Episodes per scenario.")
    shard_size: int = Field(
        512, ge=1, le=1_000_000,
        description="Target samples per shard. A shard holds whole episodes, as many as fit "
        "when every episode runs to its time limit (at least one), so shards of scenarios "
        "where episodes end early hold fewer. Peak memory per worker is about "
        "shard_size · 2 · 4·T·H·W bytes.")
    behaviour: Behaviour = Field("mixed", description="Policy driving the AVs: 'random', 'rule' or 'mixed' (per-episode choice).")
    rule_fraction: float = Field(0.5, ge=0.0, le=1.0, description="Probability that a 'mixed' episode uses the rule-based driver.")
    seed: int = Field(0, ge=0, description="Root seed; every episode's env and policy seeds derive from it.")
    workers: int = Field(1, ge=1, le=512, description="Worker processes. Does not change the data, and is not part of the dataset's hash.")
    sample_every: int = Field(1, ge=1, le=10_000, description="Record every k-th policy step (step 0, the reset observation, is always recorded).")
    env: dict[str, Any] = Field(
        default_factory=dict,
        description="Env overrides applied to every scenario, as for make_env_config: "
        "'observation' settings, or scenario fields such as 'duration' (seconds) or 'n_av'. "
        "Dotted keys ('observation.frames') are nested on validation.")

    @field_validator("scenarios")
    @classmethod
    def _check_scenarios(cls, v: list[str]) -> list[str]:
        if len(set(v)) != len(v):
            raise ValueError(f"duplicate scenario in {v}")
        for name in v:
            if name not in SCENARIOS and not name.endswith((".yaml", ".yml")):
                raise ValueError(f"unknown scenario {name!r}: choose from {', '.join(SCENARIOS)} or a .yaml spec file")
        return v

    @field_validator("env", mode="before")
    @classmethod
    def _nest_env(cls, v: Any) -> Any:
        # Nesting dotted keys makes {"observation.frames": 2} and {"observation":
        # {"frames": 2}} the same config, with the same hash.
        return merge_overrides({}, v) if isinstance(v, dict) else v

    @field_validator("env")
    @classmethod
    def _check_env(cls, v: dict[str, Any], info: ValidationInfo) -> dict[str, Any]:
        # A dataset being resumed supplies the specs it stored (validation context "specs").
        stored = (info.context or {}).get("specs") or {}
        for name in info.data.get("scenarios", []):
            try:
                make_env_config(stored.get(name, name), **v)
            except ConfigError as exc:
                raise ValueError(f"scenario {name}: {str(exc).removeprefix('invalid config: ')}") from None
        return v


def dataset_hash(cfg: CollectConfig) -> str:
    """The dataset's identity: :func:`~latentdrive.config.config_hash` of ``cfg`` with
    ``workers`` reset to 1, since the number of workers never changes the data."""
    return config_hash(cfg.model_copy(update={"workers": 1}))


def resolve_env_configs(cfg: CollectConfig, specs: Mapping[str, ScenarioSpec] | None = None) -> list[EnvConfig]:
    """The env config of each scenario, in ``cfg.scenarios`` order, with clean observations on.

    ``specs`` stand for the names they are keyed by (a dataset's stored ones, see
    :func:`dataset_specs`); other names are presets or spec files.

    Raises:
        ConfigError: an override does not apply, or the scenarios' observation shapes differ.
    """
    resolved = resolve_specs(cfg.scenarios, specs)
    out = [make_env_config(resolved[name], **merge_overrides(cfg.env, {"clean_observation": True}))
           for name in cfg.scenarios]
    names = [e.scenario.name for e in out]
    if len(set(names)) != len(names):
        raise ConfigError(f"scenarios: two specs share a name ({', '.join(names)})")
    shapes = {e.observation.shape for e in out}
    if len(shapes) > 1:
        raise ConfigError(f"env: scenarios have different observation shapes {sorted(shapes)}")
    return out


@dataclass(frozen=True)
class WorkUnit:
    """One shard's worth of work: ``episodes`` consecutive episodes of one scenario.

    ``first_episode`` is the global id of the first one; the episode with local index
    ``e`` (within its scenario) has global id ``scenario · cfg.episodes + e``.
    """

    name: str
    scenario: int
    scenario_name: str
    first_local: int
    first_episode: int
    episodes: int

    def as_dict(self) -> dict[str, Any]:
        return {"name": self.name, "scenario": self.scenario, "first_episode": self.first_episode,
                "episodes": self.episodes}


def _samples_per_episode_max(env_cfg: EnvConfig, sample_every: int) -> int:
    spec = env_cfg.scenario
    return spec.n_av * (spec.max_steps // sample_every + 1)


def plan_units(cfg: CollectConfig, env_cfgs: list[EnvConfig]) -> list[WorkUnit]:
    """The work units of ``cfg``, in scenario order then episode order."""
    units = []
    for i, env_cfg in enumerate(env_cfgs):
        per_shard = max(1, cfg.shard_size // _samples_per_episode_max(env_cfg, cfg.sample_every))
        tag = re.sub(r"[^A-Za-z0-9_.-]", "_", env_cfg.scenario.name)
        for first in range(0, cfg.episodes, per_shard):
            units.append(WorkUnit(
                name=f"{i:02d}-{tag}-{first:06d}.npz", scenario=i, scenario_name=env_cfg.scenario.name,
                first_local=first, first_episode=i * cfg.episodes + first,
                episodes=min(per_shard, cfg.episodes - first)))
    return units


def episode_seeds(seed: int, scenario_name: str, local_episode: int) -> tuple[int, np.random.Generator]:
    """``(env reset seed, policy generator)`` of one episode.

    Both derive from ``SeedSequence(seed, spawn_key=(crc32(scenario_name), local_episode))``,
    so a scenario's episodes do not change when other scenarios are added or reordered.
    """
    ss = np.random.SeedSequence(seed, spawn_key=(zlib.crc32(scenario_name.encode()), local_episode))
    env_seed = int(ss.generate_state(1, np.uint64)[0] >> np.uint64(1))  # fits int64
    return env_seed, np.random.default_rng(ss.spawn(1)[0])
