"""Initial vehicle placement from a :class:`ScenarioSpec`, shared by both backends.

Every draw comes from one ``numpy.random.Generator`` in a fixed order, vehicle by vehicle
(AVs first, then HVs): up to 64 tries of (lane, longitudinal position) until the spot is
free, then the speed, then the destination, then, for an HV, its IDM exponent δ. A spot is
free when it is ``CLEARANCE`` metres from every placed vehicle and ``min_gap`` from those
on the same lane; after 64 failed tries the first free spot of the region's 1 m grid is
taken. Given the same generator state, both backends start from the same vehicles: spots
and headings come from :mod:`latentdrive.sim.fast.lanes`, whose arithmetic is highway-env's
own, so they equal those of the reference backend's lanes bit for bit.

Draws use the generator's scalar methods, which give the same values and leave the same
state as ``ClippedGaussian.sample`` and ``Generator.choice`` on lists, at a fraction of
the cost (resets are frequent in batched training).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from latentdrive.scenarios.spec import ClippedGaussian, ScenarioError, ScenarioSpec, SpawnRegion
from latentdrive.sim.fast.lanes import heading_at, position
from latentdrive.sim.fast.network import EDGE_N_LANES, LENGTH, Network

__all__ = ["CLEARANCE", "Placement", "PlacementPlan", "draw_clipped", "draw_index", "draw_uniform", "place_vehicles"]

# Minimum centre distance between any two vehicles at spawn, whatever their lanes, metres:
# a car length plus a metre, so that footprints never overlap.
CLEARANCE = 6.0


@dataclass(frozen=True)
class Placement:
    """Initial state of one environment's vehicles, AVs first then HVs.

    Attributes:
        lane_keys: highway-env lane index ``(from, to, id)`` each vehicle starts on.
        lane: ``(n,)`` lane ids in the :class:`Network`.
        s: ``(n,)`` longitudinal position on the lane, metres.
        x, y: ``(n,)`` world position, metres.
        heading: ``(n,)`` lane heading at ``s``, radians.
        speed: ``(n,)`` m/s.
        destination: route target node per vehicle, or None.
        delta: ``(n,)`` IDM acceleration exponent of HVs (NaN for AVs).
        timer: ``(n,)`` initial lane-change timer of HVs, seconds (NaN for AVs): highway-env
            seeds it from the position, ``(x + y)·π mod lane_change_delay``.
        is_av: ``(n,)`` bool.
        goal_nodes: per AV, the nodes whose incoming edges complete its mission (its
            destination, else the scenario's goal nodes).
    """

    lane_keys: tuple[tuple[str, str, int], ...]
    lane: NDArray[np.int64]
    s: NDArray[np.float64]
    x: NDArray[np.float64]
    y: NDArray[np.float64]
    heading: NDArray[np.float64]
    speed: NDArray[np.float64]
    destination: tuple[str | None, ...]
    delta: NDArray[np.float64]
    timer: NDArray[np.float64]
    is_av: NDArray[np.bool_]
    goal_nodes: tuple[frozenset[str], ...]


def draw_clipped(g: ClippedGaussian, rng: np.random.Generator) -> float:
    """One value of ``g.sample(rng)``, drawn identically (same value, same generator state
    afterwards) without the array overhead."""
    lo, hi = g.mean - g.clip, g.mean + g.clip
    x = g.mean + g.std * rng.standard_normal()
    for _ in range(64):
        if lo <= x <= hi:
            break
        x = g.mean + g.std * rng.standard_normal()
    return min(max(x, lo), hi)


def draw_index(n: int, rng: np.random.Generator) -> int:
    """The index ``rng.choice`` of a list of ``n`` items picks (same draw, same state after;
    a choice among one item draws nothing)."""
    return 0 if n == 1 else int(rng.integers(0, n))


def draw_uniform(lo: float, hi: float, rng: np.random.Generator) -> float:
    """``rng.uniform(lo, hi)``: the same value and generator state, computed as numpy does."""
    return lo + (hi - lo) * rng.random()


@dataclass(frozen=True)
class _Region:
    spec: SpawnRegion
    lanes: list[int]  # network lane id of each lane the region lists


class PlacementPlan:
    """A scenario's spawn regions resolved against a layout, ready to place many episodes.

    Raises:
        ScenarioError: a spawn region names an edge or a lane the layout does not have, or
            its longitudinal window leaves the edge.
    """

    def __init__(self, spec: ScenarioSpec, network: Network) -> None:
        self.spec, self.network = spec, network
        self._regions: dict[int, _Region] = {}
        for field in ("av_spawn", "hv_spawn"):
            for i, region in enumerate(getattr(spec, field)):
                self._regions.setdefault(id(region), self._resolve(region, f"scenario {spec.name!r}: {field}[{i}]"))

    def _resolve(self, region: SpawnRegion, where: str) -> _Region:
        edge = (region.edge[0], region.edge[1])
        if edge not in self.network.edge_keys:
            raise ScenarioError(f"{where}: edge {region.edge} is not in the {self.spec.layout} layout")
        n_lanes = int(self.network.table.edges[EDGE_N_LANES, self.network.edge(edge)])
        if max(region.lanes) >= n_lanes or min(region.lanes) < 0:
            raise ScenarioError(f"{where}: edge {region.edge} has lanes 0..{n_lanes - 1}, not {region.lanes}")
        lanes = [self.network.lane((*edge, k)) for k in region.lanes]
        g = region.longitudinal
        length = min(float(self.network.table.geo[LENGTH, k]) for k in lanes)
        if g.mean - g.clip < 0 or g.mean + g.clip > length:
            raise ScenarioError(
                f"{where}: longitudinal window [{g.mean - g.clip:g}, {g.mean + g.clip:g}] m "
                f"leaves edge {region.edge} (length {length:g} m)")
        return _Region(region, lanes)

    def place(self, rng: np.random.Generator) -> Placement:
        """Place the AVs then the HVs, drawing from ``rng``.

        Raises:
            ScenarioError: a region is too full to place another vehicle apart from the others.
        """
        spec = self.spec
        placed: list[tuple[float, float, int]] = []
        cols: dict[str, list[Any]] = {k: [] for k in ("key", "lane", "s", "x", "y", "heading", "speed", "dest", "delta", "timer", "av")}
        goals: list[frozenset[str]] = []
        order = [(spec.av_spawn[i % len(spec.av_spawn)], True) for i in range(spec.n_av)]
        order += [(spec.hv_spawn[i % len(spec.hv_spawn)], False) for i in range(spec.n_hv)]
        for region_spec, av in order:
            region = self._regions[id(region_spec)]
            k, s, x, y = self._spot(region, rng, placed)
            lane = region.lanes[k]
            speed = draw_clipped(region_spec.speed, rng)
            dests = region_spec.destinations
            destination = dests[draw_index(len(dests), rng)] if dests else None
            delta = timer = math.nan
            if not av:
                delta = draw_uniform(*spec.driver.delta_range, rng)
                timer = ((x + y) * math.pi) % spec.driver.lane_change_delay
            else:
                goals.append(frozenset({destination} if destination else spec.goal.nodes))
            placed.append((x, y, lane))
            for name, value in (("key", (*region_spec.edge, region_spec.lanes[k])), ("lane", lane), ("s", s),
                                ("x", x), ("y", y), ("heading", heading_at(self.network.table, lane, s)),
                                ("speed", speed), ("dest", destination), ("delta", delta),
                                ("timer", timer), ("av", av)):
                cols[name].append(value)
        return Placement(
            lane_keys=tuple(cols["key"]), lane=np.array(cols["lane"], dtype=np.int64),
            s=np.array(cols["s"]), x=np.array(cols["x"]), y=np.array(cols["y"]),
            heading=np.array(cols["heading"]), speed=np.array(cols["speed"]),
            destination=tuple(cols["dest"]), delta=np.array(cols["delta"]),
            timer=np.array(cols["timer"]), is_av=np.array(cols["av"], dtype=bool),
            goal_nodes=tuple(goals),
        )

    def _spot(self, region: _Region, rng: np.random.Generator,
              placed: list[tuple[float, float, int]]) -> tuple[int, float, float, float]:
        """``(index into region lanes, s, x, y)`` of a free spot."""
        spec = region.spec
        for _attempt in range(64):
            k = draw_index(len(spec.lanes), rng)
            s = draw_clipped(spec.longitudinal, rng)
            x, y = position(self.network.table, region.lanes[k], s, 0.0)
            if self._is_free(x, y, region.lanes[k], placed):
                return k, s, x, y
        g = spec.longitudinal
        for s_grid in np.arange(g.mean - g.clip, g.mean + g.clip + 1e-9, 1.0):
            for k, lane in enumerate(region.lanes):
                x, y = position(self.network.table, lane, float(s_grid), 0.0)
                if self._is_free(x, y, lane, placed):
                    return k, float(s_grid), x, y
        raise ScenarioError(
            f"scenario {self.spec.name!r}: cannot place another vehicle on edge {spec.edge} "
            f"{self.spec.min_gap} m from the others; lower n_av/n_hv or min_gap"
        )

    def _is_free(self, x: float, y: float, lane: int, placed: list[tuple[float, float, int]]) -> bool:
        min_gap = self.spec.min_gap
        for px, py, other in placed:
            d = math.hypot(x - px, y - py)
            if d < CLEARANCE or (other == lane and d < min_gap):
                return False
        return True


def place_vehicles(spec: ScenarioSpec, network: Network, rng: np.random.Generator) -> Placement:
    """Place the scenario's AVs then HVs, drawing from ``rng`` (see the module docstring).

    Raises:
        ScenarioError: a spawn region does not fit the layout (:class:`PlacementPlan`), or
            a region is too full to place another vehicle apart from the others.
    """
    return PlacementPlan(spec, network).place(rng)
