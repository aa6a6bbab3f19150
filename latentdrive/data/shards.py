"""On-disk format of observation datasets: quantization, shard files and the manifest.

A dataset directory holds ``manifest.json`` and one compressed ``.npz`` shard per work
unit (one scenario, one block of consecutive episodes). Shards are written with
``numpy.savez_compressed`` and read with ``numpy.load(..., allow_pickle=False)``: nothing
in a dataset is ever unpickled. Every write goes to a temporary file in the same
directory and is renamed into place, so a reader sees either the old file or the new one.

Shard arrays (``n`` samples, one per AV per recorded step):

====================  ===========================  =======================================
``noisy``             ``(n, 4, T, H, W)`` uint8    observation with sensor noise, quantized
``clean``             ``(n, 4, T, H, W)`` uint8    the same observation without noise
``scenario``          ``(n,)`` int64               index into the manifest's ``scenarios``
``episode``           ``(n,)`` int64               global episode id, unique in the dataset
``seed``              ``(n,)`` int64               the seed the episode's env was reset with
``step``              ``(n,)`` int64               policy step in the episode (0 = reset)
``agent``             ``(n,)`` int64               which AV of the scene observed it
``config_hash``       ``()`` unicode               hash of the config that wrote the shard
====================  ===========================  =======================================

Quantization: a value ``x`` in [0, 1] is stored as ``q = round(255·x)`` and read back as
``q / 255``, so every reconstructed value is within ``1/510`` (half a step) of the
original.
"""

from __future__ import annotations

import hashlib
import io
import itertools
import json
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from latentdrive.errors import LatentDriveError
from latentdrive.fileio import (
    MAX_JSON_BYTES,
    atomic_write_bytes,
    confined,
    read_bytes,
    read_json,
    seconds_recorded,
    shown,
)

__all__ = [
    "FORMAT",
    "FORMAT_VERSION",
    "IMAGE_KEYS",
    "INDEX_KEYS",
    "MANIFEST",
    "QUANT_MAX_ERROR",
    "SHARD_KEYS",
    "SHARD_WALL",
    "DatasetError",
    "array_digest",
    "dequantize",
    "quantize",
    "read_manifest",
    "read_shard",
    "write_manifest",
    "write_shard",
]

FORMAT = "latentdrive-observation-dataset"
FORMAT_VERSION = 1
MANIFEST = "manifest.json"
#: Largest absolute error of :func:`dequantize` ∘ :func:`quantize` on [0, 1]: half of 1/255.
QUANT_MAX_ERROR = 1.0 / 510.0
#: Largest shard read when the manifest's recorded size is not at hand (bytes).
MAX_SHARD_BYTES = 4 << 30
IMAGE_KEYS: tuple[str, ...] = ("noisy", "clean")
INDEX_KEYS: tuple[str, ...] = ("scenario", "episode", "seed", "step", "agent")
SHARD_KEYS: frozenset[str] = frozenset((*IMAGE_KEYS, *INDEX_KEYS, "config_hash"))


class DatasetError(LatentDriveError):
    """A dataset directory, manifest or shard is missing, corrupt or from another config.

    The one-line message names the file or directory.
    """


def quantize(x: NDArray[np.floating]) -> NDArray[np.uint8]:
    """``round(255·x)`` as uint8; ``x`` in [0, 1] (values outside are clipped first)."""
    return np.rint(np.clip(x, 0.0, 1.0) * 255.0).astype(np.uint8)


def dequantize(q: NDArray[np.uint8]) -> NDArray[np.float32]:
    """``q / 255`` as float32 in [0, 1]; within :data:`QUANT_MAX_ERROR` of the original.
    C-contiguous in ``q``'s index order, whatever its strides (one copy, divided in place)."""
    out = q.astype(np.float32, order="C")
    out /= np.float32(255.0)
    return out


def array_digest(arrays: Mapping[str, np.ndarray]) -> str:
    """sha256 of the arrays' names, dtypes, shapes and bytes (independent of the zip container).

    Two shards with equal digests hold identical data even when their files differ
    (``savez_compressed`` stamps each member with the time it was written).
    """
    h = hashlib.sha256()
    for key in sorted(arrays):
        a = np.ascontiguousarray(arrays[key])
        h.update(f"{key}|{a.dtype.str}|{a.shape}|".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def write_shard(path: Path, arrays: Mapping[str, np.ndarray]) -> tuple[str, int]:
    """Atomically write a shard; returns ``(sha256 of the file, its size in bytes)``."""
    missing = SHARD_KEYS - set(arrays)
    if missing:
        raise ValueError(f"shard arrays lack {sorted(missing)}")
    buf = io.BytesIO()
    members: dict[str, Any] = {k: np.asarray(arrays[k]) for k in sorted(SHARD_KEYS)}
    np.savez_compressed(buf, **members)
    data = buf.getvalue()
    atomic_write_bytes(path, data)
    return hashlib.sha256(data).hexdigest(), len(data)


def read_shard(
    path: Path,
    *,
    sha256: str | None,
    config_hash: str,
    sample_shape: tuple[int, ...],
    samples: int | None = None,
    size: int | None = None,
) -> dict[str, np.ndarray]:
    """Load and check one shard; every failure is a :class:`DatasetError` naming ``path``.

    Checks, in order: the file's size (at most ``size`` bytes are read when given, the
    size the manifest recorded), its sha256 (when given), that it is a zip of ``.npy``
    members (never unpickled), the exact set of arrays, their dtypes and shapes (images
    ``(n, *sample_shape)``, ``n`` equal to ``samples`` when given) and the config hash
    stored inside.
    """
    try:
        data = read_bytes(path, limit=MAX_SHARD_BYTES if size is None else size, what="shard",
                          error=DatasetError)
    except FileNotFoundError:
        raise DatasetError(f"{path}: shard is missing") from None
    if sha256 is not None and hashlib.sha256(data).hexdigest() != sha256:
        raise DatasetError(f"{path}: shard is corrupt (sha256 differs from the manifest)")
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as npz:
            keys = set(npz.files)
            if keys != SHARD_KEYS:
                raise DatasetError(
                    f"{path}: not a shard of this format (arrays {sorted(keys)}, "
                    f"expected {sorted(SHARD_KEYS)})"
                )
            arrays = {k: npz[k] for k in SHARD_KEYS}
    except DatasetError:
        raise
    except (zipfile.BadZipFile, ValueError, OSError, EOFError, KeyError) as exc:
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise DatasetError(f"{path}: shard is corrupt ({reason})") from None
    n = arrays["noisy"].shape[0] if arrays["noisy"].ndim else -1
    for key in IMAGE_KEYS:
        a = arrays[key]
        if a.dtype != np.uint8 or a.shape != (n, *sample_shape):
            raise DatasetError(
                f"{path}: array {key!r} is {a.dtype}{list(a.shape)}, expected "
                f"uint8{[n, *sample_shape]}"
            )
    for key in INDEX_KEYS:
        a = arrays[key]
        if a.dtype != np.int64 or a.shape != (n,):
            raise DatasetError(f"{path}: array {key!r} is {a.dtype}{list(a.shape)}, expected int64[{n}]")
    if samples is not None and n != samples:
        raise DatasetError(f"{path}: holds {n} samples, the manifest says {samples}")
    stored = arrays["config_hash"]
    if stored.dtype.kind != "U" or stored.shape != () or str(stored) != config_hash:
        raise DatasetError(
            f"{path}: shard belongs to config {str(stored)!r}, not this dataset's {config_hash}"
        )
    return arrays


def write_manifest(root: Path, manifest: Mapping[str, Any]) -> None:
    """Atomically (re)write ``root/manifest.json``."""
    atomic_write_bytes(root / MANIFEST, (json.dumps(manifest, indent=1) + "\n").encode())


#: A shard entry's share of its collection run's wall-clock seconds (the time since the run
#: started or wrote its previous shard): what a resumed collection had already spent on it.
SHARD_WALL = "wall_s"

_MANIFEST_KEYS = ("format", "version", "config_hash", "config", "scenarios", "env_configs",
                  "sample_shape", "units", "shards")


def read_manifest(root: Path) -> dict[str, Any]:
    """Read and check ``root/manifest.json``; :class:`DatasetError` naming it otherwise.

    Beyond its format and version, every unit must be complete (name, scenario, first
    episode, episode count) and every shard name a file inside ``root``: a manifest can
    never make a reader open a file elsewhere.
    """
    path = root / MANIFEST
    try:
        manifest = read_json(path, limit=MAX_JSON_BYTES, what="dataset manifest", error=DatasetError)
    except FileNotFoundError:
        raise DatasetError(f"{path}: no dataset manifest (collect one with `latentdrive collect`)") from None
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        raise DatasetError(f"{path}: not a latentdrive dataset manifest")
    if manifest.get("version") != FORMAT_VERSION:
        raise DatasetError(
            f"{path}: dataset format version {manifest.get('version')!r}, this latentdrive "
            f"reads version {FORMAT_VERSION}"
        )
    missing = [k for k in _MANIFEST_KEYS if k not in manifest]
    if missing:
        raise DatasetError(f"{path}: manifest is corrupt (missing {', '.join(missing)})")
    try:
        _check_manifest_types(manifest)
    except (TypeError, ValueError) as exc:
        raise DatasetError(f"{path}: manifest is corrupt ({exc})") from None
    for unit in manifest["units"]:
        confined(root, unit["name"], source=path, error=DatasetError)
    return manifest


#: Bound (exclusive) of every count and episode id in a manifest: ids and counts are int64
#: arrays once read, and a first episode id plus an episode count must stay one.
MAX_COUNT = 2**62


def _count(value: Any, what: str, low: int = 0) -> int:
    """``value`` when it is an integer in ``[low, MAX_COUNT)`` (JSON numbers such as 2.5 or
    true are not)."""
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value < MAX_COUNT:
        raise ValueError(f"{what} must be an integer >= {low} and < 2**62, got {shown(value)}")
    return value


def _check_manifest_types(m: dict[str, Any]) -> None:
    if not (isinstance(m["scenarios"], list) and all(isinstance(s, str) for s in m["scenarios"])):
        raise TypeError("scenarios must be a list of names")
    if not isinstance(m["config_hash"], str):
        raise TypeError("config_hash must be a string")
    if not (isinstance(m["sample_shape"], list) and len(m["sample_shape"]) == 4
            and all(isinstance(v, int) and v > 0 for v in m["sample_shape"])):
        raise TypeError("sample_shape must be 4 positive integers")
    if not isinstance(m["units"], list) or not isinstance(m["shards"], dict):
        raise TypeError("units must be a list and shards a mapping")
    episodes: dict[str, int] = {}
    spans = []
    for i, u in enumerate(m["units"]):
        if not isinstance(u, dict):
            raise TypeError(f"unit {i} is not a mapping")
        lacking = [k for k in ("name", "scenario", "first_episode", "episodes") if k not in u]
        if lacking:
            raise ValueError(f"unit {i} lacks {', '.join(lacking)}")
        name = u["name"]
        if not isinstance(name, str) or name in episodes:
            raise ValueError(f"unit {i} has a missing or repeated name {name!r}")
        if not 0 <= _count(u["scenario"], f"unit {name}: scenario") < len(m["scenarios"]):
            raise ValueError(f"unit {name} has scenario index {u['scenario']} out of range")
        first = _count(u["first_episode"], f"unit {name}: first_episode")
        episodes[name] = _count(u["episodes"], f"unit {name}: episodes", low=1)
        spans.append((first, first + episodes[name]))
    spans.sort()
    if any(b[0] < a[1] for a, b in itertools.pairwise(spans)):
        raise ValueError("two units share episode ids")
    for name, entry in m["shards"].items():
        if name not in episodes:
            raise ValueError(f"shard {name} is not one of the planned units")
        if not isinstance(entry, dict):
            raise TypeError(f"shard {name} is not a mapping")
        for key in ("samples", "sha256", "bytes", "episode_samples", "content_sha256"):
            if key not in entry:
                raise ValueError(f"shard {name} lacks {key!r}")
        counts = entry["episode_samples"]
        if not isinstance(counts, list) or len(counts) != episodes[name]:
            raise ValueError(f"shard {name}: episode_samples must list one count per episode")
        total = sum(_count(c, f"shard {name}: an episode's samples") for c in counts)
        if total != _count(entry["samples"], f"shard {name}: samples"):
            raise ValueError(f"shard {name}: episode sample counts do not add up")
        _count(entry["bytes"], f"shard {name}: bytes")
        if SHARD_WALL in entry:  # absent from manifests written before it was kept
            seconds_recorded(entry[SHARD_WALL], f"shard {name}", ValueError, name=SHARD_WALL)
        if not isinstance(entry["sha256"], str):
            raise TypeError(f"shard {name}: sha256 must be a string")
