"""VelocityMap frames of a batch's AVs, rendered straight from the batch's arrays.

The compiled twin of :func:`latentdrive.observe.render_frame`, which stays the reference:
the same grid, the same footprint test and eq. 13, evaluated with the same floating-point
operations in the same order (IEEE, no fastmath), so cell membership agrees with the
reference and values differ at most in the last bit of a logarithm. It reads vehicles
from :class:`~latentdrive.sim.fast.state.State` rows, sensor noise from draws made
beforehand (:func:`latentdrive.observe.draw_noise`, one per frame, from each
environment's own generator) and the road from the group's raster, and renders only the
observers asked for.

Differences from the reference that cannot show: footprints are tested in a window sized
per vehicle rather than by the largest vehicle in view (both windows contain every
covered cell), and there is no validity mask (a fast batch has no padding below its
vehicle count).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from latentdrive.observe import AV as AV_CHANNEL
from latentdrive.observe import HV as HV_CHANNEL
from latentdrive.observe import MV as MV_CHANNEL
from latentdrive.observe import RL as RL_CHANNEL
from latentdrive.sim.fast._jit import njit
from latentdrive.sim.fast.state import (
    FRENET_SPEED,
    HEADING,
    HV,
    N_AV,
    N_VEH,
    SPEED,
    VLENGTH,
    VWIDTH,
    X,
    Y,
)

__all__ = ["GRID_ROWS", "render_rows"]

# Entries of the ``grid`` argument: ObservationConfig fields, in metres, m/s and 1/(m/s).
GRID_ROWS = ("behind", "resolution", "alpha", "beta", "v0", "max_speed", "route")
BEHIND, RES, ALPHA, BETA, V0, MAX_SPEED, ROUTE = range(len(GRID_ROWS))

_TINY = float(np.finfo(np.float64).tiny)


@njit
def _log_map(v: float, alpha: float, beta: float, v0: float) -> float:
    """Eq. 13 of one relative speed (m/s), as :func:`latentdrive.observe.velocity_log_map`."""
    speed = abs(v)
    if speed < v0:
        return 1.0
    z = 1.0 - beta * math.log(alpha * max(speed, _TINY))
    return min(max(z, 0.0), 1.0)


@njit
def render_rows(
    f: NDArray[np.float64],
    kind: NDArray[np.int64],
    env_i: NDArray[np.int64],
    rows: NDArray[np.int64],
    slots: NDArray[np.int64],
    observing: NDArray[np.bool_],
    noisy: bool,
    d_pos: NDArray[np.float64],
    d_head: NDArray[np.float64],
    d_speed: NDArray[np.float64],
    missed: NDArray[np.bool_],
    road: NDArray[np.uint8],
    road_origin: NDArray[np.float64],
    road_res: float,
    road_edges: NDArray[np.uint64],
    route: NDArray[np.uint64],
    grid: NDArray[np.float64],
    out: NDArray[np.float32],
) -> None:
    """Render the frames of AV ``a`` of state row ``rows[k]`` into ``out[slots[k], a]``
    wherever ``observing[k, a]``; other frames of ``out`` are left as they are.

    Args:
        f, kind, env_i: the group's ``State.f``, ``State.i[KIND]`` and ``State.env_i``.
        rows, slots: ``(K,)`` state rows to render and where their frames go in ``out``.
        observing: ``(K, A)`` bool, the AVs that get a frame.
        noisy: apply the draws below (False: the clean scene; the draws are not read).
        d_pos, d_head, d_speed, missed: ``(K, A, S, 2)`` metres, ``(K, A, S)`` radians,
            m/s and bool: per observer and vehicle slot, the offsets of position, heading
            and Frenet speed and whether the vehicle is missed. The observer's own slot
            is never perturbed.
        road, road_origin, road_res, road_edges: the layout's raster (``RoadRaster``
            fields; ``road_edges`` is only read when ``grid[ROUTE]`` > 0).
        route: ``(K, A)`` uint64 edge bits of each observer's route (``Scene.route``),
            drawn in MV at ``grid[ROUTE]`` where that is > 0.
        grid: ``(len(GRID_ROWS),)`` the observation's geometry and eq. 13 coefficients.
        out: ``(B', A', 4, H, W)`` float32; each rendered frame is overwritten whole.
    """
    h, w = out.shape[3], out.shape[4]
    behind, res = grid[BEHIND], grid[RES]
    alpha, beta, v0, max_speed = grid[ALPHA], grid[BETA], grid[V0], grid[MAX_SPEED]
    route_value = np.float32(grid[ROUTE])
    half_h = 0.5 * h * res
    ahead = w * res - behind
    n_rows, n_cols = road.shape[0], road.shape[1]
    for k in range(rows.shape[0]):
        b, o = rows[k], slots[k]
        for a in range(env_i[N_AV, b]):
            if not observing[k, a]:
                continue
            ex, ey, eh = f[X, b, a], f[Y, b, a], f[HEADING, b, a]
            cos_k, sin_k = math.cos(eh), math.sin(eh)
            for i in range(h):
                for j in range(w):
                    out[o, a, HV_CHANNEL, i, j] = 0.0
                    out[o, a, AV_CHANNEL, i, j] = 0.0
                    out[o, a, MV_CHANNEL, i, j] = 0.0
            # RL: the raster's nearest cell under each cell centre, in the world frame.
            for i in range(h):
                yc = (i + 0.5) * res - h * res / 2.0
                for j in range(w):
                    xc = -behind + (j + 0.5) * res
                    wx = ex + cos_k * xc - sin_k * yc
                    wy = ey + sin_k * xc + cos_k * yc
                    col = np.rint((wx - road_origin[0]) / road_res)
                    row = np.rint((wy - road_origin[1]) / road_res)
                    drivable = 0.0
                    if 0.0 <= row < n_rows and 0.0 <= col < n_cols:
                        drivable = road[int(row), int(col)]
                        if route_value > 0.0 and road_edges[int(row), int(col)] & route[k, a] != 0:
                            out[o, a, MV_CHANNEL, i, j] = route_value
                    out[o, a, RL_CHANNEL, i, j] = drivable
            ego_fs = f[FRENET_SPEED, b, a]
            for v in range(env_i[N_VEH, b]):
                px, py, head, fs = f[X, b, v], f[Y, b, v], f[HEADING, b, v], f[FRENET_SPEED, b, v]
                if noisy and v != a:
                    if missed[k, a, v]:
                        continue
                    px += d_pos[k, a, v, 0]
                    py += d_pos[k, a, v, 1]
                    head += d_head[k, a, v]
                    fs += d_speed[k, a, v]
                rx, ry = px - ex, py - ey
                lx = cos_k * rx + sin_k * ry
                ly = -sin_k * rx + cos_k * ry
                length, width = f[VLENGTH, b, v], f[VWIDTH, b, v]
                radius = 0.5 * math.hypot(length, width)
                # The reference's conservative cull by the footprint's bounding circle.
                if lx + radius < -behind or lx - radius > ahead or abs(ly) - radius > half_h:
                    continue
                if v == a:
                    channel = MV_CHANNEL
                    value = np.float32(min(max(abs(f[SPEED, b, v]) / max_speed, 0.0), 1.0))
                else:
                    channel = HV_CHANNEL if kind[b, v] == HV else AV_CHANNEL
                    value = np.float32(_log_map(fs - ego_fs, alpha, beta, v0))
                # A covered centre lies within the circumradius of the vehicle's centre,
                # which lies within half a cell of its nearest cell's centre.
                half_win = math.floor(radius / res + 0.5)
                col0 = int(np.rint((lx + behind) / res - 0.5))
                row0 = int(np.rint((ly + half_h) / res - 0.5))
                rel_head = head - eh
                cos_r, sin_r = math.cos(rel_head), math.sin(rel_head)
                half_len, half_wid = 0.5 * length, 0.5 * width
                for r in range(max(row0 - half_win, 0), min(row0 + half_win + 1, h)):
                    dy = ((r + 0.5) * res - half_h) - ly
                    for c in range(max(col0 - half_win, 0), min(col0 + half_win + 1, w)):
                        dx = (-behind + (c + 0.5) * res) - lx
                        u = cos_r * dx + sin_r * dy
                        t = cos_r * dy - sin_r * dx
                        if -half_len <= u < half_len and -half_wid <= t < half_wid:
                            # The own footprint replaces the route under it.
                            if channel == MV_CHANNEL or value > out[o, a, channel, r, c]:
                                out[o, a, channel, r, c] = value
