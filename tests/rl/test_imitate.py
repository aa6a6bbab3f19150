"""DAgger, the imitation reference: its schedule, labels, update and training runs."""

import numpy as np
import pytest
import torch
from safetensors.numpy import load_file

from latentdrive.config import ConfigError, validate
from latentdrive.evaluate.planner import planner_policy
from latentdrive.evaluate.policies import reference_policy
from latentdrive.rl.config import PolicyTrainConfig
from latentdrive.rl.imitate import (
    ExpertLabels,
    ImitationConfig,
    dagger_policy,
    expert_share,
    imitation_update,
    label_weights,
)
from latentdrive.rl.policy import CHECKPOINT
from latentdrive.rl.replay import Batch
from latentdrive.rl.train import train_policy
from latentdrive.rollout import PolicyInput, rollout
from latentdrive.seeds import train_reset_seed
from latentdrive.vec import make_vec

#: A shallow planner: the tests check the machinery, not the expert's quality.
FAST_EXPERT = {"planner": {"depth": 3, "rounds": 1}}


def _quiet():
    return {"progress": False, "say": lambda _line: None}


def test_the_expert_share_falls_linearly_then_stays():
    cfg = ImitationConfig(beta_start=1.0, beta_end=0.2, beta_fraction=0.5)
    assert expert_share(cfg, 0, 1000) == 1.0
    assert expert_share(cfg, 250, 1000) == pytest.approx(0.6)
    assert expert_share(cfg, 500, 1000) == pytest.approx(0.2)
    assert expert_share(cfg, 900, 1000) == pytest.approx(0.2)


def test_beta_end_above_beta_start_is_refused():
    with pytest.raises(ConfigError, match="beta_end"):
        validate(ImitationConfig, {"beta_start": 0.1, "beta_end": 0.5})


def test_label_weights_are_inverse_frequencies_with_mean_one():
    labels = np.array([0, 0, 0, 1], dtype=np.int64)
    w = label_weights(labels, 5)
    np.testing.assert_allclose(w, [4 / 6, 2.0, 0.0, 0.0, 0.0], rtol=1e-6)
    assert w[labels].mean() == pytest.approx(1.0)


def _inp(n_env: int, n_av: int) -> PolicyInput:
    obs = np.zeros((n_env, n_av, 4, 1, 2, 2), dtype=np.float32)
    return PolicyInput(obs, np.empty(n_env, dtype=object), np.ones((n_env, n_av), dtype=bool),
                       np.array(["merge"] * n_env, dtype=object))


@pytest.mark.parametrize("beta, expect", [(1.0, "expert"), (0.0, "own")])
def test_the_behaviour_policy_mixes_and_always_records_the_expert(beta, expect):
    expert_actions = np.array([[3, 4], [0, 2]], dtype=np.int64)
    own_actions = np.array([[1, 1], [1, 1]], dtype=np.int64)
    labels = ExpertLabels()
    policy = dagger_policy(lambda _inp: expert_actions, lambda _inp: own_actions, np.random.default_rng(0),
                           lambda: beta, labels)
    acted = policy(_inp(2, 2))
    np.testing.assert_array_equal(acted, expert_actions if expect == "expert" else own_actions)
    np.testing.assert_array_equal(labels.latest, expert_actions)


def test_a_half_share_plays_each_about_half_the_time():
    labels = ExpertLabels()
    policy = dagger_policy(lambda _inp: np.zeros((50, 4), dtype=np.int64), lambda _inp: np.ones((50, 4), dtype=np.int64),
                           np.random.default_rng(1), lambda: 0.5, labels)
    share = np.mean([(policy(_inp(50, 4)) == 0).mean() for _ in range(20)])
    assert 0.45 < share < 0.55


def test_the_update_fits_labels_a_tiny_network_can_separate():
    torch.manual_seed(0)
    x = torch.randn(64, 6)
    y = (x[:, 0] > 0).long() * 3  # actions 0 and 3
    net = torch.nn.Sequential(torch.nn.Linear(6, 16), torch.nn.ReLU(), torch.nn.Linear(16, 5))
    opt = torch.optim.Adam(net.parameters(), lr=1e-2)
    batch = Batch(x, y, torch.zeros(64), x, torch.ones(64))
    weights = torch.from_numpy(label_weights(y.numpy(), 5))
    first = imitation_update(net, opt, batch, weights, grad_clip=10.0)
    for _ in range(200):
        last = imitation_update(net, opt, batch, weights, grad_clip=10.0)
    assert last < 0.1 * first
    assert (net(x).argmax(1) == y).float().mean() == 1.0


def test_dagger_needs_the_fast_backend():
    with pytest.raises(ConfigError, match="learner 'dagger' needs backend 'fast'"):
        validate(PolicyTrainConfig, {"mode": "raw", "learner": "dagger", "backend": "highway"})


@pytest.mark.parametrize("expert", ["plan", "rule"])
def test_with_the_expert_always_driving_the_labels_are_its_own_actions(tmp_path, tiny, expert):
    cfg = tiny(mode="raw", learner="dagger", steps=120, segment=200,
               imitation={**FAST_EXPERT, "expert": expert, "beta_start": 1.0, "beta_end": 1.0}, dqn={"learning_starts": 40})
    train_policy(cfg, tmp_path / "run", **_quiet())
    stored = load_file(str(next((tmp_path / "run").glob("replay-*.safetensors"))))["replay/action"]
    # The same episodes driven by the expert alone: every acting AV's action, in the order
    # the run stores its transitions (row-major over environments and AVs, step by step).
    vec = make_vec(cfg.scenario_specs(), cfg.envs, backend="fast", observation=cfg.observation.model_dump(),
                   reward=cfg.reward.model_dump())
    taken: list[np.ndarray] = []
    alone = planner_policy(cfg.imitation.planner, cfg.reward) if expert == "plan" else reference_policy("rule")()
    for rec in rollout(vec, alone, seed=train_reset_seed(cfg.seed, 0)):
        taken.append(rec.actions[rec.agents.acting])
        if sum(len(t) for t in taken) >= len(stored):
            break
    vec.close()
    np.testing.assert_array_equal(stored, np.concatenate(taken)[:len(stored)])
    assert len(set(stored.tolist())) > 1  # the expert does more than one thing


@pytest.mark.parametrize(("mode", "expert"), [("raw", "plan"), ("latent-random", "plan"), ("raw", "rule")])
def test_with_the_network_driving_the_labels_are_still_the_experts(tmp_path, tiny, monkeypatch, mode, expert):
    import latentdrive.rl.imitate as imitate_module

    logged: list[np.ndarray] = []

    def logging(make):
        def policy(inp):
            out = make(inp)
            logged.append(out[inp.active])
            return out

        return policy

    if expert == "plan":
        monkeypatch.setattr(imitate_module, "planner_policy", lambda cfg, reward: logging(planner_policy(cfg, reward)))
    else:
        monkeypatch.setattr(imitate_module, "reference_policy", lambda name: lambda: logging(reference_policy(name)()))
    cfg = tiny(mode=mode, learner="dagger", steps=80, segment=200, dqn={"learning_starts": 40},
               imitation={**FAST_EXPERT, "expert": expert, "beta_start": 0.0, "beta_end": 0.0})
    train_policy(cfg, tmp_path / "run", **_quiet())
    stored = load_file(str(next((tmp_path / "run").glob("replay-*.safetensors"))))["replay/action"]
    np.testing.assert_array_equal(stored, np.concatenate(logged)[:len(stored)])


def test_an_unknown_expert_is_refused():
    with pytest.raises(ConfigError, match=r"imitation\.expert"):
        validate(PolicyTrainConfig, {"mode": "raw", "learner": "dagger", "backend": "fast", "imitation": {"expert": "oracle"}})


def test_dagger_refuses_settings_it_would_ignore():
    for dqn in ({"n_step": 3}, {"prioritized": True}):
        with pytest.raises(ConfigError, match=r"dqn\.n_step must be 1 and dqn\.prioritized false"):
            validate(PolicyTrainConfig, {"mode": "raw", "learner": "dagger", "dqn": dqn})
    for ignored in ({"explore_rule": 0.5}, {"augment_shift": 2}):
        with pytest.raises(ConfigError, match=r"dqn\.explore_rule and dqn\.augment_shift must be 0"):
            validate(PolicyTrainConfig, {"mode": "raw", "learner": "dagger", "dqn": ignored})


def test_a_dagger_run_is_deterministic_and_resumes_bit_for_bit(tmp_path, tiny):
    # A constant share, so that the first half's schedule does not depend on the budget.
    common = {"mode": "raw", "learner": "dagger", "segment": 80, "dqn": {"learning_starts": 40},
              "imitation": {**FAST_EXPERT, "beta_start": 0.5, "beta_end": 0.5}}
    cfg = tiny(steps=160, **common)
    whole = train_policy(cfg, tmp_path / "whole", **_quiet())
    again = train_policy(cfg, tmp_path / "again", **_quiet())
    assert again["evaluation"] == whole["evaluation"]
    half = tiny(steps=80, **common)
    train_policy(half, tmp_path / "resumed", **_quiet())
    resumed = train_policy(cfg, tmp_path / "resumed", resume=True, **_quiet())
    a = load_file(str(tmp_path / "whole" / CHECKPOINT))
    b = load_file(str(tmp_path / "resumed" / CHECKPOINT))
    model = [k for k in a if k.startswith("model/")]
    assert model and all(np.array_equal(a[k], b[k]) for k in model)
    assert whole["updates"] == resumed["updates"] > 0
    assert whole["evaluation"] == resumed["evaluation"]


def test_a_dagger_run_evaluates_like_any_policy_run(tmp_path, tiny):
    from latentdrive.rl.policy import load_policy_network

    cfg = tiny(mode="raw", learner="dagger", steps=80, segment=80, dqn={"learning_starts": 40}, imitation=FAST_EXPERT)
    train_policy(cfg, tmp_path / "run", **_quiet())
    net, loaded = load_policy_network(tmp_path / "run")
    assert isinstance(loaded, PolicyTrainConfig) and loaded.learner == "dagger"
    assert net(torch.zeros(2, *cfg.observation.shape)).shape == (2, 5)
