"""Right of way on a regulated road (highway-env's RegulatedRoad, the intersection).

Twice per simulated second: vehicles that yielded resume their lane's speed limit; then
every pair whose constant-speed predictions along their routes come close within 3 s
(inflated footprints overlapping at one of the 0.25 s samples) is a conflict, and the
vehicle on the lower-priority lane (on equal priority, the one behind) yields: an HV that
must yield targets speed 0 until the next check. AVs never yield.

Pairs are found by sorting each prediction sample by x and sweeping a window of one car
length (the pre-check distance), instead of testing every pair.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from latentdrive.sim.fast._jit import njit
from latentdrive.sim.fast.kgeom import lane_heading, lane_local, lane_position
from latentdrive.sim.fast.ksort import sort_by_key
from latentdrive.sim.fast.network import (
    EDGE_FIRST_LANE,
    EDGE_N_LANES,
    INDEX_IN_EDGE,
    LENGTH,
    PRIORITY,
    SPEED_LIMIT,
    LaneTable,
)
from latentdrive.sim.fast.scratch import N_SAMPLES, Scratch
from latentdrive.sim.fast.state import (
    HEADING,
    HV,
    KIND,
    LANE,
    N_VEH,
    ROUTE_HEAD,
    ROUTE_LANE0,
    ROUTE_LEN,
    SPEED,
    TARGET_SPEED,
    VLENGTH,
    VWIDTH,
    YIELD_TIMER,
    YIELDING,
    State,
    X,
    Y,
)

__all__ = ["enforce_right_of_way", "rectangles_intersect"]

SAMPLE_STEP = 0.25  # s
# Footprints are inflated to 1.5 lengths and 0.9 widths in the conflict test.
LENGTH_FACTOR, WIDTH_FACTOR = 1.5, 0.9


@njit
def _route_lane(t: LaneTable, st: State, b: int, i: int, k: int) -> int:
    """Lane of route entry ``k`` (counted from the route's head): the start entry names its
    lane; later entries take the vehicle's current lane number on their edge."""
    head, n = st.i[ROUTE_HEAD, b, i], st.i[ROUTE_LEN, b, i]
    if head >= n:
        return st.i[LANE, b, i]
    edge = st.route[b, i, head + k]
    if head + k == 0:
        index = st.i[ROUTE_LANE0, b, i]
    else:
        index = t.ints[INDEX_IN_EDGE, st.i[LANE, b, i]]
    return t.edges[EDGE_FIRST_LANE, edge] + min(index, t.edges[EDGE_N_LANES, edge] - 1)


@njit
def predict(t: LaneTable, st: State, b: int, i: int, out: NDArray[np.float64]) -> None:
    """Positions and headings ``out[k] = (x, y, heading)`` of vehicle ``i`` after
    ``(k + 1) * 0.25`` s at constant speed along its remaining route."""
    s0, _ = lane_local(t, st.i[LANE, b, i], st.f[X, b, i], st.f[Y, b, i])
    n_entries = max(st.i[ROUTE_LEN, b, i] - st.i[ROUTE_HEAD, b, i], 1)
    for k in range(N_SAMPLES):
        s = s0 + st.f[SPEED, b, i] * ((k + 1) * SAMPLE_STEP)
        entry = 0
        lane = _route_lane(t, st, b, i, 0)
        while n_entries - entry > 1 and s > t.geo[LENGTH, lane]:
            s -= t.geo[LENGTH, lane]
            entry += 1
            lane = _route_lane(t, st, b, i, entry)
        out[k, 0], out[k, 1] = lane_position(t, lane, s, 0.0)
        out[k, 2] = lane_heading(t, lane, s)


@njit
def _inside(px: float, py: float, cx: float, cy: float, length: float, width: float, angle: float) -> bool:
    # The point is rotated by +angle about the centre, as highway-env's test does.
    c, s = math.cos(angle), math.sin(angle)
    dx, dy = px - cx, py - cy
    u, v = c * dx - s * dy, s * dx + c * dy
    return -length / 2 <= u <= length / 2 and -width / 2 <= v <= width / 2


@njit
def _has_point_inside(x1: float, y1: float, l1: float, w1: float, a1: float,
                      x2: float, y2: float, l2: float, w2: float, a2: float) -> bool:
    """Whether a corner, the centre or an edge midpoint of rectangle 1 lies in rectangle 2."""
    hl, hw = l1 / 2, w1 / 2
    pts = ((-hl, -hw), (-hl, hw), (hl, hw), (hl, -hw), (0.0, 0.0), (-hl, 0.0), (hl, 0.0), (0.0, -hw), (0.0, hw))
    c, s = math.cos(a1), math.sin(a1)
    for k in range(9):
        u, v = pts[k]
        if _inside(c * u - s * v + x1, s * u + c * v + y1, x2, y2, l2, w2, a2):
            return True
    return False


@njit
def rectangles_intersect(x1: float, y1: float, l1: float, w1: float, a1: float,
                         x2: float, y2: float, l2: float, w2: float, a2: float) -> bool:
    """highway-env's rotated-rectangle overlap test (sample points of each in the other)."""
    return (_has_point_inside(x1, y1, l1, w1, a1, x2, y2, l2, w2, a2)
            or _has_point_inside(x2, y2, l2, w2, a2, x1, y1, l1, w1, a1))


@njit
def _conflict(st: State, b: int, i: int, j: int, pred: NDArray[np.float64]) -> bool:
    li, wi = LENGTH_FACTOR * st.f[VLENGTH, b, i], WIDTH_FACTOR * st.f[VWIDTH, b, i]
    lj, wj = LENGTH_FACTOR * st.f[VLENGTH, b, j], WIDTH_FACTOR * st.f[VWIDTH, b, j]
    for k in range(N_SAMPLES):
        dx, dy = pred[j, k, 0] - pred[i, k, 0], pred[j, k, 1] - pred[i, k, 1]
        if math.sqrt(dx * dx + dy * dy) > st.f[VLENGTH, b, i]:
            continue
        if rectangles_intersect(pred[i, k, 0], pred[i, k, 1], li, wi, pred[i, k, 2],
                                pred[j, k, 0], pred[j, k, 1], lj, wj, pred[j, k, 2]):
            return True
    return False


@njit
def _yielder(t: LaneTable, st: State, b: int, i: int, j: int) -> int:
    pi, pj = t.ints[PRIORITY, st.i[LANE, b, i]], t.ints[PRIORITY, st.i[LANE, b, j]]
    if pi > pj:
        return j
    if pi < pj:
        return i
    dx, dy = st.f[X, b, j] - st.f[X, b, i], st.f[Y, b, j] - st.f[Y, b, i]
    ahead_i = math.cos(st.f[HEADING, b, i]) * dx + math.sin(st.f[HEADING, b, i]) * dy
    ahead_j = -(math.cos(st.f[HEADING, b, j]) * dx + math.sin(st.f[HEADING, b, j]) * dy)
    return i if ahead_i > ahead_j else j


@njit
def _seen_before(pred: NDArray[np.float64], i: int, j: int, k: int, radius: float) -> bool:
    """Whether the pair was already within ``radius`` at an earlier sample (and tested)."""
    for q in range(k):
        dx, dy = pred[j, q, 0] - pred[i, q, 0], pred[j, q, 1] - pred[i, q, 1]
        if math.sqrt(dx * dx + dy * dy) <= radius:
            return True
    return False


@njit
def enforce_right_of_way(t: LaneTable, st: State, b: int, sc: Scratch) -> None:
    """Release last check's yielders, then make this check's yielders stop.

    Yielding is a set, so pairs may be tested in any order; each close pair is tested once,
    at the first sample where the pair comes within the pre-check distance.
    """
    n = st.env_i[N_VEH, b]
    for v in range(n):
        if st.flag[YIELDING, b, v]:
            st.f[TARGET_SPEED, b, v] = t.geo[SPEED_LIMIT, st.i[LANE, b, v]]
            st.flag[YIELDING, b, v] = False
    pred = sc.pred
    for v in range(n):
        predict(t, st, b, v, pred[v])
    max_len = 0.0
    for v in range(n):
        max_len = max(max_len, st.f[VLENGTH, b, v])
    xs, order = sc.keys, sc.order
    for k in range(N_SAMPLES):
        for v in range(n):
            xs[v], order[v] = pred[v, k, 0], v
        sort_by_key(xs, order, n, sc.tmp_keys, sc.tmp_vals)
        for a in range(n):
            for c in range(a + 1, n):
                if xs[c] - xs[a] > max_len:
                    break
                i, j = min(order[a], order[c]), max(order[a], order[c])
                dx, dy = pred[j, k, 0] - pred[i, k, 0], pred[j, k, 1] - pred[i, k, 1]
                radius = st.f[VLENGTH, b, i]
                if math.sqrt(dx * dx + dy * dy) > radius or _seen_before(pred, i, j, k, radius):
                    continue
                if _conflict(st, b, i, j, pred):
                    y = _yielder(t, st, b, i, j)
                    if st.i[KIND, b, y] == HV:
                        st.f[TARGET_SPEED, b, y] = 0.0
                        st.flag[YIELDING, b, y] = True
                        st.i[YIELD_TIMER, b, y] = 0
