import numpy as np
import pytest

from latentdrive.scenarios import SCENARIOS, get_spec
from latentdrive.scene import Kind, Scene
from latentdrive.sim.fast import FastBackend, FastBatch
from latentdrive.sim.roads import layout_raster


def _script(seed, n_av, steps):
    return np.random.default_rng([seed, 9]).integers(0, 5, (steps, n_av))


def test_same_seed_same_episode():
    spec = get_spec("exit")
    a, b = FastBackend(spec), FastBackend(spec)
    assert a.reset(3) == b.reset(3)
    for actions in _script(3, spec.n_av, 5):
        assert a.step(actions) == b.step(actions)
    assert not np.array_equal(a.reset(3).position, a.reset(4).position)


def test_env_is_the_same_alone_or_in_a_mixed_batch_of_64():
    specs = [get_spec(SCENARIOS[k % 5]) for k in range(64)]
    seeds = [1000 + k for k in range(64)]
    batch = FastBatch(specs)
    batch.reset(seeds)
    scripts = [_script(s, spec.n_av, 6) for s, spec in zip(seeds, specs, strict=True)]
    trajectories: list[list[Scene]] = [[] for _ in specs]
    for t in range(6):
        for k, scene in enumerate(batch.step([script[t] for script in scripts])):
            trajectories[k].append(scene)
    for k in (0, 1, 2, 3, 4, 37, 63):
        alone = FastBackend(specs[k])
        alone.reset(seeds[k])
        for t in range(6):
            assert alone.step(scripts[k][t]) == trajectories[k][t], (k, t)


def test_resetting_some_envs_leaves_the_others_untouched():
    specs = [get_spec("merge"), get_spec("roundabout"), get_spec("merge")]
    batch = FastBatch(specs)
    batch.reset([0, 1, 2])
    before = batch.step(np.ones((3, 2), dtype=np.int64))
    fresh = batch.reset([5], env_ids=[2])
    assert fresh[0] == FastBackend(specs[2]).reset(5)
    after = batch.scenes()
    assert after[0] == before[0] and after[1] == before[1]
    assert after[2] == fresh[0] and after[2].time == 0.0


def test_scenes_are_snapshots():
    batch = FastBatch([get_spec("highway")])
    first = batch.reset([0])[0]
    kept = first.position.copy()
    batch.step([np.array([3, 3])])
    assert np.array_equal(first.position, kept)


def test_scene_layout_matches_the_spec():
    spec = get_spec("intersection", n_av=3)
    scene = FastBatch([spec, get_spec("merge")]).reset([0, 0])[0]
    assert scene.n_vehicles == spec.n_av + spec.n_hv and scene.n_agents == 3
    assert np.array_equal(scene.agents, [0, 1, 2])
    assert np.all(scene.kind[:3] == Kind.AV) and np.all(scene.kind[3:] == Kind.HV)
    assert scene.mask.all() and not scene.crashed.any()
    assert scene.road is layout_raster("intersection", 3)
    assert np.all(scene.road.sample(scene.position) == 1)


def test_actions_are_checked():
    batch = FastBatch([get_spec("merge"), get_spec("exit", n_av=3)])
    with pytest.raises(RuntimeError, match="reset"):
        batch.step([np.ones(2, np.int64), np.ones(3, np.int64)])
    batch.reset([0, 1])
    with pytest.raises(ValueError, match="needs 3 actions"):
        batch.step([np.ones(2, np.int64), np.ones(2, np.int64)])
    with pytest.raises(ValueError, match=r"\[0, 5\)"):
        batch.step(np.full((2, 3), 5))
    scenes = batch.step(np.array([[1, 1, 9], [1, 1, 1]]))  # entries past an env's AVs are ignored
    assert scenes[0].time == scenes[1].time == 1.0


def test_many_vehicles_run():
    # Hundreds of vehicles on one road: neighbours and collisions do not test all pairs.
    spec = get_spec("highway", n_hv=200, min_gap=15.0, hv_spawn=[{
        "edge": ["0", "1"], "lanes": [0, 1, 2], "longitudinal": {"mean": 2000, "std": 800, "clip": 1900},
        "speed": {"mean": 24, "std": 1.5, "clip": 3}}])
    batch = FastBatch([spec, spec])
    batch.reset([0, 1])
    scenes = batch.step(np.ones((2, spec.n_av), dtype=np.int64))
    assert scenes[0].n_vehicles == 202 and np.isfinite(scenes[1].position).all()
