"""Linear probes: literal target geometry, probes that must learn (and must not), end to end."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from sklearn.linear_model import Ridge
from sklearn.preprocessing import StandardScaler

from latentdrive.bnn.checkpoint import save_checkpoint
from latentdrive.config import ConfigError, ObservationConfig, validate
from latentdrive.evaluate.policies import REFERENCE_POLICIES
from latentdrive.evaluate.probe_fit import ALPHAS, fit_probes, reduce_features, split_by_episode
from latentdrive.evaluate.probe_targets import (
    FREE_WINDOW,
    TARGETS,
    forward_range,
    gap_ahead,
    goal_distance,
    lane_free,
    relative_speed_ahead,
    scene_targets,
)
from latentdrive.evaluate.probes import ProbeConfig, collect_probe_data, probe_features, run_probes
from latentdrive.models.bottleneck import BottleneckConfig, BottleneckNetwork
from latentdrive.scenarios import get_spec
from latentdrive.scene import Kind, RoadRaster, Scene
from latentdrive.seeds import (
    EVAL_RESET_SEEDS,
    MAX_ENVS,
    PROBE_RESET_SEEDS,
    TRAIN_RESET_SEEDS,
    probe_reset_seed,
)
from latentdrive.sim.fast import FastBatch
from latentdrive.sim.fast.lanes import position
from latentdrive.sim.fast.network import get_network
from latentdrive.sim.reach import distance_to_goal

pytestmark = pytest.mark.usefixtures("one_torch_thread")

NAN = np.nan
#: A small grid keeps the end-to-end runs quick: 16 x 32 cells of 1.5 m, 2 frames.
SMALL_OBS = ObservationConfig(height=16, width=32, frames=2, behind=16.0)


# ---------------------------------------------------------------------------------------
# The read-outs, on literal offsets


def test_gap_ahead_is_the_nearest_vehicle_ahead_in_the_lane() -> None:
    along = np.array([[10.0, 30.0, -5.0, NAN]])
    lateral = np.zeros((1, 4))
    assert gap_ahead(along, lateral, np.array([2.0]), 64.0).tolist() == [10.0]
    # The 10 m car one lane over (its centre 3.5 m off this lane's centreline) is not in it.
    lateral[0, 0] = 3.5
    assert gap_ahead(along, lateral, np.array([2.0]), 64.0).tolist() == [30.0]
    # Nothing ahead within the map's range: the range itself.
    assert gap_ahead(np.array([[70.0, -1.0]]), np.zeros((1, 2)), np.array([2.0]), 64.0).tolist() == [64.0]
    assert gap_ahead(np.array([[NAN]]), np.array([[NAN]]), np.array([2.0]), 64.0).tolist() == [64.0]


def test_relative_speed_is_the_leaders_minus_the_avs() -> None:
    along = np.array([[20.0, 12.0], [NAN, 80.0]])
    lateral = np.zeros((2, 2))
    speed = np.array([30.0, 18.0])
    out = relative_speed_ahead(along, lateral, np.array([2.0, 2.0]), 64.0, speed, np.array([25.0, 25.0]))
    # AV 0 follows vehicle 1 (12 m) at 18 m/s; AV 1 has nobody within 64 m.
    assert out.tolist() == [-7.0, 0.0]


def test_a_lane_is_free_when_it_exists_and_nobody_is_within_the_window() -> None:
    half, window = np.array([2.0] * 5), FREE_WINDOW
    along = np.array([[window - 1], [window + 1], [-(window - 1)], [0.0], [0.0]])
    lateral = np.array([[0.0], [0.0], [1.5], [3.0], [0.0]])
    exists = np.array([True, True, True, True, False])
    assert lane_free(along, lateral, half, exists).tolist() == [False, True, False, True, False]


def test_goal_distance_is_the_nearest_reachable_goal_floored_at_zero() -> None:
    routes = np.array([[350.0, NAN], [120.0, 80.0], [-3.0, NAN], [NAN, NAN]])
    out = goal_distance(routes)
    assert out[:3].tolist() == [350.0, 80.0, 0.0]
    assert np.isnan(out[3])
    assert np.isnan(goal_distance(np.zeros((1, 0))))[0]


def test_distance_to_goal_follows_the_route() -> None:
    highway, merge = get_network("highway", 3), get_network("merge", 3)
    assert distance_to_goal(highway, ("0", "1"), 1, 100.0, "1", 450.0) == pytest.approx(350.0)
    # merge: a-b is 230 m, b-c 80 m, then 20 m into c-d.
    assert distance_to_goal(merge, ("a", "b"), 0, 200.0, "d", 20.0) == pytest.approx(30 + 80 + 20)
    assert distance_to_goal(merge, ("c", "d"), 0, 50.0, "a", 20.0) is None


# ---------------------------------------------------------------------------------------
# The read-outs on real lane networks


def _scene(xy: list[tuple[float, float]], speed: list[float], n_av: int, heading: float = 0.0) -> Scene:
    n = len(xy)
    v = np.asarray(speed, dtype=np.float64)
    return Scene(
        position=np.asarray(xy, dtype=np.float64), heading=np.full(n, heading), speed=v, frenet_speed=v,
        length=np.full(n, 5.0), width=np.full(n, 2.0),
        kind=np.array([Kind.AV] * n_av + [Kind.HV] * (n - n_av), dtype=np.int8),
        mask=np.ones(n, dtype=bool), crashed=np.zeros(n, dtype=bool), agents=np.arange(n_av, dtype=np.int64),
        road=RoadRaster(mask=np.zeros((1, 1), dtype=np.uint8), origin=np.zeros(2), resolution=1.0),
    )


def test_highway_targets_of_a_literal_scene() -> None:
    # highway-env's highway: lane i runs along y = 4 i; y grows to the right of +x, so
    # lane 0 is the leftmost. AV 0 in the middle lane at x = 100, AV 1 in lane 0 at x = 300.
    net = get_network("highway", 3)
    scene = _scene([(100, 4), (300, 0), (110, 4), (108, 8), (150, 0)], [25, 20, 20, 25, 25], n_av=2)
    lanes = [net.lane(("0", "1", 1)), net.lane(("0", "1", 0))]
    t = scene_targets(scene, net, lanes, [("1",), ("1",)], 450.0, 64.0)
    assert set(t) == set(TARGETS)
    # AV 0: a car 10 m ahead in its lane, 5 m/s slower; a car 8 m ahead one lane to the
    # right; the left lane is empty near it (the car at x = 150 is 50 m ahead).
    assert t["gap_ahead"].tolist() == [10.0, 64.0]
    assert t["relative_speed_ahead"].tolist() == [-5.0, 0.0]
    assert t["right_free"].tolist() == [False, True]
    # AV 1 is in the leftmost lane: there is no lane on its left.
    assert t["left_free"].tolist() == [True, False]
    assert t["goal_distance"].tolist() == pytest.approx([350.0, 150.0])


def test_the_lane_ahead_continues_onto_the_next_road() -> None:
    # merge: a-b ends at x = 230; the main lanes go on as b-c lanes 0 and 1, the ramp k-b
    # (a sine lane from (150, 14.5) to (230, 8)) as b-c lane 2, at y = 8.
    net = get_network("merge", 3)
    scene = _scene([(220, 0), (210, 8.5), (240, 0), (245, 8)], [25, 20, 25, 20], n_av=2)
    lanes = [net.lane(("a", "b", 0)), net.lane(("k", "b", 0))]
    t = scene_targets(scene, net, lanes, [("d",), ("d",)], 20.0, 64.0)
    s_ramp = 210.0 - 150.0  # the sine lane's s runs along its base segment
    assert t["gap_ahead"][0] == pytest.approx(20.0)
    assert t["gap_ahead"][1] == pytest.approx(80.0 - s_ramp + 15.0, abs=0.3)
    assert t["goal_distance"][0] == pytest.approx(10 + 80 + 20)


def test_the_lane_ahead_turns_where_the_route_turns() -> None:
    # intersection: the approach o0-ir0 runs south along x = 2 and ends at y = 11; the
    # right turn ir0-il3 is a 14.1 m arc to (11, 2), the straight ir0-il2 goes on along x = 2.
    net = get_network("intersection", 3)
    approach, right = net.lane(("o0", "ir0", 0)), net.lane(("ir0", "il3", 0))
    turning_car = position(net.table, right, 14.14 / 2, 0.0)  # (4.64, 4.64): 2.6 m off x = 2
    scene = _scene([position(net.table, approach, 90.0, 0.0), turning_car], [9.0, 5.0], n_av=1, heading=-np.pi / 2)
    turn = scene_targets(scene, net, [approach], [("o3",)], 10.0, 64.0)
    assert turn["gap_ahead"][0] == pytest.approx(10.0 + 14.14 / 2, abs=0.01)
    assert turn["relative_speed_ahead"][0] == pytest.approx(-4.0)
    assert turn["goal_distance"][0] == pytest.approx(10.0 + 14.14 + 10.0, abs=0.01)
    straight = scene_targets(scene, net, [approach], [("o2",)], 10.0, 64.0)
    assert straight["gap_ahead"][0] == 64.0


def test_every_intersection_road_has_one_lane_so_no_side_is_free() -> None:
    net = get_network("intersection", 3)
    lane = net.lane(("o0", "ir0", 0))
    x, y = (float(v) for v in np.asarray(net.table.geo[[0, 1], lane]))
    t = scene_targets(_scene([(x, y)], [9.0], n_av=1), net, [lane], [("o1",)], 10.0, 64.0)
    assert t["left_free"].tolist() == [False] and t["right_free"].tolist() == [False]
    assert t["goal_distance"][0] > 100.0


def test_the_fast_backend_reports_each_avs_goals() -> None:
    batch = FastBatch([get_spec("highway"), get_spec("intersection")])
    batch.reset([0, 1])
    assert batch.goal_nodes(0) == [("1",), ("1",)]
    spec = get_spec("intersection")
    for a, goals in enumerate(batch.goal_nodes(1)):
        assert len(goals) == 1 and goals[0] in spec.av_spawn[a % len(spec.av_spawn)].destinations


# ---------------------------------------------------------------------------------------
# Fitting


def _episodes(n: int, length: int = 10) -> np.ndarray:
    return np.arange(n) // length


def _fit(x: np.ndarray, targets: dict[str, np.ndarray], groups: np.ndarray, n_train: int) -> dict:
    return fit_probes(x[:n_train], {k: v[:n_train] for k, v in targets.items()},
                      x[n_train:], {k: v[n_train:] for k, v in targets.items()}, groups=groups[:n_train])


def test_probes_recover_linear_targets_and_not_from_noise() -> None:
    rng = np.random.default_rng(0)
    n, f = 400, 20
    x, noise = rng.standard_normal((n, f)), rng.standard_normal((n, f))
    w = rng.standard_normal(f)
    targets = {"linear": x @ w + 0.05 * rng.standard_normal(n), "flag": x @ w > 0}
    s = _fit(x, targets, _episodes(n), 300)
    assert s["linear"].metric == "r2" and s["linear"].value > 0.95
    assert s["flag"].metric == "accuracy" and s["flag"].value > 0.9
    assert abs(s["linear"].baseline) < 0.1 and 0.3 < s["flag"].baseline < 0.7
    assert s["linear"].penalty in ALPHAS and s["linear"].n_train == 300 and s["linear"].n_test == 100
    # The same targets from features that carry nothing about them.
    s = _fit(noise, targets, _episodes(n), 300)
    assert abs(s["linear"].value) < 0.1
    assert abs(s["flag"].value - s["flag"].baseline) < 0.1


def test_probes_read_low_rank_structure_from_more_features_than_samples() -> None:
    rng = np.random.default_rng(1)
    n, f = 200, 600
    factors = rng.standard_normal((n, 4))
    x = factors @ rng.standard_normal((4, f)) + 0.1 * rng.standard_normal((n, f))
    y = {"y": factors @ np.array([1.0, -2.0, 0.5, 3.0])}
    assert _fit(x, y, _episodes(n), 150)["y"].value > 0.95
    assert abs(_fit(rng.standard_normal((n, f)), y, _episodes(n), 150)["y"].value) < 0.1


def test_missing_values_are_left_out_of_that_target_only() -> None:
    rng = np.random.default_rng(2)
    x = rng.standard_normal((120, 5))
    y = x[:, 0] * 3.0
    y[::4] = np.nan
    s = _fit(x, {"y": y, "z": x[:, 1]}, _episodes(120), 80)
    assert (s["y"].n_train, s["y"].n_test) == (60, 30)
    assert (s["z"].n_train, s["z"].n_test) == (80, 40)
    assert s["y"].value > 0.99


def test_the_row_space_reduction_changes_no_prediction() -> None:
    rng = np.random.default_rng(3)
    x, xt, y = rng.standard_normal((30, 200)), rng.standard_normal((10, 200)), rng.standard_normal(30)
    z, zt = reduce_features(x, xt)
    # 30 centred rows span 29 dimensions.
    assert z.shape == (30, 29) and zt.shape == (10, 29)
    scaler = StandardScaler().fit(x)
    for alpha in (0.1, 10.0):
        full = Ridge(alpha=alpha).fit(scaler.transform(x), y).predict(scaler.transform(xt))
        reduced = Ridge(alpha=alpha).fit(z, y).predict(zt)
        np.testing.assert_allclose(reduced, full, rtol=1e-8, atol=1e-8)


def test_fitting_is_deterministic() -> None:
    rng = np.random.default_rng(4)
    x = rng.standard_normal((90, 120))
    targets = {"y": x[:, :3].sum(axis=1) + rng.standard_normal(90), "flag": x[:, 0] + rng.standard_normal(90) > 0.5}
    first = _fit(x, targets, _episodes(90), 60)
    assert first == _fit(x.copy(), targets, _episodes(90), 60)
    assert first == _fit(x, targets, _episodes(90), 60)


def test_cross_validation_needs_two_training_episodes() -> None:
    x = np.zeros((20, 3))
    with pytest.raises(ValueError, match="two training episodes"):
        _fit(x, {"y": np.arange(20.0)}, np.zeros(20, dtype=np.int64), 10)


def test_episodes_are_never_split() -> None:
    episode = np.repeat(np.arange(12), 7)
    scenario = np.where(episode < 8, "merge", "exit").astype(object)
    test = split_by_episode(episode, scenario, 0.25, seed=0)
    assert not set(episode[test]) & set(episode[~test])
    assert len(set(episode[test & (scenario == "merge")])) == 2
    assert len(set(episode[test & (scenario == "exit")])) == 1
    assert np.array_equal(test, split_by_episode(episode, scenario, 0.25, seed=0))
    assert not np.array_equal(test, split_by_episode(episode, scenario, 0.25, seed=1))


# ---------------------------------------------------------------------------------------
# Seeds, features, config


def test_probe_seeds_are_neither_training_nor_evaluation_seeds() -> None:
    assert EVAL_RESET_SEEDS.stop + MAX_ENVS <= PROBE_RESET_SEEDS.start
    assert TRAIN_RESET_SEEDS.stop + MAX_ENVS <= PROBE_RESET_SEEDS.start
    assert probe_reset_seed(0) == PROBE_RESET_SEEDS.start
    assert probe_reset_seed(1) - probe_reset_seed(0) == MAX_ENVS
    with pytest.raises(ConfigError, match="probe seed"):
        probe_reset_seed(-1)


def _bnn_run(path: Path, input_shape: tuple[int, int, int]) -> tuple[Path, BottleneckNetwork]:
    path.mkdir(parents=True)
    cfg = BottleneckConfig(input_shape=input_shape, latent_dim=8, channels=(4,))
    net = BottleneckNetwork(cfg)
    save_checkpoint(path / "checkpoint.safetensors", net, step=0, epoch=0, config={"model": cfg.model_dump(mode="json")})
    return path, net


def test_features_are_what_the_vfan_is_fed(tmp_path: Path) -> None:
    obs = np.random.default_rng(5).random((6, *SMALL_OBS.shape)).astype(np.float32)
    assert np.array_equal(probe_features("raw", obs), obs.reshape(6, -1))
    run, net = _bnn_run(tmp_path / "bnn", SMALL_OBS.shape[1:])
    latent = probe_features("latent", obs, run)
    with torch.no_grad():
        expected = net.eval().encode(torch.from_numpy(obs)).reshape(6, -1).numpy()
    np.testing.assert_allclose(latent, expected, rtol=1e-6, atol=1e-6)
    # The random encoder: the run's architecture, fixed weights, the caller's stream untouched.
    state = torch.random.get_rng_state()
    rand = probe_features("latent-random", obs, run)
    assert torch.equal(state, torch.random.get_rng_state())
    assert rand.shape == (6, 24) and np.array_equal(rand, probe_features("latent-random", obs, run))
    assert not np.allclose(rand, latent)
    assert probe_features("latent-random", obs).shape == (6, 3 * BottleneckConfig().latent_dim)


def test_feature_kinds_and_bnns_are_checked(tmp_path: Path) -> None:
    obs = np.zeros((2, *SMALL_OBS.shape), dtype=np.float32)
    with pytest.raises(ConfigError, match="needs a trained BNN"):
        probe_features("latent", obs)
    with pytest.raises(ConfigError, match="unknown probe kind"):
        probe_features("end-to-end", obs)
    run, _ = _bnn_run(tmp_path / "bnn", (4, 32, 64))
    with pytest.raises(ConfigError, match="takes observations"):
        probe_features("latent", obs, run)


def test_probe_config_names_its_fields() -> None:
    assert set(ProbeConfig.model_fields["policy"].annotation.__args__) == set(REFERENCE_POLICIES)  # type: ignore[union-attr]
    with pytest.raises(ConfigError, match="scenario"):
        validate(ProbeConfig, {"scenarios": ["nowhere"]})
    with pytest.raises(ConfigError, match="test_fraction"):
        ProbeConfig().replace(test_fraction=1.0)
    with pytest.raises(ConfigError, match="episodes"):
        ProbeConfig().replace(episodes=1)


# ---------------------------------------------------------------------------------------
# End to end


def test_probe_data_is_reproducible_and_shaped_like_the_env() -> None:
    a = collect_probe_data(["merge"], 3, seed=0, observation=SMALL_OBS, envs=2)
    b = collect_probe_data(["merge"], 3, seed=0, observation=SMALL_OBS, envs=2)
    n = a.obs.shape[0]
    assert a.obs.shape == (n, *SMALL_OBS.shape) and a.obs.dtype == np.float32 and n > 0
    assert list(a.targets) == list(TARGETS) and all(v.shape == (n,) for v in a.targets.values())
    assert a.targets["left_free"].dtype == np.bool_
    assert set(a.scenario.tolist()) == {"merge"} and set(a.episode.tolist()) == {0, 1, 2}
    gap = a.targets["gap_ahead"].astype(np.float64)
    assert np.all((gap >= 0) & (gap <= forward_range(SMALL_OBS)))
    assert np.array_equal(a.obs, b.obs) and np.array_equal(a.episode, b.episode)
    for k in TARGETS:
        np.testing.assert_array_equal(a.targets[k], b.targets[k])
    c = collect_probe_data(["merge"], 3, seed=1, observation=SMALL_OBS, envs=2)
    assert c.obs.shape != a.obs.shape or not np.array_equal(c.obs, a.obs)


def test_run_probes_end_to_end() -> None:
    cfg = ProbeConfig(scenarios=("merge",), episodes=4, envs=2, observation=SMALL_OBS)
    out = run_probes(cfg, ["raw", "latent-random"])
    json.dumps(out, allow_nan=False)
    samples = out["samples"]
    assert (samples["train_episodes"], samples["test_episodes"]) == (3, 1)
    for kind in ("raw", "latent-random"):
        assert list(out[kind]) == list(TARGETS)
        for name, score in out[kind].items():
            assert score["metric"] == ("accuracy" if name.endswith("_free") else "r2")
            assert score["n_train"] + score["n_test"] <= samples["train"] + samples["test"]
            if score["metric"] == "accuracy":
                assert 0.0 <= score["value"] <= 1.0
    with pytest.raises(ConfigError, match="needs a trained BNN"):
        run_probes(cfg, ["latent"])


def test_saved_probe_results_are_checked_against_the_shape_run_probes_writes(tmp_path):
    import json

    from latentdrive.config import ConfigError
    from latentdrive.evaluate.probes import read_probe_results

    good = {"raw": {"speed": {"metric": "r2", "value": 0.5, "baseline": None, "penalty": 1.0, "n_train": 3, "n_test": 2}},
            "samples": {"train": 3, "test": 2, "train_episodes": 1, "test_episodes": 1}}
    path = tmp_path / "probes.json"
    path.write_text(json.dumps(good))
    assert read_probe_results(path) == good
    for bad, needle in ((dict(good, samples={"train": "many", "test": 2}), "samples"),
                        (dict(good, raw={"speed": {"metric": "r2"}}), "value"),
                        ([1, 2], "not a probe result")):
        path.write_text(json.dumps(bad))
        with pytest.raises(ConfigError, match=needle) as err:
            read_probe_results(path)
        assert str(path) in str(err.value) and "\n" not in str(err.value)
