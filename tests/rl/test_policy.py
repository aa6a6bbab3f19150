"""Acting while training: ε-greedy, and exploration guided by the rule driver (dqn.explore_rule)."""

import numpy as np
import pytest
import torch
from safetensors.numpy import load_file

from latentdrive.actions import N_ACTIONS
from latentdrive.config import ConfigError, validate
from latentdrive.evaluate.policies import reference_policy
from latentdrive.rl.config import PolicyTrainConfig
from latentdrive.rl.policy import FeatureCache, build_network, epsilon_greedy, greedy_actions
from latentdrive.rl.train import train_policy
from latentdrive.rollout import PolicyInput, rollout
from latentdrive.seeds import train_reset_seed
from latentdrive.vec import make_vec

N_ENV, N_AV = 40, 2


@pytest.fixture
def acting(tiny):
    cfg = tiny(mode="raw")
    net = build_network(cfg, None)
    obs = np.random.default_rng(0).random((N_ENV, N_AV, 4, 2, 16, 32), dtype=np.float32)
    inp = PolicyInput(obs, np.empty(N_ENV, dtype=object), np.ones((N_ENV, N_AV), dtype=bool),
                      np.array(["intersection"] * N_ENV, dtype=object))
    cache = FeatureCache(net, torch.device("cpu"))
    return net, cache, inp, greedy_actions(net, cache, inp)


GUIDE = np.arange(N_ENV * N_AV).reshape(N_ENV, N_AV) % N_ACTIONS


@pytest.mark.parametrize("eps, share, expect", [(1.0, 1.0, "guide"), (0.0, 1.0, "greedy"), (0.0, 0.0, "greedy")])
def test_exploration_plays_the_guide_only_when_it_explores(acting, eps, share, expect):
    net, cache, inp, greedy = acting
    policy = epsilon_greedy(net, cache, np.random.default_rng(0), lambda: eps, lambda _inp: GUIDE, share)
    np.testing.assert_array_equal(policy(inp), GUIDE if expect == "guide" else greedy)


def test_the_guide_is_not_asked_on_a_step_where_no_agent_explores(acting):
    net, cache, inp, greedy = acting
    calls = []

    def guide(_inp):
        calls.append(1)
        return GUIDE

    eps = iter([0.0, 1.0, 0.0])
    policy = epsilon_greedy(net, cache, np.random.default_rng(0), lambda: next(eps), guide, 1.0)
    np.testing.assert_array_equal(policy(inp), greedy)
    np.testing.assert_array_equal(policy(inp), GUIDE)
    np.testing.assert_array_equal(policy(inp), greedy)
    assert len(calls) == 1


def test_a_half_share_guides_about_half_the_exploratory_actions(acting):
    net, cache, inp, _ = acting
    # A guide that plays an action uniform exploration plays a fifth of the time.
    policy = epsilon_greedy(net, cache, np.random.default_rng(1), lambda: 1.0, lambda _inp: np.zeros((N_ENV, N_AV), int), 0.5)
    share = np.mean([(policy(inp) == 0).mean() for _ in range(30)])
    assert 0.5 + 0.5 / N_ACTIONS - 0.05 < share < 0.5 + 0.5 / N_ACTIONS + 0.05


def test_without_a_guide_the_random_stream_is_the_plain_epsilon_greedy_one(acting):
    """Regression: runs configured before the option must keep their actions (and resume)."""
    net, cache, inp, greedy = acting
    policy = epsilon_greedy(net, cache, np.random.default_rng(2), lambda: 0.5)
    rng = np.random.default_rng(2)
    for _ in range(3):
        explore = rng.random(greedy.shape) < 0.5
        random = rng.integers(0, N_ACTIONS, size=greedy.shape)
        np.testing.assert_array_equal(policy(inp), np.where(explore, random, greedy))


def test_a_run_exploring_with_the_rule_driver_alone_stores_its_actions(tmp_path, tiny):
    cfg = tiny(mode="raw", steps=120, segment=200,
               dqn={"learning_starts": 40, "eps_start": 1.0, "eps_end": 1.0, "explore_rule": 1.0})
    train_policy(cfg, tmp_path / "run", progress=False, say=lambda _line: None)
    stored = load_file(str(next((tmp_path / "run").glob("replay-*.safetensors"))))["replay/action"]
    vec = make_vec(cfg.scenario_specs(), cfg.envs, backend="fast", observation=cfg.observation.model_dump(),
                   reward=cfg.reward.model_dump())
    taken: list[np.ndarray] = []
    for rec in rollout(vec, reference_policy("rule")(), seed=train_reset_seed(cfg.seed, 0)):
        taken.append(rec.actions[rec.agents.acting])
        if sum(len(t) for t in taken) >= len(stored):
            break
    vec.close()
    np.testing.assert_array_equal(stored, np.concatenate(taken)[:len(stored)])
    assert len(set(stored.tolist())) > 1


def test_an_out_of_range_share_is_refused():
    with pytest.raises(ConfigError, match="explore_rule"):
        validate(PolicyTrainConfig, {"mode": "raw", "dqn": {"explore_rule": 1.5}})
