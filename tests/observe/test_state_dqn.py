"""``scripts/state_dqn.py``: its settings and its ε-greedy policy over exact states."""

import runpy
from pathlib import Path

import numpy as np
import pytest
import torch

from latentdrive.config import ConfigError
from latentdrive.evaluate.run import evaluate_policy

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "state_dqn.py"
MOD = runpy.run_path(str(SCRIPT), run_name="state_dqn")


def test_settings_reach_the_learner_and_the_reward_and_map_only_ones_are_refused():
    dqn, reward = MOD["configs"](["dqn.n_step=3", "reward.speed=0.05", "dqn.updates_per_transition=1"])
    assert (dqn.n_step, dqn.updates_per_transition, reward.speed) == (3, 1.0, 0.05)
    with pytest.raises(ConfigError, match="augment_shift"):
        MOD["configs"](["dqn.augment_shift=2"])
    with pytest.raises(ConfigError, match=r"expected dqn\.KEY=VALUE"):
        MOD["configs"](["planner.depth=1"])
    with pytest.raises(ConfigError, match="prioritized"):
        MOD["configs"](["dqn.prioritized=true"])
    with pytest.raises(ConfigError, match=r"dqn\.n_step"):
        MOD["configs"](["dqn.n_step=0"])


class _Prefers:
    """A 'network' whose Q-values always rank action ``a`` first."""

    def __init__(self, a: int) -> None:
        self.a = a

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        q = torch.zeros(x.shape[0], 5)
        q[:, self.a] = 1.0
        return q


def _played(eps: float) -> np.ndarray:
    seen: list[np.ndarray] = []
    policy = MOD["StatePolicy"](_Prefers(3), 4, 80.0, True, np.random.default_rng(0), lambda: eps)

    def make():
        def act(inp):
            a = policy(inp)
            seen.append(a[inp.active])
            assert policy.latest is not None and policy.latest.shape[:2] == a.shape
            return a
        return act

    evaluate_policy(make, ["roundabout"], 4, envs=4, observation=MOD["TINY_MAP"])
    return np.concatenate(seen)


def test_the_greedy_policy_takes_the_best_action_and_exploration_all_of_them():
    assert set(_played(0.0)) == {3}
    assert set(_played(1.0)) == {0, 1, 2, 3, 4}


def _input_after(scenario: str, envs: int, seed: int, steps: int):
    """What a policy sees after ``steps`` Idle steps of ``envs`` environments of ``scenario``
    (off the start, so that time, speeds and positions are not those of a reset)."""
    from latentdrive.rollout import rollout
    from latentdrive.vec import make_vec

    seen = []

    def idle(inp):
        seen.append(inp)
        return np.zeros(inp.active.shape, dtype=np.int64)

    for k, _ in enumerate(rollout(make_vec(scenario, envs, observation=MOD["TINY_MAP"]), idle, seed=seed)):
        if k == steps:
            break
    return seen[-1]


def test_no_pose_zeroes_the_avs_world_heading_position_and_time_only():
    from latentdrive.observe.state import state_features
    from latentdrive.scenarios import get_spec

    inp, spec = _input_after("roundabout", 2, 3, 3), get_spec("roundabout")
    full = MOD["features"](inp, [spec, spec], 12, 80.0, True, True)
    bare = MOD["features"](inp, [spec, spec], 12, 80.0, True, False)
    assert np.array_equal(full[0, 0], state_features(inp.scenes[0], 0, spec.duration, 12, 80.0, True))
    pose = np.zeros(full.shape[-1], dtype=bool)
    pose[2:7] = True  # cos, sin of the heading, world x, y, share of the episode gone
    assert np.all(np.any(full[..., pose] != 0, axis=-1)) and np.all(bare[..., pose] == 0)
    assert np.array_equal(full[..., ~pose], bare[..., ~pose])
    # --no-time: the share of the episode gone (3 decisions of 1 s) alone.
    timeless = MOD["features"](inp, [spec, spec], 12, 80.0, True, True, show_time=False)
    assert full[0, 0, 6] == pytest.approx(3 / spec.duration) and np.all(timeless[..., 6] == 0)
    assert np.array_equal(np.delete(full, 6, axis=-1), np.delete(timeless, 6, axis=-1))


def test_a_view_box_drops_the_neighbours_outside_it_and_keeps_the_others():
    from latentdrive.observe.state import PER_NEIGHBOUR
    from latentdrive.scenarios import get_spec

    inp, spec = _input_after("intersection", 4, 5, 4), get_spec("intersection")
    k = 12
    full = MOD["features"](inp, [spec] * 4, k, 80.0, True, True)
    boxed = MOD["features"](inp, [spec] * 4, k, 80.0, True, True, (10.0, 20.0, 5.0))
    start = full.shape[-1] - k * PER_NEIGHBOUR
    rows = full[..., start:].reshape(-1, k, PER_NEIGHBOUR)
    kept = boxed[..., start:].reshape(-1, k, PER_NEIGHBOUR)
    ahead, right = rows[..., 0] * 50, rows[..., 1] * 50
    inside = (ahead >= -10) & (ahead <= 20) & (np.abs(right) <= 5) & (rows[..., -1] == 1)
    outside = (rows[..., -1] == 1) & ~inside
    assert inside.any() and outside.any()  # the case is tested both ways
    assert np.array_equal(kept[inside], rows[inside]) and np.all(kept[outside] == 0)
    assert np.array_equal(boxed[..., :start], full[..., :start])


def test_each_stored_transition_leads_one_decision_on_across_auto_resets():
    # A short run of 4 roundabout environments through many episode ends. The share of the
    # episode gone (feature 6) of every stored transition's next state must be one decision
    # (1 s) later than its state's, and the AV must not jump: a next state taken from the
    # episode that followed, or from another agent, would break both.
    import argparse

    from latentdrive.rl.dqn import DQNConfig
    from latentdrive.scenarios import get_spec
    from latentdrive.scenarios.spec import RewardConfig

    args = argparse.Namespace(seed=0, arch="attention", neighbours=4, hidden=16, envs=4, steps=300, radius=80.0,
                              no_route=False, no_pose=False, no_time=False, view_box=None, out=None,
                              eval_every=0, eval_episodes=1, reader="state", precision="fp32", aux=0.0, road_pool=4, exact_vehicles=False, drop="", ego_motion=False, track_frames=2, sensor_noise=None, fill=False, smooth=False, sensor_frames=1)
    cfg = DQNConfig(n_step=1, learning_starts=100, batch_size=8)
    _, replay = MOD["train"](args, ["roundabout"], cfg, RewardConfig())
    n = replay.added
    assert n >= 300 and np.all(replay.steps[:n] == 1)
    ended = replay.terminated[:n]
    assert 0 < ended.sum() < n  # crashes and arrivals happened: the run crossed episode ends
    before, after = replay.store.get(replay.obs_id[:n]), replay.store.get(replay.next_id[:n])
    np.testing.assert_allclose(after[:, 6] - before[:, 6], 1.0 / get_spec("roundabout").duration, atol=1e-6)
    moved = np.hypot(*(100.0 * (after[:, 4:6] - before[:, 4:6])).T)
    assert moved.max() < 40.0


def test_the_map_readers_input_is_the_stacked_map_then_the_place():
    from latentdrive.scenarios import get_spec

    inp, spec = _input_after("roundabout", 2, 3, 3), get_spec("roundabout")
    inp = inp._replace(obs=np.random.default_rng(0).random((*inp.active.shape, 4, 4, 8, 8), dtype=np.float32))
    full = MOD["features"](inp, [spec, spec], 12, 80.0, True, True)
    x = MOD["map_features"](inp, [spec, spec])
    n_map = 4 * 4 * 8 * 8
    assert x.shape == (*inp.active.shape, n_map + 5) and x.dtype == np.float32
    assert np.array_equal(x[..., :n_map], inp.obs.reshape(*inp.active.shape, -1))
    assert np.array_equal(x[..., n_map:], full[..., 2:7])
    assert np.all(MOD["map_features"](inp, [spec, spec], pose=False)[..., n_map:] == 0)
    timeless = MOD["map_features"](inp, [spec, spec], show_time=False)
    assert np.all(timeless[..., -1] == 0) and np.array_equal(timeless[..., :-1], x[..., :-1])


def test_the_map_and_pose_store_rebuilds_stacks_and_keeps_the_place():
    shape = (4, 3, 4, 8)
    n_map = int(np.prod(shape))
    store = MOD["MapAndPose"](16, shape)
    rng = np.random.default_rng(1)
    frames = rng.integers(0, 256, size=(3, 4, 4, 8)).astype(np.float32) / 255.0
    place = rng.random((3, 5), dtype=np.float32)
    ids, prev = [], -1
    for k in range(3):  # one agent's episode: its stack shifts by a frame each step
        stack = np.stack([frames[max(0, k - 2 + j)] for j in range(3)], axis=1)
        row = np.concatenate([stack.reshape(-1), place[k]])[None]
        ids.append(int(store.add(row, np.array([prev]))[0]))
        prev = ids[-1]
    got = store.get(np.array(ids))
    np.testing.assert_allclose(got[:, n_map:], place)
    last = got[2, :n_map].reshape(shape)
    np.testing.assert_allclose(last, np.stack([frames[0], frames[1], frames[2]], axis=1), atol=1e-6)
    first = got[0, :n_map].reshape(shape)  # the first frame fills the older slots
    np.testing.assert_allclose(first, np.stack([frames[0]] * 3, axis=1), atol=1e-6)
    assert store.added == 3


def test_the_map_reader_reads_the_place_and_the_map():
    from latentdrive.config import ObservationConfig

    torch.manual_seed(0)
    obs = ObservationConfig()
    net = MOD["MapPoseNet"](obs, 32)
    x = torch.rand(3, net.n_map + 5)
    q = net(x)
    assert q.shape == (3, 5)
    moved_place, moved_map = x.clone(), x.clone()
    moved_place[:, net.n_map:] += 0.5
    moved_map[:, : net.n_map] = torch.rand(3, net.n_map)
    assert not torch.allclose(net(moved_place), q) and not torch.allclose(net(moved_map), q)


def test_the_map_reader_stores_each_transition_one_decision_on_across_auto_resets():
    # As the exact-state test above, through the map reader's store: the place's time must
    # advance by one decision, and the next map stack must be the stack shifted by one frame.
    import argparse

    from latentdrive.rl.dqn import DQNConfig
    from latentdrive.scenarios import get_spec
    from latentdrive.scenarios.spec import RewardConfig

    args = argparse.Namespace(seed=0, arch="attention", neighbours=4, hidden=16, envs=4, steps=200, radius=80.0,
                              no_route=True, no_pose=False, no_time=False, view_box=None, out=None,
                              eval_every=0, eval_episodes=1, reader="map", precision="fp32", aux=0.0, road_pool=4, exact_vehicles=False, drop="", ego_motion=False, track_frames=2, sensor_noise=None, fill=False, smooth=False, sensor_frames=1)
    cfg = DQNConfig(n_step=1, learning_starts=100, batch_size=8)
    _, replay = MOD["train"](args, ["roundabout"], cfg, RewardConfig())
    n = replay.added
    assert n >= 200 and 0 < replay.terminated[:n].sum() < n
    before, after = replay.store.get(replay.obs_id[:n]), replay.store.get(replay.next_id[:n])
    np.testing.assert_allclose(after[:, -1] - before[:, -1], 1.0 / get_spec("roundabout").duration, atol=1e-6)
    shape = replay.store.shape
    maps_before = before[:, : replay.store.n_map].reshape(n, *shape)
    maps_after = after[:, : replay.store.n_map].reshape(n, *shape)
    np.testing.assert_array_equal(maps_after[:, :, :-1], maps_before[:, :, 1:])
    assert not np.array_equal(maps_after[:, :, -1], maps_before[:, :, -1])


def test_a_transition_leads_to_the_ended_episodes_last_maps_not_the_next_ones_first():
    from latentdrive.rollout import StepRecord

    shape = (2, 3, 4, 1, 2, 2)
    agents = type("Agents", (), {"active": np.ones((2, 3), dtype=bool)})()
    obs, next_obs, after = (np.full(shape, v, dtype=np.float32) for v in (0.1, 0.2, 0.3))
    scenes = np.array([object(), object()], dtype=object)
    rec = StepRecord(obs, np.zeros((2, 3), dtype=np.int64), agents, next_obs, np.array([True, False]), after, [],
                     scenes, None, None)
    inp = MOD["next_input"](rec, np.array(["a", "b"], dtype=object), None)
    assert inp.obs is next_obs and inp.scenes is scenes and inp.active is agents.active


def test_outcome_files_are_read_back_and_bad_ones_named(tmp_path):
    import json

    from latentdrive.outcome import outcomes_to_json

    outcomes = evaluate_policy(lambda: lambda inp: np.zeros(inp.active.shape, dtype=np.int64), ["roundabout"], 2,
                               envs=2, observation=MOD["TINY_MAP"])
    good = tmp_path / "a.json"
    good.write_text(json.dumps(outcomes_to_json(outcomes)))
    back = MOD["read_outcomes"](str(good))
    assert [(o.seed, o.failed) for o in back] == [(o.seed, o.failed) for o in outcomes]
    assert "mixed" in MOD["format_compare"](MOD["compare"](back, outcomes), ("a", "b"))
    bad = tmp_path / "b.json"
    bad.write_text("{")
    with pytest.raises(ValueError, match=r"b\.json: not an outcomes file"):
        MOD["read_outcomes"](str(bad))
    with pytest.raises(ValueError, match="not the same evaluation episodes"):
        MOD["compare"](back, back[:1])


def test_the_auxiliary_targets_are_the_avs_speeds_and_its_neighbours_inside_the_view():
    from latentdrive.scenarios import get_spec

    inp, spec = _input_after("intersection", 2, 5, 4), get_spec("intersection")
    boxed = MOD["features"](inp, [spec, spec], 12, 80.0, False, True, MOD["MAP_VIEW"])
    x = MOD["map_features"](inp, [spec, spec], aux=True)
    aux = x[..., -MOD["N_AUX"]:]
    assert x.shape[-1] == int(np.prod(inp.obs.shape[2:])) + 5 + MOD["N_AUX"]
    assert np.array_equal(aux[..., :2], boxed[..., :2]) and np.array_equal(aux[..., 2:], boxed[..., 7:])
    assert np.any(aux[..., 2:] != 0)  # some neighbour is in view
    # The place before them is the map reader's, whether or not the targets follow.
    plain = MOD["map_features"](inp, [spec, spec])
    assert np.array_equal(x[..., : plain.shape[-1]], plain)


def test_an_auxiliary_step_teaches_the_reader_the_targets():
    from latentdrive.config import ObservationConfig

    torch.manual_seed(0)
    net = MOD["MapPoseNet"](ObservationConfig(), 64, aux=MOD["N_AUX"])
    n_in = net.n_map + 5
    obs = torch.cat([torch.rand(16, n_in), torch.rand(16, MOD["N_AUX"])], dim=1)
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    first = MOD["map_aux_step"](net, opt, obs, torch.float32)
    for _ in range(150):
        last = MOD["map_aux_step"](net, opt, obs, torch.float32)
    assert last < 0.2 * first
    assert net(obs).shape == (16, 5) and torch.equal(net(obs), net(obs[:, :n_in]))  # the targets are not read


@pytest.mark.parametrize("argv", [["--aux", "1"], ["--reader", "map", "--aux", "-1"]])
def test_auxiliary_targets_need_the_map_reader_and_a_scale_of_at_least_zero(argv, monkeypatch, capsys):
    monkeypatch.setattr("sys.argv", ["state_dqn.py", *argv])
    with pytest.raises(SystemExit) as exit_:
        MOD["main"]()
    assert exit_.value.code == 2 and "--aux takes a scale of at least 0, and only with --reader map" in capsys.readouterr().err


def test_pairing_files_of_other_episodes_is_a_one_line_error(tmp_path, monkeypatch, capsys):
    (tmp_path / "a.json").write_text("[]")
    monkeypatch.setattr("sys.argv", ["state_dqn.py", "--pair", str(tmp_path / "a.json"), str(tmp_path / "missing.json")])
    with pytest.raises(SystemExit) as exit_:
        MOD["main"]()
    err = capsys.readouterr().err
    assert exit_.value.code == 1 and "missing.json: not an outcomes file" in err and err.count("\n") == 1


def test_a_road_pool_that_does_not_divide_the_map_is_refused(monkeypatch, capsys):
    monkeypatch.setattr("sys.argv", ["state_dqn.py", "--reader", "blobs", "--road-pool", "5"])
    with pytest.raises(SystemExit) as exit_:
        MOD["main"]()
    assert exit_.value.code == 2 and "--road-pool must divide the map's 32 x 64 cells, got 5" in capsys.readouterr().err


def test_the_blob_reader_stores_what_the_detector_finds_in_each_map():
    import argparse

    from latentdrive.config import ObservationConfig
    from latentdrive.rl.dqn import DQNConfig
    from latentdrive.scenarios.spec import RewardConfig

    args = argparse.Namespace(seed=0, arch="attention", neighbours=4, hidden=16, envs=4, steps=200, radius=80.0,
                              no_route=True, no_pose=False, no_time=False, view_box=None, out=None,
                              eval_every=0, eval_episodes=1, reader="blobs", precision="fp32", aux=0.0, road_pool=8, exact_vehicles=False, drop="", ego_motion=False, track_frames=2, sensor_noise=None, fill=False, smooth=False, sensor_frames=1)
    net, replay = MOD["train"](args, ["highway"], DQNConfig(n_step=1, learning_starts=100, batch_size=8), RewardConfig())
    n = replay.added
    ego = MOD["blob_ego_size"](ObservationConfig(), 8)
    rows = replay.store.get(replay.obs_id[:n])
    assert n >= 200 and rows.shape[1] == ego + 4 * 9 == 2 + 4 * 8 + 36
    vehicles = rows[:, ego:].reshape(n, 4, 9)
    assert vehicles[:, 0, -1].mean() > 0.5  # highway traffic is in view most of the time
    assert np.all(np.diff(np.hypot(vehicles[..., 0], vehicles[..., 1]) * vehicles[..., -1], axis=1)[vehicles[:, 1:, -1] > 0] >= 0)
    assert net(torch.from_numpy(rows[:3])).shape == (3, 5)


def test_exact_vehicles_replace_the_found_ones_and_keep_the_maps_speed_and_road():
    from latentdrive.config import ObservationConfig
    from latentdrive.rollout import rollout
    from latentdrive.vec import make_vec

    vec = make_vec(["merge"], 2, backend="fast")
    specs = list(vec.simulator.specs)
    names = np.asarray([s.name for s in specs], dtype=object)
    found, exact = (MOD["StatePolicy"](_Prefers(1), 6, 80.0, False, reader="blobs", blobs=MOD["BlobReading"](exact_vehicles=e))
                    for e in (False, True))
    for step, rec in enumerate(rollout(vec, lambda inp: np.ones(inp.obs.shape[:2], dtype=np.int64), seed=2)):
        if step == 3:
            inp = MOD["next_input"](rec, names, vec.simulator)
            a, b = found.read(inp), exact.read(inp)
            break
    vec.close()
    ego = MOD["blob_ego_size"](ObservationConfig(), 4)
    rows = b[..., ego:].reshape(*b.shape[:-1], 6, 9)
    np.testing.assert_array_equal(a[..., :ego], b[..., :ego])
    assert rows[..., 8].sum() > 0 and not np.array_equal(a[..., ego:], b[..., ego:])
    # The six nearest of all the vehicles inside the view, present rows first, nearest first.
    every = MOD["features"](inp, specs, 64, 80.0, False, False, MOD["MAP_VIEW"])[..., -64 * 9:]
    every = every.reshape(*every.shape[:-1], 64, 9)
    for e, av in zip(*np.nonzero(inp.active), strict=True):
        inside = every[e, av][every[e, av, :, 8] > 0][:6]
        np.testing.assert_array_equal(rows[e, av, : len(inside)], inside)
        assert not rows[e, av, len(inside):].any()
    # --drop velocity,heading zeroes those columns of every row and nothing else.
    opts = MOD["BlobReading"](exact_vehicles=True, drop=MOD["drop_columns"]("velocity,heading"))
    dropped = MOD["StatePolicy"](_Prefers(1), 6, 80.0, False, reader="blobs", blobs=opts).read(inp)
    kept = rows.copy()
    assert np.abs(kept[..., 2:4]).sum() > 0 and np.abs(kept[..., 4:6]).sum() > 0
    kept[..., [2, 3, 4, 5]] = 0.0
    np.testing.assert_array_equal(dropped[..., ego:], kept.reshape(*b.shape[:-1], -1))
    np.testing.assert_array_equal(dropped[..., :ego], a[..., :ego])


def test_exact_vehicles_need_the_blob_reader(monkeypatch, capsys):
    monkeypatch.setattr("sys.argv", ["state_dqn.py", "--exact-vehicles"])
    with pytest.raises(SystemExit) as exit_:
        MOD["main"]()
    assert exit_.value.code == 2 and "--exact-vehicles, --ego-motion, --track-frames and --road-pool only with --reader blobs" in capsys.readouterr().err


def test_an_unknown_column_to_drop_is_refused(monkeypatch, capsys):
    monkeypatch.setattr("sys.argv", ["state_dqn.py", "--reader", "blobs", "--drop", "velocity,colour"])
    with pytest.raises(SystemExit) as exit_:
        MOD["main"]()
    assert exit_.value.code == 2 and "--drop takes velocity, heading, crashed with --reader blobs, got 'velocity,colour'" in capsys.readouterr().err


@pytest.mark.parametrize(("argv", "message"), [
    (["--reader", "blobs", "--drop", "heading"], "--drop heading or crashed only with --exact-vehicles"),
    (["--road-pool", "8"], "--road-pool only with --reader blobs"),
    (["--reader", "blobs", "--track-frames", "5"], "--track-frames must be 2 to the map's 4 frames, got 5"),
    (["--reader", "blobs", "--sensor-noise"], "--sensor-noise takes all or position, speed, heading, miss, with --exact-vehicles"),
    (["--reader", "blobs", "--exact-vehicles", "--sensor-noise", "miss,colour"], "got 'miss,colour'"),
    (["--reader", "blobs", "--fill"], "--fill and --smooth follow a vehicle through two older frames"),
    (["--reader", "blobs", "--track-frames", "3", "--fill", "--exact-vehicles"], "not on --exact-vehicles"),
    (["--reader", "blobs", "--track-frames", "2", "--smooth"], "they need --reader blobs and --track-frames 3 or 4"),
    (["--reader", "blobs", "--exact-vehicles", "--sensor-frames", "4"], "--sensor-frames takes a count of at least 1, with --sensor-noise"),
])
def test_blob_reader_options_out_of_place_are_refused(argv, message, monkeypatch, capsys):
    monkeypatch.setattr("sys.argv", ["state_dqn.py", *argv])
    with pytest.raises(SystemExit) as exit_:
        MOD["main"]()
    assert exit_.value.code == 2 and message in capsys.readouterr().err


def _rows(n: int) -> np.ndarray:
    """``n`` present vehicle rows heading 0.5 rad off the observer, 20 m ahead, 5 m right."""
    row = np.array([20 / 50, 5 / 50, 0.1, -0.2, np.cos(0.5), np.sin(0.5), 0.0, 0.0, 1.0], dtype=np.float32)
    return np.tile(row, (n, 1))


def test_sensor_noise_draws_the_maps_noise_on_exact_rows():
    from latentdrive.config import NoiseConfig

    rows = _rows(4000)[None]
    noisy = MOD["sensor_noise"](rows, NoiseConfig())[0]
    kept = noisy[:, 8] > 0.5
    assert 0.08 < 1 - kept.mean() < 0.12  # miss_prob 0.1
    assert not noisy[~kept].any()  # a missed vehicle is a zero row
    d = (noisy[kept] - rows[0, kept]).astype(np.float64)
    np.testing.assert_allclose(d[:, :2].std(0) * 50, 0.75, rtol=0.06)  # metres on each axis
    # The speed's jitter lies along the vehicle's heading: 1 m/s in size.
    along = (d[:, 2] * np.cos(0.5) + d[:, 3] * np.sin(0.5)) * 20
    across = (-d[:, 2] * np.sin(0.5) + d[:, 3] * np.cos(0.5)) * 20
    assert abs(along.std() - 1.0) < 0.06 and np.abs(across).max() < 0.05
    turn = np.arctan2(noisy[kept, 5], noisy[kept, 4]) - 0.5
    assert abs(turn.std() - 0.02) < 0.002
    np.testing.assert_allclose(np.hypot(noisy[kept, 4], noisy[kept, 5]), 1.0, atol=1e-6)
    np.testing.assert_array_equal(d[:, 6:], 0.0)


def test_sensor_noise_is_the_same_for_the_same_rows_and_spares_absent_ones():
    from latentdrive.config import NoiseConfig

    rows = np.zeros((2, 3, 10, 9), dtype=np.float32)
    rows[..., :6, :] = _rows(6)
    rows[1, 2, :6, 0] += 0.01  # one observer sees something else
    noisy = MOD["sensor_noise"](rows, NoiseConfig())
    np.testing.assert_array_equal(noisy, MOD["sensor_noise"](rows.copy(), NoiseConfig()))
    np.testing.assert_array_equal(noisy[0, 0], noisy[1, 1])  # same rows, same draws
    assert not np.array_equal(noisy[0, 0], noisy[1, 2])
    assert not noisy[..., 6:, :].any()
    # Only the parts named are drawn.
    only_miss = MOD["sensor_noise"](rows, MOD["sensor_config"]("miss"))
    kept = only_miss[..., 8] > 0.5
    np.testing.assert_array_equal(only_miss[kept], rows[kept])
    assert MOD["sensor_config"]("position,speed").miss_prob == 0.0
    assert MOD["sensor_config"]("all") == NoiseConfig() and MOD["sensor_config"](None) is None
    four = MOD["sensor_config"]("all", 4)  # a perfect tracker's mean of four frames
    assert (four.position_std, four.speed_std, four.heading_std) == (0.375, 0.5, 0.01)
    assert abs(four.miss_prob - 1e-4) < 1e-12


def test_exact_vehicles_with_sensor_noise_keep_the_view_and_the_nearest_first_order():
    from latentdrive.rollout import rollout
    from latentdrive.vec import make_vec

    vec = make_vec(["highway"], 2, backend="fast")
    specs = list(vec.simulator.specs)
    names = np.asarray([s.name for s in specs], dtype=object)
    for step, rec in enumerate(rollout(vec, lambda inp: np.ones(inp.obs.shape[:2], dtype=np.int64), seed=3)):
        if step == 3:
            inp = MOD["next_input"](rec, names, vec.simulator)
            break
    vec.close()
    clean = MOD["exact_in_view"](inp, specs, 16)
    noisy = MOD["exact_in_view"](inp, specs, 16, MOD["sensor_config"]("all"))
    behind, ahead, side = MOD["MAP_VIEW"]
    present, seen = noisy[..., 8] > 0.5, clean[..., 8] > 0.5
    # About one vehicle in ten is missed; a few just outside the view are jittered into it.
    assert 0.7 * seen.sum() < present.sum() < seen.sum() + 8
    assert not np.array_equal(noisy, clean)
    # Every noisy vehicle lies within 4 m (over five standard deviations) of an exact one
    # (inside the view or just outside it).
    every = MOD["features"](inp, specs, 64, 80.0, False, False)[..., -64 * 9:]
    every = every.reshape(*every.shape[:-1], 64, 9)
    for e, a in zip(*np.nonzero(present.any(-1)), strict=True):
        d = np.hypot(noisy[e, a, :, None, 0] - every[e, a, None, :, 0], noisy[e, a, :, None, 1] - every[e, a, None, :, 1])
        d = np.where(every[e, a, None, :, 8] > 0.5, d, np.inf).min(1) * 50
        assert (d[present[e, a]] < 4.0).all()
    x, y = noisy[..., 0][present] * 50, noisy[..., 1][present] * 50
    assert (x >= -behind).all() and (x <= ahead).all() and (np.abs(y) <= side).all()
    # Present rows first: no present row after an absent one.
    assert not (np.diff(present.astype(int), axis=-1) > 0).any()
