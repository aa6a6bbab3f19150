"""Where and how torch runs: the device a config names, its numeric precision, thread count and
determinism for a run.

One ``precision`` setting (``auto|fp32|bf16``) serves every network (the BNN, the frozen
encoder, the VFAN learner): :func:`resolve_precision` turns it into a dtype for a device,
and :func:`autocast` runs a block in it. ``auto`` picks bf16 autocast on CUDA and on CPUs
with bf16 matrix units (AMX-BF16 or AVX512-BF16), where it is faster, and fp32 elsewhere,
where bf16 is emulated and slower.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from contextlib import AbstractContextManager
from typing import Literal

import torch

__all__ = ["PRECISIONS", "Precision", "autocast", "check_device", "cpu_has_bf16", "resolve_device",
           "resolve_precision", "torch_settings", "usable_cpus"]

Precision = Literal["auto", "fp32", "bf16"]
#: The values of every config's ``precision`` field.
PRECISIONS: tuple[str, ...] = ("auto", "fp32", "bf16")


def check_device(v: str) -> str:
    """Validate a device spec: ``'auto'``, ``'cpu'``, ``'cuda'`` or ``'cuda:N'`` (config validator)."""
    ok = v in ("auto", "cpu", "cuda") or (v.startswith("cuda:") and v[5:].isdigit())
    if not ok:
        raise ValueError(f"expected 'auto', 'cpu', 'cuda' or 'cuda:N', got {v!r}")
    return v


def resolve_device(spec: str) -> torch.device:
    """``'auto'`` → CUDA if available, else CPU; otherwise ``torch.device(spec)``."""
    if spec == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(spec)


def cpu_has_bf16() -> bool:
    """Whether this CPU has bf16 matrix instructions (AMX-BF16 or AVX512-BF16)."""
    get = getattr(torch.cpu, "get_capabilities", None)
    if get is None:  # older torch: no way to tell, so never guess bf16
        return False
    caps = get()
    return bool(caps.get("amx_bf16") or caps.get("avx512_bf16"))


def resolve_precision(spec: str, device: torch.device) -> torch.dtype:
    """The compute dtype of ``spec`` on ``device``: ``torch.float32`` or ``torch.bfloat16``.

    ``auto`` → bf16 on CUDA and on CPUs with bf16 matrix units (:func:`cpu_has_bf16`),
    fp32 elsewhere. ``fp32`` and ``bf16`` are taken as they are.
    """
    if spec not in PRECISIONS:
        raise ValueError(f"precision must be one of {', '.join(PRECISIONS)}, got {spec!r}")
    if spec == "fp32":
        return torch.float32
    if spec == "bf16":
        return torch.bfloat16
    if device.type == "cuda" or (device.type == "cpu" and cpu_has_bf16()):
        return torch.bfloat16
    return torch.float32


def autocast(dtype: torch.dtype, device: torch.device) -> AbstractContextManager[object]:
    """A block in ``dtype``: autocast for bf16 (weights and optimizer state stay fp32), nothing for fp32.

    Losses should be computed on ``.float()`` outputs outside or at the end of the block.
    """
    if dtype == torch.float32:
        return contextlib.nullcontext()
    return torch.autocast(device_type=device.type, dtype=dtype)


@contextlib.contextmanager
def torch_settings(enabled: bool, device: torch.device, num_threads: int) -> Iterator[None]:
    """Set deterministic algorithms and the thread count for a run; restore the process's after."""
    prev = torch.are_deterministic_algorithms_enabled()
    prev_warn = torch.is_deterministic_algorithms_warn_only_enabled()
    prev_bench = torch.backends.cudnn.benchmark
    prev_threads = torch.get_num_threads()
    if num_threads > 0:
        torch.set_num_threads(num_threads)
    if enabled:
        if device.type == "cuda":
            # cuBLAS needs a fixed workspace for reproducible matmuls.
            os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
            torch.backends.cudnn.benchmark = False
        torch.use_deterministic_algorithms(True, warn_only=device.type != "cpu")
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(prev, warn_only=prev_warn)
        torch.backends.cudnn.benchmark = prev_bench
        torch.set_num_threads(prev_threads)


def usable_cpus() -> int:
    """CPUs this process may run on (its affinity mask, which a container or ``taskset``
    can narrow below the machine's count)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
