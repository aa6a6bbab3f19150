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

__all__ = ["RoadHost", "build_road", "layout_raster"]

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
def layout_raster(layout: str, lanes_count: int, resolution: float = 0.5) -> RoadRaster:
    """Drivable-area raster of a layout, computed once per (layout, lanes) and cached.

    Every lane is sampled along its centreline every ``resolution/2`` metres; the samples
    are handed to :func:`latentdrive.scene.rasterize_strips`.
    """
    road = build_road(layout, lanes_count, np.random.default_rng(0))
    centers, headings, half = [], [], []
    for lanes in (lanes for tos in road.network.graph.values() for lanes in tos.values()):
        for lane in lanes:
            s = np.arange(0.0, lane.length + 1e-9, resolution / 2)
            centers.append(np.array([lane.position(si, 0.0) for si in s]))
            headings.append(np.array([lane.heading_at(si) for si in s]))
            half.append(np.array([lane.width_at(si) / 2 for si in s]))
    raster = rasterize_strips(np.concatenate(centers), np.concatenate(headings), np.concatenate(half), resolution)
    raster.mask.flags.writeable = False
    return raster
