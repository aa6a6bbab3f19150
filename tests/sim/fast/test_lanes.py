import itertools

import numpy as np
import pytest

from latentdrive.sim.fast import kgeom
from latentdrive.sim.fast import lanes as L
from latentdrive.sim.fast.network import CURVE_BOX, LENGTH, get_network
from latentdrive.sim.roads import build_road

LAYOUTS = ("roundabout", "intersection", "merge", "exit", "highway")


def _road(layout):
    return build_road(layout, 3, np.random.default_rng(0))


@pytest.mark.parametrize("layout", LAYOUTS)
def test_geometry_matches_highway_env_on_every_lane(layout):
    net, road = get_network(layout, 3), _road(layout)
    assert [key for key in road.network.lanes_dict()] == list(net.lane_keys)
    rng = np.random.default_rng(1)
    for k, key in enumerate(net.lane_keys):
        lane = road.network.get_lane(key)
        s = rng.uniform(-20, lane.length + 20, 40)
        r = rng.uniform(-6, 6, 40)
        x, y = L.position(net.table, k, s, r)
        ref = np.array([lane.position(a, b) for a, b in zip(s, r, strict=True)])
        np.testing.assert_allclose(np.stack([x, y], 1), ref, atol=1e-9, rtol=0)
        np.testing.assert_allclose(L.heading_at(net.table, k, s), [lane.heading_at(a) for a in s], atol=1e-9, rtol=0)
        ls, lr = L.local_coordinates(net.table, k, ref[:, 0], ref[:, 1])
        ref_local = np.array([lane.local_coordinates(p) for p in ref])
        np.testing.assert_allclose(np.stack([ls, lr], 1), ref_local, atol=1e-9, rtol=0)
        assert np.array_equal(L.on_lane(net.table, k, x, y, 1.0),
                              [lane.on_lane(p, margin=1) for p in ref])


@pytest.mark.parametrize("layout", LAYOUTS)
def test_local_coordinates_round_trip(layout):
    net = get_network(layout, 3)
    rng = np.random.default_rng(2)
    for k in range(net.n_lanes):
        length = net.table.geo[LENGTH, k]
        s, r = rng.uniform(0, length, 30), rng.uniform(-1.9, 1.9, 30)
        x, y = L.position(net.table, k, s, r)
        s2, r2 = L.local_coordinates(net.table, k, x, y)
        np.testing.assert_allclose(s2, s, atol=1e-9)
        np.testing.assert_allclose(r2, r, atol=1e-9)


@pytest.mark.parametrize("layout", LAYOUTS)
def test_compiled_geometry_agrees_with_vectorized(layout):
    net = get_network(layout, 3)
    t = net.table
    rng = np.random.default_rng(3)
    pts = rng.uniform(-150, 150, (20, 2)) + np.array([150 if layout in ("merge", "exit", "highway") else 0, 0])
    for k in range(net.n_lanes):
        s, r = L.local_coordinates(t, k, pts[:, 0], pts[:, 1])
        x, y = L.position(t, k, s, r)
        h = L.heading_at(t, k, s)
        for j in range(len(pts)):
            assert kgeom.lane_local(t, k, pts[j, 0], pts[j, 1]) == pytest.approx((s[j], r[j]), abs=1e-9)
            assert kgeom.lane_position(t, k, s[j], r[j]) == pytest.approx((x[j], y[j]), abs=1e-9)
            assert kgeom.lane_heading(t, k, s[j]) == pytest.approx(h[j], abs=1e-12)


@pytest.mark.parametrize("layout", LAYOUTS)
def test_closest_lane_matches_highway_env(layout):
    net, road = get_network(layout, 3), _road(layout)
    rng = np.random.default_rng(4)
    keys = list(net.lane_keys)
    for _ in range(200):
        lane = int(rng.integers(net.n_lanes))
        s = rng.uniform(-10, net.table.geo[LENGTH, lane] + 10)
        x, y = L.position(net.table, lane, s, rng.uniform(-4, 4))
        heading = float(L.heading_at(net.table, lane, s)) + rng.normal(0, 0.3)
        ref = road.network.get_closest_lane_index(np.array([x, y]), heading)
        assert keys[kgeom.closest_lane(net.table, float(x), float(y), heading, int(rng.integers(net.n_lanes)))] == ref


@pytest.mark.parametrize("layout", LAYOUTS)
def test_curve_boxes_bound_lane_distance_from_below(layout):
    # The closest-lane search skips lanes by these boxes; it is exact only if they bound.
    net = get_network(layout, 3)
    rng = np.random.default_rng(5)
    pts = rng.uniform(-300, 1100, (400, 2)) * [1, 0.3]
    for k in range(net.n_lanes):
        d = L.distance(net.table, k, pts[:, 0], pts[:, 1])
        box = np.array([kgeom.box_distance(net.table.boxes[CURVE_BOX, k], px, py) for px, py in pts])
        assert np.all(box <= d + 1e-9)


def test_routes_follow_highway_env_planner():
    net, road = get_network("roundabout", 3), _road("roundabout")
    for destination in ("exr", "nxr", "wxr", "sxr"):
        lane = net.lane(("ser", "ses", 0))
        path = road.network.shortest_path("ses", destination)
        expected = [("ser", "ses"), *itertools.pairwise(path)]
        assert [net.edge_keys[e] for e in net.route_edges(lane, destination)] == expected
    assert net.route_edges(lane, "nowhere") == [net.edge(("ser", "ses"))]
