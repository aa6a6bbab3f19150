"""``scripts/map_blobs.py``: the vehicles a fixed detector and tracker finds in a map."""

import runpy
from pathlib import Path

import numpy as np
import pytest

from latentdrive.config import ObservationConfig
from latentdrive.observe.state import PER_NEIGHBOUR
from latentdrive.observe.velocitymap import AV, HV, MV, RL

MOD = runpy.run_path(str(Path(__file__).resolve().parents[2] / "scripts" / "map_blobs.py"), run_name="map_blobs")
CFG = ObservationConfig()  # 32 x 64 cells of 1.5 m, 32 m behind
OLD, NEW = 0, 1


def _maps(n: int = 1) -> np.ndarray:
    return np.zeros((n, 4, 2, CFG.height, CFG.width), dtype=np.float32)


def test_a_vehicle_is_placed_in_metres_and_its_motion_is_the_step_from_the_frame_before():
    m = _maps()
    m[0, HV, NEW, 16:18, 30:33] = 0.8  # centre: row 16.5, column 31
    m[0, HV, OLD, 16:18, 28:31] = 0.7  # two columns (3 m) further back
    m[0, AV, NEW, 4:6, 10:12] = 0.5  # centre: row 4.5, column 10.5; no AV before it
    m[0, HV, OLD, 4:6, 12:14] = 0.5  # near it, but a human driver's: not its match
    rows = MOD["blob_features"](m, CFG, 3)[0, MOD["ego_size"](CFG, 4):].reshape(3, PER_NEIGHBOUR)
    # x = (column + 0.5)·1.5 − 32, y = (row + 0.5)·1.5 − 24, nearest first.
    np.testing.assert_allclose(rows[0], [15.25 / 50, 1.5 / 50, 3.0 / 20, 0.0, 0.8, 1.0, 0.0, 0.6, 1.0], atol=1e-6)
    np.testing.assert_allclose(rows[1], [-15.5 / 50, -16.5 / 50, 0.0, 0.0, 0.5, 0.0, 1.0, 0.4, 1.0], atol=1e-6)
    assert not rows[2].any()  # padding


def test_the_avs_part_is_its_speed_in_two_frames_and_the_pooled_road():
    m = _maps()
    m[0, MV, OLD, 15:17, 21:24] = 0.30
    m[0, MV, NEW, 15:17, 21:24] = 0.35
    m[0, RL, NEW, 8:24] = 1.0  # row blocks 2 to 5 of 4 cells
    m[0, RL, OLD] = 1.0  # the older road is not read
    ego = MOD["blob_features"](m, CFG, 2)[0, : MOD["ego_size"](CFG, 4)]
    np.testing.assert_allclose(ego[:2], [0.30, 0.35])
    road = ego[2:].reshape(8, 16)
    assert (road[2:6] == 1.0).all() and not road[:2].any() and not road[6:].any()
    assert MOD["ego_size"](CFG, 2) == 2 + 16 * 32


def test_a_vehicle_beyond_the_gate_or_in_another_observation_is_not_matched():
    m = _maps(2)
    m[0, HV, NEW, 16:18, 40:43] = 1.0
    gate_cells = int(MOD["GATE"] / CFG.resolution) + 1
    m[0, HV, OLD, 16:18, 40 - gate_cells: 43 - gate_cells] = 1.0  # just beyond the gate
    m[1, HV, OLD, 16:18, 40:43] = 1.0  # the same place, another observation
    rows = MOD["blob_features"](m, CFG, 1)[:, MOD["ego_size"](CFG, 4):]
    assert rows[0, 5] == 0.0 and rows[0, 2] == 0.0 and rows[0, 8] == 1.0
    assert not rows[1].any()  # observation 1 has no vehicle in its newest frame


def test_only_the_k_nearest_are_kept_and_leading_dimensions_are_kept():
    m = _maps(6).reshape(2, 3, 4, 2, CFG.height, CFG.width)
    for col in (60, 22, 40, 5, 30):  # the AV stands at column 21
        m[1, 2, HV, NEW, 15:17, col:col + 2] = 1.0
    out = MOD["blob_features"](m, CFG, 2)
    assert out.shape == (2, 3, MOD["ego_size"](CFG, 4) + 2 * PER_NEIGHBOUR)
    rows = out[1, 2, MOD["ego_size"](CFG, 4):].reshape(2, PER_NEIGHBOUR)
    x = rows[:, 0] * 50
    np.testing.assert_allclose(x, [(22.5 + 0.5) * 1.5 - 32, (30.5 + 0.5) * 1.5 - 32], atol=1e-5)
    assert not out[0].any() and not out[1, :2].any()


def test_bad_maps_and_pools_are_refused_by_name():
    with pytest.raises(ValueError, match="expected maps"):
        MOD["blob_features"](np.zeros((1, 4, 1, 32, 64), dtype=np.float32), CFG, 2)
    with pytest.raises(ValueError, match="pool must divide"):
        MOD["blob_features"](_maps(), CFG, 2, pool=5)


def test_on_a_drawn_map_the_vehicles_are_found_where_the_scene_puts_them():
    # The fast backend's own maps, sensor noise included: most vehicles found in the newest
    # frame lie within 1.5 m of a vehicle of the exact-state vector inside the map's view.
    from latentdrive.rollout import rollout
    from latentdrive.vec import make_vec

    state = runpy.run_path(str(Path(__file__).resolve().parents[2] / "scripts" / "state_dqn.py"), run_name="sd")
    vec = make_vec(["highway", "roundabout"], 2, backend="fast")
    specs = list(vec.simulator.specs)
    names = np.asarray([s.name for s in specs], dtype=object)
    gaps: list[float] = []
    for step, rec in enumerate(rollout(vec, lambda inp: np.ones(inp.obs.shape[:2], dtype=np.int64), seed=4)):
        if step < 5:
            continue
        exact = state["features"](state["next_input"](rec, names, vec.simulator), specs, 12, 80.0, False, False,
                                  state["MAP_VIEW"])
        blobs = MOD["blob_features"](rec.next_obs, CFG, 12)
        for e, a in zip(*np.nonzero(rec.agents.active), strict=True):
            b = blobs[e, a, MOD["ego_size"](CFG, 4):].reshape(12, PER_NEIGHBOUR)
            s = exact[e, a, -12 * PER_NEIGHBOUR:].reshape(12, PER_NEIGHBOUR)
            b, s = b[b[:, -1] > 0, :2] * 50, s[s[:, -1] > 0, :2] * 50
            if len(b) and len(s):
                gaps += list(np.hypot(b[:, None, 0] - s[None, :, 0], b[:, None, 1] - s[None, :, 1]).min(1))
        break
    vec.close()
    assert len(gaps) >= 4 and np.mean(np.asarray(gaps) < 1.5) >= 0.75


def _road(pose: tuple[float, float, float]) -> np.ndarray:
    """A road of two crossing bands drawn in the frame of an observer at world pose
    (x, y, heading toward +y), ``(H, W)``: the same geometry in the map's axes."""
    x0, y0, th = pose
    cols, rows = np.meshgrid(np.arange(CFG.width), np.arange(CFG.height))
    lx = (cols + 0.5) * CFG.resolution - CFG.behind
    ly = (rows + 0.5) * CFG.resolution - 0.5 * CFG.height * CFG.resolution
    wx = x0 + np.cos(th) * lx - np.sin(th) * ly
    wy = y0 + np.sin(th) * lx + np.cos(th) * ly
    return ((np.abs(wy) < 6.0) | (np.abs(wx - 30.0) < 4.0)).astype(np.float32)


def _arc(speed: float, turn: float, steps: int) -> tuple[float, float, float]:
    """The pose after ``steps`` steps of 1 s of an observer leaving (0, 0, 0) at ``speed``
    m/s, turning ``turn`` radians a step toward +y: a circle of radius speed / turn."""
    radius, heading = speed / turn, turn * steps
    return radius * np.sin(heading), radius * (1.0 - np.cos(heading)), heading


def test_the_observers_turn_is_found_by_matching_the_road():
    speed, turn = 10.0, 0.3
    old, new = _road((0.0, 0.0, 0.0)), _road(_arc(speed, turn, 1))
    found = MOD["observer_turn"](old[None], new[None], np.array([speed], dtype=np.float32), CFG)
    assert abs(found[0] - turn) <= 0.041  # one step of the candidate grid
    assert abs(MOD["observer_turn"](old[None], old[None], np.array([0.0], dtype=np.float32), CFG)[0]) < 1e-9


def test_with_the_observers_motion_a_car_keeping_its_course_has_the_relative_velocity_of_the_scene():
    # The observer turns by 0.3 rad at 10 m/s; a car drives along world +x at 12 m/s. Its
    # velocity relative to the observer, in the newer frame's axes, is R(-0.3)·(12, 0) - (10, 0).
    speed, turn = 10.0, 0.3
    car_old, car_new = np.array([20.0, 4.5]), np.array([32.0, 4.5])

    def local(p, pose):
        d = p - np.array(pose[:2])
        c, s = np.cos(pose[2]), np.sin(pose[2])
        return np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1]])

    m = _maps()
    for frame, pose, car in ((OLD, (0.0, 0.0, 0.0), car_old), (NEW, _arc(speed, turn, 1), car_new)):
        lx, ly = local(car, pose)
        col = round(float((lx + CFG.behind) / CFG.resolution - 0.5))
        row = round(float((ly + 0.5 * CFG.height * CFG.resolution) / CFG.resolution - 0.5))
        m[0, HV, frame, row - 1: row + 1, col - 1: col + 2] = 1.0
        m[0, RL, frame] = _road(pose)
        m[0, MV, frame, 15:17, 20:23] = speed / CFG.max_speed
    c, s = np.cos(turn), np.sin(turn)
    want = np.array([c * 12.0, -s * 12.0]) - np.array([speed, 0.0])
    ego = MOD["ego_size"](CFG, 4)
    moved = MOD["blob_features"](m, CFG, 1, ego_motion=True)[0, ego:]
    plain = MOD["blob_features"](m, CFG, 1)[0, ego:]
    assert moved[5] == 1.0
    np.testing.assert_allclose(moved[2:4] * 20, want, atol=1.6)  # cells of 1.5 m, one turn step
    assert np.abs(plain[2:4] * 20 - want).max() > 3.0  # without it the world seems to swing


def test_the_check_pairs_found_vehicles_with_exact_ones_nearby():
    check = runpy.run_path(str(Path(__file__).resolve().parents[2] / "scripts" / "blob_check.py"), run_name="check")
    n_exact, n_found, p, near, covered, spurious = check["pairs"]("highway", 2, 6, 4, 3.0, False)
    assert 0.5 * n_exact < covered <= n_exact and 0 <= spurious < 0.5 * n_found
    assert n_exact > 0 and 0 < len(p) <= n_found and p.shape[1] == 6 and len(near) and np.median(near) < 1.5
    assert (p[:, 0] <= 3.0).all() and np.median(p[:, 0]) < 1.5
    matched = p[p[:, 1] > 0]
    assert len(matched) and np.median(np.hypot(*(matched[:, 2:4] - matched[:, 4:6]).T)) < 3.0


def test_a_track_through_four_frames_skips_a_missed_frame_and_follows_its_line():
    m = np.zeros((1, 4, 4, CFG.height, CFG.width), dtype=np.float32)
    for frame, col in ((0, 20), (1, 22), (3, 26)):  # two cells (3 m) a step; missed in frame 2
        m[0, HV, frame, 8:10, col:col + 2] = 1.0
    m[0, HV, 0, 8:10, 23:25] = 1.0  # in the oldest frame, a car nearer its last place (1.5 m) than its line's
    ego = MOD["ego_size"](CFG, 4)
    four = MOD["blob_features"](m, CFG, 1, frames=4)[0, ego:]
    np.testing.assert_allclose(four[[2, 3, 5]], [3.0 / 20, 0.0, 1.0], atol=1e-6)
    two = MOD["blob_features"](m, CFG, 1, frames=2)[0, ego:]
    assert two[5] == 0.0 and two[2] == 0.0  # frame 2 holds no car: nothing to match
    with pytest.raises(ValueError, match="frames must be 2 to the stack's 4"):
        MOD["blob_features"](m, CFG, 1, frames=5)


def test_a_four_frame_track_of_a_turning_observer_gives_the_velocity_relative_to_it_now():
    # The observer turns 0.2 rad a step at 10 m/s; a car drives along world +x at 12 m/s.
    # Relative to the observer now, in its axes: R(-0.6)·(12, 0) - (10, 0).
    speed, turn = 10.0, 0.2
    m = np.zeros((1, 4, 4, CFG.height, CFG.width), dtype=np.float32)
    for frame in range(4):
        x0, y0, th = _arc(speed, turn, frame)
        d = np.array([20.0 + 12.0 * frame - x0, 10.0 - y0])
        lx, ly = np.cos(th) * d[0] + np.sin(th) * d[1], -np.sin(th) * d[0] + np.cos(th) * d[1]
        col = round(float((lx + CFG.behind) / CFG.resolution - 0.5))
        row = round(float((ly + 0.5 * CFG.height * CFG.resolution) / CFG.resolution - 0.5))
        m[0, HV, frame, row - 1: row + 1, col - 1: col + 2] = 1.0
        m[0, RL, frame] = _road((x0, y0, th))
        m[0, MV, frame, 15:17, 20:23] = speed / CFG.max_speed
    want = np.array([12.0 * np.cos(3 * turn) - speed, -12.0 * np.sin(3 * turn)])
    got = MOD["blob_features"](m, CFG, 1, ego_motion=True, frames=4)[0, MOD["ego_size"](CFG, 4):]
    assert got[5] == 1.0
    np.testing.assert_allclose(got[2:4] * 20, want, atol=1.2)


def test_fill_puts_a_car_the_newest_frame_lost_one_step_on_along_its_track():
    m = np.zeros((1, 4, 3, CFG.height, CFG.width), dtype=np.float32)
    m[0, HV, 0, 8:10, 20:22] = 1.0  # two cells (3 m) a step along the road...
    m[0, HV, 1, 8:10, 22:24] = 1.0
    # ...and missed in the newest frame, which holds a car elsewhere (tracked, at rest).
    m[0, HV, :, 20:22, 40:42] = 0.5
    m[0, HV, 1, 26:28, 2:4] = 1.0  # lost as well, but with no motion of its own: not put back
    ego = MOD["ego_size"](CFG, 4)
    plain = MOD["blob_features"](m, CFG, 3, frames=3)[0, ego:].reshape(3, PER_NEIGHBOUR)
    assert plain[0, 8] == 1.0 and not plain[1:].any()
    rows = MOD["blob_features"](m, CFG, 3, frames=3, fill=True)[0, ego:].reshape(3, PER_NEIGHBOUR)
    # Put back at column 24.5 (x = 25·1.5 − 32 = 5.5 m), row 8.5 (y = 9·1.5 − 24 = −10.5 m),
    # with its motion of 3 m a step; nearer the AV than the car at column 40.5.
    np.testing.assert_allclose(rows[0], [5.5 / 50, -10.5 / 50, 3.0 / 20, 0.0, 1.0, 1.0, 0.0, 0.4, 1.0], atol=1e-6)
    np.testing.assert_allclose(rows[1, [0, 1, 2, 3, 8]], [29.5 / 50, 7.5 / 50, 0.0, 0.0, 1.0], atol=1e-6)
    assert not rows[2].any()


def test_fill_leaves_a_car_that_the_newest_frame_holds_and_one_that_drove_out_of_the_map():
    m = np.zeros((1, 4, 3, CFG.height, CFG.width), dtype=np.float32)
    for frame in range(3):
        m[0, HV, frame, 8:10, 20 + 2 * frame:22 + 2 * frame] = 1.0  # tracked in every frame
    m[0, HV, 0, 20:22, 58:60] = 1.0  # 4.5 m a step toward the map's far edge, last seen at 61
    m[0, HV, 1, 20:22, 61:63] = 1.0
    ego = MOD["ego_size"](CFG, 4)
    plain = MOD["blob_features"](m, CFG, 2, frames=3)[0, ego:]
    np.testing.assert_array_equal(MOD["blob_features"](m, CFG, 2, frames=3, fill=True)[0, ego:], plain)
    for option in ("fill", "smooth"):
        with pytest.raises(ValueError, match="frames must be at least 3"):
            MOD["blob_features"](m, CFG, 2, frames=2, **{option: True})


def test_smooth_places_a_tracked_car_on_its_fitted_line():
    m = np.zeros((1, 4, 4, CFG.height, CFG.width), dtype=np.float32)
    # One cell at columns 20, 22, 25, 26 in frames t = −3 to 0: about two cells a step, with
    # noise; the least-squares line through them passes column 26.4 at t = 0, not 26.
    for frame, col in enumerate((20, 22, 25, 26)):
        m[0, HV, frame, 8:10, col:col + 1] = 1.0
    t = np.array([-3.0, -2.0, -1.0, 0.0])
    c = np.array([20.0, 22.0, 25.0, 26.0])
    slope, at0 = np.polyfit(t, c, 1)
    ego = MOD["ego_size"](CFG, 4)
    raw = MOD["blob_features"](m, CFG, 1, frames=4)[0, ego:]
    fit = MOD["blob_features"](m, CFG, 1, frames=4, smooth=True)[0, ego:]
    np.testing.assert_allclose(raw[0] * 50, (26 + 0.5) * 1.5 - 32, atol=1e-5)  # its newest blob
    np.testing.assert_allclose(fit[0] * 50, (at0 + 0.5) * 1.5 - 32, atol=1e-5)
    np.testing.assert_allclose([fit[2] * 20, raw[2] * 20], slope * 1.5, atol=1e-5)
    np.testing.assert_array_equal(np.delete(fit, 0), np.delete(raw, 0))


def test_fill_puts_nothing_back_where_no_frame_lost_a_car_though_two_tracks_took_the_same_one():
    # Two cars 9 m (six cells) apart, each moving 9 m a step, in all three frames: both newest
    # cars are followed back to the same car of the frame before (the nearest), which leaves
    # the other one unclaimed. Nothing was lost, so nothing is put back.
    m = np.zeros((1, 4, 3, CFG.height, CFG.width), dtype=np.float32)
    for frame in range(3):
        for start in (10, 16):
            m[0, HV, frame, 8:10, start + 6 * frame:start + 6 * frame + 2] = 1.0
    ego = MOD["ego_size"](CFG, 4)
    plain = MOD["blob_features"](m, CFG, 4, frames=3)[0, ego:]
    assert plain.reshape(4, PER_NEIGHBOUR)[:, 8].sum() == 2
    np.testing.assert_array_equal(MOD["blob_features"](m, CFG, 4, frames=3, fill=True)[0, ego:], plain)


def test_fill_does_not_put_a_car_back_onto_a_car_of_the_newest_frame():
    def maps(row: int) -> np.ndarray:
        m = np.zeros((1, 4, 3, CFG.height, CFG.width), dtype=np.float32)
        m[0, HV, 0, 8:10, 20:22] = 1.0  # car A, 3 m a step, lost in the newest frame:
        m[0, HV, 1, 8:10, 22:24] = 1.0  # one step on it would lie at columns 24-25, rows 8-9
        m[0, HV, 1:, row:row + 2, 26:28] = 1.0  # car C, at rest, in the last two frames
        return m

    ego = MOD["ego_size"](CFG, 4)
    for row, back in ((8, 0), (20, 1)):  # C 3 m ahead of A's place (within FILL_CLEAR), or 18 m aside
        plain = MOD["blob_features"](maps(row), CFG, 4, frames=3)[0, ego:].reshape(4, PER_NEIGHBOUR)
        filled = MOD["blob_features"](maps(row), CFG, 4, frames=3, fill=True)[0, ego:].reshape(4, PER_NEIGHBOUR)
        assert plain[:, 8].sum() == 1 and filled[:, 8].sum() == 1 + back
