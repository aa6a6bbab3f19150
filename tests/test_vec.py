from typing import Any

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import latentdrive
from latentdrive.config import ConfigError
from latentdrive.env import make_env
from latentdrive.scenarios import SCENARIOS

SMALL: dict[str, Any] = {"observation": {"height": 16, "width": 32, "frames": 2}}


def _run(vec, steps, seed=0):
    """Observations, rewards and done flags of a scripted rollout (auto-reset included)."""
    script = np.random.default_rng(seed)
    obs, _ = vec.reset(seed=100)
    out = [obs]
    for _ in range(steps):
        actions = script.integers(0, 5, size=(32, vec.n_av))[: vec.num_envs]
        obs, rew, term, trunc, _ = vec.step(actions)
        out.append((obs, rew, term, trunc))
    return out


def test_env_i_is_the_same_alone_or_in_a_mixed_batch():
    names = list(SCENARIOS) * 2
    batch = _run(latentdrive.make_vec(names, len(names), backend="fast", **SMALL), 12)
    for i in (0, 3, 7):
        # Alone: environment i's scenario, seeded as it is in the batch (100 + i), and the
        # batch's actions for row i.
        alone_vec = latentdrive.make_vec(names[i], 1, backend="fast", **SMALL)
        script = np.random.default_rng(0)
        obs, _ = alone_vec.reset(seed=[100 + i])
        assert np.array_equal(obs[0], batch[0][i])
        for t in range(12):
            actions = script.integers(0, 5, size=(32, alone_vec.n_av))[i:i + 1]
            obs, rew, term, trunc, _ = alone_vec.step(actions)
            b_obs, b_rew, b_term, b_trunc = batch[t + 1]
            assert np.array_equal(obs[0], b_obs[i]) and rew[0] == b_rew[i]
            assert term[0] == b_term[i] and trunc[0] == b_trunc[i]


def test_vector_env_matches_single_envs_and_auto_resets():
    vec = latentdrive.make_vec(["merge", "exit"], 2, backend="highway", **SMALL)
    singles = [make_env("merge", **SMALL), make_env("exit", **SMALL)]
    obs, _ = vec.reset(seed=7)
    for i, env in enumerate(singles):
        o, _ = env.reset(seed=7 + i)
        assert np.array_equal(o, obs[i])
    script = np.random.default_rng(3)
    resets = 0
    for _ in range(20):
        actions = script.integers(0, 5, size=(2, 2))
        obs, rew, term, trunc, info = vec.step(actions)
        for i, env in enumerate(singles):
            o, r, te, tr, inf = env.step(actions[i])
            assert r == rew[i] and te == term[i] and tr == trunc[i]
            # info["agents"] describes the transition just taken, like rew/term/trunc.
            np.testing.assert_array_equal(inf["agents"].reward, info["agents"].reward[i])
            np.testing.assert_array_equal(inf["agents"].truncated, info["agents"].truncated[i])
            if te or tr:
                resets += 1
                assert info["_final_obs"][i] and info["_final_info"][i]
                np.testing.assert_array_equal(info["final_obs"][i], o)
                # gymnasium 1.x: final_info is a dict of arrays with per-key masks.
                fin = info["final_info"]
                assert fin["_crashed"][i] and fin["episode_seed"][i] == inf["episode_seed"]
                np.testing.assert_array_equal(fin["crashed"][i], inf["crashed"])
                o, inf = env.reset()  # the next episode seed comes from the env's own stream
                # ... and the rest of info is the new episode's, not a mix of both.
                assert info["episode_seed"][i] == inf["episode_seed"]
                np.testing.assert_array_equal(info["agent_rewards"][i], [0.0, 0.0])
            else:
                assert not info["_final_info"][i]
            np.testing.assert_array_equal(o, obs[i])
    assert resets >= 2


@pytest.mark.parametrize("name", SCENARIOS)
def test_fast_backend_env_passes_checks_and_matches_reference(name):
    fast = make_env(name, backend="fast", **SMALL)
    check_env(fast, skip_render_check=True)
    ref = make_env(name, **SMALL)
    a, _ = fast.reset(seed=2)
    b, _ = ref.reset(seed=2)
    assert np.array_equal(a, b)
    script = np.random.default_rng(0)
    for _ in range(6):
        act = script.integers(0, 5, 2)
        a, ra, ta, _, ia = fast.step(act)
        b, rb, tb, _, ib = ref.step(act)
        np.testing.assert_allclose(ia["scene"].position, ib["scene"].position, atol=1e-6)
        assert ra == pytest.approx(rb, abs=1e-9) and ta == tb
        if ta:
            break


def test_mixed_batch_needs_one_agent_count():
    with pytest.raises(ConfigError, match="n_av"):
        latentdrive.make_vec([latentdrive.make_env("merge", n_av=3).spec_, "exit"], 2, backend="fast")
    with pytest.raises(ConfigError, match="num_envs"):
        latentdrive.make_vec("merge", 0)
    with pytest.raises(ConfigError, match="backend"):
        latentdrive.make_vec("merge", 2, backend="warp")


def test_bad_vector_actions_are_rejected():
    vec = latentdrive.make_vec("merge", 3, **SMALL)
    vec.reset(seed=0)
    with pytest.raises(ValueError, match="actions"):
        vec.step(np.zeros((2, 2), dtype=int))


def test_seedless_reset_continues_the_seeded_sequence():
    """Like a single env: reset(seed=s) fixes every later episode, reset() included."""
    a = latentdrive.make_vec("merge", 2, **SMALL)
    b = latentdrive.make_vec("merge", 2, **SMALL)
    a.reset(seed=5)
    b.reset(seed=5)
    _, ia = a.reset()
    _, ib = b.reset()
    np.testing.assert_array_equal(ia["episode_seed"], ib["episode_seed"])
    single = make_env("merge", backend="fast", **SMALL)
    single.reset(seed=5)
    _, i1 = single.reset()
    assert i1["episode_seed"] == ia["episode_seed"][0]


def test_vector_reset_info_marks_every_agent_active():
    vec = latentdrive.make_vec("merge", 3, **SMALL)
    _, info = vec.reset(seed=0)
    assert info["agents"].active.shape == (3, 2) and info["agents"].active.all()
    assert not info["agents"].acting.any()
    _, _, _, _, info = vec.step(np.ones((3, 2), dtype=int))
    assert info["agents"].acting.all()
