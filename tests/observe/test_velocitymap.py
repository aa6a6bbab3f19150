"""Literal cases for the VelocityMap: eq. 13, grid geometry, channels, noise, stacking."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from latentdrive.config import ObservationConfig
from latentdrive.observe import CHANNELS, FrameStack, draw_noise, render_frame, velocity_log_map
from latentdrive.observe.velocitymap import AV, HV, MV, RL
from latentdrive.scene import Kind, RoadRaster, Scene, rasterize_strips

# 1 m cells, 16 rows x 32 columns, 7.5 m behind. Cell centres sit on whole metres along
# the observer (x_c = j - 7) and on half metres across it (y_c = i - 7.5), so a 5 m x 2 m
# car centred on a whole-metre x and y = 0 has its sides on cell boundaries.
CFG = ObservationConfig(height=16, width=32, resolution=1.0, behind=7.5)
DEFAULTS = ObservationConfig()


def _straight_road(vertical: bool = False, half_width: float = 4.0) -> RoadRaster:
    s = np.arange(-50.0, 300.0, 0.25)
    zeros = np.zeros_like(s)
    centers = np.stack([zeros, s] if vertical else [s, zeros], axis=-1)
    headings = np.full(s.shape, math.pi / 2 if vertical else 0.0)
    return rasterize_strips(centers, headings, np.full(s.shape, half_width))


ROAD = _straight_road()


def _scene(vehicles: list[dict], agents: list[int], road: RoadRaster = ROAD) -> Scene:
    """Vehicles as dicts with x, y and optional heading, speed, fs, length, width, kind, mask."""

    def col(key: str, default: float) -> np.ndarray:
        return np.array([v.get(key, default) for v in vehicles], dtype=np.float64)

    return Scene(
        position=np.stack([col("x", 0.0), col("y", 0.0)], axis=-1).reshape(-1, 2),
        heading=col("heading", 0.0),
        speed=col("speed", 20.0),
        frenet_speed=col("fs", 20.0),
        length=col("length", 5.0),
        width=col("width", 2.0),
        kind=np.array([v.get("kind", Kind.HV) for v in vehicles], dtype=np.int8),
        mask=np.array([v.get("mask", True) for v in vehicles], dtype=bool),
        crashed=np.zeros(len(vehicles), dtype=bool),
        agents=np.array(agents, dtype=np.int64),
        road=road,
    )


def _cells(channel: np.ndarray) -> set[tuple[int, int]]:
    return {(int(i), int(j)) for i, j in zip(*np.nonzero(channel), strict=True)}


def _block(rows: range, cols: range) -> set[tuple[int, int]]:
    return {(i, j) for i in rows for j in cols}


def _hv_cells(scene: Scene) -> set[tuple[int, int]]:
    """Cells lit in the first observer's HV channel."""
    return _cells(render_frame(scene, scene.agents, CFG)[0, HV])


EGO = {"x": 100.0, "y": 0.0, "kind": Kind.AV}


# --- eq. 13 -----------------------------------------------------------------------------


def test_map_is_one_below_v0_without_warnings():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        z = velocity_log_map([0.0, 0.5, 1.99, -1.99], alpha=0.5, beta=0.37, v0=2.0)
    np.testing.assert_array_equal(z, [1.0, 1.0, 1.0, 1.0])


def test_map_literal_values():
    z = velocity_log_map([10.0, -10.0, 5.0, 30.0, 60.0], DEFAULTS.alpha, DEFAULTS.beta, DEFAULTS.v0)
    # 1 - 0.3 ln(5) = 0.517169..., 1 - 0.3 ln(2.5) = 0.725113..., 1 - 0.3 ln(15) = 0.187585...,
    # and 60 m/s (1 - 0.3 ln 30 < 0) clips to 0.
    np.testing.assert_allclose(z, [0.5171686, 0.5171686, 0.7251128, 0.1875849, 0.0], atol=1e-6)


def test_map_is_continuous_at_v0_with_defaults():
    assert DEFAULTS.v0 == pytest.approx(1.0 / DEFAULTS.alpha)
    a, b, v0 = DEFAULTS.alpha, DEFAULTS.beta, DEFAULTS.v0
    z = velocity_log_map([v0 - 1e-6, v0, v0 + 1e-6], a, b, v0)
    np.testing.assert_allclose(z, [1.0, 1.0, 1.0], atol=1e-5)


def test_map_steps_at_v0_when_v0_exceeds_one_over_alpha():
    # H(0) = 1: at |v| = v0 the log term is already on.
    z = velocity_log_map([3.99, 4.0], alpha=0.5, beta=0.37, v0=4.0)
    np.testing.assert_allclose(z, [1.0, 1.0 - 0.37 * 0.6931472], atol=1e-6)


def test_map_monotone_bounded_symmetric_float32():
    v = np.linspace(0.0, 80.0, 4001)
    z = velocity_log_map(v, DEFAULTS.alpha, DEFAULTS.beta, DEFAULTS.v0)
    assert z.dtype == np.float32 and z.shape == v.shape
    assert np.all(np.diff(z) <= 0.0)
    assert z.min() == 0.0 and z.max() == 1.0
    np.testing.assert_array_equal(
        z, velocity_log_map(-v, DEFAULTS.alpha, DEFAULTS.beta, DEFAULTS.v0)
    )


# --- rasterization ----------------------------------------------------------------------


def test_frame_shape_dtype_range_and_channel_order():
    assert CHANNELS == ("HV", "AV", "RL", "MV")
    assert (HV, AV, RL, MV) == (0, 1, 2, 3)
    scene = _scene([EGO, {"x": 110.0, "y": 0.0}, {"x": 90.0, "y": 4.0, "kind": Kind.AV}], [0, 2])
    out = render_frame(scene, scene.agents, CFG)
    assert out.shape == (2, 4, 16, 32) and out.dtype == np.float32
    assert out.min() >= 0.0 and out.max() <= 1.0


def test_car_ten_metres_ahead_covers_its_five_by_two_cells():
    scene = _scene([EGO, {"x": 110.0, "y": 0.0, "fs": 25.0}], [0])
    hv = render_frame(scene, scene.agents, CFG)[0, HV]
    # x in [7.5, 12.5) holds centres x_c = 8..12 (columns 15..19); y in [-1, 1) holds
    # y_c = -0.5, 0.5 (rows 7, 8).
    assert _cells(hv) == _block(range(7, 9), range(15, 20))
    np.testing.assert_allclose(hv[7:9, 15:20], 0.7251128, atol=1e-6)  # 5 m/s faster


def test_rows_grow_to_the_observers_right_and_columns_forward():
    right = _scene([EGO, {"x": 110.0, "y": 4.0}], [0])
    behind = _scene([EGO, {"x": 95.0, "y": 0.0}], [0])
    assert _hv_cells(right) == _block(range(11, 13), range(15, 20))
    assert _hv_cells(behind) == _block(range(7, 9), range(0, 5))


def test_observer_heading_rotates_the_grid():
    up = math.pi / 2
    ego = {**EGO, "heading": up}
    # Heading +y, forward is +y and right is -x.
    ahead = _scene([ego, {"x": 100.0, "y": 10.0, "heading": up}], [0])
    right = _scene([ego, {"x": 96.0, "y": 10.0, "heading": up}], [0])
    assert _hv_cells(ahead) == _block(range(7, 9), range(15, 20))
    assert _hv_cells(right) == _block(range(11, 13), range(15, 20))


def test_vehicle_heading_rotates_its_footprint():
    # Crossing at 90°: 5 m along the observer's y, 2 m along its x. Centre (10.5, 0.5):
    # x in [9.5, 11.5) -> columns 17, 18; y in [-2, 3) -> rows 6..10.
    scene = _scene([EGO, {"x": 110.5, "y": 0.5, "heading": math.pi / 2}], [0])
    assert _hv_cells(scene) == _block(range(6, 11), range(17, 19))


def test_vehicle_centred_outside_the_grid_is_drawn_where_it_reaches_in():
    # Local y = 8.5 (grid edge at 8): y in [7.5, 9.5) reaches row 15 (y_c = 7.5).
    side = _scene([EGO, {"x": 110.0, "y": 8.5}], [0])
    assert _hv_cells(side) == _block(range(15, 16), range(15, 20))
    # Local x = -9 (grid edge at -7.5): x in [-11.5, -6.5) reaches column 0 (x_c = -7).
    back = _scene([EGO, {"x": 91.0, "y": 0.0}], [0])
    assert _hv_cells(back) == _block(range(7, 9), range(0, 1))


def test_long_vehicle_covers_its_whole_length():
    # 13 m x 1 m at (10.5, 0.5): x in [4, 17) -> x_c 4..16 (columns 11..23); y in [0, 1)
    # -> y_c 0.5 (row 8).
    scene = _scene([EGO, {"x": 110.5, "y": 0.5, "length": 13.0, "width": 1.0}], [0])
    assert _hv_cells(scene) == _block(range(8, 9), range(11, 24))


def test_rotated_footprints_match_cell_by_cell_geometry():
    trucks = [
        {"x": 112.3, "y": -2.2, "heading": 0.52, "length": 12.0, "width": 2.5},
        {"x": 96.1, "y": 3.7, "heading": -1.05, "length": 4.5, "width": 1.8},
    ]
    ego = {**EGO, "heading": 0.2}
    for truck in trucks:
        scene = _scene([ego, truck], [0])
        c, s = math.cos(0.2), math.sin(0.2)
        dx, dy = truck["x"] - 100.0, truck["y"]
        lx, ly = c * dx + s * dy, -s * dx + c * dy
        phi = truck["heading"] - 0.2
        expected = set()
        for i in range(16):
            for j in range(32):
                ex, ey = (j - 7.0) - lx, (i - 7.5) - ly
                u = math.cos(phi) * ex + math.sin(phi) * ey
                v = -math.sin(phi) * ex + math.cos(phi) * ey
                if abs(u) < truck["length"] / 2 and abs(v) < truck["width"] / 2:
                    expected.add((i, j))
        assert len(expected) > 5
        assert _hv_cells(scene) == expected


def test_hv_and_av_channels_and_mv_is_only_the_observer():
    scene = _scene(
        [
            {**EGO, "speed": 20.0},
            {"x": 105.0, "y": 0.0, "kind": Kind.AV, "speed": 30.0, "fs": 30.0},
            {"x": 95.0, "y": 0.0, "kind": Kind.HV},
        ],
        [0, 1],
    )
    out = render_frame(scene, scene.agents, CFG)
    ego_cells = _block(range(7, 9), range(5, 10))  # x in [-2.5, 2.5) -> columns 5..9
    # Observer 0: the HV 5 m behind, the other AV 5 m ahead and 10 m/s faster, itself in MV.
    assert _cells(out[0, HV]) == _block(range(7, 9), range(0, 5))
    assert _cells(out[0, AV]) == _block(range(7, 9), range(10, 15))
    np.testing.assert_allclose(out[0, AV][7:9, 10:15], 0.5171686, atol=1e-6)
    assert _cells(out[0, MV]) == ego_cells
    np.testing.assert_allclose(out[0, MV][7:9, 5:10], 20.0 / 40.0)
    # Observer 1: AV 0 5 m behind (10 m/s slower, same value by symmetry); the HV is 10 m
    # behind, its front at -7.5 m, short of the first cell centre at -7 m.
    assert _cells(out[1, AV]) == _block(range(7, 9), range(0, 5))
    np.testing.assert_allclose(out[1, AV][7:9, 0:5], 0.5171686, atol=1e-6)
    assert not out[1, HV].any()
    assert _cells(out[1, MV]) == ego_cells
    np.testing.assert_allclose(out[1, MV][7:9, 5:10], 0.75)


def test_mv_uses_absolute_speed_clipped():
    reverse = _scene([{**EGO, "speed": -8.0}], [0])
    fast = _scene([{**EGO, "speed": 55.0}], [0])
    np.testing.assert_allclose(render_frame(reverse, reverse.agents, CFG)[0, MV][7:9, 5:10], 0.2)
    np.testing.assert_allclose(render_frame(fast, fast.agents, CFG)[0, MV][7:9, 5:10], 1.0)


def test_masked_vehicle_is_not_drawn():
    scene = _scene([EGO, {"x": 110.0, "y": 0.0, "mask": False}], [0])
    out = render_frame(scene, scene.agents, CFG)
    assert not out[0, HV].any() and not out[0, AV].any()


@pytest.mark.parametrize("slow_first", [True, False])
def test_overlapping_footprints_take_the_max(slow_first):
    slow = {"x": 110.0, "y": 0.0, "fs": 20.0}  # relative 0 -> 1
    fast = {"x": 112.0, "y": 0.0, "fs": 30.0}  # relative 10 -> 0.4045
    scene = _scene([EGO, slow, fast] if slow_first else [EGO, fast, slow], [0])
    hv = render_frame(scene, scene.agents, CFG)[0, HV]
    np.testing.assert_allclose(hv[7:9, 15:20], 1.0)
    np.testing.assert_allclose(hv[7:9, 20:22], 0.5171686, atol=1e-6)


def test_footprint_sides_on_cell_centres_cover_length_over_resolution_cells():
    # Centre x = 10.5, y = 0.5: sides at x = 8, 13 and y = -0.5, 1.5 pass through cell
    # centres; the half-open footprint keeps the lower ones, so 5 x 2 cells again.
    scene = _scene([EGO, {"x": 110.5, "y": 0.5}], [0])
    assert _hv_cells(scene) == _block(range(7, 9), range(15, 20))


def test_road_layout_channel():
    # Road |y| <= 4 m, observer 2 m right of its centre line: centres with world
    # y = 2 + y_c in [-3.5, 3.5] (rows 2..9) are on it, |y| >= 4.5 (rows <= 1, >= 10) off.
    scene = _scene([{**EGO, "y": 2.0}], [0])
    rl = render_frame(scene, scene.agents, CFG)[0, RL]
    assert np.all(rl[2:10] == 1.0)
    assert not rl[:2].any() and not rl[10:].any()
    # The same picture heading +y on a road along y, 2 m right (-x) of its centre line.
    vertical = _scene([{"x": -2.0, "y": 100.0, "heading": math.pi / 2}], [0], _straight_road(True))
    np.testing.assert_array_equal(render_frame(vertical, vertical.agents, CFG)[0, RL], rl)
    # Heading across the road: it becomes a band of columns (|x_c| <= 3 on, >= 5 off).
    across = _scene([{**EGO, "heading": math.pi / 2}], [0])
    rl = render_frame(across, across.agents, CFG)[0, RL]
    assert np.all(rl[:, 4:11] == 1.0)
    assert not rl[:, :3].any() and not rl[:, 12:].any()


# --- noise ------------------------------------------------------------------------------


def _busy_scene() -> Scene:
    others = [
        {"x": 100.0 + dx, "y": dy, "fs": 15.0 + dx / 4, "kind": Kind.AV if dx == 6 else Kind.HV}
        for dx, dy in [(-6, 4), (6, 0), (12, -4), (18, 4), (4, -4)]
    ]
    return _scene([EGO, *others], [0, 2])


def test_same_seed_same_frames_different_seed_different():
    scene = _busy_scene()
    a = render_frame(scene, scene.agents, CFG, np.random.default_rng(7))
    b = render_frame(scene, scene.agents, CFG, np.random.default_rng(7))
    c = render_frame(scene, scene.agents, CFG, np.random.default_rng(8))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def test_clean_equals_zero_noise():
    scene = _busy_scene()
    zero = CFG.replace(
        noise={"position_std": 0.0, "speed_std": 0.0, "heading_std": 0.0, "miss_prob": 0.0}
    )
    np.testing.assert_array_equal(
        render_frame(scene, scene.agents, CFG),
        render_frame(scene, scene.agents, zero, np.random.default_rng(3)),
    )


def test_miss_prob_one_removes_every_other_vehicle():
    scene = _busy_scene()
    clean = render_frame(scene, scene.agents, CFG)
    blind = render_frame(
        scene, scene.agents, CFG.replace(noise={"miss_prob": 1.0}), np.random.default_rng(0)
    )
    assert clean[:, [HV, AV]].any()
    assert not blind[:, [HV, AV]].any()
    np.testing.assert_array_equal(blind[:, [RL, MV]], clean[:, [RL, MV]])


def test_observer_itself_is_not_jittered():
    scene = _busy_scene()
    loud = CFG.replace(noise={"position_std": 5.0, "heading_std": 0.5, "speed_std": 5.0})
    noisy = render_frame(scene, scene.agents, loud, np.random.default_rng(1))
    clean = render_frame(scene, scene.agents, CFG)
    np.testing.assert_array_equal(noisy[:, MV], clean[:, MV])
    assert not np.array_equal(noisy[:, HV], clean[:, HV])


# --- frame stack ------------------------------------------------------------------------


def _frame(value: float) -> np.ndarray:
    return np.full((2, 4, 3, 5), value, dtype=np.float32)


def test_frame_stack_order_most_recent_last():
    fs = FrameStack(4)
    fs.reset(_frame(0.0))
    s = fs.stack
    assert s.shape == (2, 4, 4, 3, 5) and s.dtype == np.float32
    assert np.all(s == 0.0)
    for v in (1.0, 2.0):
        fs.push(_frame(v))
    np.testing.assert_array_equal(fs.stack[0, 0, :, 0, 0], [0.0, 0.0, 1.0, 2.0])
    for v in (3.0, 4.0, 5.0):
        fs.push(_frame(v))
    np.testing.assert_array_equal(fs.stack[1, 3, :, 2, 4], [2.0, 3.0, 4.0, 5.0])


def test_frame_stack_is_copy_safe_and_checks_use():
    fs = FrameStack(2)
    with pytest.raises(RuntimeError):
        fs.push(_frame(1.0))
    frame = _frame(1.0)
    fs.reset(frame)
    frame[...] = 9.0
    s = fs.stack
    s[...] = 7.0
    assert np.all(fs.stack == 1.0)
    with pytest.raises(ValueError):
        fs.push(np.zeros((1, 4, 3, 5), dtype=np.float32))


def test_frame_stack_push_moves_only_the_chosen_rows():
    fs = FrameStack(3)
    fs.reset(_frame(0.0))
    fs.push(_frame(1.0), rows=np.array([True, False]))
    fs.push(_frame(2.0), rows=np.array([False, True]))
    stack = fs.stack
    np.testing.assert_array_equal(stack[0, 0, :, 0, 0], [0.0, 0.0, 1.0])
    np.testing.assert_array_equal(stack[1, 0, :, 0, 0], [0.0, 0.0, 2.0])


def test_noise_draws_given_or_drawn_render_alike():
    scene = _busy_scene()
    drawn = render_frame(scene, scene.agents, CFG, np.random.default_rng(5))
    draws = draw_noise(np.random.default_rng(5), scene.n_agents, scene.n_vehicles, CFG.noise)
    np.testing.assert_array_equal(render_frame(scene, scene.agents, CFG, noise=draws), drawn)
    # One observer's rows of the same draws give that observer's frame.
    np.testing.assert_array_equal(render_frame(scene, scene.agents[1:], CFG, noise=draws.rows(np.array([1])))[0], drawn[1])
    with pytest.raises(ValueError, match="not both"):
        render_frame(scene, scene.agents, CFG, np.random.default_rng(5), noise=draws)
    with pytest.raises(ValueError, match="noise draws are"):
        render_frame(scene, scene.agents[:1], CFG, noise=draws)


def test_frame_stack_keeps_its_frames_in_the_storage_given():
    storage = np.zeros((2, 4, 3, 3, 5), dtype=np.float32)
    fs = FrameStack(3, storage)
    fs.reset(_frame(1.0))
    fs.push(_frame(2.0))
    assert fs.view is storage and storage[:, :, -1].min() == 2.0 and storage[:, :, 0].max() == 1.0
    with pytest.raises(ValueError, match="does not fit"):
        fs.reset(np.zeros((1, 4, 3, 5), dtype=np.float32))
    with pytest.raises(ValueError, match="storage must be"):
        FrameStack(2, storage)


def test_noise_draws_follow_the_documented_stream_order():
    cfg = CFG.noise
    draws = draw_noise(np.random.default_rng(9), 3, 4, cfg)
    rng = np.random.default_rng(9)
    np.testing.assert_array_equal(draws.position, rng.standard_normal((3, 4, 2)) * cfg.position_std)
    np.testing.assert_array_equal(draws.heading, rng.standard_normal((3, 4)) * cfg.heading_std)
    np.testing.assert_array_equal(draws.speed, rng.standard_normal((3, 4)) * cfg.speed_std)
    np.testing.assert_array_equal(draws.missed, rng.random((3, 4)) < cfg.miss_prob)


# --- the route option -------------------------------------------------------------------


def _two_roads() -> RoadRaster:
    """Edge 0: the road |y| <= 4 m; edge 1: a parallel road 8 m <= y <= 12 m."""
    s = np.arange(-50.0, 300.0, 0.25)
    centers = np.concatenate([np.stack([s, np.zeros_like(s)], -1), np.stack([s, np.full_like(s, 10.0)], -1)])
    half = np.concatenate([np.full(s.shape, 4.0), np.full(s.shape, 2.0)])
    edges = np.repeat([0, 1], s.size)
    return rasterize_strips(centers, np.zeros(2 * s.size), half, edges=edges)


def test_route_is_drawn_in_mv_on_the_route_edges_under_the_own_footprint():
    road = _two_roads()
    # Observer 2 m right of edge 0's centre line, at 4 m/s (MV footprint 0.1): rows 2..9
    # lie on edge 0 (as in test_road_layout_channel), rows 14..15 (world y 8.5, 9.5) on
    # edge 1; its footprint covers rows 7..8, columns 5..9.
    base = _scene([{**EGO, "y": 2.0, "speed": 4.0}], [0], road)
    cfg = CFG.model_copy(update={"route": 0.3})
    footprint = _block(range(7, 9), range(5, 10))
    for bits, rows in ((1 << 1, range(14, 16)), (1 << 0, range(2, 10)), (0b11, [*range(2, 10), 14, 15])):
        scene = Scene(**{**base.__dict__, "route": np.array([bits], dtype=np.uint64)})
        mv = render_frame(scene, scene.agents, cfg)[0, MV]
        route_cells = _block(range(16), range(32)) & {(i, j) for i in rows for j in range(32)}
        assert _cells(mv == np.float32(0.3)) == route_cells - footprint
        assert _cells(mv > 0) == route_cells | footprint
        # The footprint is the AV's speed even where it is lower than the route's value.
        assert all(mv[i, j] == np.float32(0.1) for i, j in footprint)
    # route = 0 (the default) draws no route, whatever the Scene's bits.
    scene = Scene(**{**base.__dict__, "route": np.array([0b11], dtype=np.uint64)})
    assert _cells(render_frame(scene, scene.agents, CFG)[0, MV]) == footprint
    np.testing.assert_array_equal(render_frame(scene, scene.agents, CFG), render_frame(base, base.agents, CFG))


def test_route_bits_are_checked_and_default_to_zero():
    scene = _scene([EGO, {"x": 110.0}], [0])
    assert scene.route is not None and scene.route.dtype == np.uint64 and not scene.route.any()
    with pytest.raises(ValueError, match=r"Scene\.route"):
        Scene(**{**scene.__dict__, "route": np.array([1, 2], dtype=np.uint64)})
    with pytest.raises(ValueError, match="edge id in"):
        rasterize_strips(np.zeros((2, 2)), np.zeros(2), np.ones(2), edges=np.array([0, 64]))
