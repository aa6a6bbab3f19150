"""Collect denoising datasets for the bottleneck network: (noisy, clean) VelocityMap pairs.

:func:`collect` rolls out episodes of every configured scenario with a behaviour policy
(:mod:`latentdrive.data.policies`) and records, at every recorded step and for every AV,
the noisy observation ``(4, T, H, W)`` (the network's input) and the noise-free one (its
target), quantized to uint8 (error at most 1/510, see :mod:`latentdrive.data.shards`).

The work is cut into units, one per (scenario, block of consecutive episodes), each
written to its own shard. The unit list and every episode's seeds follow from the
:class:`CollectConfig` alone, and a shard's content depends only on its unit, so workers
are independent, the result does not depend on how many there are, and an interrupted
run resumes by redoing only the units that are not finished. ``manifest.json`` is updated
by the main process as each shard completes.
"""

from __future__ import annotations

import hashlib
import multiprocessing
import re
import sys
import time
import zlib
from collections.abc import Callable, Iterator, Mapping
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import Field, ValidationInfo, field_validator

from latentdrive.config import Config, ConfigError, config_hash, merge_overrides, validate
from latentdrive.data.policies import Behaviour, episode_policy
from latentdrive.data.shards import (
    FORMAT,
    FORMAT_VERSION,
    MANIFEST,
    QUANT_MAX_ERROR,
    DatasetError,
    array_digest,
    quantize,
    read_manifest,
    write_manifest,
    write_shard,
)
from latentdrive.env import EnvConfig, make_env_config
from latentdrive.fileio import confined, is_temp_file
from latentdrive.rollout import rollout, scene_policy
from latentdrive.runlock import LOCK_NAME, dir_lock
from latentdrive.scenarios import SCENARIOS, ScenarioSpec, resolve_specs
from latentdrive.vec import DrivingVecEnv

__all__ = [
    "CollectConfig",
    "CollectSummary",
    "DatasetError",
    "WorkUnit",
    "check_collect_target",
    "collect",
    "dataset_hash",
    "dataset_specs",
    "episode_seeds",
    "plan_units",
    "resolve_env_configs",
]


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


@dataclass(frozen=True)
class _Job:
    cfg: CollectConfig
    env_cfg: EnvConfig
    unit: WorkUnit
    root: Path
    config_hash: str


@dataclass(frozen=True)
class _UnitResult:
    name: str
    samples: int
    sha256: str
    bytes: int
    content_sha256: str
    episode_samples: list[int]
    episode_policies: list[str]
    seconds: float


def _unit_vec_env(env_cfg: EnvConfig) -> DrivingVecEnv:
    """A one-environment vector env of ``env_cfg`` with clean observations on.

    Its environment 0 reset with seed ``s`` runs exactly the episode of
    ``DrivingEnv(config=env_cfg).reset(seed=s)``.
    """
    overrides = {k: getattr(env_cfg, k) for k in EnvConfig.model_fields if k not in ("scenario", "backend")}
    overrides["clean_observation"] = True
    return DrivingVecEnv([env_cfg.scenario], backend=env_cfg.backend, **overrides)


def _rollout_unit(cfg: CollectConfig, env_cfg: EnvConfig, unit: WorkUnit) -> tuple[dict[str, np.ndarray], list[int], list[str]]:
    """Roll out a unit's episodes; returns the shard's arrays (without the config hash).

    Each episode is :func:`~latentdrive.rollout.rollout` of a one-environment vector env
    reset with the episode's env seed, up to the step that ends it. Its observation after
    ``step`` policy steps (the reset one is step 0) is recorded, noisy and clean, when
    ``step % cfg.sample_every == 0``; the same rule applies to the final observation.
    """
    vec = _unit_vec_env(env_cfg)
    n_av = env_cfg.scenario.n_av
    noisy: list[np.ndarray] = []
    clean: list[np.ndarray] = []
    index: dict[str, list[int]] = {"episode": [], "seed": [], "step": []}
    counts, policies = [], []
    for e in range(unit.first_local, unit.first_local + unit.episodes):
        env_seed, rng = episode_seeds(cfg.seed, unit.scenario_name, e)
        policy_name, policy = episode_policy(
            cfg.behaviour, rng, rule_fraction=cfg.rule_fraction,
            cruise_speeds=env_cfg.scenario.av_target_speeds)
        recorded = 0
        # Record k is the step from the observation after k policy steps to the one after
        # k + 1 (the episode's final observation on the record that ends it).
        for k, rec in enumerate(rollout(vec, scene_policy(policy, rng), seed=env_seed)):
            ended = bool(rec.ended[0])
            views = [(k, rec.obs, rec.clean_obs)]
            if ended:
                views.append((k + 1, rec.next_obs, rec.clean_next_obs))
            for step, obs, clean_obs in views:
                if step % cfg.sample_every != 0:
                    continue
                if clean_obs is None:
                    raise RuntimeError("the vector env returned no clean observations")
                # Quantize at once: a shard's float32 observations would take 4× the memory.
                noisy.append(quantize(obs[0]))
                clean.append(quantize(clean_obs[0]))
                index["episode"].append(unit.scenario * cfg.episodes + e)
                index["seed"].append(env_seed)
                index["step"].append(step)
                recorded += n_av
            if ended:
                break
        counts.append(recorded)
        policies.append(policy_name)
    vec.close()
    shape = env_cfg.observation.shape
    arrays = {
        "noisy": np.concatenate(noisy) if noisy else np.zeros((0, *shape), np.uint8),
        "clean": np.concatenate(clean) if clean else np.zeros((0, *shape), np.uint8),
        "scenario": np.full(sum(counts), unit.scenario, dtype=np.int64),
        "agent": np.tile(np.arange(n_av, dtype=np.int64), len(index["step"])),
    }
    for key, values in index.items():
        arrays[key] = np.repeat(np.asarray(values, dtype=np.int64), n_av)
    return arrays, counts, policies


def _run_unit(job: _Job) -> _UnitResult:
    """Collect one unit and write its shard (runs in a worker process or in-process)."""
    t0 = time.perf_counter()
    arrays, counts, policies = _rollout_unit(job.cfg, job.env_cfg, job.unit)
    arrays["config_hash"] = np.array(job.config_hash)
    digest = array_digest(arrays)
    sha, size = write_shard(job.root / job.unit.name, arrays)
    return _UnitResult(job.unit.name, int(arrays["noisy"].shape[0]), sha, size, digest, counts,
                       policies, time.perf_counter() - t0)


@dataclass(frozen=True)
class CollectSummary:
    """What :func:`collect` did."""

    root: Path
    shards_total: int
    shards_written: int
    shards_skipped: int
    samples_written: int
    samples_total: int
    seconds: float

    @property
    def samples_per_s(self) -> float:
        """Samples written per wall-clock second of this run."""
        return self.samples_written / self.seconds if self.seconds > 0 else 0.0


def _new_manifest(cfg: CollectConfig, chash: str, env_cfgs: list[EnvConfig], units: list[WorkUnit]) -> dict[str, Any]:
    return {
        "format": FORMAT,
        "version": FORMAT_VERSION,
        "config_hash": chash,
        "config": cfg.model_dump(mode="json"),
        "scenarios": [e.scenario.name for e in env_cfgs],
        "env_configs": [e.model_dump(mode="json") for e in env_cfgs],
        "sample_shape": list(env_cfgs[0].observation.shape),
        "quantization": {"dtype": "uint8", "value": "round(255*x)", "max_abs_error": QUANT_MAX_ERROR},
        "units": [u.as_dict() for u in units],
        "shards": {},
    }


def _file_sha256(path: Path) -> str | None:
    """sha256 of a file's bytes, or None when it cannot be read."""
    h = hashlib.sha256()
    try:
        with open(path, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
    except OSError:
        return None
    return h.hexdigest()


def _existing_manifest(root: Path, fresh: dict[str, Any]) -> dict[str, Any] | None:
    """The manifest of the dataset in ``root`` that ``fresh``'s collection would continue
    (None when there is none yet), checked without writing anything."""
    if root.exists() and not root.is_dir():
        raise DatasetError(f"{root}: exists and is not a directory")
    if not (root / MANIFEST).exists():
        if root.exists() and any(not is_temp_file(p) and p.name != LOCK_NAME for p in root.iterdir()):
            raise DatasetError(f"{root}: directory is not empty and holds no {MANIFEST}; collect into an empty or new directory")
        return None
    manifest = read_manifest(root)
    if manifest["config_hash"] != fresh["config_hash"]:
        raise DatasetError(
            f"{root}: holds a dataset of config {manifest['config_hash']}, not this config's "
            f"{fresh['config_hash']}; rerun with the same settings to resume, or use another directory")
    for key in ("scenarios", "env_configs", "sample_shape", "units"):
        if manifest[key] != fresh[key]:
            raise DatasetError(
                f"{root}: the same config now resolves to different {key} than when the "
                "dataset was collected (scenario presets changed?); use another directory")
    return manifest


def dataset_specs(out_dir: str | Path) -> dict[str, ScenarioSpec]:
    """The scenario specs a dataset in ``out_dir`` was collected on, keyed by the names of
    its config (empty when ``out_dir`` holds no dataset yet).

    They are what its manifest recorded, with the config's env overrides applied; applying
    them again changes nothing, so a resumption from these needs no spec file and meets no
    later change of a preset.

    Raises:
        DatasetError: the manifest is corrupt.
    """
    root = Path(out_dir)
    if not (root / MANIFEST).is_file():
        return {}
    manifest = read_manifest(root)
    names = manifest["config"].get("scenarios") if isinstance(manifest["config"], dict) else None
    envs = manifest["env_configs"]
    if (not isinstance(names, list) or not isinstance(envs, list) or len(names) != len(envs)
            or not all(isinstance(n, str) and isinstance(e, dict) for n, e in zip(names, envs, strict=True))):
        raise DatasetError(f"{root / MANIFEST}: manifest is corrupt (its scenarios and env_configs do not pair up)")
    try:
        return {n: validate(ScenarioSpec, e.get("scenario"), prefix="scenario.") for n, e in zip(names, envs, strict=True)}
    except ConfigError as exc:
        raise DatasetError(f"{root / MANIFEST}: manifest is corrupt ({exc})") from None


def _fresh_manifest(cfg: CollectConfig, specs: Mapping[str, ScenarioSpec] | None = None) -> dict[str, Any]:
    env_cfgs = resolve_env_configs(cfg, specs)
    return _new_manifest(cfg, dataset_hash(cfg), env_cfgs, plan_units(cfg, env_cfgs))


def check_collect_target(cfg: CollectConfig, out_dir: str | Path) -> None:
    """Raise what :func:`collect` of ``cfg`` into ``out_dir`` would refuse, writing nothing.

    For commands that write files of their own beside the dataset: they check first, so
    that a refused dataset leaves everything as it was.
    """
    _existing_manifest(Path(out_dir), _fresh_manifest(cfg, _resumable_specs(cfg, out_dir)))


def _resumable_specs(cfg: CollectConfig, out_dir: str | Path) -> dict[str, ScenarioSpec]:
    """The specs stored by the dataset in ``out_dir`` when ``cfg`` would resume it (same
    hash); otherwise none, and ``cfg``'s names resolve afresh (and are refused there)."""
    root = Path(out_dir)
    if not (root / MANIFEST).is_file() or read_manifest(root)["config_hash"] != dataset_hash(cfg):
        return {}
    return dataset_specs(root)


def _open_dataset_dir(root: Path, fresh: dict[str, Any], say: Callable[[str], None]) -> dict[str, Any]:
    """The manifest to continue from: a new one, or the existing one with unverifiable shards dropped."""
    existing = _existing_manifest(root, fresh)
    if existing is None:
        root.mkdir(parents=True, exist_ok=True)
        manifest = fresh
    else:
        manifest = existing
        kept = {}
        for name, entry in manifest["shards"].items():
            path = confined(root, name, source=root / MANIFEST, error=DatasetError)
            if _file_sha256(path) == entry["sha256"]:
                kept[name] = entry
            else:
                say(f"{path}: missing or changed since it was recorded; collecting it again")
        manifest["shards"] = kept
    for p in root.iterdir():
        if is_temp_file(p):  # left by an interrupted write; its shard is redone
            p.unlink()
    write_manifest(root, manifest)
    return manifest


def collect(cfg: CollectConfig, out_dir: str | Path, progress: bool = True) -> CollectSummary:
    """Collect the dataset of ``cfg`` into ``out_dir``, resuming what is already there.

    Shards recorded in the manifest whose file is present with the recorded sha256 are
    kept; every other unit is (re)collected, so rerunning after an interruption never
    duplicates samples and ends with the same content as an uninterrupted run. With
    ``cfg.workers > 1`` units run in spawned worker processes, each building its own envs;
    a script calling it so must guard its entry point with ``if __name__ == "__main__":``.

    Raises:
        DatasetError: ``out_dir`` holds another config's dataset (the message names both
            hashes), is a non-empty directory without a manifest, or has a corrupt manifest.
        ConfigError: the env overrides do not apply to a scenario.
    """
    root = Path(out_dir)

    def say(msg: str) -> None:
        if progress:
            print(msg, file=sys.stderr, flush=True)

    if root.exists() and not root.is_dir():
        raise DatasetError(f"{root}: exists and is not a directory")
    env_cfgs = resolve_env_configs(cfg, _resumable_specs(cfg, root))
    units = plan_units(cfg, env_cfgs)
    chash = dataset_hash(cfg)
    fresh = _new_manifest(cfg, chash, env_cfgs, units)
    # Held until the manifest's last update: a second collect into `root` is refused.
    with dir_lock(root, "collect"):
        manifest = _open_dataset_dir(root, fresh, say)
        todo = [u for u in units if u.name not in manifest["shards"]]
        skipped = len(units) - len(todo)
        if skipped:
            say(f"{root}: {skipped} of {len(units)} shards already collected")
        jobs = [_Job(cfg, env_cfgs[u.scenario], u, root, chash) for u in todo]
        t0 = time.perf_counter()
        written = 0
        for k, res in enumerate(_execute(jobs, cfg.workers), start=1):
            manifest["shards"][res.name] = {
                "samples": res.samples, "sha256": res.sha256, "bytes": res.bytes,
                "content_sha256": res.content_sha256, "episode_samples": res.episode_samples,
                "episode_policies": res.episode_policies,
            }
            write_manifest(root, manifest)
            written += res.samples
            wall = time.perf_counter() - t0
            say(f"[{skipped + k}/{len(units)}] {res.name}: {res.samples} samples, {res.bytes / 2**20:.1f} MiB, "
                f"{res.samples / max(res.seconds, 1e-9):.0f} samples/s in its worker, "
                f"{written / max(wall, 1e-9):.0f} samples/s overall")
        total = sum(int(e["samples"]) for e in manifest["shards"].values())
        summary = CollectSummary(root, len(units), len(todo), skipped, written, total, time.perf_counter() - t0)
        say(f"{root}: {total} samples in {len(units)} shards ({written} new in {summary.seconds:.1f} s)")
        return summary


def _execute(jobs: list[_Job], workers: int) -> Iterator[_UnitResult]:
    """Results of ``jobs`` as they complete (in-process for one worker)."""
    if workers <= 1 or len(jobs) <= 1:
        for job in jobs:
            yield _run_unit(job)
        return
    # Spawned workers start from a fresh interpreter: no simulator state (highway-env
    # writes some driver parameters on classes) is inherited from the parent. An executor
    # rather than multiprocessing.Pool: when a worker dies (killed, out of memory, or a
    # script without a __main__ guard) it fails instead of respawning workers forever.
    ex = ProcessPoolExecutor(max_workers=min(workers, len(jobs)),
                             mp_context=multiprocessing.get_context("spawn"))
    try:
        futures = [ex.submit(_run_unit, job) for job in jobs]
        for fut in as_completed(futures):
            yield fut.result()
    except BrokenProcessPool:
        raise DatasetError(
            f"{jobs[0].root}: a collection worker process died (out of memory, killed, or "
            "collect() called with workers > 1 from a script without an "
            "`if __name__ == '__main__':` guard); finished shards are kept, rerun to resume"
        ) from None
    finally:
        ex.shutdown(wait=True, cancel_futures=True)
