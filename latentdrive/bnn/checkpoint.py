"""Training checkpoints as safetensors files, written atomically, read without unpickling.

One file holds everything needed to continue a run exactly where it stopped:

- tensors ``model/<name>``: the model's ``state_dict``;
- tensors ``optim/<param index>/<key>``: the optimizer's per-parameter tensor state
  (e.g. Adam's ``exp_avg``, ``exp_avg_sq``, ``step``); ``optim-<name>/<param index>/<key>``
  that of each further optimizer named in ``extra_optimizers``;
- tensor ``rng/torch``: a ``torch.Generator`` state (uint8), when one is given;
- tensors ``extra/<name>``: caller tensors (e.g. CUDA generator states);
- header metadata (strings): ``format``, ``version``, ``state``, a JSON document with the
  step, the epoch, the caller's config, the optimizer's class, param groups and
  non-tensor per-parameter state (and each further optimizer's), the numpy ``Generator.bit_generator.state`` and caller
  ``extra`` values; and ``digest``, a SHA-256 over every tensor's name, dtype, shape and
  bytes and over the ``state`` text, which catches corruption the safetensors header
  check cannot see, in the tensors and in the state alike. (Version 1 files, whose digest
  covers the tensors only, are still read.)

The file is read without unpickling anything (safetensors holds raw tensor bytes), and
its header is checked before the rest of the file is read. Any failure to read a
checkpoint, a foreign or corrupt file, or one made for another architecture raises
:class:`CheckpointError`, a ``ValueError`` with a one-line message that starts with the
file's path. Nothing is loaded into the model or optimizer unless the whole checkpoint
matches them.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors.torch import load as st_load
from safetensors.torch import save as st_save
from torch import nn

from latentdrive.errors import LatentDriveError, first_line
from latentdrive.fileio import atomic_write_bytes

__all__ = [
    "FORMAT",
    "VERSION",
    "CheckpointError",
    "CheckpointInfo",
    "load_checkpoint",
    "read_checkpoint",
    "save_checkpoint",
    "section",
    "tensors_digest",
]

FORMAT = "latentdrive.checkpoint"
#: Written by this version; 2 added the state JSON to the digest.
VERSION = 2
#: Versions read: 1's digest covers the tensors only.
_READABLE = ("1", "2")
#: Largest safetensors header read, the limit of the safetensors library itself (bytes).
MAX_HEADER_BYTES = 100_000_000


class CheckpointError(LatentDriveError, ValueError):
    """A checkpoint cannot be used; the one-line message starts with the file's path."""


@dataclass(frozen=True)
class CheckpointInfo:
    """What a checkpoint holds besides the model and optimizer tensors."""

    path: Path
    step: int
    epoch: int
    config: dict[str, Any]
    extra: dict[str, Any]
    extra_tensors: dict[str, torch.Tensor] = field(default_factory=dict)


# ---------------------------------------------------------------------------------------
# JSON helpers


def _to_json(obj: Any) -> Any:
    """JSON-ready copy of RNG / optimizer state; numpy arrays and scalars become tagged lists."""
    if isinstance(obj, np.ndarray):
        return {"__ndarray__": obj.tolist(), "dtype": str(obj.dtype)}
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Mapping):
        return {str(k): _to_json(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_to_json(v) for v in obj]
    if obj is None or isinstance(obj, bool | int | float | str):
        return obj
    raise TypeError(f"cannot store a value of type {type(obj).__name__} in a checkpoint")


def _from_json(obj: Any) -> Any:
    if isinstance(obj, dict):
        if set(obj) == {"__ndarray__", "dtype"}:
            return np.asarray(obj["__ndarray__"], dtype=obj["dtype"])
        return {k: _from_json(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_from_json(v) for v in obj]
    return obj


def _digest(tensors: Mapping[str, torch.Tensor], state: str | None) -> str:
    """SHA-256 of the tensors (names, dtypes, shapes, bytes) and the state JSON text.

    ``state=None`` gives version 1's digest, over the tensors only.
    """
    h = hashlib.sha256()
    for name in sorted(tensors):
        t = tensors[name]
        h.update(f"{name}|{t.dtype}|{tuple(t.shape)}|".encode())
        h.update(t.detach().cpu().contiguous().reshape(-1).view(torch.uint8).numpy().tobytes())
    if state is not None:
        # After every tensor's bytes, behind a tag no tensor name can produce.
        h.update(b"\x00state|" + state.encode("utf-8"))
    return h.hexdigest()


def tensors_digest(tensors: Mapping[str, torch.Tensor]) -> str:
    """SHA-256 of named tensors (names, dtypes, shapes, bytes), as a checkpoint digests its own.

    For a file kept beside a checkpoint (a policy run's replay): the checkpoint records the
    digest in its state, which its own digest covers, and the reader compares.
    """
    return _digest(tensors, None)


# ---------------------------------------------------------------------------------------
# Save


def save_checkpoint(
    path: str | Path,
    model: nn.Module,
    optimizer: torch.optim.Optimizer | None = None,
    *,
    step: int,
    epoch: int,
    config: Mapping[str, Any] | None = None,
    torch_generator: torch.Generator | None = None,
    numpy_generator: np.random.Generator | None = None,
    extra: Mapping[str, Any] | None = None,
    extra_tensors: Mapping[str, torch.Tensor] | None = None,
    extra_optimizers: Mapping[str, torch.optim.Optimizer] | None = None,
) -> Path:
    """Write a checkpoint atomically to ``path`` (conventionally ``*.safetensors``).

    ``step`` counts optimizer steps taken, ``epoch`` epochs completed. ``config`` and
    ``extra`` must be JSON-serializable mappings (pydantic configs: ``model_dump(mode="json")``).
    ``extra_optimizers``, by name (letters, digits, ``_``): optimizers beside ``optimizer``,
    over ``model``'s parameters or others, for :func:`load_checkpoint` to restore by the same names.
    """
    tensors: dict[str, torch.Tensor] = {}
    # Clone so that tensors sharing storage (tied weights, views) serialize independently.
    for name, t in model.state_dict().items():
        tensors[f"model/{name}"] = t.detach().cpu().clone().contiguous()

    optim_json = None if optimizer is None else _optimizer_entries(optimizer, "optim", tensors)
    others = {name: _optimizer_entries(opt, f"optim-{name}", tensors) for name, opt in (extra_optimizers or {}).items()}

    if torch_generator is not None:
        tensors["rng/torch"] = torch_generator.get_state().clone()
    for name, t in (extra_tensors or {}).items():
        tensors[f"extra/{name}"] = t.detach().cpu().clone().contiguous()

    state = {
        "step": int(step),
        "epoch": int(epoch),
        "config": _to_json(dict(config or {})),
        "optimizer": optim_json,
        **({"extra_optimizers": others} if others else {}),
        "numpy_rng": (
            None if numpy_generator is None else _to_json(numpy_generator.bit_generator.state)
        ),
        "extra": _to_json(dict(extra or {})),
    }
    state_text = json.dumps(state, sort_keys=True)
    metadata = {
        "format": FORMAT,
        "version": str(VERSION),
        "digest": _digest(tensors, state_text),
        "state": state_text,
    }
    return atomic_write_bytes(path, st_save(tensors, metadata=metadata))


def _optimizer_entries(optimizer: torch.optim.Optimizer, prefix: str, tensors: dict[str, torch.Tensor]) -> dict[str, Any]:
    """Put ``optimizer``'s tensor state into ``tensors`` as ``<prefix>/<param id>/<key>``;
    return the rest of its state, JSON values only."""
    if not re.fullmatch(r"optim(-\w+)?", prefix):
        raise ValueError(f"optimizer names are letters, digits and '_': {prefix!r}")
    sd = optimizer.state_dict()
    scalar_state: dict[str, dict[str, Any]] = {}
    for pid, st in sd["state"].items():
        for key, val in st.items():
            if isinstance(val, torch.Tensor):
                tensors[f"{prefix}/{pid}/{key}"] = val.detach().cpu().clone().contiguous()
            else:
                scalar_state.setdefault(str(pid), {})[key] = _to_json(val)
    return {
        "class": type(optimizer).__name__,
        "param_groups": _to_json(sd["param_groups"]),
        "state_ids": [int(pid) for pid in sd["state"]],
        "scalar_state": scalar_state,
    }


# ---------------------------------------------------------------------------------------
# Load


def section(tensors: Mapping[str, torch.Tensor], prefix: str) -> dict[str, torch.Tensor]:
    """The tensors stored under ``prefix`` (e.g. ``"model/"``, or a caller's ``"target/"`` in
    :attr:`CheckpointInfo.extra_tensors`), keyed without it."""
    return {k.removeprefix(prefix): v for k, v in tensors.items() if k.startswith(prefix)}


def read_checkpoint(path: str | Path) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """Read and verify a checkpoint: ``(tensors by name, state JSON)``; nothing is loaded anywhere.

    Raises :class:`CheckpointError` for a missing, foreign, truncated or corrupt file.
    """
    p = Path(path)

    def fail(reason: str) -> CheckpointError:
        return CheckpointError(f"{p}: {reason}")

    try:
        with open(p, "rb") as f:
            # The safetensors layout: 8-byte little-endian header length, JSON header,
            # tensor data. The header is checked before the (possibly large) rest is read.
            size = os.fstat(f.fileno()).st_size
            head = f.read(8)
            if len(head) < 8:
                raise fail("not a safetensors file (too short)")
            n = int.from_bytes(head, "little")
            if n > min(size - 8, MAX_HEADER_BYTES):
                raise fail("not a safetensors file (bad header length; truncated or foreign file)")
            header_bytes = f.read(n)
            meta = _metadata(header_bytes, fail)
            data = head + header_bytes + f.read()
    except OSError as exc:
        raise fail(f"cannot read checkpoint ({exc.strerror or first_line(exc)})") from None
    try:
        tensors = st_load(data)
    except Exception as exc:  # the safetensors parser raises its own error types
        raise fail(f"corrupt checkpoint ({first_line(exc)})") from None
    state_text = meta.get("state")
    if not isinstance(state_text, str):
        raise fail("corrupt checkpoint (no state metadata)")
    covered = None if meta["version"] == "1" else state_text
    if _digest(tensors, covered) != meta.get("digest"):
        raise fail("corrupt checkpoint (checksum mismatch)")
    try:
        state = json.loads(state_text)
        int(state["step"])
        int(state["epoch"])
    except (KeyError, TypeError, ValueError, RecursionError):
        raise fail("corrupt checkpoint (unreadable state metadata)") from None
    return tensors, state


def _metadata(header: bytes, fail: Callable[[str], CheckpointError]) -> dict[str, Any]:
    """The ``__metadata__`` of a safetensors header, when it is a latentdrive checkpoint's."""
    try:
        parsed = json.loads(header)
    except (UnicodeDecodeError, ValueError, RecursionError):
        raise fail("not a safetensors file (unreadable header)") from None
    meta = parsed.get("__metadata__") if isinstance(parsed, dict) else None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise fail("not a latentdrive checkpoint (missing format metadata)")
    if meta.get("version") not in _READABLE:
        raise fail(f"checkpoint format version {meta.get('version')!r}, this latentdrive reads "
                   f"{', '.join(_READABLE)}")
    return meta


def _describe_mismatch(
    file_sd: Mapping[str, torch.Tensor], model_sd: Mapping[str, torch.Tensor]
) -> str:
    missing = sorted(set(model_sd) - set(file_sd))
    unexpected = sorted(set(file_sd) - set(model_sd))
    parts = []
    if missing:
        parts.append(f"missing {', '.join(missing[:3])}{' …' if len(missing) > 3 else ''}")
    if unexpected:
        parts.append(f"unexpected {', '.join(unexpected[:3])}{' …' if len(unexpected) > 3 else ''}")
    for name in sorted(set(file_sd) & set(model_sd)):
        a, b = tuple(file_sd[name].shape), tuple(model_sd[name].shape)
        if a != b:
            parts.append(f"{name} has shape {a} in the file but {b} in the model")
            break
    return "; ".join(parts)


def _optimizer_state(oj: Mapping[str, Any] | None, tensors: Mapping[str, torch.Tensor],
                     optimizer: torch.optim.Optimizer, prefix: str,
                     fail: Callable[[str], CheckpointError]) -> dict[str, Any]:
    """The optimizer ``state_dict`` a checkpoint holds (its JSON part ``oj``, its tensors
    under ``prefix/``), checked against ``optimizer``."""
    if not oj:
        raise fail("checkpoint holds no optimizer state" if prefix == "optim"
                   else f"checkpoint holds no state of optimizer {prefix.removeprefix('optim-')!r}")
    if oj.get("class") != type(optimizer).__name__:
        have, want = type(optimizer).__name__, oj.get("class")
        raise fail(f"optimizer is {have} but the checkpoint holds {want}")
    groups = oj["param_groups"]
    own = optimizer.param_groups
    if len(groups) != len(own) or any(
        len(g["params"]) != len(o["params"]) for g, o in zip(groups, own, strict=False)
    ):
        raise fail("optimizer parameter groups differ from the checkpoint's")
    # Map the file's parameter ids onto the live parameters to check state shapes.
    params = [q for g in own for q in g["params"]]
    ids = [i for g in groups for i in g["params"]]
    by_id = dict(zip(ids, params, strict=True))
    opt_state: dict[int, dict[str, Any]] = {}
    for pid in oj["state_ids"]:
        opt_state[int(pid)] = dict(_from_json(oj["scalar_state"].get(str(pid), {})))
    for name, t in tensors.items():
        if not name.startswith(f"{prefix}/"):
            continue
        _, pid_s, key = name.split("/", 2)
        pid = int(pid_s)
        if pid not in opt_state or pid not in by_id:
            raise fail(f"optimizer state for unknown parameter {pid}")
        q = by_id[pid]
        if t.ndim > 0 and tuple(t.shape) != tuple(q.shape):
            raise fail(
                f"optimizer state {key} of parameter {pid} has shape {tuple(t.shape)} "
                f"but the parameter has {tuple(q.shape)}"
            )
        opt_state[pid][key] = t
    return {"state": opt_state, "param_groups": _from_json(groups)}


def load_checkpoint(
    path: str | Path,
    model: nn.Module,
    optimizer: torch.optim.Optimizer | None = None,
    *,
    torch_generator: torch.Generator | None = None,
    numpy_generator: np.random.Generator | None = None,
    extra_optimizers: Mapping[str, torch.optim.Optimizer] | None = None,
) -> CheckpointInfo:
    """Load a checkpoint written by :func:`save_checkpoint` into ``model`` (and the rest).

    ``optimizer``, ``torch_generator`` and ``numpy_generator`` are restored in place when
    given; the file must then hold their state. Tensors are copied onto the devices of the
    model's parameters. Raises :class:`CheckpointError` when the file is unreadable, or
    when its model or optimizer differs in architecture from the ones given; in that case
    nothing has been modified.
    """
    p = Path(path)

    def fail(reason: str) -> CheckpointError:
        return CheckpointError(f"{p}: {reason}")

    tensors, state = read_checkpoint(p)
    model_sd = model.state_dict()
    file_sd = {k[len("model/"):]: v for k, v in tensors.items() if k.startswith("model/")}
    mismatch = _describe_mismatch(file_sd, model_sd)
    if mismatch:
        raise fail(f"checkpoint architecture differs from the model: {mismatch}")

    wanted = {"optim": optimizer} if optimizer is not None else {}
    wanted.update({f"optim-{name}": opt for name, opt in (extra_optimizers or {}).items()})
    optim_sds: dict[str, dict[str, Any]] = {}
    for prefix, opt in wanted.items():
        try:
            oj = state.get("optimizer") if prefix == "optim" else \
                (state.get("extra_optimizers") or {}).get(prefix.removeprefix("optim-"))
            optim_sds[prefix] = _optimizer_state(oj, tensors, opt, prefix, fail)
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            if isinstance(exc, CheckpointError):
                raise
            raise fail(f"corrupt checkpoint (unreadable optimizer state: {first_line(exc)})") from None

    if torch_generator is not None and "rng/torch" not in tensors:
        raise fail("checkpoint holds no torch generator state")
    if numpy_generator is not None and state.get("numpy_rng") is None:
        raise fail("checkpoint holds no numpy generator state")

    # Everything matches: only now modify the caller's objects.
    try:
        model.load_state_dict(file_sd, strict=True)
        for prefix, opt in wanted.items():
            opt.load_state_dict(optim_sds[prefix])
        if torch_generator is not None:
            torch_generator.set_state(tensors["rng/torch"])
        if numpy_generator is not None:
            numpy_generator.bit_generator.state = _from_json(state["numpy_rng"])
    except (RuntimeError, ValueError, TypeError, KeyError) as exc:
        raise fail(f"cannot restore checkpoint ({first_line(exc)})") from None

    extra_tensors = {k[len("extra/"):]: v for k, v in tensors.items() if k.startswith("extra/")}
    return CheckpointInfo(
        path=p,
        step=int(state["step"]),
        epoch=int(state["epoch"]),
        config=dict(state.get("config") or {}),
        extra=dict(_from_json(state.get("extra") or {})),
        extra_tensors=extra_tensors,
    )
