"""Literal cases for the compiled kernels, and agreement with highway-env's helpers."""

import numpy as np
import pytest
from highway_env import utils

from latentdrive.scenarios import get_spec
from latentdrive.sim.fast import FastBatch
from latentdrive.sim.fast.kcollide import polygons_intersect
from latentdrive.sim.fast.kcontrol import speed_to_index
from latentdrive.sim.fast.kneighbours import build_members, neighbours
from latentdrive.sim.fast.kregulate import rectangles_intersect
from latentdrive.sim.fast.ksort import sort_by_key
from latentdrive.sim.fast.state import HEADING, X, Y
from latentdrive.sim.highway import HighwayBackend


def _box(cx, cy, length, width, heading):
    c, s = np.cos(heading), np.sin(heading)
    pts = np.array([[-length / 2, -width / 2], [-length / 2, width / 2], [length / 2, width / 2], [length / 2, -width / 2]])
    pts = pts @ np.array([[c, s], [-s, c]]) + [cx, cy]
    return np.vstack([pts, pts[:1]])


def test_sort_by_key_is_stable():
    rng = np.random.default_rng(0)
    keys = rng.integers(0, 10, 100).astype(float)
    vals = np.arange(100)
    expected = np.argsort(keys, kind="stable")
    sort_by_key(keys, vals, 100, np.empty(100), np.empty(100, np.int64))
    assert np.array_equal(vals, expected) and np.all(np.diff(keys) >= 0)


def test_separating_axes_literal():
    a, b = _box(0, 0, 5, 2, 0), _box(4, 0, 5, 2, 0)  # 1 m overlap along x
    assert polygons_intersect(a, b, 0, 0, 0, 0)[:2] == (True, True)
    far = _box(6, 0, 5, 2, 0)  # 1 m apart
    assert polygons_intersect(a, far, 0, 0, 0, 0)[:2] == (False, False)
    hit, will, tx, ty = polygons_intersect(a, far, 2.0, 0, 0, 0)  # closing 2 m in the step
    assert (hit, will) == (False, True) and tx == pytest.approx(-1.0) and ty == pytest.approx(0.0, abs=1e-12)


def test_collision_test_agrees_with_highway_env():
    rng = np.random.default_rng(1)
    for _ in range(500):
        p = rng.uniform(-4, 4, 2)
        a, b = _box(0, 0, 5, 2, rng.uniform(-3, 3)), _box(p[0], p[1], 5, 2, rng.uniform(-3, 3))
        da, db = rng.uniform(-2, 2, 2), rng.uniform(-2, 2, 2)
        ref = utils.are_polygons_intersecting(a, b, da, db)
        got = polygons_intersect(a, b, da[0], da[1], db[0], db[1])
        assert got[:2] == tuple(ref[:2])
        if ref[1]:
            np.testing.assert_allclose(got[2:], ref[2], atol=1e-9)
        r1 = ((0.0, 0.0), 7.5, 1.8, rng.uniform(-3, 3))
        r2 = (tuple(p), 7.5, 1.8, rng.uniform(-3, 3))
        assert rectangles_intersect(0.0, 0.0, 7.5, 1.8, r1[3], p[0], p[1], 7.5, 1.8, r2[3]) == \
            utils.rotated_rectangles_intersect(r1, r2)


def test_neighbours_on_a_straight_lane_as_highway_env_finds_them():
    # Slots 0-1 AVs, 2-4 HVs, placed by hand on the three-lane highway (lanes 4 m apart);
    # slot 4 straddles lanes 0 and 1 (within the 1 m margin of both), level with slot 1.
    spec = get_spec("highway", n_av=2, n_hv=3)
    xs, ys = [100.0, 130.0, 160.0, 140.0, 130.0], [0.0, 0.0, 0.0, 4.0, 2.5]
    batch = FastBatch([spec])
    batch.reset([0])
    group = batch._groups[0]
    st, t, sc = group.state, group.network.table, group.scratch
    st.f[X, 0, :5], st.f[Y, 0, :5], st.f[HEADING, 0, :5] = xs, ys, 0.0
    build_members(t, st, 0, sc)
    assert neighbours(t, st, 0, sc, 1, 0) == (4, 0)  # equal s: the later slot leads...
    assert neighbours(t, st, 0, sc, 4, 0) == (1, 0)  # ...and equal s counts as ahead
    assert neighbours(t, st, 0, sc, 1, 1) == (4, -1)
    assert neighbours(t, st, 0, sc, 2, 2) == (-1, -1)

    hw = HighwayBackend(spec)
    hw.reset(0)
    assert hw.road is not None
    for v, x, y in zip(hw.road.vehicles, xs, ys, strict=True):
        v.position = np.array([x, y])
    index = {id(v): k for k, v in enumerate(hw.road.vehicles)}
    for ego in range(5):
        for lane in range(3):
            ref = hw.road.neighbour_vehicles(hw.road.vehicles[ego], ("0", "1", lane))
            assert neighbours(t, st, 0, sc, ego, lane) == tuple(-1 if v is None else index[id(v)] for v in ref)


def test_speed_index_rounds_half_to_even():
    batch = FastBatch([get_spec("roundabout")])  # target speeds 0, 8, 16
    batch.reset([0])
    st = batch._groups[0].state
    got = [speed_to_index(st, 0, v) for v in (-3.0, 3.9, 4.0, 4.1, 12.0, 20.0)]
    assert got == [0, 0, 0, 1, 2, 2]
