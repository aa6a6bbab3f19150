import itertools

import numpy as np
import pytest
from highway_env.vehicle.objects import Obstacle

from latentdrive.scenarios import get_spec
from latentdrive.sim.fast import kgeom
from latentdrive.sim.fast import lanes as L
from latentdrive.sim.fast.network import CURVE_BOX, LENGTH, get_network
from latentdrive.sim.fast.state import LANE, allocate, slots_needed, write_template
from latentdrive.sim.roads import build_road

LAYOUTS = ("roundabout", "intersection", "merge", "exit", "highway")


def _road(layout):
    return build_road(layout, 3, np.random.default_rng(0))


def _points(rng, length, n):
    """``n`` Frenet points from 20 m before a lane to 20 m beyond it, 6 m either side."""
    return zip(rng.uniform(-20, length + 20, n).tolist(), rng.uniform(-6, 6, n).tolist(), strict=True)


@pytest.mark.parametrize("layout", LAYOUTS)
def test_geometry_matches_highway_env_on_every_lane(layout):
    # Positions and headings bit for bit: placement starts both backends from them.
    # Local coordinates to rounding: highway-env takes dot products and norms there.
    net, road = get_network(layout, 3), _road(layout)
    t = net.table
    assert list(road.network.lanes_dict()) == list(net.lane_keys)
    rng = np.random.default_rng(1)
    for k, key in enumerate(net.lane_keys):
        lane = road.network.get_lane(key)
        for s, r in _points(rng, lane.length, 40):
            x, y = L.position(t, k, s, r)
            assert [x, y] == lane.position(s, r).tolist()
            assert L.heading_at(t, k, s) == lane.heading_at(s)
            p = np.array([x, y])
            assert L.local_coordinates(t, k, x, y) == pytest.approx(lane.local_coordinates(p), abs=1e-9)
            heading = float(rng.uniform(-4, 4))
            assert L.distance_with_heading(t, k, x, y, heading) == pytest.approx(
                lane.distance_with_heading(p, heading), abs=1e-9)


@pytest.mark.parametrize("layout", LAYOUTS)
def test_local_coordinates_round_trip(layout):
    net = get_network(layout, 3)
    rng = np.random.default_rng(2)
    for k in range(net.n_lanes):
        length = net.table.geo[LENGTH, k]
        for s, r in zip(rng.uniform(0, length, 30).tolist(), rng.uniform(-1.9, 1.9, 30).tolist(), strict=True):
            assert L.local_coordinates(net.table, k, *L.position(net.table, k, s, r)) == pytest.approx((s, r), abs=1e-9)


@pytest.mark.parametrize("layout", LAYOUTS)
def test_compiled_geometry_agrees_with_numpys(layout):
    net = get_network(layout, 3)
    t = net.table
    rng = np.random.default_rng(3)
    pts = rng.uniform(-150, 150, (20, 2)) + np.array([150 if layout in ("merge", "exit", "highway") else 0, 0])
    for k in range(net.n_lanes):
        for px, py in pts.tolist():
            s, r = L.local_coordinates(t, k, px, py)
            assert kgeom.lane_local(t, k, px, py) == pytest.approx((s, r), abs=1e-9)
            assert kgeom.lane_position(t, k, s, r) == pytest.approx(L.position(t, k, s, r), abs=1e-9)
            assert kgeom.lane_heading(t, k, s) == pytest.approx(L.heading_at(t, k, s), abs=1e-12)


@pytest.mark.parametrize("layout", LAYOUTS)
def test_closest_lane_matches_highway_env(layout):
    net, road = get_network(layout, 3), _road(layout)
    rng = np.random.default_rng(4)
    keys = list(net.lane_keys)
    for _ in range(200):
        lane = int(rng.integers(net.n_lanes))
        s = float(rng.uniform(-10, net.table.geo[LENGTH, lane] + 10))
        x, y = L.position(net.table, lane, s, float(rng.uniform(-4, 4)))
        heading = L.heading_at(net.table, lane, s) + float(rng.normal(0, 0.3))
        ref = road.network.get_closest_lane_index(np.array([x, y]), heading)
        assert keys[kgeom.closest_lane(net.table, x, y, heading, int(rng.integers(net.n_lanes)))] == ref


def test_obstacles_sit_on_highway_envs_lanes():
    # The merge layout's ramp ends in the only obstacle of the five layouts.
    spec = get_spec("merge")
    net, road = get_network(spec.layout, spec.lanes_count), _road(spec.layout)
    expected = [o.lane_index for o in road.objects if isinstance(o, Obstacle)]
    assert len(expected) == len(net.obstacles) == 1
    st = allocate(1, slots_needed(spec, net), len(spec.av_target_speeds), 8, net.n_nodes)
    write_template(st, 0, spec, net)
    n_veh = spec.n_av + spec.n_hv
    assert [net.lane_keys[k] for k in st.i[LANE, 0, n_veh:n_veh + len(expected)]] == expected


@pytest.mark.parametrize("layout", LAYOUTS)
def test_curve_boxes_bound_lane_distance_from_below(layout):
    # The closest-lane search skips lanes by these boxes; it is exact only if they bound.
    net = get_network(layout, 3)
    rng = np.random.default_rng(5)
    pts = rng.uniform(-300, 1100, (400, 2)) * [1, 0.3]
    for k in range(net.n_lanes):
        for px, py in pts.tolist():
            box = kgeom.box_distance(net.table.boxes[CURVE_BOX, k], px, py)
            assert box <= kgeom.lane_distance(net.table, k, px, py) + 1e-9


def test_routes_follow_highway_env_planner():
    net, road = get_network("roundabout", 3), _road("roundabout")
    for destination in ("exr", "nxr", "wxr", "sxr"):
        lane = net.lane(("ser", "ses", 0))
        path = road.network.shortest_path("ses", destination)
        expected = [("ser", "ses"), *itertools.pairwise(path)]
        assert [net.edge_keys[e] for e in net.route_edges(lane, destination)] == expected
    assert net.route_edges(lane, "nowhere") == [net.edge(("ser", "ses"))]
