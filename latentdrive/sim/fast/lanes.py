"""Vectorized lane geometry over a :class:`~latentdrive.sim.fast.network.LaneTable`.

Pure numpy functions of lane ids and coordinates, any broadcastable shapes. They follow
highway-env's definitions term by term (straight, sine and circular lanes), including its
operation order, so that values agree to rounding. Frenet coordinates: ``s`` metres along
the lane from its start, ``r`` metres to its right (highway-env's lateral axis).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from latentdrive.sim.fast.network import (
    AMPLITUDE,
    BASE_HEADING,
    CDIR,
    CENTER_X,
    CENTER_Y,
    CIRCULAR,
    DIR_X,
    DIR_Y,
    KIND,
    LAT_X,
    LAT_Y,
    LENGTH,
    PHASE,
    PULSATION,
    RADIUS,
    SINE,
    START_PHASE,
    START_X,
    START_Y,
    WIDTH,
    LaneTable,
)

__all__ = [
    "distance",
    "distance_with_heading",
    "heading_at",
    "local_coordinates",
    "on_lane",
    "point",
    "position",
    "wrap_to_pi",
]

FArr = NDArray[np.float64]


def wrap_to_pi(x: ArrayLike) -> FArr:
    """Angles wrapped to ``[-π, π)``, radians."""
    return np.asarray(((np.asarray(x, dtype=np.float64) + np.pi) % (2 * np.pi)) - np.pi)


def _prep(lane: ArrayLike, *xs: ArrayLike) -> tuple[tuple[int, ...], list[NDArray[Any]]]:
    """Broadcast inputs, flattened to 1-D (results are reshaped to the returned shape)."""
    arrays = np.broadcast_arrays(np.asarray(lane, dtype=np.int64), *(np.asarray(x, dtype=np.float64) for x in xs))
    return arrays[0].shape, [a.reshape(-1) for a in arrays]


def position(t: LaneTable, lane: ArrayLike, s: ArrayLike, r: ArrayLike) -> tuple[FArr, FArr]:
    """World ``(x, y)`` of Frenet ``(s, r)`` on each lane, metres."""
    g = t.geo
    shape, (lane_, s_, r_) = _prep(lane, s, r)
    kind = t.ints[KIND][lane_]
    sine = kind == SINE
    # A sine lane is its base segment with the lateral offset displaced by the sine.
    r_eff = np.where(sine, r_ + g[AMPLITUDE][lane_] * np.sin(g[PULSATION][lane_] * s_ + g[PHASE][lane_]), r_)
    x = g[START_X][lane_] + s_ * g[DIR_X][lane_] + r_eff * g[LAT_X][lane_]
    y = g[START_Y][lane_] + s_ * g[DIR_Y][lane_] + r_eff * g[LAT_Y][lane_]
    circ = kind == CIRCULAR
    if circ.any():
        c = lane_[circ]
        cdir, radius = g[CDIR][c], g[RADIUS][c]
        phi = cdir * s_[circ] / radius + g[START_PHASE][c]
        rho = radius - r_[circ] * cdir
        x[circ] = g[CENTER_X][c] + rho * np.cos(phi)
        y[circ] = g[CENTER_Y][c] + rho * np.sin(phi)
    return x.reshape(shape), y.reshape(shape)


def point(t: LaneTable, lane: int, s: float, r: float) -> tuple[float, float]:
    """:func:`position` of one point, without array overhead (same arithmetic)."""
    g = t.geo
    if t.ints[KIND, lane] == CIRCULAR:
        phi = g[CDIR, lane] * s / g[RADIUS, lane] + g[START_PHASE, lane]
        rho = g[RADIUS, lane] - r * g[CDIR, lane]
        return float(g[CENTER_X, lane] + rho * np.cos(phi)), float(g[CENTER_Y, lane] + rho * np.sin(phi))
    if t.ints[KIND, lane] == SINE:
        r = r + g[AMPLITUDE, lane] * np.sin(g[PULSATION, lane] * s + g[PHASE, lane])
    return (float(g[START_X, lane] + s * g[DIR_X, lane] + r * g[LAT_X, lane]),
            float(g[START_Y, lane] + s * g[DIR_Y, lane] + r * g[LAT_Y, lane]))


def heading_at(t: LaneTable, lane: ArrayLike, s: ArrayLike) -> FArr:
    """Lane heading at ``s``, radians."""
    g = t.geo
    shape, (lane_, s_) = _prep(lane, s)
    kind = t.ints[KIND][lane_]
    h = g[BASE_HEADING][lane_].copy()
    sine = kind == SINE
    if sine.any():
        c = lane_[sine]
        h[sine] += np.arctan(g[AMPLITUDE][c] * g[PULSATION][c] * np.cos(g[PULSATION][c] * s_[sine] + g[PHASE][c]))
    circ = kind == CIRCULAR
    if circ.any():
        c = lane_[circ]
        phi = g[CDIR][c] * s_[circ] / g[RADIUS][c] + g[START_PHASE][c]
        h[circ] = phi + np.pi / 2 * g[CDIR][c]
    return h.reshape(shape)


def local_coordinates(t: LaneTable, lane: ArrayLike, x: ArrayLike, y: ArrayLike) -> tuple[FArr, FArr]:
    """Frenet ``(s, r)`` of world points on each lane, metres (inverse of :func:`position`)."""
    g = t.geo
    shape, (lane_, x_, y_) = _prep(lane, x, y)
    kind = t.ints[KIND][lane_]
    dx, dy = x_ - g[START_X][lane_], y_ - g[START_Y][lane_]
    s = dx * g[DIR_X][lane_] + dy * g[DIR_Y][lane_]
    r = dx * g[LAT_X][lane_] + dy * g[LAT_Y][lane_]
    sine = kind == SINE
    if sine.any():
        c = lane_[sine]
        r[sine] -= g[AMPLITUDE][c] * np.sin(g[PULSATION][c] * s[sine] + g[PHASE][c])
    circ = kind == CIRCULAR
    if circ.any():
        c = lane_[circ]
        cx, cy = x_[circ] - g[CENTER_X][c], y_[circ] - g[CENTER_Y][c]
        phase0 = g[START_PHASE][c]
        # Angles are measured within ±π of the lane's start, as highway-env does.
        phi = phase0 + wrap_to_pi(np.arctan2(cy, cx) - phase0)
        s[circ] = g[CDIR][c] * (phi - phase0) * g[RADIUS][c]
        r[circ] = g[CDIR][c] * (g[RADIUS][c] - np.sqrt(cx * cx + cy * cy))
    return s.reshape(shape), r.reshape(shape)


def distance(t: LaneTable, lane: ArrayLike, x: ArrayLike, y: ArrayLike) -> FArr:
    """highway-env's L1 lane distance ``|r| + overshoot beyond either end``, metres."""
    g = t.geo
    lane_ = np.asarray(lane, dtype=np.int64)
    s, r = local_coordinates(t, lane_, x, y)
    return np.abs(r) + np.maximum(s - g[LENGTH][lane_], 0.0) + np.maximum(-s, 0.0)


def distance_with_heading(t: LaneTable, lane: ArrayLike, x: ArrayLike, y: ArrayLike, heading: ArrayLike) -> FArr:
    """:func:`distance` plus the absolute heading error to the lane (1 m per radian)."""
    g = t.geo
    lane_ = np.asarray(lane, dtype=np.int64)
    s, r = local_coordinates(t, lane_, x, y)
    angle = np.abs(wrap_to_pi(np.asarray(heading) - heading_at(t, lane_, s)))
    return np.abs(r) + np.maximum(s - g[LENGTH][lane_], 0.0) + np.maximum(-s, 0.0) + angle


def on_lane(t: LaneTable, lane: ArrayLike, x: ArrayLike, y: ArrayLike, margin: float = 0.0) -> NDArray[np.bool_]:
    """Whether points lie on each lane: within half a width (+ ``margin``) laterally and
    no more than a car length (5 m) beyond either end."""
    g = t.geo
    lane_ = np.asarray(lane, dtype=np.int64)
    s, r = local_coordinates(t, lane_, x, y)
    return np.asarray(
        (np.abs(r) <= g[WIDTH][lane_] / 2 + margin) & (s >= -5.0) & (s < g[LENGTH][lane_] + 5.0)
    )
