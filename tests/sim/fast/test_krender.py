"""The compiled VelocityMap renderer against the reference ``render_frame``."""

from functools import cache

import numpy as np
import pytest
from helpers import examples
from hypothesis import given, settings
from hypothesis import strategies as st

import latentdrive
from latentdrive.config import ObservationConfig
from latentdrive.env import make_env
from latentdrive.observe import draw_noise, render_agents
from latentdrive.scenarios import SCENARIOS, get_spec
from latentdrive.sim.fast import FastBatch

# The dataset stores frames as uint8 over [0, 1]: half a step of 1/255.
QUANTUM = 1.0 / 510
SMALL = {"observation": {"height": 16, "width": 32, "frames": 2}}


@cache
def _batch(name: str) -> FastBatch:
    return FastBatch([get_spec(name)] * 2)


def _draws(batch: FastBatch, ids: list[int], seed: int, cfg: ObservationConfig):
    rng = np.random.default_rng(seed)
    return [draw_noise(rng, batch.specs[i].n_av, batch.scene(i).n_vehicles, cfg.noise) for i in ids]


def _reference(batch, ids, cfg, noise, observing):
    out = np.zeros((len(ids), observing.shape[1], 4, cfg.height, cfg.width), dtype=np.float32)
    for k, i in enumerate(ids):
        scene = batch.scene(i)
        out[k, : scene.n_agents] = render_agents(scene, cfg, None if noise is None else noise[k],
                                                 observing[k, : scene.n_agents])
    return out


@settings(max_examples=examples(25), deadline=None)
@given(
    name=st.sampled_from(SCENARIOS),
    seed=st.integers(0, 2**31),
    steps=st.integers(0, 12),
    noisy=st.booleans(),
    geometry=st.sampled_from([(16, 32, 1.5, 16.0), (32, 64, 1.5, 32.0), (24, 40, 0.75, 5.0), (12, 20, 3.0, 0.0)]),
    loud=st.booleans(),
    route=st.sampled_from([0.0, 0.0, 0.3, 1.0]),
)
def test_compiled_frames_match_the_reference_within_the_dataset_quantum(name, seed, steps, noisy, geometry, loud,
                                                                        route):
    h, w, res, behind = geometry
    noise = {"position_std": 3.0, "heading_std": 0.5, "speed_std": 4.0, "miss_prob": 0.3} if loud else {}
    cfg = ObservationConfig.model_validate({"height": h, "width": w, "resolution": res, "behind": behind,
                                            "noise": noise, "route": route})
    batch = _batch(name)
    batch.reset([seed, seed + 1])
    script = np.random.default_rng(seed)
    for _ in range(steps):
        batch.step(script.integers(0, 5, (2, batch.specs[0].n_av)))
    ids = [1, 0]
    observing = script.random((2, batch.specs[0].n_av)) < 0.7
    draws = _draws(batch, ids, seed, cfg) if noisy else None
    fast = batch.render(ids, cfg, draws, observing)
    ref = _reference(batch, ids, cfg, draws, observing)
    assert fast.dtype == np.float32 and fast.shape == ref.shape
    np.testing.assert_allclose(fast, ref, rtol=0.0, atol=QUANTUM)
    assert not fast[~observing].any()


def test_frames_do_not_depend_on_the_batch_around_them():
    names = [SCENARIOS[k % 5] for k in range(10)]
    big = FastBatch([get_spec(n) for n in names])
    seeds = [50 + k for k in range(10)]
    big.reset(seeds)
    n_av = max(s.n_av for s in big.specs)
    script = np.random.default_rng(4).integers(0, 5, (5, 10, n_av))
    for actions in script:
        big.advance(actions)
    cfg = ObservationConfig()
    observing = np.ones((10, n_av), dtype=bool)
    draws = _draws(big, list(range(10)), 9, cfg)
    frames = big.render(range(10), cfg, draws, observing)
    for k in (0, 3, 7):
        alone = FastBatch([get_spec(names[k])])
        alone.reset([seeds[k]])
        for actions in script:
            alone.advance(actions[k : k + 1])
        mine = alone.render([0], cfg, [draws[k]], observing[k : k + 1, : alone.specs[0].n_av])
        np.testing.assert_array_equal(mine[0], frames[k, : alone.specs[0].n_av])
    # A subset renders exactly the rows of the whole.
    np.testing.assert_array_equal(big.render([7, 2], cfg, [draws[7], draws[2]], observing[[7, 2]]), frames[[7, 2]])


def test_same_seed_same_observations_in_the_vector_env():
    def run(seed):
        vec = latentdrive.make_vec(["merge", "intersection"], 4, backend="fast", **SMALL)
        out = [vec.reset(seed=seed)[0]]
        kept = out[0].copy()
        script = np.random.default_rng(0)
        for _ in range(6):
            out.append(vec.step(script.integers(0, 5, (4, vec.n_av)))[0])
        # Observations handed out are the caller's: later steps leave them alone.
        np.testing.assert_array_equal(out[0], kept)
        return np.stack(out)

    a, b, c = run(3), run(3), run(4)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


@pytest.mark.parametrize("name", ["intersection", "exit"])
def test_vector_env_observations_match_the_reference_env(name):
    """The compiled path of make_vec and the reference path of make_env draw the same
    noise from each episode's stream and keep done AVs' stacks alike, resets included."""
    vec = latentdrive.make_vec(name, 3, backend="fast", clean_observation=True, **SMALL)
    singles = [make_env(name, backend="fast", clean_observation=True, **SMALL) for _ in range(3)]
    obs, info = vec.reset(seed=11)
    for i, env in enumerate(singles):
        o, inf = env.reset(seed=11 + i)
        np.testing.assert_allclose(obs[i], o, rtol=0.0, atol=QUANTUM)
        np.testing.assert_allclose(info["clean_observation"][i], inf["clean_observation"], rtol=0.0, atol=QUANTUM)
    script = np.random.default_rng(2)
    ended = 0
    for _ in range(25):
        actions = script.integers(0, 5, (3, vec.n_av))
        obs, _, _, _, info = vec.step(actions)
        for i, env in enumerate(singles):
            o, _, te, tr, inf = env.step(actions[i])
            mine = info["final_obs"][i] if te or tr else obs[i]
            np.testing.assert_allclose(mine, o, rtol=0.0, atol=QUANTUM)
            if te or tr:
                ended += 1
                o, inf = env.reset()
                np.testing.assert_allclose(obs[i], o, rtol=0.0, atol=QUANTUM)
    assert ended >= 1


def test_render_refuses_mismatched_arguments():
    batch = _batch("merge")
    batch.reset([1, 2])
    cfg = ObservationConfig()
    n_av = batch.specs[0].n_av
    with pytest.raises(ValueError, match="observing must be"):
        batch.render([0, 1], cfg, None, np.ones((2, n_av + 1), dtype=bool))
    wrong = [draw_noise(np.random.default_rng(0), n_av, 3, cfg.noise)] * 2
    with pytest.raises(ValueError, match="noise draws are"):
        batch.render([0, 1], cfg, wrong, np.ones((2, n_av), dtype=bool))
    with pytest.raises(ValueError, match="noise draws for 1"):
        batch.render([0, 1], cfg, wrong[:1], np.ones((2, n_av), dtype=bool))
