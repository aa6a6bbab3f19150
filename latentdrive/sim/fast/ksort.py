"""A stable key sort for the kernels (insertion sort when short, merge sort otherwise).

Hand-written rather than numpy's ``argsort``: it sorts in place with caller-provided
buffers (the kernels do not allocate), and compiles quickly.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from latentdrive.sim.fast._jit import njit

__all__ = ["sort_by_key"]

# Runs this short are sorted by insertion, which is fastest there.
_RUN = 16


@njit
def _insertion(keys: NDArray[np.float64], vals: NDArray[np.int64], lo: int, hi: int) -> None:
    for k in range(lo + 1, hi):
        key, val = keys[k], vals[k]
        q = k
        while q > lo and keys[q - 1] > key:
            keys[q] = keys[q - 1]
            vals[q] = vals[q - 1]
            q -= 1
        keys[q], vals[q] = key, val


@njit
def sort_by_key(keys: NDArray[np.float64], vals: NDArray[np.int64], n: int,
                tk: NDArray[np.float64], tv: NDArray[np.int64]) -> None:
    """Sort ``keys[:n]`` ascending, carrying ``vals[:n]`` along; equal keys keep their order.

    O(n log n): insertion-sorted runs of 16, merged bottom-up through ``tk``/``tv`` (at
    least ``n`` long).
    """
    for lo in range(0, n, _RUN):
        _insertion(keys, vals, lo, min(lo + _RUN, n))
    if n <= _RUN:
        return
    width = _RUN
    while width < n:
        for lo in range(0, n, 2 * width):
            mid, hi = min(lo + width, n), min(lo + 2 * width, n)
            a, c, k = lo, mid, lo
            while a < mid and c < hi:
                if keys[c] < keys[a]:
                    tk[k], tv[k] = keys[c], vals[c]
                    c += 1
                else:
                    tk[k], tv[k] = keys[a], vals[a]
                    a += 1
                k += 1
            while a < mid:
                tk[k], tv[k] = keys[a], vals[a]
                a += 1
                k += 1
            while c < hi:
                tk[k], tv[k] = keys[c], vals[c]
                c += 1
                k += 1
        for k in range(n):
            keys[k], vals[k] = tk[k], tv[k]
        width *= 2
