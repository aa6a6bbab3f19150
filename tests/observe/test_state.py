"""The exact-state vector: literal geometry in the AV's frame, order, reach and the route bits;
the view targets: the same rows for the vehicles inside each AV's map."""

from __future__ import annotations

import math

import numpy as np
import pytest

from latentdrive.config import ObservationConfig
from latentdrive.observe.state import (
    PER_NEIGHBOUR,
    ROUTE_BITS,
    nearest,
    state_features,
    state_size,
    view_box,
    view_target_size,
    view_targets,
)
from latentdrive.scene import Kind, RoadRaster, Scene

ROAD = RoadRaster(mask=np.ones((4, 4), dtype=np.uint8), origin=np.zeros(2), resolution=1.0)


def _scene(rows: list[tuple[float, float, float, float, int]], route: int = 0, time: float = 0.0,
           agents: tuple[int, ...] = (0,)) -> Scene:
    """Vehicles as (x, y, heading, speed, kind); ``agents`` the AV agents (vehicle 0 alone by default)."""
    a = np.array(rows, dtype=np.float64)
    n = len(rows)
    return Scene(position=a[:, :2], heading=a[:, 2], speed=a[:, 3], frenet_speed=a[:, 3] - 1.0,
                 length=np.full(n, 5.0), width=np.full(n, 2.0), kind=a[:, 4].astype(np.int8),
                 mask=np.ones(n, dtype=bool), crashed=np.array([False] + [True] * (n - 1)),
                 agents=np.array(agents), road=ROAD, time=time,
                 route=np.full(len(agents), route, dtype=np.uint64))


def test_a_car_ahead_and_to_the_right_of_an_av_heading_along_y() -> None:
    # The AV heads along +y at 10 m/s; a human driver 20 m further along +y and 4 m towards
    # -x (to the AV's right: the right of a car heading +y is -x) drives along +x at 5 m/s.
    up = math.pi / 2
    scene = _scene([(100.0, 50.0, up, 10.0, Kind.AV), (96.0, 70.0, 0.0, 5.0, Kind.HV)], time=3.0)
    f = state_features(scene, 0, duration=15.0, k=2, radius=80.0, route=False)
    assert f.shape == (state_size(2, route=False),) == (7 + 2 * PER_NEIGHBOUR,)
    np.testing.assert_allclose(f[:7], [0.5, 0.45, 0.0, 1.0, 1.0, 0.5, 0.2], atol=1e-6)
    # Ahead 20 m, right 4 m; its velocity (5, 0) less the AV's (0, 10) is (5, -10) in the
    # world: 10 m/s closing along the AV's heading and 5 m/s towards its left (+x is the
    # left of a car heading +y), heading a quarter turn to its left.
    np.testing.assert_allclose(f[7:16], [20 / 50, 4 / 50, -10 / 20, -5 / 20, 0.0, -1.0, 0.0, 1.0, 1.0], atol=1e-6)
    np.testing.assert_array_equal(f[16:], 0.0)  # the second row: nobody


def test_neighbours_come_nearest_first_and_stop_at_the_radius() -> None:
    scene = _scene([(0.0, 0.0, 0.0, 10.0, Kind.AV), (30.0, 0.0, 0.0, 10.0, Kind.HV),
                    (-10.0, 0.0, 0.0, 10.0, Kind.AV), (0.0, 90.0, 0.0, 10.0, Kind.HV)])
    f = state_features(scene, 0, 15.0, k=3, radius=80.0, route=False).reshape(-1)[7:].reshape(3, PER_NEIGHBOUR)
    np.testing.assert_allclose(f[:, 0], [-10 / 50, 30 / 50, 0.0], atol=1e-6)
    np.testing.assert_array_equal(f[:, 6], [1.0, 0.0, 0.0])  # the AV first, then the human; 90 m is out
    np.testing.assert_array_equal(f[:, 8], [1.0, 1.0, 0.0])
    np.testing.assert_array_equal(nearest(scene, 0, k=3, radius=80.0), [2, 1])
    np.testing.assert_array_equal(nearest(scene, 0, k=1, radius=80.0), [2])


def test_the_route_bits_follow_the_ego_values() -> None:
    scene = _scene([(0.0, 0.0, 0.0, 10.0, Kind.AV)], route=0b1001)
    f = state_features(scene, 0, 15.0, k=1, radius=80.0, route=True)
    assert f.shape == (state_size(1, route=True),) == (7 + ROUTE_BITS + PER_NEIGHBOUR,)
    np.testing.assert_array_equal(np.flatnonzero(f[7:7 + ROUTE_BITS]), [0, 3])


def test_a_route_beyond_the_kept_bits_is_refused() -> None:
    scene = _scene([(0.0, 0.0, 0.0, 10.0, Kind.AV)], route=1 << ROUTE_BITS)
    with pytest.raises(ValueError, match="beyond the 32"):
        state_features(scene, 0, 15.0, k=1, radius=80.0, route=True)


def test_the_view_box_is_the_default_maps_extent() -> None:
    # 64 columns and 32 rows of 1.5 m cells, 32 m of them behind the observer.
    assert view_box(ObservationConfig()) == (32.0, 64.0, 24.0)


def test_view_targets_keep_the_vehicles_inside_each_avs_map_nearest_first() -> None:
    # Two AVs at the origin heading +x (vehicle 0) and -x (vehicle 1, 10 m ahead of vehicle 0);
    # humans 40 m behind vehicle 0 (outside its 32 m), 60 m ahead, and 30 m to its left
    # (outside its 24 m), all heading +x.
    scene = _scene([(0.0, 0.0, 0.0, 10.0, Kind.AV), (10.0, 0.0, math.pi, 4.0, Kind.AV),
                    (-40.0, 0.0, 0.0, 10.0, Kind.HV), (60.0, 0.0, 0.0, 10.0, Kind.HV),
                    (5.0, -30.0, 0.0, 10.0, Kind.HV)], agents=(0, 1))
    t = view_targets(scene, ObservationConfig(), k=3)
    assert t.shape == (2, view_target_size(3)) == (2, 2 + 3 * PER_NEIGHBOUR)
    np.testing.assert_allclose(t[:, :2], [[10 / 20, 9 / 20], [4 / 20, 3 / 20]], atol=1e-6)
    rows = t[:, 2:].reshape(2, 3, PER_NEIGHBOUR)
    # Vehicle 0 sees the AV 10 m ahead, coming at it (-4 - 10 m/s), then the human 60 m ahead.
    np.testing.assert_allclose(rows[0, 0], [10 / 50, 0.0, -14 / 20, 0.0, -1.0, 0.0, 1.0, 1.0, 1.0], atol=1e-6)
    np.testing.assert_allclose(rows[0, 1, [0, 6, 8]], [60 / 50, 0.0, 1.0], atol=1e-6)
    np.testing.assert_array_equal(rows[0, 2], 0.0)
    # Vehicle 1 faces -x: vehicle 0 is 10 m ahead of it, the human at -40 is 50 m ahead, the
    # one at +60 is 50 m behind (outside its 32 m), and the one at y = -30 lies 30 m to its
    # right (outside).
    np.testing.assert_allclose(rows[1, :2, 0], [10 / 50, 50 / 50], atol=1e-6)
    np.testing.assert_array_equal(rows[1, :, 8], [1.0, 1.0, 0.0])


def test_view_targets_rows_agree_with_the_state_vector() -> None:
    scene = _scene([(100.0, 50.0, math.pi / 2, 10.0, Kind.AV), (96.0, 70.0, 0.0, 5.0, Kind.HV)])
    t = view_targets(scene, ObservationConfig(), k=2)
    f = state_features(scene, 0, duration=15.0, k=2, radius=80.0, route=False)
    np.testing.assert_allclose(t[0, :2], f[:2])
    np.testing.assert_allclose(t[0, 2:], f[7:], atol=1e-7)
