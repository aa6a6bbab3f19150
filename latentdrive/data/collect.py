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

import multiprocessing
import sys
import time
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from latentdrive.data.manifest import (
    check_collect_target,
    dataset_specs,
    new_manifest,
    open_dataset_dir,
    resumable_specs,
)
from latentdrive.data.plan import (
    CollectConfig,
    WorkUnit,
    dataset_hash,
    episode_seeds,
    plan_units,
    resolve_env_configs,
)
from latentdrive.data.policies import episode_policy
from latentdrive.data.shards import (
    SHARD_WALL,
    DatasetError,
    array_digest,
    quantize,
    write_manifest,
    write_shard,
)
from latentdrive.env import EnvConfig
from latentdrive.lifetime import die_with_parent
from latentdrive.rollout import rollout, scene_policy
from latentdrive.runlock import dir_lock
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
    #: Wall-clock seconds that earlier runs spent on the shards this one kept (0 for a new
    #: dataset; the sum of those shards' recorded shares, so a shard redone counts once).
    resumed_s: float = 0.0

    @property
    def samples_per_s(self) -> float:
        """Samples written per wall-clock second of this run."""
        return self.samples_written / self.seconds if self.seconds > 0 else 0.0


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
    env_cfgs = resolve_env_configs(cfg, resumable_specs(cfg, root))
    units = plan_units(cfg, env_cfgs)
    chash = dataset_hash(cfg)
    fresh = new_manifest(cfg, chash, env_cfgs, units)
    # Held until the manifest's last update: a second collect into `root` is refused.
    with dir_lock(root, "collect"):
        manifest = open_dataset_dir(root, fresh, say)
        todo = [u for u in units if u.name not in manifest["shards"]]
        skipped = len(units) - len(todo)
        if skipped:
            say(f"{root}: {skipped} of {len(units)} shards already collected")
        jobs = [_Job(cfg, env_cfgs[u.scenario], u, root, chash) for u in todo]
        # Shards of a manifest written before their time was kept count none.
        resumed = sum(float(e.get(SHARD_WALL, 0.0)) for e in manifest["shards"].values())
        t0 = time.perf_counter()
        written, last = 0, 0.0
        for k, res in enumerate(_execute(jobs, cfg.workers), start=1):
            wall = time.perf_counter() - t0
            manifest["shards"][res.name] = {
                "samples": res.samples, "sha256": res.sha256, "bytes": res.bytes,
                "content_sha256": res.content_sha256, "episode_samples": res.episode_samples,
                "episode_policies": res.episode_policies, SHARD_WALL: round(wall - last, 3),
            }
            last = wall
            write_manifest(root, manifest)
            written += res.samples
            say(f"[{skipped + k}/{len(units)}] {res.name}: {res.samples} samples, {res.bytes / 2**20:.1f} MiB, "
                f"{res.samples / max(res.seconds, 1e-9):.0f} samples/s in its worker, "
                f"{written / max(wall, 1e-9):.0f} samples/s overall")
        total = sum(int(e["samples"]) for e in manifest["shards"].values())
        summary = CollectSummary(root, len(units), len(todo), skipped, written, total, time.perf_counter() - t0,
                                 resumed_s=resumed)
        say(f"{root}: {total} samples in {len(units)} shards ({written} new in {summary.seconds:.1f} s)")
        return summary


def worker_pool(workers: int) -> ProcessPoolExecutor:
    """Spawned collection workers, each ending with the process that started them."""
    return ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                               initializer=die_with_parent)


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
    ex = worker_pool(min(workers, len(jobs)))
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
