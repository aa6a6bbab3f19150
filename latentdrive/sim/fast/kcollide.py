"""Collisions: sort-and-sweep candidate pairs, then highway-env's separating-axis test.

highway-env checks every pair (i < j) in slot order: a circle pre-check, then a
separating-axis test of the two rectangles, also swept over one physics step at constant
velocity. Overlapping rectangles crash both vehicles now; rectangles that will overlap
within the step receive an impact (half the minimum translation each, all of it for a
vehicle hitting a static obstacle), applied and marked crashed on the next step; a later
pair overwrites an earlier pair's impact. Here candidate pairs come from sorting slots by
x and sweeping a window as wide as the largest pre-check radius; each slot keeps the
impact of its pair that the all-pairs loop would visit last, so the outcome is the same.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from latentdrive.sim.fast._jit import njit
from latentdrive.sim.fast.ksort import sort_by_key
from latentdrive.sim.fast.scratch import Scratch
from latentdrive.sim.fast.state import (
    CRASHED,
    HAS_IMPACT,
    HEADING,
    IMPACT_X,
    IMPACT_Y,
    KIND,
    N_TOT,
    OBSTACLE,
    PAD,
    SPEED,
    VLENGTH,
    VWIDTH,
    State,
    X,
    Y,
)

__all__ = ["collide", "polygons_intersect"]


@njit
def _corners(st: State, b: int, i: int, out: NDArray[np.float64]) -> None:
    """Write the ``(5, 2)`` closed footprint polygon of slot ``i`` (highway-env's corner order)."""
    hl, hw = st.f[VLENGTH, b, i] / 2, st.f[VWIDTH, b, i] / 2
    c, s = math.cos(st.f[HEADING, b, i]), math.sin(st.f[HEADING, b, i])
    for k in range(4):
        u = -hl if k < 2 else hl
        v = -hw if k == 0 or k == 3 else hw
        out[k, 0] = c * u - s * v + st.f[X, b, i]
        out[k, 1] = s * u + c * v + st.f[Y, b, i]
    out[4, 0], out[4, 1] = out[0, 0], out[0, 1]


@njit
def _project(poly: NDArray[np.float64], nx: float, ny: float) -> tuple[float, float]:
    lo, hi = math.inf, -math.inf
    for k in range(poly.shape[0]):
        p = poly[k, 0] * nx + poly[k, 1] * ny
        lo, hi = min(lo, p), max(hi, p)
    return lo, hi


@njit
def _interval_distance(min_a: float, max_a: float, min_b: float, max_b: float) -> float:
    return min_b - max_a if min_a < min_b else min_a - max_b


@njit
def polygons_intersect(a: NDArray[np.float64], b: NDArray[np.float64], dax: float, day: float,
                       dbx: float, dby: float) -> tuple[bool, bool, float, float]:
    """Separating-axis test of two closed convex polygons ``(5, 2)``.

    Returns ``(intersecting, will_intersect, tx, ty)``: whether they overlap now, whether
    they overlap when ``a`` is swept by its displacement relative to ``b``, and the
    minimum translation pushing ``a`` out of ``b`` (meaningful when ``will_intersect``).
    """
    intersecting = will = True
    min_distance = math.inf
    ax_x = ax_y = 0.0
    ca_x = (a[0, 0] + a[1, 0] + a[2, 0] + a[3, 0]) / 4
    ca_y = (a[0, 1] + a[1, 1] + a[2, 1] + a[3, 1]) / 4
    cb_x = (b[0, 0] + b[1, 0] + b[2, 0] + b[3, 0]) / 4
    cb_y = (b[0, 1] + b[1, 1] + b[2, 1] + b[3, 1]) / 4
    dx, dy = ca_x - cb_x, ca_y - cb_y
    rel_x, rel_y = dax - dbx, day - dby
    for which in range(2):
        poly = a if which == 0 else b
        for k in range(4):
            nx = -poly[k + 1, 1] + poly[k, 1]
            ny = poly[k + 1, 0] - poly[k, 0]
            norm = math.sqrt(nx * nx + ny * ny)
            nx, ny = nx / norm, ny / norm
            min_a, max_a = _project(a, nx, ny)
            min_b, max_b = _project(b, nx, ny)
            if _interval_distance(min_a, max_a, min_b, max_b) > 0:
                intersecting = False
            vp = nx * rel_x + ny * rel_y
            if vp < 0:
                min_a += vp
            else:
                max_a += vp
            distance = _interval_distance(min_a, max_a, min_b, max_b)
            if distance > 0:
                will = False
            if not intersecting and not will:
                return False, False, 0.0, 0.0
            if abs(distance) < min_distance:
                min_distance = abs(distance)
                sign = 1.0 if dx * nx + dy * ny > 0 else -1.0
                ax_x, ax_y = sign * nx, sign * ny
    return intersecting, will, min_distance * ax_x, min_distance * ax_y


@njit
def _pair(st: State, b: int, i: int, j: int, dt: float, sc: Scratch) -> None:
    """highway-env's collision handling of slots ``i < j`` (``j`` may be an obstacle).

    A slot in several colliding pairs keeps the impact of the pair highway-env's loop
    visits last, the one with the largest ``(i, j)``, whatever order pairs come here in.
    """
    n = st.env_i[N_TOT, b]
    dx, dy = st.f[X, b, j] - st.f[X, b, i], st.f[Y, b, j] - st.f[Y, b, i]
    diag_i = math.sqrt(st.f[VLENGTH, b, i] ** 2 + st.f[VWIDTH, b, i] ** 2)
    diag_j = math.sqrt(st.f[VLENGTH, b, j] ** 2 + st.f[VWIDTH, b, j] ** 2)
    if math.sqrt(dx * dx + dy * dy) > (diag_i + diag_j) / 2 + st.f[SPEED, b, i] * dt:
        return
    vi, vj = st.f[SPEED, b, i] * dt, st.f[SPEED, b, j] * dt
    hi, hj = st.f[HEADING, b, i], st.f[HEADING, b, j]
    _corners(st, b, i, sc.polygons[0])
    _corners(st, b, j, sc.polygons[1])
    inter, will, tx, ty = polygons_intersect(
        sc.polygons[0], sc.polygons[1],
        vi * math.cos(hi), vi * math.sin(hi), vj * math.cos(hj), vj * math.sin(hj))
    if will:
        key = i * n + j
        if key > sc.best_pair[i]:
            sc.best_pair[i] = key
            share = 1.0 if st.i[KIND, b, j] == OBSTACLE else 0.5
            st.f[IMPACT_X, b, i], st.f[IMPACT_Y, b, i] = share * tx, share * ty
            st.flag[HAS_IMPACT, b, i] = True
        if st.i[KIND, b, j] != OBSTACLE and key > sc.best_pair[j]:
            sc.best_pair[j] = key
            st.f[IMPACT_X, b, j], st.f[IMPACT_Y, b, j] = -tx / 2, -ty / 2
            st.flag[HAS_IMPACT, b, j] = True
    if inter:
        st.flag[CRASHED, b, i] = True
        st.flag[CRASHED, b, j] = True


@njit
def collide(st: State, b: int, dt: float, sc: Scratch) -> None:
    """Resolve the collisions of environment ``b`` after a physics step."""
    n = st.env_i[N_TOT, b]
    reach = 0.0  # the widest pre-check radius any pair can have
    max_diag = 0.0
    for i in range(n):
        sc.best_pair[i] = -1
        if st.i[KIND, b, i] == PAD:
            continue
        max_diag = max(max_diag, math.sqrt(st.f[VLENGTH, b, i] ** 2 + st.f[VWIDTH, b, i] ** 2))
        reach = max(reach, abs(st.f[SPEED, b, i]) * dt)
    reach += max_diag
    xs, order = sc.keys, sc.order
    for k in range(n):
        xs[k], order[k] = st.f[X, b, k], k
    sort_by_key(xs, order, n, sc.tmp_keys, sc.tmp_vals)
    for a in range(n):
        i = order[a]
        if st.i[KIND, b, i] == PAD:
            continue
        for c in range(a + 1, n):
            j = order[c]
            if xs[c] - xs[a] > reach:
                break
            if st.i[KIND, b, j] == PAD or (st.i[KIND, b, i] == OBSTACLE and st.i[KIND, b, j] == OBSTACLE):
                continue
            if abs(st.f[Y, b, j] - st.f[Y, b, i]) > reach:
                continue
            _pair(st, b, min(i, j), max(i, j), dt, sc)
