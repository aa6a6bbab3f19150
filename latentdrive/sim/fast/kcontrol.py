"""Route following, the steering and speed controllers, meta-actions and the kinematic bicycle.

The equations and constants are highway-env 1.12's ControlledVehicle / MDPVehicle /
Vehicle: a cascaded lateral-position → heading → steering controller, a proportional
speed controller, and a bicycle model with the slip angle at the centre of gravity,
integrated with explicit Euler in that order (position, heading, speed).
"""

from __future__ import annotations

import math

from latentdrive.sim.fast._jit import njit
from latentdrive.sim.fast.kgeom import (
    closest_lane,
    lane_distance,
    lane_heading,
    lane_local,
    lane_position,
    not_zero,
    wrap_to_pi,
)
from latentdrive.sim.fast.network import (
    EDGE,
    EDGE_FIRST_LANE,
    EDGE_FROM,
    EDGE_N_LANES,
    EDGE_TO,
    FORBIDDEN,
    INDEX_IN_EDGE,
    LENGTH,
    WIDTH,
    LaneTable,
)
from latentdrive.sim.fast.state import (
    ACCEL,
    CRASHED,
    HAS_IMPACT,
    HEADING,
    HV,
    IMPACT_X,
    IMPACT_Y,
    KIND,
    LANE,
    N_SPEEDS,
    ROUTE_HEAD,
    ROUTE_LANE0,
    ROUTE_LEN,
    SPEED,
    SPEED_INDEX,
    STEER,
    TARGET,
    TARGET_SPEED,
    TIMER,
    VEHICLE_LENGTH,
    VLENGTH,
    State,
    X,
    Y,
)

__all__ = [
    "follow_road",
    "integrate",
    "is_reachable",
    "meta_action",
    "next_lane",
    "steering_control",
]

TAU_ACC = 0.6  # s, speed response time
TAU_HEADING = 0.2  # s
TAU_LATERAL = 0.6  # s
TAU_PURSUIT = 0.5 * TAU_HEADING  # s, look-ahead of the heading reference
KP_A = 1 / TAU_ACC
KP_HEADING = 1 / TAU_HEADING
KP_LATERAL = 1 / TAU_LATERAL
MAX_STEERING_ANGLE = math.pi / 3
MAX_SPEED, MIN_SPEED = 40.0, -40.0  # m/s

# Meta-action indices (latentdrive.actions.META_ACTIONS order).
LANE_LEFT, IDLE, LANE_RIGHT, FASTER, SLOWER = 0, 1, 2, 3, 4


@njit
def _lane_of(t: LaneTable, edge: int, index: int) -> int:
    return t.edges[EDGE_FIRST_LANE, edge] + index


@njit
def _next_id_on(t: LaneTable, edge: int, index: int, next_edge: int, next_index: int,
                px: float, py: float) -> tuple[int, float]:
    """Lane on ``next_edge`` and its distance to ``(px, py)``: the same lane number when
    both edges have as many lanes (or the given one), else the closest lane."""
    if t.edges[EDGE_N_LANES, edge] == t.edges[EDGE_N_LANES, next_edge]:
        if next_index < 0:
            next_index = index
    else:
        best_d = math.inf
        for k in range(t.edges[EDGE_N_LANES, next_edge]):
            d = lane_distance(t, _lane_of(t, next_edge, k), px, py)
            if d < best_d:
                best_d, next_index = d, k
    lane = _lane_of(t, next_edge, next_index)
    return lane, lane_distance(t, lane, px, py)


@njit
def next_lane(t: LaneTable, st: State, b: int, i: int) -> int:
    """The lane vehicle ``i`` follows once its target lane ends (may consume a route entry).

    With a planned route the next road is the route's; otherwise, among the roads leaving
    the end node, the one whose lane lies closest to the vehicle's projection on its
    current target lane; at a dead end the target lane is kept.
    """
    current = st.i[TARGET, b, i]
    edge = t.ints[EDGE, current]
    index = t.ints[INDEX_IN_EDGE, current]
    end_node = t.edges[EDGE_TO, edge]
    next_edge, next_index = -1, -1
    head, n_route = st.i[ROUTE_HEAD, b, i], st.i[ROUTE_LEN, b, i]
    if head < n_route:
        if st.route[b, i, head] == edge:
            head += 1
            st.i[ROUTE_HEAD, b, i] = head
        if head < n_route and t.edges[EDGE_FROM, st.route[b, i, head]] == end_node:
            next_edge = st.route[b, i, head]
            next_index = st.i[ROUTE_LANE0, b, i] if head == 0 else -1
    s, _ = lane_local(t, current, st.f[X, b, i], st.f[Y, b, i])
    px, py = lane_position(t, current, s, 0.0)
    if next_edge >= 0:
        lane, _ = _next_id_on(t, edge, index, next_edge, next_index, px, py)
        return lane
    first, last = t.node_out_start[end_node], t.node_out_start[end_node + 1]
    if first == last:
        return current
    best, best_d = current, math.inf
    for k in range(first, last):
        lane, d = _next_id_on(t, edge, index, t.node_out_edges[k], -1, px, py)
        if d < best_d:
            best, best_d = lane, d
    return best


@njit
def follow_road(t: LaneTable, st: State, b: int, i: int) -> None:
    """Switch the target to the next lane within half a car length of the target's end."""
    lane = st.i[TARGET, b, i]
    s, _ = lane_local(t, lane, st.f[X, b, i], st.f[Y, b, i])
    if s > t.geo[LENGTH, lane] - VEHICLE_LENGTH / 2:
        st.i[TARGET, b, i] = next_lane(t, st, b, i)


@njit
def is_reachable(t: LaneTable, lane: int, x: float, y: float) -> bool:
    """A lane change towards ``lane`` is allowed from ``(x, y)``: not forbidden, within
    two widths laterally and along the lane (up to a car length past its end)."""
    if t.ints[FORBIDDEN, lane]:
        return False
    s, r = lane_local(t, lane, x, y)
    return abs(r) <= 2 * t.geo[WIDTH, lane] and 0 <= s < t.geo[LENGTH, lane] + VEHICLE_LENGTH


@njit
def steering_control(t: LaneTable, st: State, b: int, i: int) -> float:
    """Steering angle (rad) that brings vehicle ``i`` onto its target lane's centreline."""
    lane = st.i[TARGET, b, i]
    speed = st.f[SPEED, b, i]
    s, r = lane_local(t, lane, st.f[X, b, i], st.f[Y, b, i])
    future_heading = lane_heading(t, lane, s + speed * TAU_PURSUIT)
    lateral_speed = -KP_LATERAL * r
    heading_command = math.asin(min(max(lateral_speed / not_zero(speed), -1.0), 1.0))
    heading_ref = future_heading + min(max(heading_command, -math.pi / 4), math.pi / 4)
    heading_rate = KP_HEADING * wrap_to_pi(heading_ref - st.f[HEADING, b, i])
    slip = math.asin(min(max(st.f[VLENGTH, b, i] / 2 / not_zero(speed) * heading_rate, -1.0), 1.0))
    steering = math.atan(2 * math.tan(slip))
    return min(max(steering, -MAX_STEERING_ANGLE), MAX_STEERING_ANGLE)


@njit
def speed_to_index(st: State, b: int, speed: float) -> int:
    """Index of the allowed target speed nearest to ``speed`` (round half to even)."""
    n = st.env_i[N_SPEEDS, b]
    lo, hi = st.speeds[b, 0], st.speeds[b, n - 1]
    x = (speed - lo) / (hi - lo) * (n - 1)
    k = math.floor(x + 0.5)
    if k - x == 0.5 and k % 2 != 0:
        k -= 1
    return int(min(max(k, 0), n - 1))


@njit
def meta_action(t: LaneTable, st: State, b: int, i: int, action: int) -> None:
    """Apply a meta-action to AV ``i``: step its speed index from its current speed, or
    move its target one lane left/right when that lane is reachable; then follow the road."""
    if action == FASTER or action == SLOWER:
        k = speed_to_index(st, b, st.f[SPEED, b, i]) + (1 if action == FASTER else -1)
        k = min(max(k, 0), st.env_i[N_SPEEDS, b] - 1)
        st.i[SPEED_INDEX, b, i] = k
        st.f[TARGET_SPEED, b, i] = st.speeds[b, k]
        follow_road(t, st, b, i)
        return
    follow_road(t, st, b, i)
    if action == LANE_LEFT or action == LANE_RIGHT:
        target = st.i[TARGET, b, i]
        edge = t.ints[EDGE, target]
        k = t.ints[INDEX_IN_EDGE, target] + (-1 if action == LANE_LEFT else 1)
        k = min(max(k, 0), t.edges[EDGE_N_LANES, edge] - 1)
        candidate = _lane_of(t, edge, k)
        if is_reachable(t, candidate, st.f[X, b, i], st.f[Y, b, i]):
            st.i[TARGET, b, i] = candidate


@njit
def integrate(t: LaneTable, st: State, b: int, i: int, dt: float) -> None:
    """One Euler step of the kinematic bicycle for vehicle ``i``, then its lane update.

    A crashed vehicle steers straight and brakes to a stop; a pending collision impact is
    applied after the move (and marks the vehicle crashed).
    """
    f = st.f
    if st.i[KIND, b, i] == HV:
        f[TIMER, b, i] += dt
    steer, accel, speed = f[STEER, b, i], f[ACCEL, b, i], f[SPEED, b, i]
    if st.flag[CRASHED, b, i]:
        steer = 0.0
        accel = -1.0 * speed
    if speed > MAX_SPEED:
        accel = min(accel, 1.0 * (MAX_SPEED - speed))
    elif speed < MIN_SPEED:
        accel = max(accel, 1.0 * (MIN_SPEED - speed))
    beta = math.atan(1 / 2 * math.tan(steer))
    heading = f[HEADING, b, i]
    f[X, b, i] += speed * math.cos(heading + beta) * dt
    f[Y, b, i] += speed * math.sin(heading + beta) * dt
    if st.flag[HAS_IMPACT, b, i]:
        f[X, b, i] += f[IMPACT_X, b, i]
        f[Y, b, i] += f[IMPACT_Y, b, i]
        st.flag[CRASHED, b, i] = True
        st.flag[HAS_IMPACT, b, i] = False
    f[HEADING, b, i] = heading + speed * math.sin(beta) / (f[VLENGTH, b, i] / 2) * dt
    f[SPEED, b, i] = speed + accel * dt
    st.i[LANE, b, i] = closest_lane(t, f[X, b, i], f[Y, b, i], f[HEADING, b, i], st.i[LANE, b, i])
