"""Where and how torch runs: the device a config names, its numeric precision, thread count and
determinism for a run.

One ``precision`` setting (``auto|fp32|bf16``) serves every network (the BNN, the frozen
encoder, the VFAN learner): :func:`resolve_precision` turns it into a dtype for a device,
and :func:`autocast` runs a block in it. ``auto`` picks bf16 autocast on CPUs with AMX-BF16
matrix units, where it is faster, and fp32 elsewhere: where bf16 is emulated it is slower;
on CPUs with AVX512-BF16 but no AMX oneDNN's kernels return non-finite weight gradients
for strided 3D convolutions (:func:`cpu_bf16_gradients_sound`); and on CUDA these small
networks and batches are bound by the host's kernel launches, not by arithmetic, so bf16's
extra casts made them no faster (measured on an H100: docs/performance.md, "On one GPU").
"""

from __future__ import annotations

import contextlib
import functools
import os
import warnings
from collections.abc import Iterator
from contextlib import AbstractContextManager
from pathlib import Path
from typing import Literal

import torch

__all__ = ["PRECISIONS", "Precision", "autocast", "available_memory", "bf16_conv_gradients_agree", "check_device", "cpu_bf16_gradients_sound", "cpu_has_bf16",
           "onednn", "resolve_device", "resolve_precision", "torch_settings", "usable_cpus"]

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
    """Whether this CPU has AMX-BF16 matrix units, where bf16 autocast is faster than fp32
    (`latentdrive bench --bottleneck` and `bench --train` measure both in one run)."""
    get = getattr(torch.cpu, "get_capabilities", None)
    if get is None:  # older torch: no way to tell, so never guess bf16
        return False
    return bool(get().get("amx_bf16"))


def bf16_conv_gradients_agree() -> bool:
    """Whether bf16 autocast, with torch's backends as they are set now, gives the weight
    gradient of the BNN encoder's last stage that fp32 gives (to bf16's precision).

    The convolution: 48 × 16 channels, a 2 × 4 × 8 input, a 3 × 3 × 3 kernel, stride
    1 × 2 × 2. Its data come from a generator of its own, leaving torch's global one untouched.
    """
    def grad(x: torch.Tensor, weight: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
        w = weight.clone().requires_grad_(True)
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=dtype == torch.bfloat16):
            y = torch.nn.functional.conv3d(x, w, stride=(1, 2, 2), padding=1)
        y.float().sum().backward()
        assert w.grad is not None
        return w.grad

    # A caller may be under no_grad, inference mode or its own autocast: the check is not.
    with torch.inference_mode(False), torch.enable_grad():
        g = torch.Generator().manual_seed(0)
        x = torch.rand(48, 16, 2, 4, 8, generator=g)
        weight = (torch.rand(16, 16, 3, 3, 3, generator=g) - 0.5) * 0.1
        low = grad(x, weight, torch.bfloat16)
        ref = grad(x, weight, torch.float32)
    return bool(torch.isfinite(low).all() and torch.allclose(low, ref, rtol=0.05, atol=0.05 * float(ref.abs().max())))


@functools.cache
def cpu_bf16_gradients_sound() -> bool:
    """:func:`bf16_conv_gradients_agree` through oneDNN, once per process.

    torch 2.13's oneDNN kernels for AVX512-BF16 without AMX (``jit_bf16:avx512_core_bf16``)
    return inf or far-off weight gradients for that convolution: a BNN trained in bf16 there
    reads NaN from its second step.
    """
    with onednn(True):
        return bf16_conv_gradients_agree()


def onednn(enabled: bool) -> AbstractContextManager[object]:
    """oneDNN on or off for a block, its other flags (determinism, TF32) as they are."""
    m = torch.backends.mkldnn
    return m.flags(enabled=enabled, deterministic=m.deterministic, allow_tf32=m.allow_tf32,
                   fp32_precision=m.fp32_precision)


def resolve_precision(spec: str, device: torch.device) -> torch.dtype:
    """The compute dtype of ``spec`` on ``device``: ``torch.float32`` or ``torch.bfloat16``.

    ``auto`` → bf16 on CPUs with AMX-BF16 (:func:`cpu_has_bf16`) whose kernels pass
    :func:`cpu_bf16_gradients_sound`, fp32 elsewhere, CUDA included (see the module's note). ``fp32`` and ``bf16`` are taken
    as they are (:func:`torch_settings` makes an explicit bf16 sound where the kernels are not).
    """
    if spec not in PRECISIONS:
        raise ValueError(f"precision must be one of {', '.join(PRECISIONS)}, got {spec!r}")
    if spec == "fp32":
        return torch.float32
    if spec == "bf16":
        return torch.bfloat16
    if device.type == "cpu" and cpu_has_bf16() and cpu_bf16_gradients_sound():
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
def torch_settings(enabled: bool, device: torch.device, num_threads: int,
                   dtype: torch.dtype = torch.float32) -> Iterator[None]:
    """Set deterministic algorithms and the thread count for a run; restore the process's after.

    A bf16 run on a CPU whose oneDNN bf16 gradients are unsound
    (:func:`cpu_bf16_gradients_sound`) runs without oneDNN: finite gradients at bf16's
    precision (where oneDNN's are inf), but much slower than fp32, so it warns; ``auto``
    never chooses it.
    """
    if dtype == torch.bfloat16 and device.type == "cpu" and not cpu_bf16_gradients_sound():
        warnings.warn("precision bf16: this CPU's oneDNN bf16 kernels return non-finite convolution "
                      "gradients, so the run goes without oneDNN, much slower than fp32; "
                      "precision auto or fp32 avoids it", RuntimeWarning, stacklevel=3)
        backend = onednn(False)
    else:
        backend = contextlib.nullcontext()
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
        with backend:
            yield
    finally:
        torch.use_deterministic_algorithms(prev, warn_only=prev_warn)
        torch.backends.cudnn.benchmark = prev_bench
        torch.set_num_threads(prev_threads)


def usable_cpus() -> int:
    """CPUs this process may run on (its affinity mask, which a container or ``taskset``
    can narrow below the machine's count)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def available_memory() -> int | None:
    """Bytes of memory available to new allocations without swapping: the kernel's
    ``MemAvailable``, or less where this process's cgroup (a container, a Slurm job) caps
    it; None where neither can be read (not Linux)."""
    have = None
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    have = int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    for cap_file, used_file in _cgroup_memory_files():
        try:
            cap = cap_file.read_text().strip()
            if cap != "max" and int(cap) < 2**60:  # v1 writes "no limit" as a huge number
                left = int(cap) - int(used_file.read_text())
                have = left if have is None else min(have, left)
        except (OSError, ValueError):
            pass
    return have


def _cgroup_memory_files() -> list[tuple[Path, Path]]:
    """(limit, usage) files of this process's memory cgroup: v2's group named in
    ``/proc/self/cgroup``, and v1's controller as a container sees it."""
    files = [(Path("/sys/fs/cgroup/memory/memory.limit_in_bytes"), Path("/sys/fs/cgroup/memory/memory.usage_in_bytes"))]
    try:
        lines = Path("/proc/self/cgroup").read_text().splitlines()
    except OSError:
        return files
    for line in lines:
        if line.startswith("0::"):
            folder = Path("/sys/fs/cgroup") / line[3:].strip().lstrip("/")
            files.append((folder / "memory.max", folder / "memory.current"))
    return files
