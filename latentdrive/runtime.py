"""Where and how torch runs: the device a config names, thread count and determinism for a run."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator

import torch

__all__ = ["check_device", "resolve_device", "torch_settings"]


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
