"""Branches: copies of environments' current states, advanced independently (lookahead).

A planner asks "what happens if the AVs do this for the next few seconds?" many times per
decision. :meth:`FastBatch.branch <latentdrive.sim.fast.batch.FastBatch.branch>` copies
the simulation state of some environments, ``copies`` times each, into a separate batch
that the same compiled step advances; the original environments are never touched.
Copying a state is a few array gathers, which is what makes simulator lookahead cheap
here and impractical with highway-env's object graph (``copy.deepcopy`` of a Road).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from latentdrive.actions import N_ACTIONS, idle_when_done
from latentdrive.sim.fast.kstep import step_envs
from latentdrive.sim.fast.network import LaneTable
from latentdrive.sim.fast.scratch import Scratch
from latentdrive.sim.fast.state import (
    ARRIVED,
    CRASHED,
    HV,
    KIND,
    ROUTE_HEAD,
    ROUTE_LEN,
    SPEED,
    TIME,
    State,
)

__all__ = ["BranchPart", "Branches", "take_rows"]



def take_rows(st: State, rows: NDArray[np.int64]) -> State:
    """A new State whose row ``k`` is a copy of ``st``'s row ``rows[k]``."""
    return State(
        env_f=st.env_f[:, rows], env_i=st.env_i[:, rows], speeds=st.speeds[rows],
        f=st.f[:, rows], i=st.i[:, rows], flag=st.flag[:, rows],
        route=st.route[rows], goal=st.goal[rows],
    )


@dataclass
class BranchPart:
    """The branches of one road layout (one compiled table)."""

    table: LaneTable
    state: State
    scratch: Scratch
    out: NDArray[np.int64]  # branch index of each row of ``state``


class Branches:
    """``M`` simulations, each a copy of one environment's state at branching time.

    Built by :meth:`FastBatch.branch`; branch ``k * copies + j`` is copy ``j`` of
    environment ``env_ids[k]``. Actions are meta-action indices ``(M, A)`` with
    ``A >= n_av``; as in the env, an AV that has crashed or completed its mission is
    driven Idle whatever it is given.

    Attributes:
        n_av: the AV count (the branched environments must share it).
    """

    def __init__(self, parts: list[BranchPart], n_branches: int, n_av: int) -> None:
        self._parts = parts
        self.num_branches = n_branches
        self.n_av = n_av

    def advance(self, actions: NDArray[np.integer]) -> None:
        """Simulate one decision period in every branch."""
        acts = np.asarray(actions, dtype=np.int64)
        if acts.shape[0] != self.num_branches or acts.shape[1] < self.n_av:
            raise ValueError(f"actions must be ({self.num_branches}, >= {self.n_av}), got {acts.shape}")
        if acts.size and (acts[:, : self.n_av].min() < 0 or acts[:, : self.n_av].max() >= N_ACTIONS):
            raise ValueError(f"actions must be integers in [0, {N_ACTIONS})")
        for p in self._parts:
            a = acts[p.out, : self.n_av]
            done = p.state.flag[CRASHED, :, : self.n_av] | p.state.flag[ARRIVED, :, : self.n_av]
            a = idle_when_done(a, done)
            step_envs(p.table, p.state, np.arange(p.out.size, dtype=np.int64), a, p.scratch)

    def forget_human_routes(self) -> None:
        """Drop every human driver's remaining route in these branches.

        From here on each HV follows the road: at a junction it takes the continuation
        closest to its lane (as an HV without a destination does), not the exit or turn it
        was given at spawn. A planner that branches after this no longer knows where the
        human drivers are going; the environments branched from keep their routes.
        """
        for p in self._parts:
            human = p.state.i[KIND] == HV
            p.state.i[ROUTE_LEN][human] = p.state.i[ROUTE_HEAD][human]

    def agents(self) -> tuple[NDArray[np.float64], NDArray[np.bool_], NDArray[np.bool_]]:
        """Every branch's AV speeds (m/s), crashed and arrived flags, each ``(M, n_av)``."""
        speed = np.zeros((self.num_branches, self.n_av))
        crashed = np.zeros((self.num_branches, self.n_av), dtype=bool)
        arrived = np.zeros((self.num_branches, self.n_av), dtype=bool)
        for p in self._parts:
            speed[p.out] = p.state.f[SPEED, :, : self.n_av]
            crashed[p.out] = p.state.flag[CRASHED, :, : self.n_av]
            arrived[p.out] = p.state.flag[ARRIVED, :, : self.n_av]
        return speed, crashed, arrived

    def time(self) -> NDArray[np.float64]:
        """``(M,)`` simulated seconds since each branch's episode began."""
        out = np.zeros(self.num_branches)
        for p in self._parts:
            out[p.out] = p.state.env_f[TIME]
        return out
