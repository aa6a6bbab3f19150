"""One decision step of every environment of a batch, in highway-env's order.

Per environment: the AVs' meta-actions; then, per physics step, every vehicle decides its
commands in slot order (AVs, then HVs: a later vehicle sees earlier vehicles' new target
lanes), the right-of-way check runs when due, every vehicle moves, and collisions are
resolved; finally the mission flags and Frenet speeds are updated. Environments are
independent, so a row's result does not depend on the others in the batch.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from latentdrive.sim.fast._jit import njit
from latentdrive.sim.fast.kbehavior import act_av, act_hv
from latentdrive.sim.fast.kcollide import collide
from latentdrive.sim.fast.kcontrol import integrate, meta_action
from latentdrive.sim.fast.kgeom import lane_heading, lane_local
from latentdrive.sim.fast.kneighbours import build_members, index_targets
from latentdrive.sim.fast.kregulate import enforce_right_of_way
from latentdrive.sim.fast.network import EDGE, EDGE_TO, LaneTable
from latentdrive.sim.fast.scratch import Scratch
from latentdrive.sim.fast.state import (
    ARRIVED,
    AV,
    DT,
    FRENET_SPEED,
    GOAL_LONG,
    HEADING,
    HV,
    KIND,
    LANE,
    N_AV,
    N_SUB,
    N_VEH,
    REG_PERIOD,
    REG_STEPS,
    SPEED,
    TARGET,
    TIME,
    State,
    X,
    Y,
)

__all__ = ["physics_step", "step_envs", "update_outputs"]


@njit
def physics_step(t: LaneTable, st: State, b: int, m: Scratch) -> None:
    """Advance environment ``b`` by one physics step of ``dt`` seconds."""
    dt = st.env_f[DT, b]
    build_members(t, st, b, m)
    index_targets(st, b, m)
    for i in range(st.env_i[N_VEH, b]):
        before = st.i[TARGET, b, i]
        if st.i[KIND, b, i] == AV:
            act_av(t, st, b, i)
        elif st.i[KIND, b, i] == HV:
            act_hv(t, st, b, m, i)
        if st.i[TARGET, b, i] != before:
            m.changed[m.n_changed[0]] = i
            m.n_changed[0] += 1
    if st.env_i[REG_PERIOD, b] > 0:
        st.env_i[REG_STEPS, b] += 1
        if st.env_i[REG_STEPS, b] % st.env_i[REG_PERIOD, b] == 0:
            enforce_right_of_way(t, st, b, m)
    for i in range(st.env_i[N_VEH, b]):
        integrate(t, st, b, i, dt)
    collide(st, b, dt, m)


@njit
def update_outputs(t: LaneTable, st: State, b: int) -> None:
    """Frenet speeds along each vehicle's lane, and AV mission completion (sticky)."""
    for i in range(st.env_i[N_VEH, b]):
        lane = st.i[LANE, b, i]
        s, _ = lane_local(t, lane, st.f[X, b, i], st.f[Y, b, i])
        st.f[FRENET_SPEED, b, i] = st.f[SPEED, b, i] * math.cos(st.f[HEADING, b, i] - lane_heading(t, lane, s))
        if st.i[KIND, b, i] == AV and not st.flag[ARRIVED, b, i]:
            if st.goal[b, i, t.edges[EDGE_TO, t.ints[EDGE, lane]]]:
                st.flag[ARRIVED, b, i] = s >= st.env_f[GOAL_LONG, b]


@njit
def step_envs(t: LaneTable, st: State, rows: NDArray[np.int64], actions: NDArray[np.int64], m: Scratch) -> None:
    """Apply ``actions[k, a]`` (meta-action of AV ``a``) to environment ``rows[k]`` and
    simulate one decision period there."""
    for k in range(rows.shape[0]):
        b = rows[k]
        for i in range(st.env_i[N_AV, b]):
            meta_action(t, st, b, i, actions[k, i])
        for _ in range(st.env_i[N_SUB, b]):
            physics_step(t, st, b, m)
        st.env_f[TIME, b] += st.env_i[N_SUB, b] * st.env_f[DT, b]
        update_outputs(t, st, b)
