"""The reference backend: highway-env 1.12.x, the simulator the paper used.

It runs highway-env's vehicle models (IDM + MOBIL human drivers, MDPVehicle meta-action
controllers on a kinematic bicycle) on highway-env's road layouts
(:mod:`latentdrive.sim.roads`), but places every vehicle itself from the
:class:`ScenarioSpec`, with the fast backend's placement, so that every scenario can hold
several AVs and both backends start from the same instant. It never constructs
highway-env's own environments, whose resets write driver constants on shared classes.

highway-env is imported by three modules only: this one (vehicles), :mod:`latentdrive.sim.roads`
(roads) and :mod:`latentdrive.sim.fast.network` (which reads a road into arrays once); a
contract in pyproject.toml keeps it so.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from highway_env.envs.common.observation import OccupancyGridObservation
from highway_env.road.road import Road
from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.controller import MDPVehicle

from latentdrive.actions import META_ACTIONS
from latentdrive.config import ObservationConfig
from latentdrive.scenarios.spec import DriverParams, ScenarioError, ScenarioSpec
from latentdrive.scene import Kind, Scene
from latentdrive.sim.fast.network import get_network
from latentdrive.sim.fast.placement import PlacementPlan
from latentdrive.sim.roads import RoadHost, build_road, layout_edges, layout_raster

__all__ = ["HighwayBackend", "ScenarioError"]

# Driver parameters written per instance; instance attributes shadow the class ones.
_DRIVER_ATTRS = {
    "acc_max": "ACC_MAX",
    "comfort_acc_max": "COMFORT_ACC_MAX",
    "comfort_acc_min": "COMFORT_ACC_MIN",
    "distance_wanted": "DISTANCE_WANTED",
    "time_wanted": "TIME_WANTED",
    "politeness": "POLITENESS",
    "lane_change_min_acc_gain": "LANE_CHANGE_MIN_ACC_GAIN",
    "lane_change_max_braking_imposed": "LANE_CHANGE_MAX_BRAKING_IMPOSED",
    "lane_change_delay": "LANE_CHANGE_DELAY",
}


def _set_driver(vehicle: IDMVehicle, params: DriverParams, delta: float, timer: float) -> None:
    for field, attr in _DRIVER_ATTRS.items():
        setattr(vehicle, attr, getattr(params, field))
    vehicle.DELTA = delta
    # IDMVehicle seeds its lane-change timer from the class-level delay at construction;
    # the placement computed it from the spec's delay instead.
    vehicle.timer = timer


class HighwayBackend:
    """Runs one scenario on highway-env and reports each instant as a :class:`Scene`.

    Args:
        spec: the scenario.
    """

    name = "highway"

    def __init__(self, spec: ScenarioSpec) -> None:
        self.spec = spec
        self.raster = layout_raster(spec.layout, spec.lanes_count)
        self._edges = layout_edges(spec.layout, spec.lanes_count)  # the raster's edge ids
        self._plan = PlacementPlan(spec, get_network(spec.layout, spec.lanes_count))
        self.road: Road | None = None
        self.avs: list[MDPVehicle] = []
        self._goal_nodes: list[frozenset[str]] = []
        self._arrived = np.zeros(spec.n_av, dtype=bool)
        self.time = 0.0

    # -- episode -----------------------------------------------------------------------
    def reset(self, seed: int) -> Scene:
        """Build the road and place every vehicle, deterministically for ``seed``."""
        rng = np.random.default_rng(seed)
        # The road's own generator drives highway-env's internal draws (route choices at
        # forks, regulation); keep it separate from placement so adding one vehicle type
        # does not shift the other's randomness.
        road_rng = np.random.default_rng([seed, 1])
        self.road = build_road(self.spec.layout, self.spec.lanes_count, road_rng)
        # Where every vehicle starts: the same placement code as the fast backend, so both
        # backends start from the same instant for the same seed.
        p = self._plan.place(rng)
        self.avs = []
        self._goal_nodes = list(p.goal_nodes)
        network = self.road.network
        for i, lane_index in enumerate(p.lane_keys):
            lane = network.get_lane(lane_index)
            s = float(p.s[i])
            pos, heading, speed = lane.position(s, 0.0), lane.heading_at(s), float(p.speed[i])
            vehicle: Any
            if p.is_av[i]:
                vehicle = MDPVehicle(self.road, pos, heading=heading, speed=speed, target_lane_index=lane_index,
                                     target_speeds=np.asarray(self.spec.av_target_speeds))
                self.avs.append(vehicle)
            else:
                vehicle = IDMVehicle(self.road, pos, heading=heading, speed=speed, target_lane_index=lane_index)
                _set_driver(vehicle, self.spec.driver, float(p.delta[i]), float(p.timer[i]))
            # Vehicles start on the lane they were placed on, not on whichever lane is closest.
            vehicle.lane_index = lane_index
            vehicle.lane = lane
            if p.destination[i]:
                vehicle.plan_route_to(p.destination[i])
            self.road.vehicles.append(vehicle)
        self.time = 0.0
        self._arrived = np.zeros(self.spec.n_av, dtype=bool)
        self._update_arrived()
        return self.scene()

    def step(self, actions: np.ndarray) -> Scene:
        """Apply one meta-action per AV, then simulate one policy period."""
        assert self.road is not None, "reset() first"
        for vehicle, a in zip(self.avs, np.asarray(actions).reshape(-1), strict=True):
            vehicle.act(META_ACTIONS[int(a)])
        dt = 1.0 / self.spec.simulation_frequency
        for _ in range(self.spec.steps_per_action):
            self.road.act()
            self.road.step(dt)
        self.time += self.spec.steps_per_action * dt
        self._update_arrived()
        return self.scene()

    def _update_arrived(self) -> None:
        for i, (vehicle, goal) in enumerate(zip(self.avs, self._goal_nodes, strict=True)):
            if not self._arrived[i] and vehicle.lane_index[1] in goal:
                s, _ = vehicle.lane.local_coordinates(vehicle.position)
                self._arrived[i] = s >= self.spec.goal.longitudinal

    # -- observation -------------------------------------------------------------------
    def scene(self) -> Scene:
        """The current instant as arrays (vehicle order: AVs first, then HVs)."""
        assert self.road is not None
        vehicles = list(self.road.vehicles)
        n = len(vehicles)
        position = np.array([v.position for v in vehicles], dtype=np.float64).reshape(n, 2)
        heading = np.array([v.heading for v in vehicles], dtype=np.float64)
        speed = np.array([v.speed for v in vehicles], dtype=np.float64)
        lane_heading = np.array(
            [v.lane.heading_at(v.lane.local_coordinates(v.position)[0]) for v in vehicles], dtype=np.float64
        )
        av_ids = {id(v) for v in self.avs}
        kind = np.array([Kind.AV if id(v) in av_ids else Kind.HV for v in vehicles], dtype=np.int8)
        agents = np.array([vehicles.index(v) for v in self.avs], dtype=np.int64)
        arrived = np.zeros(n, dtype=bool)
        arrived[agents] = self._arrived
        return Scene(
            position=position,
            heading=heading,
            speed=speed,
            frenet_speed=speed * np.cos(heading - lane_heading),
            length=np.array([v.LENGTH for v in vehicles], dtype=np.float64),
            width=np.array([v.WIDTH for v in vehicles], dtype=np.float64),
            kind=kind,
            mask=np.ones(n, dtype=bool),
            crashed=np.array([v.crashed for v in vehicles], dtype=bool),
            arrived=arrived,
            agents=agents,
            road=self.raster,
            time=self.time,
            route=np.array([self._route_bits(v) for v in self.avs], dtype=np.uint64),
        )

    def _route_bits(self, vehicle: MDPVehicle) -> np.uint64:
        """``Scene.route`` of one AV: the edge of the lane it steers along and the route
        highway-env has not consumed yet (it drops an entry once the vehicle follows the
        road past it)."""
        bits = np.uint64(0)
        for key in (vehicle.target_lane_index, *(vehicle.route or ())):
            bits |= np.uint64(1) << np.uint64(self._edges[(key[0], key[1])])
        return bits

    # -- reference observation, for benchmarks ---------------------------------------
    def occupancy_grid(self, cfg: ObservationConfig) -> Callable[[], np.ndarray]:
        """highway-env's OccupancyGridObservation over the same cells as ``cfg``'s VelocityMap.

        Returns a function that observes the current instant once per AV, giving
        ``(n_av, 4, W, H)`` (features presence, vx, vy, on_road; grid aligned with each
        AV's axes, ``cfg.width × cfg.height`` cells of ``cfg.resolution`` metres). Used by
        ``latentdrive bench`` as the per-agent-frame cost of highway-env's grid.
        """
        assert self.road is not None, "reset() first"
        host = RoadHost.for_layout(self.spec.layout, self.spec.lanes_count, np.random.default_rng(0))
        host.road = self.road
        ahead = cfg.width * cfg.resolution - cfg.behind
        half = cfg.height * cfg.resolution / 2
        grid = OccupancyGridObservation(
            host,
            features=["presence", "vx", "vy", "on_road"],
            grid_size=((-cfg.behind, ahead), (-half, half)),
            grid_step=(cfg.resolution, cfg.resolution),
            align_to_vehicle_axes=True,
        )

        def observe() -> np.ndarray:
            out = []
            for av in self.avs:
                grid.observer_vehicle = av
                out.append(grid.observe())
            return np.stack(out)

        return observe
