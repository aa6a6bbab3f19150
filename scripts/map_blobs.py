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
map. At an episode's start the stack repeats its first frame, so every vehicle is matched
with no motion until the frames differ.

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
from latentdrive.observe.state import view_box
from latentdrive.observe.velocitymap import AV, HV, MV, RL

#: Values per vehicle; equal to :data:`latentdrive.observe.state.PER_NEIGHBOUR`, whose
#: last value is also 1 for a vehicle and 0 for padding.
PER_VEHICLE = 9
#: ``ego_motion``'s candidate turns of the observer between two frames, radians (toward its
#: right positive): a car at 10 m/s on a 20 m roundabout turns 0.5 rad a second.
TURNS = np.linspace(-0.8, 0.8, 41)
#: Seconds between two frames of the stack (one policy step at the presets' 1 Hz).
STEP_S = 1.0

#: Metres within which a track with a fitted line takes the vehicle nearest its prediction.
TRACK_GATE = 6.0
#: Metres from every vehicle of the newest frame that a vehicle put back by ``fill`` keeps:
#: about one car's length and twice the sensor's position noise.
FILL_CLEAR = 4.0
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


def blob_features(maps: NDArray[np.float32], cfg: ObservationConfig, k: int, pool: int = 4,
                  ego_motion: bool = False, frames: int = 2, fill: bool = False,
                  smooth: bool = False) -> NDArray[np.float32]:
    """``(..., ego_size + k·PER_VEHICLE)`` from stacked maps ``(..., 4, T, H, W)`` (T ≥ 2) of
    geometry ``cfg``; the layout is the module docstring's. With ``ego_motion`` the older
    frame's vehicles are first carried into the newest frame's axes by the observer's own
    motion (:func:`observer_turn`), so that a turning observer does not see the world swing.
    ``frames`` (2 to T) is how many of the newest frames the tracker follows each vehicle
    through; its motion is then the least-squares slope of its places (:func:`vehicle_rows`).
    With ``fill``, a vehicle the newest frame lost is put back where its track says it is
    (:func:`vehicle_rows`; ``frames`` ≥ 3). With ``smooth``, a tracked vehicle's place is its
    fitted line's at the newest frame instead of its newest blob's centre (the sensor's
    position noise is independent from frame to frame, so the fit averages it down)."""
    *lead, c, t, h, w = maps.shape
    if c != 4 or t < 2 or (h, w) != (cfg.height, cfg.width):
        raise ValueError(f"expected maps (..., 4, T >= 2, {cfg.height}, {cfg.width}), got {maps.shape}")
    if pool < 1 or h % pool or w % pool:
        raise ValueError(f"pool must divide the map's {h} x {w} cells, got {pool}")
    if not 2 <= frames <= t:
        raise ValueError(f"frames must be 2 to the stack's {t}, got {frames}")
    if (fill or smooth) and frames < 3:
        raise ValueError(f"fill and smooth follow a vehicle through two older frames: frames must be at least 3, got {frames}")
    x = maps.reshape(-1, 4, t, h, w)
    n_obs = x.shape[0]
    mv_peak = x[:, MV, -frames:].reshape(n_obs, frames, -1).max(-1)  # |v| / max_speed in each frame
    road = x[:, RL, -1].reshape(n_obs, h // pool, pool, w // pool, pool).mean((2, 4)).reshape(n_obs, -1)
    own = mv_peak * cfg.max_speed
    step_speed = 0.5 * (own[:, :-1] + own[:, 1:])  # (n_obs, frames - 1), m/s
    turn = (np.stack([observer_turn(x[:, RL, j - frames], x[:, RL, j - frames + 1], step_speed[:, j], cfg)
                      for j in range(frames - 1)], axis=1) if ego_motion else None)
    rows = vehicle_rows(x[:, [HV, AV], -frames:], cfg, k, turn, step_speed, fill, smooth)
    out = np.concatenate([mv_peak[:, -2:], road, rows.reshape(n_obs, -1)], axis=1, dtype=np.float32)
    return out.reshape(*lead, -1)


def _step(turn: NDArray[np.float64], speed: NDArray[np.float64]) -> NDArray[np.float64]:
    """``(..., 2)`` the observer's move over one step in the older frame's axes, metres: the
    chord of an arc at ``speed`` m/s turning by ``turn`` radians."""
    return speed[..., None] * STEP_S * np.stack([np.cos(turn / 2), np.sin(turn / 2)], axis=-1)


def _to_newer(p: NDArray[np.float64], turn: NDArray[np.float64], speed: NDArray[np.float64]) -> NDArray[np.float64]:
    """Points ``(..., 2)`` of the older frame, in the newer frame's axes, as the observer
    moved by ``turn`` and ``speed`` (broadcast over ``p``'s leading axes)."""
    q = p - _step(turn, speed)
    c, s = np.cos(turn)[..., None], np.sin(turn)[..., None]
    return np.concatenate([c * q[..., :1] + s * q[..., 1:], -s * q[..., :1] + c * q[..., 1:]], axis=-1)


def observer_turn(road_old: NDArray[np.float32], road_new: NDArray[np.float32], speed: NDArray[np.float32],
                  cfg: ObservationConfig) -> NDArray[np.float64]:
    """``(N,)`` the observer's turn between two frames, radians toward its right: the
    candidate of :data:`TURNS` under which the older road channel ``(N, H, W)``, carried by
    that turn and ``speed`` (m/s) into the newer frame, best matches the newer one (least
    squared difference over every other cell that lands inside the older frame)."""
    n, h, w = road_new.shape
    rr, cc = np.meshgrid(np.arange(0, h, 2), np.arange(0, w, 2), indexing="ij")
    q = np.stack([(cc + 0.5) * cfg.resolution - cfg.behind, (rr + 0.5) * cfg.resolution - 0.5 * h * cfg.resolution],
                 axis=-1).reshape(-1, 2)  # newer-frame cell centres (M, 2)
    turn = TURNS[None, :, None]  # (1, C, 1)
    c, s = np.cos(turn), np.sin(turn)
    # The newer frame's point q lies at R(turn)·q + step in the older frame's axes.
    step = _step(TURNS[None, :], speed.astype(np.float64)[:, None])  # (N, C, 2)
    ox = c * q[None, None, :, 0] - s * q[None, None, :, 1] + step[..., :1]
    oy = s * q[None, None, :, 0] + c * q[None, None, :, 1] + step[..., 1:]
    col = np.floor((ox + cfg.behind) / cfg.resolution).astype(np.int64)
    row = np.floor((oy + 0.5 * h * cfg.resolution) / cfg.resolution).astype(np.int64)
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    old = road_old[np.arange(n)[:, None, None], np.clip(row, 0, h - 1), np.clip(col, 0, w - 1)]
    new = road_new[:, rr.ravel(), cc.ravel()][:, None, :]
    seen = inside.sum(-1)
    err = np.where(seen > 0, np.where(inside, (old - new) ** 2, 0.0).sum(-1) / np.maximum(seen, 1), np.inf)
    # Least error first; among equals (a uniform road, nothing seen) the smallest turn.
    order = np.lexsort((np.broadcast_to(np.abs(TURNS), err.shape), err), axis=1)
    return TURNS[order[:, 0]]


def vehicle_rows(veh: NDArray[np.float32], cfg: ObservationConfig, k: int, turn: NDArray[np.float64] | None = None,
                 speed: NDArray[np.float32] | None = None, fill: bool = False,
                 smooth: bool = False) -> NDArray[np.float32]:
    """``(N, k, PER_VEHICLE)``: the ``k`` nearest vehicles of the newest frame of ``veh``
    ``(N, 2 channels HV and AV, F frames oldest first, H, W)``, each followed back through
    the older frames. With ``turn`` and ``speed`` ``(N, F - 1)``, the observer's motion
    between consecutive frames, the older frames' vehicles are first carried into the
    newest frame's axes and moved on by the observer's own steps, so that a car keeping the
    observer's speed and course stays put.

    Following: in each older frame, the vehicle of the same channel nearest the place the
    track predicts (its last place until it has two, then its fitted line), within
    :data:`GATE` metres until it has two places and :data:`TRACK_GATE` after; a frame
    without one is skipped. The motion is the least-squares slope of the track's places
    against time (with two frames, the displacement between them), metres per step.

    Filling (``fill``): the sensor drops each vehicle from a frame with probability
    ``miss_prob``, so a vehicle of the frame before that no vehicle of the newest frame
    followed back to, and that has a motion of its own (its track through the frames before
    it holds two places), is put back one step on along that motion when the place lands
    inside the map, clear of the newest frame's vehicles, and while the newest frame holds
    fewer vehicles than the frame before (:func:`_put_back`); its row is that of a vehicle of
    the newest frame (a car that left the view or hid behind another may be put back as
    well, for one step). With ``smooth``, a tracked
    vehicle's place (and a lost one's, before its step on) is its fitted line's at its own
    frame."""
    n_obs, _, f, h, _ = veh.shape
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
    if turn is not None and speed is not None:
        for j in range(f - 1):  # blobs of frames up to j, in frame j's axes, into frame j + 1's
            sel = np.flatnonzero(b_frame <= j)
            v = speed[b_obs[sel], j].astype(np.float64)
            moved = _to_newer(np.stack([bx[sel], by[sel]], axis=-1), turn[b_obs[sel], j], v)
            bx[sel], by[sel] = moved[:, 0], moved[:, 1]
        # The places now lie still in the newest frame's axes; moving each on by the
        # observer's newest velocity for the steps it lies back makes their slope the velocity
        # relative to the observer now, as the exact-state rows hold it.
        bx += speed[b_obs, f - 2].astype(np.float64) * (f - 1 - b_frame) * STEP_S
    group = b_obs * 2 + b_ch
    new = np.flatnonzero(b_frame == f - 1)
    dx, dy, matched, claimed, fitted = _track(new, b_frame, group, bx, by, f)
    if smooth:
        bx[new], by[new] = fitted
    if fill:
        lost = np.setdiff1d(np.flatnonzero(b_frame == f - 2), claimed)
        lx, ly, moving, _, (fx, fy) = _track(lost, b_frame, group, bx, by, f - 1)
        px, py = (fx, fy) if smooth else (bx[lost], by[lost])
        px, py = px + lx * STEP_S, py + ly * STEP_S
        behind, ahead, side = view_box(cfg)
        inside = (px >= -behind) & (px < ahead) & (np.abs(py) < side)
        back = _put_back(lost, moving > 0, inside, px, py, new, b_frame, group, bx, by, f)
        lost = lost[back]
        new = np.concatenate([new, lost])
        bx[lost], by[lost] = px[back], py[back]
        dx, dy, matched = (np.concatenate([a, b[back]]) for a, b in ((dx, lx), (dy, ly), (matched, moving)))
    # Nearest first within each observation; the first k of each are kept.
    order = np.lexsort((np.hypot(bx[new], by[new]), b_obs[new]))
    owner = b_obs[new][order]
    rank = np.arange(len(order)) - np.searchsorted(owner, owner, "left")
    keep = rank < k
    feats = np.stack([bx[new] / 50.0, by[new] / 50.0, dx / 20.0, dy / 20.0, value[new], matched,
                      b_ch[new].astype(np.float64), count[new] / 10.0, np.ones(len(new))], axis=1)
    rows[owner[keep], rank[keep]] = feats[order[keep]]
    return rows


def _put_back(lost: NDArray[np.int64], moving: NDArray[np.bool_], inside: NDArray[np.bool_], px: NDArray[np.float64],
              py: NDArray[np.float64], new: NDArray[np.int64], b_frame: NDArray[np.int64], group: NDArray[np.int64],
              bx: NDArray[np.float64], by: NDArray[np.float64], f: int) -> NDArray[np.bool_]:
    """Which of the blobs ``lost`` (of frame ``f`` − 2, unclaimed by the newest frame's
    tracks) :func:`vehicle_rows`' fill puts back at ``(px, py)``: those with a motion of their
    own whose place lies inside the map and at least :data:`FILL_CLEAR` metres from every
    vehicle of the same group in the newest frame (``new``; a car there is most likely the
    same one, followed by a track that claimed another), and in each group at most as many
    as the frame before holds more vehicles than the newest frame (a frame that lost none
    gets none back), farthest from the newest frame's vehicles first."""
    if len(lost) == 0:
        return np.zeros(0, dtype=bool)
    near = _nearest(px, py, group[lost], new, group, bx, by, np.full(len(lost), 1e9))  # any distance
    clear = np.where(near >= 0, np.hypot(px - bx[near], py - by[near]), np.inf)
    ok = moving & inside & (clear >= FILL_CLEAR)
    n_groups = int(group.max()) + 1
    older = np.bincount(group[b_frame == f - 2], minlength=n_groups)
    newest = np.bincount(group[new], minlength=n_groups)
    allowed = np.maximum(older - newest, 0)[group[lost]]
    # Rank within each group, farthest clear first; candidates that are not ok rank last.
    order = np.lexsort((-np.where(ok, clear, -1.0), group[lost]))
    g = group[lost][order]
    rank = np.empty(len(lost), dtype=np.int64)
    rank[order] = np.arange(len(order)) - np.searchsorted(g, g, "left")
    return ok & (rank < allowed)


def _track(new: NDArray[np.int64], b_frame: NDArray[np.int64], group: NDArray[np.int64], bx: NDArray[np.float64],
           by: NDArray[np.float64], f: int
           ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.int64],
                      tuple[NDArray[np.float64], NDArray[np.float64]]]:
    """For blobs ``new`` of frame ``f`` − 1 (frames counted from 0): the slope (x, y) of the
    places of each one's track back through the frames before (:func:`vehicle_rows`), 1
    where the track holds an older place (0, 0 and 0 elsewhere), the blobs of frame
    ``f`` − 2 that some track took, and the fitted line's place (x, y) at frame ``f`` − 1
    (the blob's own where the track holds one place)."""
    x0, y0 = bx[new], by[new]
    # Least-squares sums over each track's places; time in steps, 0 at the newest frame.
    npts, st, stt = np.ones(len(new)), np.zeros(len(new)), np.zeros(len(new))  # places, Σt, Σt²
    sx, sy, stx, sty = x0.copy(), y0.copy(), np.zeros(len(new)), np.zeros(len(new))
    lastx, lasty = x0.copy(), y0.copy()
    ux, uy = np.zeros(len(new)), np.zeros(len(new))
    claimed = np.zeros(0, dtype=np.int64)
    for j in range(f - 2, -1, -1):
        t = float(j - (f - 1))
        line = npts >= 2
        # On the fitted line (through the places' mean time and place) once there are two.
        tbar = st / npts
        qx = np.where(line, sx / npts + ux * (t - tbar), lastx)
        qy = np.where(line, sy / npts + uy * (t - tbar), lasty)
        idx = _nearest(qx, qy, group[new], np.flatnonzero(b_frame == j), group, bx, by,
                       np.where(line, TRACK_GATE, GATE))
        ok = idx >= 0
        if j == f - 2:
            claimed = idx[ok]
        px, py = bx[idx[ok]], by[idx[ok]]
        npts[ok] += 1
        st[ok] += t
        stt[ok] += t * t
        sx[ok] += px
        sy[ok] += py
        stx[ok] += t * px
        sty[ok] += t * py
        lastx[ok], lasty[ok] = px, py
        fit = npts >= 2
        var = stt[fit] - st[fit] ** 2 / npts[fit]
        ux[fit] = (stx[fit] - st[fit] * sx[fit] / npts[fit]) / var
        uy[fit] = (sty[fit] - st[fit] * sy[fit] / npts[fit]) / var
    tbar = st / npts
    fitted = (sx / npts - ux * tbar, sy / npts - uy * tbar)  # the line at t = 0
    return ux / STEP_S, uy / STEP_S, (npts >= 2).astype(np.float64), claimed, fitted


def _nearest(qx: NDArray[np.float64], qy: NDArray[np.float64], qgroup: NDArray[np.int64], cand: NDArray[np.int64],
             group: NDArray[np.int64], bx: NDArray[np.float64], by: NDArray[np.float64],
             gate: NDArray[np.float64]) -> NDArray[np.int64]:
    """For each query place ``(qx, qy)`` of group ``qgroup``: the blob of ``cand`` in the same
    group nearest it within its ``gate`` metres, or -1."""
    out = np.full(len(qx), -1, dtype=np.int64)
    if len(qx) == 0 or len(cand) == 0:
        return out
    cand = cand[np.argsort(group[cand], kind="stable")]
    lo = np.searchsorted(group[cand], qgroup, "left")
    hi = np.searchsorted(group[cand], qgroup, "right")
    span = int((hi - lo).max())
    if span == 0:
        return out
    slots = lo[:, None] + np.arange(span)
    valid = slots < hi[:, None]
    ids = cand[np.where(valid, slots, 0)]
    dist2 = np.where(valid, (qx[:, None] - bx[ids]) ** 2 + (qy[:, None] - by[ids]) ** 2, np.inf)
    best = dist2.argmin(1)
    pick = np.arange(len(qx))
    ok = dist2[pick, best] <= gate**2
    out[ok] = ids[pick, best][ok]
    return out
