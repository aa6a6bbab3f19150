"""The vehicles of a VelocityMap found by a fixed detector and tracker: ``state_dqn.py --reader blobs``.

Does the attention reader's learned stem hold the map's policies back, or what the map
shows? This reader replaces the stem with rules. A *vehicle* is a connected blob
(8-neighbourhood) of non-zero cells in one frame's HV or AV channel, as in
:mod:`latentdrive.bnn.vehicles`; its place is the mean of its cell centres in metres in the
observer's frame (x ahead, y to its right), its value the mean of its cells (the map's
eq. 13 of the relative speed's size), its size the cell count. A vehicle of the newest
frame is matched to the nearest vehicle of the same channel in the frame before within
:data:`GATE` metres; the displacement between the two is its motion relative to the
observer over one policy step (the map's frames are one step apart), signed, which the
map's values alone do not give. Two cars whose footprints touch are one blob; sensor
noise moves the centres and drops vehicles from frames, as it does for any reader of the
map.

Each observation becomes the same layout as :func:`latentdrive.observe.state.state_features`
so that the ego-attention network of ``scripts/state_copy.py`` reads it unchanged: the AV's
part is its speed (the MV channel's peak, ``|v| / max_speed``) in the last two frames and
the newest frame's road channel averaged over ``pool`` × ``pool`` cells; then the ``k``
nearest vehicles of the newest frame, nearest first, :data:`PER_VEHICLE` values each:
x, y / 50, dx, dy / 20 (metres per step), value, 1 if matched, 1 if an AV, cells / 10,
1 (present); zero rows where fewer.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from latentdrive.config import ObservationConfig
from latentdrive.observe.velocitymap import AV, HV, MV, RL

#: Values per vehicle; equal to :data:`latentdrive.observe.state.PER_NEIGHBOUR`, whose
#: last value is also 1 for a vehicle and 0 for padding.
PER_VEHICLE = 9
#: Metres within which a vehicle of the newest frame is matched to one of the frame before:
#: a car 15 m/s faster or slower than the observer, with its position noise, moves about
#: that far in a step of one second.
GATE = 15.0

# One frame's 8-neighbourhood inside a (observation, channel, frame, row, column) array:
# blobs never join across observations, channels or frames.
_STRUCTURE = np.zeros((3, 3, 3, 3, 3), dtype=bool)
_STRUCTURE[1, 1, 1] = True


def ego_size(cfg: ObservationConfig, pool: int) -> int:
    """Length of the AV's part of :func:`blob_features`' rows."""
    return 2 + (cfg.height // pool) * (cfg.width // pool)


def blob_features(maps: NDArray[np.float32], cfg: ObservationConfig, k: int, pool: int = 4) -> NDArray[np.float32]:
    """``(..., ego_size + k·PER_VEHICLE)`` from stacked maps ``(..., 4, T, H, W)`` (T ≥ 2) of
    geometry ``cfg``; the layout is the module docstring's."""
    *lead, c, t, h, w = maps.shape
    if c != 4 or t < 2 or (h, w) != (cfg.height, cfg.width):
        raise ValueError(f"expected maps (..., 4, T >= 2, {cfg.height}, {cfg.width}), got {maps.shape}")
    if pool < 1 or h % pool or w % pool:
        raise ValueError(f"pool must divide the map's {h} x {w} cells, got {pool}")
    x = maps.reshape(-1, 4, t, h, w)
    n_obs = x.shape[0]
    speed = x[:, MV, -2:].reshape(n_obs, 2, -1).max(-1)
    road = x[:, RL, -1].reshape(n_obs, h // pool, pool, w // pool, pool).mean((2, 4)).reshape(n_obs, -1)
    rows = vehicle_rows(x[:, [HV, AV], -2:], cfg, k)
    out = np.concatenate([speed, road, rows.reshape(n_obs, -1)], axis=1, dtype=np.float32)
    return out.reshape(*lead, -1)


def vehicle_rows(veh: NDArray[np.float32], cfg: ObservationConfig, k: int) -> NDArray[np.float32]:
    """``(N, k, PER_VEHICLE)``: the ``k`` nearest vehicles of the newest frame of ``veh``
    ``(N, 2 channels HV and AV, 2 frames oldest first, H, W)``, matched to the older frame."""
    n_obs, _, _, h, _ = veh.shape
    rows = np.zeros((n_obs, k, PER_VEHICLE), dtype=np.float32)
    labels, n = ndimage.label(veh > 0, _STRUCTURE)
    if n == 0:
        return rows
    cells = np.flatnonzero(labels)
    blob = labels.ravel()[cells] - 1
    count = np.bincount(blob, minlength=n).astype(np.float64)

    def mean(values: NDArray[np.generic]) -> NDArray[np.float64]:
        return np.bincount(blob, weights=values.astype(np.float64), minlength=n) / count

    obs_i, ch, frame, r, col = np.unravel_index(cells, labels.shape)
    # A blob lies in one observation, channel and frame, so their means are exact.
    b_obs, b_ch, b_frame = (np.rint(mean(v)).astype(np.int64) for v in (obs_i, ch, frame))
    bx = (mean(col) + 0.5) * cfg.resolution - cfg.behind
    by = (mean(r) + 0.5) * cfg.resolution - 0.5 * h * cfg.resolution
    value = mean(veh.ravel()[cells])
    new, old = np.flatnonzero(b_frame == 1), np.flatnonzero(b_frame == 0)
    dx, dy, matched = _match(new, old, b_obs * 2 + b_ch, bx, by)
    # Nearest first within each observation; the first k of each are kept.
    order = np.lexsort((np.hypot(bx[new], by[new]), b_obs[new]))
    owner = b_obs[new][order]
    rank = np.arange(len(order)) - np.searchsorted(owner, owner, "left")
    keep = rank < k
    feats = np.stack([bx[new] / 50.0, by[new] / 50.0, dx / 20.0, dy / 20.0, value[new], matched,
                      b_ch[new].astype(np.float64), count[new] / 10.0, np.ones(len(new))], axis=1)
    rows[owner[keep], rank[keep]] = feats[order[keep]]
    return rows


def _match(new: NDArray[np.int64], old: NDArray[np.int64], group: NDArray[np.int64], bx: NDArray[np.float64],
           by: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """For blobs ``new``: the displacement (x, y) from the nearest blob of ``old`` in the
    same ``group`` within :data:`GATE`, and 1 where there is one (0 and 0 elsewhere)."""
    dx, dy, matched = np.zeros(len(new)), np.zeros(len(new)), np.zeros(len(new))
    if len(new) == 0 or len(old) == 0:
        return dx, dy, matched
    old = old[np.argsort(group[old], kind="stable")]
    lo = np.searchsorted(group[old], group[new], "left")
    hi = np.searchsorted(group[old], group[new], "right")
    span = int((hi - lo).max())
    if span == 0:
        return dx, dy, matched
    cand = lo[:, None] + np.arange(span)
    valid = cand < hi[:, None]
    cand = old[np.where(valid, cand, 0)]
    ddx, ddy = bx[new][:, None] - bx[cand], by[new][:, None] - by[cand]
    dist2 = np.where(valid, ddx**2 + ddy**2, np.inf)
    best = dist2.argmin(1)
    pick = np.arange(len(new))
    ok = dist2[pick, best] <= GATE**2
    return np.where(ok, ddx[pick, best], 0.0), np.where(ok, ddy[pick, best], 0.0), ok.astype(np.float64)
