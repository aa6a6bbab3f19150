"""Lane geometry in numpy's arithmetic, one lane and one point per call.

highway-env's lanes take their sines, cosines and arctangents from numpy; the compiled
kernels (:mod:`latentdrive.sim.fast.kgeom`) take them from the C library, which differs in
the last bit for some arguments. Values that must equal highway-env's bit for bit, because
both backends start from them, come from here: where placed vehicles stand and head
(:mod:`latentdrive.sim.fast.placement`) and which lane each obstacle sits on. Every
formula follows highway-env's term by term, in its operation order, on Python floats.

Frenet coordinates: ``s`` metres along the lane from its start, ``r`` metres to its right
(highway-env's lateral axis); angles in radians.
"""

from __future__ import annotations

import numpy as np

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
    LaneTable,
)

__all__ = ["distance_with_heading", "heading_at", "local_coordinates", "position", "wrap_to_pi"]


def wrap_to_pi(a: float) -> float:
    """``a`` wrapped to ``[-π, π)``."""
    return ((a + np.pi) % (2 * np.pi)) - np.pi


def position(t: LaneTable, lane: int, s: float, r: float) -> tuple[float, float]:
    """World ``(x, y)`` of Frenet ``(s, r)`` on ``lane``, metres."""
    g = t.geo
    if t.ints.item(KIND, lane) == CIRCULAR:
        cdir, radius = g.item(CDIR, lane), g.item(RADIUS, lane)
        phi = cdir * s / radius + g.item(START_PHASE, lane)
        rho = radius - r * cdir
        return g.item(CENTER_X, lane) + rho * float(np.cos(phi)), g.item(CENTER_Y, lane) + rho * float(np.sin(phi))
    if t.ints.item(KIND, lane) == SINE:
        # A sine lane is its base segment with the lateral offset displaced by the sine.
        r = r + g.item(AMPLITUDE, lane) * float(np.sin(g.item(PULSATION, lane) * s + g.item(PHASE, lane)))
    return (g.item(START_X, lane) + s * g.item(DIR_X, lane) + r * g.item(LAT_X, lane),
            g.item(START_Y, lane) + s * g.item(DIR_Y, lane) + r * g.item(LAT_Y, lane))


def heading_at(t: LaneTable, lane: int, s: float) -> float:
    """Heading of ``lane`` at ``s``."""
    g = t.geo
    if t.ints.item(KIND, lane) == CIRCULAR:
        cdir = g.item(CDIR, lane)
        return cdir * s / g.item(RADIUS, lane) + g.item(START_PHASE, lane) + np.pi / 2 * cdir
    if t.ints.item(KIND, lane) == SINE:
        amplitude, pulsation = g.item(AMPLITUDE, lane), g.item(PULSATION, lane)
        slope = amplitude * pulsation * float(np.cos(pulsation * s + g.item(PHASE, lane)))
        return g.item(BASE_HEADING, lane) + float(np.arctan(slope))
    return g.item(BASE_HEADING, lane)


def local_coordinates(t: LaneTable, lane: int, x: float, y: float) -> tuple[float, float]:
    """Frenet ``(s, r)`` of the world point ``(x, y)`` on ``lane`` (inverse of :func:`position`)."""
    g = t.geo
    if t.ints.item(KIND, lane) == CIRCULAR:
        cx, cy = x - g.item(CENTER_X, lane), y - g.item(CENTER_Y, lane)
        cdir, radius, phase0 = g.item(CDIR, lane), g.item(RADIUS, lane), g.item(START_PHASE, lane)
        # Angles are measured within ±π of the lane's start, as highway-env does.
        phi = phase0 + wrap_to_pi(float(np.arctan2(cy, cx)) - phase0)
        return cdir * (phi - phase0) * radius, cdir * (radius - float(np.sqrt(cx * cx + cy * cy)))
    dx, dy = x - g.item(START_X, lane), y - g.item(START_Y, lane)
    s = dx * g.item(DIR_X, lane) + dy * g.item(DIR_Y, lane)
    r = dx * g.item(LAT_X, lane) + dy * g.item(LAT_Y, lane)
    if t.ints.item(KIND, lane) == SINE:
        r -= g.item(AMPLITUDE, lane) * float(np.sin(g.item(PULSATION, lane) * s + g.item(PHASE, lane)))
    return s, r


def distance_with_heading(t: LaneTable, lane: int, x: float, y: float, heading: float) -> float:
    """highway-env's lane distance: ``|r|``, plus the overshoot beyond either end, plus the
    absolute heading error (1 m per radian)."""
    s, r = local_coordinates(t, lane, x, y)
    length = t.geo.item(LENGTH, lane)
    return abs(r) + max(s - length, 0.0) + max(-s, 0.0) + abs(wrap_to_pi(heading - heading_at(t, lane, s)))
