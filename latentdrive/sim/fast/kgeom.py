"""Scalar lane geometry for the compiled kernels (one lane, one point per call).

highway-env's definitions, as :mod:`latentdrive.sim.fast.lanes` writes them for Python
callers, here compiled to tight loops; compiled code takes its trigonometry from the C
library instead of numpy, which is why placement, whose values must equal highway-env's
bit for bit, uses the other module. Coordinates: world ``(x, y)`` metres; Frenet ``s``
along the lane, ``r`` to its right; radians.
"""

from __future__ import annotations

import math

from latentdrive.sim.fast._jit import njit
from latentdrive.sim.fast.network import (
    AMPLITUDE,
    BASE_HEADING,
    CDIR,
    CENTER_X,
    CENTER_Y,
    CIRCULAR,
    CURVE_BOX,
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
    LaneTable,
)

__all__ = [
    "box_distance",
    "closest_lane",
    "in_box",
    "lane_distance",
    "lane_heading",
    "lane_local",
    "lane_position",
    "not_zero",
    "wrap_to_pi",
]


@njit
def wrap_to_pi(a: float) -> float:
    """``a`` wrapped to ``[-π, π)``."""
    return ((a + math.pi) % (2 * math.pi)) - math.pi


@njit
def not_zero(x: float) -> float:
    """``x`` pushed away from zero to at least 0.01 in magnitude (keeps its sign, 0 → +)."""
    if abs(x) > 0.01:
        return x
    if x >= 0:
        return 0.01
    return -0.01


@njit
def lane_position(t: LaneTable, lane: int, s: float, r: float) -> tuple[float, float]:
    """World point at Frenet ``(s, r)`` of ``lane``."""
    if t.ints[KIND, lane] == CIRCULAR:
        phi = t.geo[CDIR, lane] * s / t.geo[RADIUS, lane] + t.geo[START_PHASE, lane]
        rho = t.geo[RADIUS, lane] - r * t.geo[CDIR, lane]
        return t.geo[CENTER_X, lane] + rho * math.cos(phi), t.geo[CENTER_Y, lane] + rho * math.sin(phi)
    if t.ints[KIND, lane] == SINE:
        r = r + t.geo[AMPLITUDE, lane] * math.sin(t.geo[PULSATION, lane] * s + t.geo[PHASE, lane])
    return (t.geo[START_X, lane] + s * t.geo[DIR_X, lane] + r * t.geo[LAT_X, lane],
            t.geo[START_Y, lane] + s * t.geo[DIR_Y, lane] + r * t.geo[LAT_Y, lane])


@njit
def lane_heading(t: LaneTable, lane: int, s: float) -> float:
    """Lane heading at ``s``."""
    if t.ints[KIND, lane] == CIRCULAR:
        phi = t.geo[CDIR, lane] * s / t.geo[RADIUS, lane] + t.geo[START_PHASE, lane]
        return phi + math.pi / 2 * t.geo[CDIR, lane]
    if t.ints[KIND, lane] == SINE:
        slope = t.geo[AMPLITUDE, lane] * t.geo[PULSATION, lane] * math.cos(t.geo[PULSATION, lane] * s + t.geo[PHASE, lane])
        return t.geo[BASE_HEADING, lane] + math.atan(slope)
    return t.geo[BASE_HEADING, lane]


@njit
def lane_local(t: LaneTable, lane: int, x: float, y: float) -> tuple[float, float]:
    """Frenet ``(s, r)`` of a world point on ``lane``."""
    if t.ints[KIND, lane] == CIRCULAR:
        cx = x - t.geo[CENTER_X, lane]
        cy = y - t.geo[CENTER_Y, lane]
        phase0 = t.geo[START_PHASE, lane]
        phi = phase0 + wrap_to_pi(math.atan2(cy, cx) - phase0)
        s = t.geo[CDIR, lane] * (phi - phase0) * t.geo[RADIUS, lane]
        return s, t.geo[CDIR, lane] * (t.geo[RADIUS, lane] - math.sqrt(cx * cx + cy * cy))
    dx = x - t.geo[START_X, lane]
    dy = y - t.geo[START_Y, lane]
    s = dx * t.geo[DIR_X, lane] + dy * t.geo[DIR_Y, lane]
    r = dx * t.geo[LAT_X, lane] + dy * t.geo[LAT_Y, lane]
    if t.ints[KIND, lane] == SINE:
        r -= t.geo[AMPLITUDE, lane] * math.sin(t.geo[PULSATION, lane] * s + t.geo[PHASE, lane])
    return s, r


@njit
def lane_distance(t: LaneTable, lane: int, x: float, y: float) -> float:
    """highway-env's L1 distance to a lane: ``|r|`` plus the overshoot beyond either end."""
    s, r = lane_local(t, lane, x, y)
    return abs(r) + max(s - t.geo[LENGTH, lane], 0.0) + max(0.0 - s, 0.0)


@njit
def in_box(box_row: object, x: float, y: float) -> bool:
    """Whether ``(x, y)`` lies in an axis-aligned box ``(xmin, ymin, xmax, ymax)``."""
    return box_row[0] <= x <= box_row[2] and box_row[1] <= y <= box_row[3]  # type: ignore[index]


@njit
def box_distance(box_row: object, x: float, y: float) -> float:
    """Euclidean distance from ``(x, y)`` to an axis-aligned box (0 inside)."""
    dx = max(box_row[0] - x, 0.0, x - box_row[2])  # type: ignore[index]
    dy = max(box_row[1] - y, 0.0, y - box_row[3])  # type: ignore[index]
    return math.sqrt(dx * dx + dy * dy)


@njit
def closest_lane(t: LaneTable, x: float, y: float, heading: float, hint: int) -> int:
    """The lane minimising position distance + heading error, first in lane order on ties.

    ``hint`` (usually the current lane) seeds the search; a lane whose curve box is
    farther than the best distance so far cannot win, because the box distance bounds
    the lane distance from below, so it is skipped without computing its coordinates.
    """
    n = t.ints.shape[1]
    best = hint
    s, r = lane_local(t, hint, x, y)
    best_d = (abs(r) + max(s - t.geo[LENGTH, hint], 0.0) + max(0.0 - s, 0.0)
              + abs(wrap_to_pi(heading - lane_heading(t, hint, s))))
    for lane in range(n):
        if lane == hint or box_distance(t.boxes[CURVE_BOX, lane], x, y) > best_d:
            continue
        s, r = lane_local(t, lane, x, y)
        d = (abs(r) + max(s - t.geo[LENGTH, lane], 0.0) + max(0.0 - s, 0.0)
             + abs(wrap_to_pi(heading - lane_heading(t, lane, s))))
        if d < best_d or (d == best_d and lane < best):
            best, best_d = lane, d
    return best
