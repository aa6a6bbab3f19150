"""Do the vehicles survive the bottleneck? Object-level scores for reconstructions.

The mean squared error says little about the few cells that matter: a map with every
vehicle erased scores well, because vehicles cover about 1% of the cells. These functions
count vehicles instead. A *vehicle* is a connected blob (8-neighbourhood, one frame) of
non-zero cells in a clean vehicle channel (HV or AV). It counts as *recovered* when the
reconstruction reaches at least ``rel_threshold`` (default half) of the blob's peak value
somewhere on the blob or within ``tolerance`` cells of it (default 1 cell, 1.5 m at the
default grid: the denoising input itself is off by about that much, its position noise
being 0.75 m). A faded car still counts; a car that is gone or drawn elsewhere does not.
*Precision* guards the other side: the share of reconstructed cells at or above
``cell_threshold`` that lie within ``tolerance`` cells of a real vehicle. A model that
paints everything bright recovers every vehicle and has a low precision.

Limits, by construction: vehicles whose footprints touch (a queue) form one blob and
count once; with a tolerance, a blob can be "recovered" by a neighbouring car's
brightness; and recall is relative to each blob's peak while precision uses a fixed
threshold, so a very faint car (a stopped car seen at speed has peak 0.1) counts as
recovered by a haze that precision does not see. Such faint cars are rare in the study's
data (under 0.1% of blobs have a peak below 0.3).

All functions are pure torch, vectorized over the batch and frames; masks and maps are
``(N, H, W)`` with ``N`` any number of frames.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor

from latentdrive.observe.objects import label_blobs

__all__ = ["REACH_CELLS", "VehicleCounts", "bright_cell_reach", "label_blobs", "vehicle_counts"]

#: Distances (cells) at which :func:`bright_cell_reach` counts drawn cells by default.
REACH_CELLS: tuple[int, ...] = (1, 2, 3, 5, 8)


class VehicleCounts(NamedTuple):
    """Counts summed over frames; add two with :meth:`plus`."""

    vehicles: int  #: vehicle blobs in the clean target
    recovered: int  #: of those, how many the reconstruction shows (see module doc)
    bright_cells: int  #: reconstructed cells at or above the cell threshold
    bright_on_vehicles: int  #: of those, how many lie on or next to a real vehicle

    def plus(self, other: VehicleCounts) -> VehicleCounts:
        # Not `+`, which on a NamedTuple concatenates.
        return VehicleCounts(*(a + b for a, b in zip(self, other, strict=True)))

    @staticmethod
    def total(counts: Iterable[VehicleCounts]) -> VehicleCounts:
        """The sum of ``counts`` (all zero when empty)."""
        out = VehicleCounts(0, 0, 0, 0)
        for c in counts:
            out = out.plus(c)
        return out

    @property
    def recall(self) -> float:
        """Recovered vehicles / vehicles (NaN without vehicles)."""
        return self.recovered / self.vehicles if self.vehicles else float("nan")

    @property
    def precision(self) -> float:
        """Bright cells on or next to vehicles / bright cells (NaN without bright cells)."""
        return self.bright_on_vehicles / self.bright_cells if self.bright_cells else float("nan")


def vehicle_counts(
    recon: Tensor,
    target: Tensor,
    *,
    rel_threshold: float = 0.5,
    cell_threshold: float = 0.25,
    tolerance: int = 1,
) -> VehicleCounts:
    """Vehicle recovery of reconstructions ``recon`` of clean vehicle maps ``target``.

    Both are ``(N, H, W)`` in [0, 1] (cell values of one vehicle channel, any number of
    frames). Returns :class:`VehicleCounts`; see the module doc for the rules.
    """
    if recon.shape != target.shape or target.ndim != 3:
        raise ValueError(
            f"expected equal (N, H, W) shapes, got {tuple(recon.shape)} and {tuple(target.shape)}"
        )
    if tolerance < 0:
        raise ValueError(f"tolerance must be >= 0 cells, got {tolerance}")
    mask = target > 0
    k_size = 2 * tolerance + 1
    # Each cell's largest reconstruction within `tolerance` cells: its max over a blob's
    # cells is the reconstruction's max over the blob grown by `tolerance`.
    reach = F.max_pool2d(recon.unsqueeze(1), k_size, stride=1, padding=tolerance).squeeze(1)
    labels = label_blobs(mask).flatten()
    on = labels > 0
    blob_ids, inverse = torch.unique(labels[on], return_inverse=True)
    k = int(blob_ids.numel())
    recovered = 0
    if k:
        peak_t = torch.zeros(k, dtype=target.dtype, device=target.device)
        peak_t = peak_t.scatter_reduce(0, inverse, target.flatten()[on], "amax", include_self=False)
        peak_r = torch.zeros(k, dtype=recon.dtype, device=recon.device)
        peak_r = peak_r.scatter_reduce(0, inverse, reach.flatten()[on], "amax", include_self=False)
        recovered = int((peak_r >= rel_threshold * peak_t).sum())
    near = _near(mask, tolerance)
    bright = recon >= cell_threshold
    return VehicleCounts(
        vehicles=k,
        recovered=recovered,
        bright_cells=int(bright.sum()),
        bright_on_vehicles=int((bright & near).sum()),
    )


def bright_cell_reach(
    recon: Tensor,
    target: Tensor,
    tolerances: Iterable[int] = REACH_CELLS,
    *,
    cell_threshold: float = 0.25,
) -> tuple[int, tuple[int, ...]]:
    """Where the drawn cells lie: how far reconstructed vehicle cells are from real vehicles.

    ``recon`` and ``target`` are ``(N, H, W)`` as for :func:`vehicle_counts`. Returns the
    number of cells of ``recon`` at or above ``cell_threshold`` and, for each tolerance k
    (cells, in the order given), how many of them lie within k cells (Chebyshev distance,
    so a (2k+1)-cell square) of a non-zero ``target`` cell of the same frame. At k = 1 the
    count is :meth:`VehicleCounts.bright_on_vehicles`: the precision's numerator. A
    decoder that draws cars in about the right place with a blurred outline has its drawn
    cells within 2–3 cells; one that draws cars where there are none has them far away.
    """
    if recon.shape != target.shape or target.ndim != 3:
        raise ValueError(
            f"expected equal (N, H, W) shapes, got {tuple(recon.shape)} and {tuple(target.shape)}"
        )
    ks = tuple(int(k) for k in tolerances)
    if any(k < 0 for k in ks):
        raise ValueError(f"tolerances must be >= 0 cells, got {ks}")
    bright = recon >= cell_threshold
    mask = target > 0
    return int(bright.sum()), tuple(int((bright & _near(mask, k)).sum()) for k in ks)


def _near(mask: Tensor, k: int) -> Tensor:
    """Cells within ``k`` cells (Chebyshev distance) of a True cell of boolean masks ``(N, H, W)``."""
    return F.max_pool2d(mask.to(torch.float32).unsqueeze(1), 2 * k + 1, stride=1, padding=k).squeeze(1) > 0
