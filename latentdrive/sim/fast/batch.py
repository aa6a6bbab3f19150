"""``FastBatch``: B environments stepped together, each reported as a :class:`Scene`.

Environments are grouped by road layout (layout name and lane count); each group keeps one
:class:`~latentdrive.sim.fast.state.State` with a row per environment, padded to the
group's largest vehicle count, and is advanced by one compiled call per decision step.
Scenarios may differ freely inside a batch (vehicle counts, frequencies, driver
parameters, spawn regions). Every row is simulated independently of the others, so an
environment's trajectory depends only on its spec, its seed and its actions, never on the
batch around it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from latentdrive.actions import N_ACTIONS
from latentdrive.config import ObservationConfig
from latentdrive.observe import SensorNoise
from latentdrive.scenarios.spec import ScenarioSpec
from latentdrive.scene import Kind, RoadRaster, Scene
from latentdrive.sim.fast.branch import Branches, BranchPart, take_rows
from latentdrive.sim.fast.krender import GRID_ROWS, render_rows
from latentdrive.sim.fast.kreset import PF_ROWS, PI_ROWS, load_rows
from latentdrive.sim.fast.kstep import step_envs
from latentdrive.sim.fast.network import EDGE, Network, get_network
from latentdrive.sim.fast.placement import PlacementPlan
from latentdrive.sim.fast.scratch import Scratch, make_scratch
from latentdrive.sim.fast.state import (
    ARRIVED,
    AV,
    CRASHED,
    FRENET_SPEED,
    HEADING,
    HV,
    KIND,
    LANE,
    N_AV,
    N_VEH,
    ROUTE_HEAD,
    ROUTE_LEN,
    SPEED,
    TARGET,
    TIME,
    VLENGTH,
    VWIDTH,
    State,
    X,
    Y,
    allocate,
    slots_needed,
    write_template,
)
from latentdrive.sim.roads import layout_raster

__all__ = ["FastBatch"]

assert (int(Kind.AV), int(Kind.HV)) == (AV, HV)


def route_bits(net: Network, st: State, rows: NDArray[np.int64], width: int) -> NDArray[np.uint64]:
    """``(len(rows), width)`` uint64: for vehicle slot ``a`` of each state row, the bits
    (:attr:`latentdrive.scene.RoadRaster.edges`) of the edge of the lane it steers along and
    of the route entries it has not passed (``Scene.route``)."""
    one = np.uint64(1)
    # The target lane, not the closest one: inside a junction the closest lane can be
    # another connector than the one the route takes.
    lane = np.clip(st.i[TARGET][rows, :width], 0, net.n_lanes - 1)  # slots beyond a row's vehicles hold no lane
    bits = np.left_shift(one, net.table.ints[EDGE][lane].astype(np.uint64))
    route = st.route[rows, :width]  # (K, A, R) edge ids, -1 beyond the route
    q = np.arange(route.shape[2])
    ahead = (q >= st.i[ROUTE_HEAD][rows, :width, None]) & (q < st.i[ROUTE_LEN][rows, :width, None]) & (route >= 0)
    shifted = np.left_shift(one, np.where(ahead, route, 0).astype(np.uint64))
    return bits | np.bitwise_or.reduce(np.where(ahead, shifted, np.uint64(0)), axis=2)


@dataclass
class _Group:
    network: Network
    state: State
    template: State  # what each row's episodes start from, before placement
    scratch: Scratch
    envs: list[int]  # batch index of each row
    raster: RoadRaster


class FastBatch:
    """B environments, possibly of different scenarios, stepped with one call per group.

    Args:
        specs: one scenario spec per environment.

    Actions are meta-action indices (:data:`latentdrive.actions.ACTION_NAMES`), one per
    AV; pass a sequence of ``(n_av_i,)`` arrays or one ``(B, A)`` array with
    ``A >= max n_av`` (entries beyond an environment's AV count are ignored).
    """

    name = "fast"

    def __init__(self, specs: Sequence[ScenarioSpec]) -> None:
        if not specs:
            raise ValueError("FastBatch needs at least one scenario spec")
        self.specs = list(specs)
        keys: dict[tuple[str, int], list[int]] = {}
        for i, spec in enumerate(self.specs):
            keys.setdefault((spec.layout, spec.lanes_count), []).append(i)
        self._groups: list[_Group] = []
        self._where: list[tuple[int, int]] = [(0, 0)] * len(self.specs)
        for (layout, lanes_count), envs in keys.items():
            net = get_network(layout, lanes_count)
            group_specs = [self.specs[i] for i in envs]
            n_slots = max(slots_needed(s, net) for s in group_specs)
            n_speeds = max(len(s.av_target_speeds) for s in group_specs)
            route_cap = net.route_table[0].shape[2]
            state = allocate(len(envs), n_slots, n_speeds, route_cap, net.n_nodes)
            template = allocate(len(envs), n_slots, n_speeds, route_cap, net.n_nodes)
            g = len(self._groups)
            self._groups.append(_Group(net, state, template, make_scratch(net.n_lanes, n_slots), envs,
                                       layout_raster(layout, lanes_count)))
            for row, i in enumerate(envs):
                self._where[i] = (g, row)
                write_template(template, row, self.specs[i], net)
        plans: dict[int, PlacementPlan] = {}
        self._plans = [plans.setdefault(id(s), PlacementPlan(s, self._groups[self._where[i][0]].network))
                       for i, s in enumerate(self.specs)]
        self._n_av = np.array([s.n_av for s in self.specs], dtype=np.int64)
        self._ready = np.zeros(len(self.specs), dtype=bool)

    @property
    def num_envs(self) -> int:
        return len(self.specs)

    # -- episodes ----------------------------------------------------------------------
    def reset(self, seeds: Sequence[int], env_ids: Sequence[int] | None = None) -> list[Scene]:
        """Start new episodes in ``env_ids`` (all by default), env ``env_ids[k]`` from
        ``seeds[k]``; returns their initial Scenes in that order."""
        ids = list(range(self.num_envs)) if env_ids is None else [int(i) for i in env_ids]
        if len(seeds) != len(ids):
            raise ValueError(f"got {len(seeds)} seeds for {len(ids)} environments")
        by_group: dict[int, list[tuple[int, int]]] = {}
        for i, seed in zip(ids, seeds, strict=True):
            by_group.setdefault(self._where[i][0], []).append((i, int(seed)))
        for g, items in by_group.items():
            self._reset_group(self._groups[g], items)
        self._ready[ids] = True
        return self.scenes(ids)

    def _reset_group(self, group: _Group, items: list[tuple[int, int]]) -> None:
        net = group.network
        n_slots = group.state.f.shape[2]
        pf = np.zeros((len(PF_ROWS), len(items), n_slots))
        pi = np.full((len(PI_ROWS), len(items), n_slots), -1, dtype=np.int64)
        rows = np.empty(len(items), dtype=np.int64)
        for k, (i, seed) in enumerate(items):
            rows[k] = self._where[i][1]
            p = self._plans[i].place(np.random.default_rng(seed))
            n = p.lane.shape[0]
            pf[:, k, :n] = (p.x, p.y, p.heading, p.speed, p.timer, p.delta)
            pi[0, k, :n] = p.lane
            pi[1, k, :n] = [key[2] for key in p.lane_keys]
            pi[2, k, :n] = [-1 if d is None else net.destination_id(d) for d in p.destination]
        routes, lengths = net.route_table
        load_rows(net.table, group.state, group.template, rows, pf, pi, routes, lengths)

    def step(self, actions: Sequence[NDArray[np.integer]] | NDArray[np.integer]) -> list[Scene]:
        """Apply one meta-action per AV in every environment and simulate one decision
        period; returns every environment's Scene."""
        self.advance(actions)
        return self.scenes()

    def advance(self, actions: Sequence[NDArray[np.integer]] | NDArray[np.integer]) -> None:
        """:meth:`step` without building Scenes (read them with :meth:`scene`)."""
        if not self._ready.all():
            raise RuntimeError(f"reset() environments {np.flatnonzero(~self._ready).tolist()} first")
        table = self._action_table(actions)
        for group in self._groups:
            rows = np.arange(len(group.envs), dtype=np.int64)
            step_envs(group.network.table, group.state, rows, table[group.envs], group.scratch)

    def _action_table(self, actions: Sequence[NDArray[np.integer]] | NDArray[np.integer]) -> NDArray[np.int64]:
        width = int(self._n_av.max())
        if isinstance(actions, np.ndarray) and actions.ndim == 2:
            if actions.shape[0] != self.num_envs or actions.shape[1] < width:
                raise ValueError(f"actions must be ({self.num_envs}, >= {width}), got {actions.shape}")
            table = np.asarray(actions[:, :width], dtype=np.int64)
        else:
            if len(actions) != self.num_envs:
                raise ValueError(f"got actions for {len(actions)} environments, batch has {self.num_envs}")
            table = np.zeros((self.num_envs, width), dtype=np.int64)
            for i, a in enumerate(actions):
                a = np.asarray(a, dtype=np.int64).reshape(-1)
                if a.shape != (self._n_av[i],):
                    raise ValueError(f"environment {i} needs {self._n_av[i]} actions, got {a.shape[0]}")
                table[i, : a.shape[0]] = a
        used = np.arange(width)[None, :] < self._n_av[:, None]
        if np.any(used & ((table < 0) | (table >= N_ACTIONS))):
            raise ValueError(f"actions must be integers in [0, {N_ACTIONS})")
        return table

    # -- lookahead ---------------------------------------------------------------------
    def branch(self, env_ids: Sequence[int] | NDArray[np.integer], copies: int) -> Branches:
        """``copies`` independent copies of each environment in ``env_ids`` at its current
        instant (branch ``k * copies + j`` copies ``env_ids[k]``), for lookahead; advancing
        them leaves this batch unchanged."""
        ids = np.asarray(env_ids, dtype=np.int64).reshape(-1)
        if copies < 1 or ids.size == 0:
            raise ValueError(f"branch needs environments and copies >= 1, got {ids.size} and {copies}")
        if not self._ready[ids].all():
            raise RuntimeError("reset() the environments before branching them")
        n_av = {int(self._n_av[i]) for i in ids}
        if len(n_av) != 1:
            raise ValueError(f"branched environments must share their AV count, got {sorted(n_av)}")
        out = np.arange(ids.size * copies, dtype=np.int64).reshape(ids.size, copies)
        parts = []
        for g, group in enumerate(self._groups):
            mine = [k for k, i in enumerate(ids) if self._where[i][0] == g]
            if not mine:
                continue
            rows = np.repeat([self._where[int(ids[k])][1] for k in mine], copies).astype(np.int64)
            parts.append(BranchPart(group.network.table, take_rows(group.state, rows),
                                    make_scratch(group.network.n_lanes, group.state.f.shape[2]),
                                    out[mine].reshape(-1)))
        return Branches(parts, ids.size * copies, n_av.pop())

    # -- observation -------------------------------------------------------------------
    def scene(self, i: int) -> Scene:
        """Environment ``i``'s current instant (vehicle order: AVs first, then HVs)."""
        return self.scenes([i])[0]

    def scenes(self, env_ids: Sequence[int] | None = None) -> list[Scene]:
        """Scenes of ``env_ids`` (all by default), in that order.

        Each group's arrays are copied once and every Scene holds views of that copy, so
        Scenes stay valid (and unchanged) after later steps.
        """
        ids = range(self.num_envs) if env_ids is None else env_ids
        snaps: dict[int, tuple[np.ndarray, ...]] = {}
        out = []
        for i in ids:
            g, r = self._where[i]
            if g not in snaps:
                snaps[g] = self._snapshot(self._groups[g].network, self._groups[g].state)
            f, pos, kind, flags, n_veh, n_av, time, route = snaps[g]
            n = int(n_veh[r])
            out.append(Scene(
                position=pos[r, :n], heading=f[0, r, :n], speed=f[1, r, :n], frenet_speed=f[2, r, :n],
                length=f[3, r, :n], width=f[4, r, :n], kind=kind[r, :n], mask=np.ones(n, dtype=bool),
                crashed=flags[0, r, :n], arrived=flags[1, r, :n],
                agents=np.arange(int(n_av[r]), dtype=np.int64), road=self._groups[g].raster,
                time=float(time[r]), route=route[r, : int(n_av[r])].copy(),
            ))
        return out

    @staticmethod
    def _snapshot(net: Network, st: State) -> tuple[np.ndarray, ...]:
        return (
            st.f[[HEADING, SPEED, FRENET_SPEED, VLENGTH, VWIDTH]],
            np.stack((st.f[X], st.f[Y]), axis=-1),
            st.i[KIND].astype(np.int8),
            st.flag[[CRASHED, ARRIVED]],
            st.env_i[N_VEH].copy(),
            st.env_i[N_AV].copy(),
            st.env_f[TIME].copy(),
            route_bits(net, st, np.arange(st.f.shape[1]), int(st.env_i[N_AV].max(initial=0))),
        )

    def render(self, env_ids: Sequence[int], cfg: ObservationConfig, noise: Sequence[SensorNoise] | None,
               observing: NDArray[np.bool_]) -> NDArray[np.float32]:
        """VelocityMap frames of the current instant, one compiled call per road layout.

        Args:
            env_ids: ``(K,)`` environments to render.
            cfg: the observation's geometry and eq. 13 coefficients.
            noise: per environment, the frame's draws ``(n_av, n_veh)`` of
                :func:`~latentdrive.observe.draw_noise`; None renders the clean scene.
            observing: ``(K, A)`` bool, the AVs that get a frame (``A`` = the batch's
                largest AV count).

        Returns:
            ``(K, A, 4, H, W)`` float32: frame ``[k, a]`` is AV ``a``'s of environment
            ``env_ids[k]``, as :func:`~latentdrive.observe.render_frame` draws it within
            the last bit of a logarithm; zeros where ``observing`` is False.
        """
        ids = [int(i) for i in env_ids]
        width = int(self._n_av.max())
        seen = np.asarray(observing, dtype=bool)
        if seen.shape != (len(ids), width):
            raise ValueError(f"observing must be ({len(ids)}, {width}), got {seen.shape}")
        if noise is not None and len(noise) != len(ids):
            raise ValueError(f"got noise draws for {len(noise)} environments, rendering {len(ids)}")
        if not self._ready[ids].all():
            raise RuntimeError("reset() the environments before rendering them")
        out = np.zeros((len(ids), width, 4, cfg.height, cfg.width), dtype=np.float32)
        grid = np.array([getattr(cfg, name) for name in GRID_ROWS], dtype=np.float64)
        by_group: dict[int, list[int]] = {}
        for k, i in enumerate(ids):
            by_group.setdefault(self._where[i][0], []).append(k)
        for g, ks in by_group.items():
            group = self._groups[g]
            st = group.state
            slots = np.asarray(ks, dtype=np.int64)
            rows = np.array([self._where[ids[k]][1] for k in ks], dtype=np.int64)
            shape = (len(ks), width, st.f.shape[2]) if noise is not None else (1, 1, 1)
            d_pos, d_head = np.zeros((*shape, 2)), np.zeros(shape)
            d_speed, missed = np.zeros(shape), np.zeros(shape, dtype=bool)
            if noise is not None:
                for j, k in enumerate(ks):
                    n_obs, n_veh = noise[k].heading.shape
                    if (n_obs, n_veh) != (self._n_av[ids[k]], st.env_i[N_VEH, rows[j]]):
                        raise ValueError(f"environment {ids[k]}: noise draws are {(n_obs, n_veh)}, its frame "
                                         f"needs {(int(self._n_av[ids[k]]), int(st.env_i[N_VEH, rows[j]]))}")
                    d_pos[j, :n_obs, :n_veh] = noise[k].position
                    d_head[j, :n_obs, :n_veh] = noise[k].heading
                    d_speed[j, :n_obs, :n_veh] = noise[k].speed
                    missed[j, :n_obs, :n_veh] = noise[k].missed
            raster = group.raster
            assert raster.edges is not None
            route = route_bits(group.network, st, rows, width) if cfg.route > 0 else np.zeros((len(ks), width), np.uint64)
            render_rows(st.f, st.i[KIND], st.env_i, rows, slots, seen[slots], noise is not None,
                        d_pos, d_head, d_speed, missed, raster.mask, raster.origin, raster.resolution,
                        raster.edges, route, grid, out)
        return out

    def lane_keys(self, i: int) -> list[tuple[str, str, int]]:
        """highway-env lane index ``(from, to, id)`` each vehicle of environment ``i`` is on."""
        g, r = self._where[i]
        group = self._groups[g]
        n = int(group.state.env_i[N_VEH, r])
        return [group.network.lane_keys[int(k)] for k in group.state.i[LANE, r, :n]]

    def goal_nodes(self, i: int) -> list[tuple[str, ...]]:
        """Names of the nodes each AV of environment ``i`` may complete its mission at (its
        destination when it drew one, else the spec's goal nodes), in agent order."""
        g, r = self._where[i]
        group = self._groups[g]
        names = group.network.node_names
        goals = group.state.goal[r, : int(group.state.env_i[N_AV, r])]
        return [tuple(names[int(k)] for k in np.flatnonzero(row)) for row in goals]
