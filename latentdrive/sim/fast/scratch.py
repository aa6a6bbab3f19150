"""Working memory of the kernels, allocated once per batch and reused for every environment.

The kernels run without numba's reference-counted allocator (it would cost atomic
reference-count updates on every call that passes arrays), so every buffer they need is
here, sized for the batch's lanes ``L`` and slots ``N``.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

__all__ = ["N_SAMPLES", "Scratch", "make_scratch"]

# Right-of-way predictions per vehicle: 0.25, 0.5, ..., 2.75 s ahead.
N_SAMPLES = 11


class Scratch(NamedTuple):
    """Buffers for one environment at a time."""

    n_on: NDArray[np.int64]  # (L,) occupants per lane
    idx: NDArray[np.int64]  # (L, N) occupant slots, sorted by s
    s: NDArray[np.float64]  # (L, N) occupant positions along the lane, metres
    cos_h: NDArray[np.float64]  # (N,) cosine and sine of each slot's heading this step
    sin_h: NDArray[np.float64]
    keys: NDArray[np.float64]  # (N,) sort keys
    order: NDArray[np.int64]  # (N,) slots in key order
    tmp_keys: NDArray[np.float64]  # (N,) merge-sort buffers
    tmp_vals: NDArray[np.int64]
    by_target_start: NDArray[np.int64]  # (L + 1,) CSR offsets: vehicles by target lane
    by_target: NDArray[np.int64]  # (N,) vehicles grouped by target lane at the start of a step
    cursor: NDArray[np.int64]  # (L,) fill positions
    changed: NDArray[np.int64]  # (N,) vehicles whose target changed since, in order
    n_changed: NDArray[np.int64]  # (1,)
    best_pair: NDArray[np.int64]  # (N,) collision pair whose impact a slot keeps
    polygons: NDArray[np.float64]  # (2, 5, 2) two closed footprints
    pred: NDArray[np.float64]  # (N, N_SAMPLES, 3) predicted x, y, heading


def make_scratch(n_lanes: int, n_slots: int) -> Scratch:
    """Buffers for environments of up to ``n_slots`` slots on ``n_lanes`` lanes."""
    n = max(n_slots, 1)
    return Scratch(
        n_on=np.zeros(n_lanes, np.int64),
        idx=np.zeros((n_lanes, n), np.int64),
        s=np.zeros((n_lanes, n)),
        cos_h=np.zeros(n),
        sin_h=np.zeros(n),
        keys=np.zeros(n),
        order=np.zeros(n, np.int64),
        tmp_keys=np.zeros(n),
        tmp_vals=np.zeros(n, np.int64),
        by_target_start=np.zeros(n_lanes + 1, np.int64),
        by_target=np.zeros(n, np.int64),
        cursor=np.zeros(n_lanes, np.int64),
        changed=np.zeros(n, np.int64),
        n_changed=np.zeros(1, np.int64),
        best_pair=np.zeros(n, np.int64),
        polygons=np.zeros((2, 5, 2)),
        pred=np.zeros((n, N_SAMPLES, 3)),
    )
