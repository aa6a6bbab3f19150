"""The batched simulation state: one row per environment, one column per vehicle slot.

Slot order within a row is the order highway-env keeps its road's vehicles in, which
decides who acts first and how collisions resolve: AVs, then HVs, then static obstacles,
then padding (``kind == PAD``) up to the batch's slot count.

Fields are packed into a few arrays indexed by the row constants below (``st.f[SPEED, b,
i]``): compiled kernels take the state as one small tuple, which keeps compilation quick.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from latentdrive.scenarios.spec import ScenarioSpec
from latentdrive.sim.fast.lanes import distance_with_heading
from latentdrive.sim.fast.network import Network

__all__ = ["AV", "HV", "OBSTACLE", "PAD", "State", "allocate", "slots_needed", "write_template"]

HV, AV, OBSTACLE, PAD = 0, 1, 2, -1

# Vehicle footprint, metres (highway-env's Vehicle.LENGTH and WIDTH).
VEHICLE_LENGTH, VEHICLE_WIDTH = 5.0, 2.0

# Rows of State.env_f / env_i (per environment).
ENV_F_ROWS = ("dt", "time", "goal_long")
DT, TIME, GOAL_LONG = range(len(ENV_F_ROWS))
ENV_I_ROWS = ("n_veh", "n_av", "n_tot", "n_sub", "reg_period", "reg_steps", "n_speeds")
N_VEH, N_AV, N_TOT, N_SUB, REG_PERIOD, REG_STEPS, N_SPEEDS = range(len(ENV_I_ROWS))
# Rows of State.f (per slot, float).
F_ROWS = (
    "x", "y", "heading", "speed", "vlength", "vwidth",  # metres, radians, m/s
    "target_speed", "steer", "accel",  # m/s, current commands (rad, m/s²)
    "impact_x", "impact_y",  # pending collision displacement, metres
    "timer",  # HVs: seconds since the last lane-change decision
    # HVs: IDM / MOBIL parameters (highway-env's IDMVehicle attributes)
    "acc_max", "comfort_acc_max", "comfort_acc_min", "distance_wanted", "time_wanted", "delta",
    "politeness", "min_gain", "max_braking", "lc_delay",
    "frenet_speed",  # speed along the current lane, m/s
)
(X, Y, HEADING, SPEED, VLENGTH, VWIDTH, TARGET_SPEED, STEER, ACCEL, IMPACT_X, IMPACT_Y, TIMER,
 ACC_MAX, COMFORT_ACC_MAX, COMFORT_ACC_MIN, DISTANCE_WANTED, TIME_WANTED, DELTA, POLITENESS,
 MIN_GAIN, MAX_BRAKING, LC_DELAY, FRENET_SPEED) = range(len(F_ROWS))
# Rows of State.i (per slot, int).
I_ROWS = (
    "kind",  # HV, AV, OBSTACLE or PAD
    "lane",  # lane the vehicle is on (its closest lane)
    "target",  # lane it steers to
    "speed_index",  # AVs: index into the speed grid
    "route_len", "route_head",  # route entries before the head are done
    "route_lane0",  # lane id on its edge of route entry 0 (the start lane)
    "yield_timer",
)
KIND, LANE, TARGET, SPEED_INDEX, ROUTE_LEN, ROUTE_HEAD, ROUTE_LANE0, YIELD_TIMER = range(len(I_ROWS))
# Rows of State.flag (per slot, bool).
FLAG_ROWS = ("crashed", "has_impact", "yielding", "arrived")
CRASHED, HAS_IMPACT, YIELDING, ARRIVED = range(len(FLAG_ROWS))

FArr = NDArray[np.float64]
IArr = NDArray[np.int64]
BArr = NDArray[np.bool_]


class State(NamedTuple):
    """Arrays of a batch of B environments with N vehicle slots each.

    Attributes:
        env_f: ``(len(ENV_F_ROWS), B)`` physics step (s), time since reset (s), metres
            along a goal edge that complete the mission.
        env_i: ``(len(ENV_I_ROWS), B)`` vehicle counts, physics steps per decision,
            right-of-way period (0: unregulated road) and clock, size of the speed grid.
        speeds: ``(B, K)`` AV target speeds, m/s.
        f, i, flag: ``(len(F_ROWS) | len(I_ROWS) | len(FLAG_ROWS), B, N)`` per-slot fields.
        route: ``(B, N, R)`` planned route as edge ids (-1 beyond its length).
        goal: ``(B, N, V)`` AVs' goal nodes.
    """

    env_f: FArr
    env_i: IArr
    speeds: FArr
    f: FArr
    i: IArr
    flag: BArr
    route: IArr
    goal: BArr


def slots_needed(spec: ScenarioSpec, network: Network) -> int:
    """Slots one environment of ``spec`` occupies."""
    return spec.n_av + spec.n_hv + network.obstacles.shape[0]


def allocate(n_envs: int, n_slots: int, n_speeds: int, route_len: int, n_nodes: int) -> State:
    """A zeroed state with every slot padding."""
    b, n = n_envs, n_slots
    st = State(
        env_f=np.zeros((len(ENV_F_ROWS), b)),
        env_i=np.zeros((len(ENV_I_ROWS), b), dtype=np.int64),
        speeds=np.zeros((b, n_speeds)),
        f=np.zeros((len(F_ROWS), b, n)),
        i=np.zeros((len(I_ROWS), b, n), dtype=np.int64),
        flag=np.zeros((len(FLAG_ROWS), b, n), dtype=bool),
        route=np.full((b, n, route_len), -1, dtype=np.int64),
        goal=np.zeros((b, n, n_nodes), dtype=bool),
    )
    st.i[KIND] = PAD
    return st


_DRIVER_FIELDS = (
    (ACC_MAX, "acc_max"), (COMFORT_ACC_MAX, "comfort_acc_max"), (COMFORT_ACC_MIN, "comfort_acc_min"),
    (DISTANCE_WANTED, "distance_wanted"), (TIME_WANTED, "time_wanted"), (POLITENESS, "politeness"),
    (MIN_GAIN, "lane_change_min_acc_gain"), (MAX_BRAKING, "lane_change_max_braking_imposed"),
    (LC_DELAY, "lane_change_delay"),
)


def write_template(st: State, row: int, spec: ScenarioSpec, network: Network) -> None:
    """Write what every episode of ``spec`` starts with into ``row``: counts, timing, the
    speed grid, footprints, driver parameters, obstacles and default AV goals. The
    placement of each episode is written over it (:func:`~latentdrive.sim.fast.kreset.load_rows`)."""
    n_veh, n_av = spec.n_av + spec.n_hv, spec.n_av
    obstacles = network.obstacles
    n_tot = n_veh + obstacles.shape[0]
    dt = 1.0 / spec.simulation_frequency
    st.f[:, row] = 0.0
    st.i[:, row] = 0
    st.i[KIND, row] = PAD
    st.flag[:, row] = False
    st.route[row] = -1
    st.goal[row] = False
    st.env_i[:, row] = 0
    st.env_i[N_VEH, row], st.env_i[N_AV, row], st.env_i[N_TOT, row] = n_veh, n_av, n_tot
    st.env_i[N_SUB, row] = spec.steps_per_action
    # highway-env's RegulatedRoad checks right of way twice a second of simulated time.
    st.env_i[REG_PERIOD, row] = int(1 / dt / 2) if network.regulated else 0
    st.env_f[DT, row], st.env_f[TIME, row], st.env_f[GOAL_LONG, row] = dt, 0.0, spec.goal.longitudinal
    speeds = np.asarray(spec.av_target_speeds, dtype=np.float64)
    st.env_i[N_SPEEDS, row] = speeds.size
    st.speeds[row] = 0.0
    st.speeds[row, : speeds.size] = speeds

    f, i = st.f[:, row], st.i[:, row]
    i[KIND, :n_av], i[KIND, n_av:n_veh] = AV, HV
    f[VLENGTH, :n_veh], f[VWIDTH, :n_veh] = VEHICLE_LENGTH, VEHICLE_WIDTH
    for field, name in _DRIVER_FIELDS:
        f[field, :n_veh] = getattr(spec.driver, name)
    for node in spec.goal.nodes:
        if node in network.node_names:
            st.goal[row, :n_av, network.node(node)] = True

    o = slice(n_veh, n_tot)
    i[KIND, o] = OBSTACLE
    f[X, o], f[Y, o], f[HEADING, o] = obstacles[:, 0], obstacles[:, 1], obstacles[:, 2]
    f[VLENGTH, o], f[VWIDTH, o] = obstacles[:, 3], obstacles[:, 4]
    for k, (x, y, heading) in enumerate(obstacles[:, :3].tolist()):
        # Obstacles sit on their closest lane (the first of equals), as every highway-env
        # road object does.
        closest = min(range(network.n_lanes), key=lambda lane: distance_with_heading(network.table, lane, x, y, heading))
        i[LANE, n_veh + k] = i[TARGET, n_veh + k] = closest
