"""The vehicles a VelocityMap shows, found by a fixed rule: the objects reader's input.

A *vehicle* is a connected blob (8-neighbourhood, one frame) of non-zero cells in the HV or
AV channel, the definition :mod:`latentdrive.bnn.vehicles` scores reconstructions by. Of the
newest frame, each vehicle is described by its place (the mean of its cell centres, metres
in the observer's axes: x ahead, y to its right, as the map is drawn,
:func:`latentdrive.observe.velocitymap.render_frame`), its mean value (the map's eq. 13 of
its speed relative to the observer), whether it is an AV, and its size in cells. Two cars
whose footprints touch are one blob, and the sensor noise the map carries moves the places
and drops vehicles from frames, as it does for any reader of the map: these are rules, not a
tracker, and they read one frame (a detector's motion estimate between frames misled its
reader more than it informed it: docs/readers.md); a reader of several frames calls them
once per frame.

Everything is torch, vectorized over the batch, on whatever device the maps are on.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from latentdrive.observe.velocitymap import AV, HV

__all__ = ["PER_OBJECT", "label_blobs", "map_objects"]

#: Values per vehicle row of :func:`map_objects`: x / 50, y / 50 (metres), mean value, 1 if
#: an AV, cells / 10, 1 (0 in padding rows).
PER_OBJECT = 6


def label_blobs(mask: Tensor) -> Tensor:
    """8-connected components of boolean masks ``(N, H, W)`` → int64 labels ``(N, H, W)``.

    Background is 0; every blob gets one label > 0, unique across the whole batch (the
    largest flat index ``n·H·W + i·W + j + 1`` of its cells). Found by propagating the
    maximum label to 3×3 neighbours inside the mask until nothing changes, so the number
    of iterations is the largest blob's diameter in cells: a few for vehicles.
    """
    if mask.ndim != 3:
        raise ValueError(f"expected masks of shape (N, H, W), got {tuple(mask.shape)}")
    n, h, w = mask.shape
    # Labels are carried as floats: float32 holds every integer up to 2**24 (the labels of
    # 8,192 maps of 32 × 64 cells) exactly and is faster on CPU; float64 (exact up to 2**53)
    # beyond that.
    dtype = torch.float32 if n * h * w <= 2**24 else torch.float64
    ids = torch.arange(1, n * h * w + 1, device=mask.device, dtype=dtype).view(n, 1, h, w)
    m = mask.view(n, 1, h, w)
    labels = torch.where(m, ids, torch.zeros_like(ids))
    while True:
        grown = torch.where(m, _max3x3(labels), labels)
        if torch.equal(grown, labels):
            return labels.view(n, h, w).to(torch.int64)
        labels = grown


def _max3x3(x: Tensor) -> Tensor:
    """Each cell's maximum over its 3×3 neighbourhood, of non-negative ``(N, 1, H, W)``;
    as rows then columns of shifted maxima (zero padding), several times faster on CPU than
    ``max_pool2d`` for one channel."""
    p = F.pad(x, (1, 1, 1, 1))
    rows = torch.maximum(torch.maximum(p[:, :, :-2], p[:, :, 1:-1]), p[:, :, 2:])
    return torch.maximum(torch.maximum(rows[..., :-2], rows[..., 1:-1]), rows[..., 2:])


def map_objects(maps: Tensor, resolution: float, behind: float, k: int) -> Tensor:
    """The ``k`` vehicles nearest the observer in the newest frame of ``maps``.

    Args:
        maps: stacked VelocityMaps ``(B, 4, T, H, W)`` in [0, 1] (channels HV, AV, RL, MV).
        resolution: metres per cell; behind: metres the map sees behind the observer
            (``ObservationConfig``): where the cells lie.
        k: rows per observation.

    Returns:
        ``(B, k, PER_OBJECT)`` float32: per vehicle x / 50 and y / 50 (metres, observer's
        axes), mean cell value, 1 if an AV, cells / 10, and 1; nearest first (ties by
        place in the map), then rows of zeros where fewer than ``k``.
    """
    if maps.ndim != 5 or maps.shape[1] != 4:
        raise ValueError(f"expected maps of shape (B, 4, T, H, W), got {tuple(maps.shape)}")
    if k < 1:
        raise ValueError(f"k must be at least 1, got {k}")
    b, _, _, h, w = maps.shape
    newest = maps[:, [HV, AV], -1].float()  # (B, 2, H, W)
    labels = label_blobs(newest.reshape(2 * b, h, w) > 0).flatten()
    out = torch.zeros(b, k, PER_OBJECT, dtype=torch.float32, device=maps.device)
    on = torch.nonzero(labels).squeeze(1)
    if on.numel() == 0:
        return out
    ids, blob = torch.unique(labels[on], return_inverse=True)
    n = int(ids.numel())

    def total(values: Tensor) -> Tensor:
        return torch.zeros(n, dtype=torch.float64, device=maps.device).index_add_(0, blob, values.double())

    count = total(torch.ones_like(on))
    col = on % w
    row = (on // w) % h
    # Cell (i, j) is centred (j + ½)·resolution − behind ahead of the observer and
    # (i + ½)·resolution − H·resolution/2 to its right.
    x = (total(col) / count + 0.5) * resolution - behind
    y = (total(row) / count + 0.5) * resolution - 0.5 * h * resolution
    value = total(newest.flatten()[on]) / count
    # A blob's label is one of its cells' flat index + 1, so it names the (observation,
    # channel) layer the blob lies in.
    layer = (ids - 1) // (h * w)
    obs, is_av = layer // 2, layer % 2
    # Nearest first within each observation: sort by distance, then stably by observation.
    dist = torch.hypot(x, y)
    order = torch.argsort(dist, stable=True)
    order = order[torch.argsort(obs[order], stable=True)]
    owner = obs[order]
    rank = torch.arange(n, device=maps.device) - torch.searchsorted(owner, owner, side="left")
    keep = rank < k
    rows = torch.stack([x / 50.0, y / 50.0, value, is_av.double(), count / 10.0, torch.ones_like(x)], dim=1)
    out[owner[keep], rank[keep]] = rows[order[keep]].float()
    return out
