"""A dataset folder's manifest: the record a collection creates, checks and resumes from.

``manifest.json`` names the config, the resolved env config of every scenario, the work
units and every finished shard with its sha256. A collection continues a folder only when
the same config resolves to the same units there, and keeps only the shards whose files
still match their recorded digest.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from latentdrive.config import ConfigError, validate
from latentdrive.data.plan import (
    CollectConfig,
    WorkUnit,
    dataset_hash,
    plan_units,
    resolve_env_configs,
)
from latentdrive.data.shards import (
    FORMAT,
    FORMAT_VERSION,
    MANIFEST,
    QUANT_MAX_ERROR,
    DatasetError,
    read_manifest,
    write_manifest,
)
from latentdrive.env import EnvConfig
from latentdrive.fileio import confined, is_temp_file
from latentdrive.runlock import LOCK_NAME
from latentdrive.scenarios import ScenarioSpec

__all__ = ["check_collect_target", "dataset_specs", "existing_manifest", "file_sha256", "fresh_manifest",
           "new_manifest", "open_dataset_dir", "resumable_specs"]


def new_manifest(cfg: CollectConfig, chash: str, env_cfgs: list[EnvConfig], units: list[WorkUnit]) -> dict[str, Any]:
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


def file_sha256(path: Path) -> str | None:
    """sha256 of a file's bytes, or None when it cannot be read."""
    h = hashlib.sha256()
    try:
        with open(path, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
    except OSError:
        return None
    return h.hexdigest()


def existing_manifest(root: Path, fresh: dict[str, Any]) -> dict[str, Any] | None:
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
        if _resolved(key, manifest[key]) != fresh[key]:
            raise DatasetError(
                f"{root}: the same config now resolves to different {key} than when the "
                "dataset was collected (scenario presets changed?); use another directory")
    return manifest


def _resolved(key: str, value: Any) -> Any:
    """A manifest entry as today's code resolves it: env configs written before a setting
    existed gain its default (which leaves the data unchanged), so they still match."""
    if key != "env_configs" or not isinstance(value, list):
        return value
    try:
        return [validate(EnvConfig, c).model_dump(mode="json") for c in value]
    except ConfigError:
        return value


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


def fresh_manifest(cfg: CollectConfig, specs: Mapping[str, ScenarioSpec] | None = None) -> dict[str, Any]:
    env_cfgs = resolve_env_configs(cfg, specs)
    return new_manifest(cfg, dataset_hash(cfg), env_cfgs, plan_units(cfg, env_cfgs))


def check_collect_target(cfg: CollectConfig, out_dir: str | Path) -> None:
    """Raise what :func:`collect` of ``cfg`` into ``out_dir`` would refuse, writing nothing.

    For commands that write files of their own beside the dataset: they check first, so
    that a refused dataset leaves everything as it was.
    """
    existing_manifest(Path(out_dir), fresh_manifest(cfg, resumable_specs(cfg, out_dir)))


def resumable_specs(cfg: CollectConfig, out_dir: str | Path) -> dict[str, ScenarioSpec]:
    """The specs stored by the dataset in ``out_dir`` when ``cfg`` would resume it (same
    hash); otherwise none, and ``cfg``'s names resolve afresh (and are refused there)."""
    root = Path(out_dir)
    if not (root / MANIFEST).is_file() or read_manifest(root)["config_hash"] != dataset_hash(cfg):
        return {}
    return dataset_specs(root)


def open_dataset_dir(root: Path, fresh: dict[str, Any], say: Callable[[str], None]) -> dict[str, Any]:
    """The manifest to continue from: a new one, or the existing one with unverifiable shards dropped."""
    existing = existing_manifest(root, fresh)
    if existing is None:
        root.mkdir(parents=True, exist_ok=True)
        manifest = fresh
    else:
        manifest = existing
        kept = {}
        for name, entry in manifest["shards"].items():
            path = confined(root, name, source=root / MANIFEST, error=DatasetError)
            if file_sha256(path) == entry["sha256"]:
                kept[name] = entry
            else:
                say(f"{path}: missing or changed since it was recorded; collecting it again")
        manifest["shards"] = kept
    for p in root.iterdir():
        if is_temp_file(p):  # left by an interrupted write; its shard is redone
            p.unlink()
    write_manifest(root, manifest)
    return manifest
