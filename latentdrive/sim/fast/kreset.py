"""Start new episodes in some rows of a batch: template row plus placement, in one call."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from latentdrive.sim.fast._jit import njit
from latentdrive.sim.fast.kcontrol import speed_to_index
from latentdrive.sim.fast.kstep import update_outputs
from latentdrive.sim.fast.network import LaneTable
from latentdrive.sim.fast.state import (
    AV,
    DELTA,
    HEADING,
    KIND,
    LANE,
    N_VEH,
    ROUTE_LANE0,
    ROUTE_LEN,
    SPEED,
    SPEED_INDEX,
    TARGET,
    TARGET_SPEED,
    TIMER,
    State,
    X,
    Y,
)

__all__ = ["PF_ROWS", "PI_ROWS", "load_rows"]

# Rows of the placement arrays handed to load_rows.
PF_ROWS = ("x", "y", "heading", "speed", "timer", "delta")
PX, PY, PHEADING, PSPEED, PTIMER, PDELTA = range(len(PF_ROWS))
PI_ROWS = ("lane", "lane0", "destination")  # network lane, lane id on its edge, route column (-1: none)
PLANE, PLANE0, PDEST = range(len(PI_ROWS))


@njit
def load_rows(t: LaneTable, st: State, template: State, rows: NDArray[np.int64], pf: NDArray[np.float64],
              pi: NDArray[np.int64], routes: NDArray[np.int64], route_lens: NDArray[np.int64]) -> None:
    """Reset ``rows[k]`` from its template and placement ``pf[:, k]``, ``pi[:, k]``.

    AVs track the allowed speed nearest their initial speed and HVs their initial speed;
    vehicles with a destination get its planned route (and an AV that goal alone).
    """
    for k in range(rows.shape[0]):
        b = rows[k]
        for q in range(st.f.shape[0]):
            for v in range(st.f.shape[2]):
                st.f[q, b, v] = template.f[q, b, v]
        for q in range(st.i.shape[0]):
            for v in range(st.i.shape[2]):
                st.i[q, b, v] = template.i[q, b, v]
        for q in range(st.flag.shape[0]):
            for v in range(st.flag.shape[2]):
                st.flag[q, b, v] = template.flag[q, b, v]
        for q in range(st.env_f.shape[0]):
            st.env_f[q, b] = template.env_f[q, b]
        for q in range(st.env_i.shape[0]):
            st.env_i[q, b] = template.env_i[q, b]
        for q in range(st.speeds.shape[1]):
            st.speeds[b, q] = template.speeds[b, q]
        for v in range(st.route.shape[1]):
            for q in range(st.route.shape[2]):
                st.route[b, v, q] = -1
            for q in range(st.goal.shape[2]):
                st.goal[b, v, q] = template.goal[b, v, q]
        for v in range(st.env_i[N_VEH, b]):
            st.f[X, b, v], st.f[Y, b, v] = pf[PX, k, v], pf[PY, k, v]
            st.f[HEADING, b, v], st.f[SPEED, b, v] = pf[PHEADING, k, v], pf[PSPEED, k, v]
            lane = pi[PLANE, k, v]
            st.i[LANE, b, v] = st.i[TARGET, b, v] = lane
            st.i[ROUTE_LANE0, b, v] = pi[PLANE0, k, v]
            if st.i[KIND, b, v] == AV:
                index = speed_to_index(st, b, pf[PSPEED, k, v])
                st.i[SPEED_INDEX, b, v] = index
                st.f[TARGET_SPEED, b, v] = st.speeds[b, index]
            else:
                st.f[TARGET_SPEED, b, v] = pf[PSPEED, k, v]
                st.f[TIMER, b, v], st.f[DELTA, b, v] = pf[PTIMER, k, v], pf[PDELTA, k, v]
            dest = pi[PDEST, k, v]
            if dest >= 0:
                n_route = route_lens[lane, dest]
                for q in range(n_route):
                    st.route[b, v, q] = routes[lane, dest, q]
                st.i[ROUTE_LEN, b, v] = n_route
                if st.i[KIND, b, v] == AV:
                    for q in range(st.goal.shape[2]):
                        st.goal[b, v, q] = q == dest
        update_outputs(t, st, b)
