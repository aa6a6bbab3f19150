"""The compiler for the simulation kernels: numba when installed, plain Python otherwise.

Kernels are written as explicit loops over environments and vehicles so that one code
path serves both: compiled, they are the fast backend; interpreted, they give the same
results very slowly (useful only where numba cannot be installed). Compiled kernels are
cached on disk next to this package, so only the first import on a machine pays for
compilation.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar

__all__ = ["HAVE_NUMBA", "njit"]

F = TypeVar("F", bound=Callable[..., Any])

try:
    import numba

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover - exercised only without numba
    HAVE_NUMBA = False


# Disk cache, no GIL, and (private option) no reference-counted allocator.
_OPTIONS: dict[str, Any] = {"cache": True, "nogil": True, "_nrt": False}


def njit(func: F) -> F:
    """Compile ``func`` in nopython mode with IEEE semantics (no fastmath), so results do
    not depend on how many environments share a batch.

    Kernels run without numba's reference-counted allocator: they never allocate (buffers
    come from :mod:`latentdrive.sim.fast.scratch`), and a call that passes arrays then
    costs no atomic reference-count updates, which otherwise dominate small functions.
    """
    if not HAVE_NUMBA:  # pragma: no cover
        return func
    try:
        return numba.njit(**_OPTIONS)(func)
    except (KeyError, TypeError):  # pragma: no cover - a numba without the private option
        return numba.njit(cache=True, nogil=True)(func)  # type: ignore[return-value]

