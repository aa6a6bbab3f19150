"""Human drivers: IDM car-following and MOBIL lane changes (highway-env's IDMVehicle).

Functions take the environment row ``b`` and slot ids; ``p`` names the vehicle whose
driver parameters are used, because a MOBIL decision evaluates the IDM of its
neighbours with the deciding driver's parameters, as highway-env does.
"""

from __future__ import annotations

import math

from latentdrive.sim.fast._jit import njit
from latentdrive.sim.fast.kcontrol import (
    KP_A,
    MAX_STEERING_ANGLE,
    follow_road,
    is_reachable,
    steering_control,
)
from latentdrive.sim.fast.kgeom import lane_local, not_zero
from latentdrive.sim.fast.kneighbours import neighbours
from latentdrive.sim.fast.network import EDGE, EDGE_N_LANES, INDEX_IN_EDGE, SPEED_LIMIT, LaneTable
from latentdrive.sim.fast.scratch import Scratch
from latentdrive.sim.fast.state import (
    ACC_MAX,
    ACCEL,
    COMFORT_ACC_MAX,
    COMFORT_ACC_MIN,
    CRASHED,
    DELTA,
    DISTANCE_WANTED,
    KIND,
    LANE,
    LC_DELAY,
    MAX_BRAKING,
    MIN_GAIN,
    OBSTACLE,
    POLITENESS,
    ROUTE_HEAD,
    ROUTE_LANE0,
    ROUTE_LEN,
    SPEED,
    STEER,
    TARGET,
    TARGET_SPEED,
    TIME_WANTED,
    TIMER,
    State,
    X,
    Y,
)

__all__ = ["act_av", "act_hv", "desired_gap", "idm_acceleration", "mobil"]


@njit
def desired_gap(st: State, b: int, m: Scratch, ego: int, front: int, p: int) -> float:
    """IDM desired distance (m) of ``ego`` to ``front``, with the closing speed projected
    on ``ego``'s heading (headings' cosines and sines from ``m``, this step's)."""
    f = st.f
    ab = -f[COMFORT_ACC_MAX, b, p] * f[COMFORT_ACC_MIN, b, p]
    ce, se = m.cos_h[ego], m.sin_h[ego]
    cf, sf = m.cos_h[front], m.sin_h[front]
    ve, vf = f[SPEED, b, ego], f[SPEED, b, front]
    dv = (ve * ce - vf * cf) * ce + (ve * se - vf * sf) * se
    return f[DISTANCE_WANTED, b, p] + ve * f[TIME_WANTED, b, p] + ve * dv / (2 * math.sqrt(ab))


@njit
def lane_gap(t: LaneTable, st: State, b: int, ego: int, other: int) -> float:
    """Signed distance (m) from ``ego`` to ``other`` along ``ego``'s current lane."""
    lane = st.i[LANE, b, ego]
    s_other, _ = lane_local(t, lane, st.f[X, b, other], st.f[Y, b, other])
    s_ego, _ = lane_local(t, lane, st.f[X, b, ego], st.f[Y, b, ego])
    return s_other - s_ego


@njit
def idm_acceleration(t: LaneTable, st: State, b: int, m: Scratch, ego: int, front: int, p: int) -> float:
    """IDM acceleration (m/s²) of ``ego`` behind ``front`` (-1: free road) with the
    parameters of ``p``; 0 for no ego or a static obstacle. The desired speed is capped
    by ``ego``'s lane speed limit."""
    if ego < 0 or st.i[KIND, b, ego] == OBSTACLE:
        return 0.0
    f = st.f
    target = f[TARGET_SPEED, b, ego]
    limit = t.geo[SPEED_LIMIT, st.i[LANE, b, ego]]
    if not math.isnan(limit):
        target = min(max(target, 0.0), limit)
    cmax = f[COMFORT_ACC_MAX, b, p]
    ratio = max(f[SPEED, b, ego], 0.0) / abs(not_zero(target))
    acc = cmax * (1 - ratio ** f[DELTA, b, p])
    if front >= 0:
        d = lane_gap(t, st, b, ego, front)
        acc -= cmax * (desired_gap(st, b, m, ego, front, p) / not_zero(d)) ** 2
    return acc


@njit
def _sign(x: int) -> int:
    if x > 0:
        return 1
    return -1 if x < 0 else 0


@njit
def mobil(t: LaneTable, st: State, b: int, m: Scratch, i: int, lane: int) -> bool:
    """MOBIL: should HV ``i`` move to ``lane``? Never if its new follower would brake
    harder than allowed; with its start lane still ahead in its route, only towards that
    lane and only if safe for itself; otherwise if the acceleration it gains (plus
    politeness times its followers' gains) reaches the threshold."""
    new_front, new_rear = neighbours(t, st, b, m, i, lane)
    new_rear_a = idm_acceleration(t, st, b, m, new_rear, new_front, i)
    new_rear_pred_a = idm_acceleration(t, st, b, m, new_rear, i, i)
    max_braking = st.f[MAX_BRAKING, b, i]
    if new_rear_pred_a < -max_braking:
        return False
    old_front, old_rear = neighbours(t, st, b, m, i, st.i[LANE, b, i])
    self_pred_a = idm_acceleration(t, st, b, m, i, new_front, i)
    if st.i[ROUTE_HEAD, b, i] == 0 and st.i[ROUTE_LEN, b, i] > 0:
        current = t.ints[INDEX_IN_EDGE, st.i[TARGET, b, i]]
        if _sign(t.ints[INDEX_IN_EDGE, lane] - current) != _sign(st.i[ROUTE_LANE0, b, i] - current):
            return False
        return self_pred_a >= -max_braking
    self_a = idm_acceleration(t, st, b, m, i, old_front, i)
    old_rear_a = idm_acceleration(t, st, b, m, old_rear, i, i)
    old_rear_pred_a = idm_acceleration(t, st, b, m, old_rear, old_front, i)
    gain = self_pred_a - self_a + st.f[POLITENESS, b, i] * (
        new_rear_pred_a - new_rear_a + old_rear_pred_a - old_rear_a)
    return gain >= st.f[MIN_GAIN, b, i]


@njit
def _contests(t: LaneTable, st: State, b: int, m: Scratch, i: int, v: int, target: int) -> bool:
    """Whether ``v``, also changing into ``target``, is ahead of ``i`` within its desired gap."""
    if v == i or st.i[LANE, b, v] == target or st.i[TARGET, b, v] != target:
        return False
    d = lane_gap(t, st, b, i, v)
    return 0 < d < desired_gap(st, b, m, i, v, i)


@njit
def _abort_if_contested(t: LaneTable, st: State, b: int, m: Scratch, i: int) -> None:
    """Mid lane change: give up if another vehicle changing into the same lane is ahead
    within the desired gap. Candidates are the vehicles that targeted that lane when the
    step began plus those whose target changed since, not every vehicle."""
    target = st.i[TARGET, b, i]
    for k in range(m.by_target_start[target], m.by_target_start[target + 1]):
        if _contests(t, st, b, m, i, m.by_target[k], target):
            st.i[TARGET, b, i] = st.i[LANE, b, i]
            return
    for k in range(m.n_changed[0]):
        if _contests(t, st, b, m, i, m.changed[k], target):
            st.i[TARGET, b, i] = st.i[LANE, b, i]
            return


@njit
def _change_lane_policy(t: LaneTable, st: State, b: int, m: Scratch, i: int) -> None:
    lane, target = st.i[LANE, b, i], st.i[TARGET, b, i]
    if lane != target:
        if t.ints[EDGE, lane] == t.ints[EDGE, target]:
            _abort_if_contested(t, st, b, m, i)
        return
    # Decisions are taken once per lane-change delay.
    if not st.f[LC_DELAY, b, i] < st.f[TIMER, b, i]:
        return
    st.f[TIMER, b, i] = 0.0
    edge, index = t.ints[EDGE, lane], t.ints[INDEX_IN_EDGE, lane]
    for side in (-1, 1):
        if not 0 <= index + side < t.edges[EDGE_N_LANES, edge]:
            continue
        candidate = lane + side
        if not is_reachable(t, candidate, st.f[X, b, i], st.f[Y, b, i]):
            continue
        if abs(st.f[SPEED, b, i]) < 1:
            continue
        if mobil(t, st, b, m, i, candidate):
            st.i[TARGET, b, i] = candidate


@njit
def act_hv(t: LaneTable, st: State, b: int, m: Scratch, i: int) -> None:
    """Decide HV ``i``'s commands: follow the road, maybe change lane, steer to the target
    lane, and take the IDM acceleration behind the leader on its lane (and on the target
    lane while changing), bounded by ``acc_max``. A crashed HV decides nothing."""
    if st.flag[CRASHED, b, i]:
        return
    follow_road(t, st, b, i)
    _change_lane_policy(t, st, b, m, i)
    st.f[STEER, b, i] = min(max(steering_control(t, st, b, i), -MAX_STEERING_ANGLE), MAX_STEERING_ANGLE)
    lane, target = st.i[LANE, b, i], st.i[TARGET, b, i]
    front, _ = neighbours(t, st, b, m, i, lane)
    acc = idm_acceleration(t, st, b, m, i, front, i)
    if lane != target:
        front, _ = neighbours(t, st, b, m, i, target)
        acc = min(acc, idm_acceleration(t, st, b, m, i, front, i))
    acc_max = st.f[ACC_MAX, b, i]
    st.f[ACCEL, b, i] = min(max(acc, -acc_max), acc_max)


@njit
def act_av(t: LaneTable, st: State, b: int, i: int) -> None:
    """AV ``i``'s low-level commands for its current target lane and speed."""
    follow_road(t, st, b, i)
    st.f[STEER, b, i] = min(max(steering_control(t, st, b, i), -MAX_STEERING_ANGLE), MAX_STEERING_ANGLE)
    st.f[ACCEL, b, i] = KP_A * (st.f[TARGET_SPEED, b, i] - st.f[SPEED, b, i])
