"""Neighbour search by sorting: each lane's occupants ordered by their Frenet position.

highway-env finds a vehicle's leader and follower on a lane geometrically: among all
vehicles and obstacles whose centre lies on that lane (within half a width plus 1 m, and
at most a car length beyond either end), the nearest ahead (``s ≥ s_ego``) and behind
(``s < s_ego``). Here every slot is sorted into the lanes it lies on once per physics
step (a box test skips most lanes), and each query is a binary search: O(N·L + N log N)
per environment instead of highway-env's scan of all vehicles per query.
"""

from __future__ import annotations

import math

from latentdrive.sim.fast._jit import njit
from latentdrive.sim.fast.kgeom import in_box, lane_local
from latentdrive.sim.fast.ksort import sort_by_key
from latentdrive.sim.fast.network import LENGTH, REGION_BOX, WIDTH, LaneTable
from latentdrive.sim.fast.scratch import Scratch
from latentdrive.sim.fast.state import (
    HEADING,
    KIND,
    N_TOT,
    N_VEH,
    PAD,
    TARGET,
    VEHICLE_LENGTH,
    State,
    X,
    Y,
)

__all__ = ["build_members", "index_targets", "neighbours"]

# Lateral margin beyond half a lane width within which a vehicle counts as on the lane, m;
# lengthwise, it counts up to a car length (VEHICLE_LENGTH) beyond either end, as in
# highway-env's on-lane test.
ON_LANE_MARGIN = 1.0


@njit
def build_members(t: LaneTable, st: State, b: int, m: Scratch) -> None:
    """Sort the slots of environment ``b`` into the lanes they lie on (and note the
    cosine and sine of each slot's heading)."""
    n_lanes = m.n_on.shape[0]
    for lane in range(n_lanes):
        m.n_on[lane] = 0
    for j in range(st.env_i[N_TOT, b]):
        if st.i[KIND, b, j] == PAD:
            continue
        x, y = st.f[X, b, j], st.f[Y, b, j]
        m.cos_h[j], m.sin_h[j] = math.cos(st.f[HEADING, b, j]), math.sin(st.f[HEADING, b, j])
        for lane in range(n_lanes):
            if not in_box(t.boxes[REGION_BOX, lane], x, y):
                continue
            s, r = lane_local(t, lane, x, y)
            if abs(r) <= t.geo[WIDTH, lane] / 2 + ON_LANE_MARGIN and -VEHICLE_LENGTH <= s < t.geo[LENGTH, lane] + VEHICLE_LENGTH:
                k = m.n_on[lane]
                m.s[lane, k], m.idx[lane, k] = s, j
                m.n_on[lane] = k + 1
    for lane in range(n_lanes):
        if m.n_on[lane] > 1:
            sort_by_key(m.s[lane], m.idx[lane], m.n_on[lane], m.tmp_keys, m.tmp_vals)


@njit
def index_targets(st: State, b: int, m: Scratch) -> None:
    """Group the vehicles of environment ``b`` by target lane (a counting sort) and clear
    the list of targets changed since."""
    n_lanes = m.cursor.shape[0]
    for lane in range(n_lanes + 1):
        m.by_target_start[lane] = 0
    n = st.env_i[N_VEH, b]
    for v in range(n):
        m.by_target_start[st.i[TARGET, b, v] + 1] += 1
    for lane in range(n_lanes):
        m.by_target_start[lane + 1] += m.by_target_start[lane]
        m.cursor[lane] = m.by_target_start[lane]
    for v in range(n):
        lane = st.i[TARGET, b, v]
        m.by_target[m.cursor[lane]] = v
        m.cursor[lane] += 1
    m.n_changed[0] = 0


@njit
def neighbours(t: LaneTable, st: State, b: int, m: Scratch, ego: int, lane: int) -> tuple[int, int]:
    """``(front, rear)`` slots of ``ego`` on ``lane`` (-1 for none).

    The front is the nearest occupant with ``s ≥ s_ego`` (the last slot among equal
    positions), the rear the nearest with ``s < s_ego`` (the first among equal positions),
    as highway-env's scan in vehicle order resolves ties.
    """
    s_ego, _ = lane_local(t, lane, st.f[X, b, ego], st.f[Y, b, ego])
    n = m.n_on[lane]
    lo, hi = 0, n
    while lo < hi:
        mid = (lo + hi) // 2
        if m.s[lane, mid] < s_ego:
            lo = mid + 1
        else:
            hi = mid
    front = -1
    k = lo
    while k < n and m.idx[lane, k] == ego:
        k += 1
    if k < n:
        front_s = m.s[lane, k]
        front = m.idx[lane, k]
        k += 1
        while k < n and m.s[lane, k] == front_s:
            if m.idx[lane, k] != ego:
                front = m.idx[lane, k]
            k += 1
    rear = -1
    k = lo - 1
    if k >= 0:
        rear_s = m.s[lane, k]
        while k >= 0 and m.s[lane, k] == rear_s:
            rear = m.idx[lane, k]
            k -= 1
    return front, rear
