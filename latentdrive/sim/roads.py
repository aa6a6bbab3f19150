"""highway-env's road layouts, built without its environments, and their drivable-area rasters.

Both backends drive on these roads: :mod:`latentdrive.sim.highway` runs highway-env's
vehicles on a fresh one every episode, :mod:`latentdrive.sim.fast.network` reads one into
arrays once per layout. Keeping the builders here, below both, lets each backend use them
without importing the other.
"""

from __future__ import annotations

from functools import cache
from typing import Any

import numpy as np
from highway_env.envs.exit_env import ExitEnv
from highway_env.envs.highway_env import HighwayEnv
from highway_env.envs.intersection_env import IntersectionEnv
from highway_env.envs.merge_env import MergeEnv
from highway_env.envs.roundabout_env import RoundaboutEnv
from highway_env.road.road import Road

from latentdrive.scene import RoadRaster, rasterize_strips

__all__ = ["RoadHost", "build_road", "layout_edges", "layout_raster"]

# Road builders of highway-env, called on a small host object rather than on a constructed
# env: constructing IntersectionEnv resets it, and its reset mutates IDMVehicle's class.
_ROAD_BUILDERS: dict[str, tuple[Any, str]] = {
    "roundabout": (RoundaboutEnv, "_make_road"),
    "intersection": (IntersectionEnv, "_make_road"),
    "merge": (MergeEnv, "_make_road"),
    "exit": (ExitEnv, "_create_road"),
    "highway": (HighwayEnv, "_create_road"),
}


class RoadHost:
    """Just enough of an AbstractEnv for highway-env's road builders and observations."""

    def __init__(self, config: dict[str, Any], np_random: np.random.Generator) -> None:
        self.config = config
        self.np_random = np_random
        self.road: Road | None = None
        self.vehicle: Any = None

    @classmethod
    def for_layout(cls, layout: str, lanes_count: int, rng: np.random.Generator) -> RoadHost:
        """A host with the layout's highway-env default config, ``lanes_count`` lanes."""
        env_cls, _ = _ROAD_BUILDERS[layout]
        config: dict[str, Any] = env_cls.default_config()
        config.update(lanes_count=lanes_count, show_trajectories=False)
        return cls(config, rng)


def build_road(layout: str, lanes_count: int, rng: np.random.Generator) -> Road:
    """A fresh highway-env Road of a layout, drawing from ``rng``."""
    env_cls, method = _ROAD_BUILDERS[layout]
    host = RoadHost.for_layout(layout, lanes_count, rng)
    getattr(env_cls, method)(host)
    assert host.road is not None
    return host.road


@cache
def layout_edges(layout: str, lanes_count: int) -> dict[tuple[str, str], int]:
    """Edge id of each ``(from, to)`` node pair of a layout's lane graph, in highway-env's
    graph iteration order (the order :mod:`latentdrive.sim.fast.network` numbers them in)."""
    graph = build_road(layout, lanes_count, np.random.default_rng(0)).network.graph
    return {(a, b): e for e, (a, b) in enumerate((a, b) for a, tos in graph.items() for b in tos)}


@cache
def layout_raster(layout: str, lanes_count: int, resolution: float = 0.5) -> RoadRaster:
    """Drivable-area raster of a layout, computed once per (layout, lanes) and cached.

    Every lane is sampled along its centreline every ``resolution/2`` metres; the samples,
    each with its lane's edge id (:func:`layout_edges`), are handed to
    :func:`latentdrive.scene.rasterize_strips`, so the raster also marks which edges each
    cell belongs to (what a route is drawn from).
    """
    road = build_road(layout, lanes_count, np.random.default_rng(0))
    ids = layout_edges(layout, lanes_count)
    centers, headings, half, edges = [], [], [], []
    for a, tos in road.network.graph.items():
        for b, lanes in tos.items():
            for lane in lanes:
                s = np.arange(0.0, lane.length + 1e-9, resolution / 2)
                centers.append(np.array([lane.position(si, 0.0) for si in s]))
                headings.append(np.array([lane.heading_at(si) for si in s]))
                half.append(np.array([lane.width_at(si) / 2 for si in s]))
                edges.append(np.full(s.size, ids[(a, b)]))
    raster = rasterize_strips(np.concatenate(centers), np.concatenate(headings), np.concatenate(half), resolution,
                              edges=np.concatenate(edges))
    raster.mask.flags.writeable = False
    assert raster.edges is not None
    raster.edges.flags.writeable = False
    return raster
