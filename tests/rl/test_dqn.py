"""Double-DQN math with literal cases, and a tiny task the learner must solve."""

import numpy as np
import pytest
import torch
from torch import nn

from latentdrive.rl.dqn import DQNConfig, epsilon, td_targets, update
from latentdrive.rl.replay import LatentStore, Replay


def test_td_targets_bootstrap_only_where_the_agent_did_not_terminate():
    reward = torch.tensor([1.0, 1.0, 0.5])
    bootstrap = torch.tensor([0.0, 1.0, 1.0])  # terminated; cut off; driving on
    q_online = torch.tensor([[0.0, 9.0], [0.0, 9.0], [5.0, 1.0]])
    q_target = torch.tensor([[3.0, 2.0], [3.0, 2.0], [4.0, 7.0]])
    # Double DQN: the online net picks (1, 1, 0), the target net values them (2, 2, 4).
    y = td_targets(reward, bootstrap, q_online, q_target, gamma=0.5, double=True)
    torch.testing.assert_close(y, torch.tensor([1.0, 1.0 + 0.5 * 2.0, 0.5 + 0.5 * 4.0]))
    # Plain DQN takes the target net's own max (3, 3, 7).
    y = td_targets(reward, bootstrap, q_online, q_target, gamma=0.5, double=False)
    torch.testing.assert_close(y, torch.tensor([1.0, 1.0 + 0.5 * 3.0, 0.5 + 0.5 * 7.0]))


def test_epsilon_decays_linearly_then_stays():
    cfg = DQNConfig(eps_start=1.0, eps_end=0.1, eps_fraction=0.5)
    assert epsilon(cfg, 0, 1000) == 1.0
    assert epsilon(cfg, 250, 1000) == pytest.approx(0.55)
    assert epsilon(cfg, 500, 1000) == pytest.approx(0.1)
    assert epsilon(cfg, 900, 1000) == pytest.approx(0.1)


def test_dqn_learns_a_deterministic_chain():
    """A 6-state chain: action 1 moves right, action 0 left; reaching the end pays 1 and
    terminates. Greedy actions must all point right and Q must approach γ^distance."""
    n, gamma = 6, 0.9
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # a tiny net: more threads only add overhead
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    net = nn.Sequential(nn.Linear(n, 64), nn.ReLU(), nn.Linear(64, 2))
    target = nn.Sequential(nn.Linear(n, 64), nn.ReLU(), nn.Linear(64, 2))
    target.load_state_dict(net.state_dict())
    cfg = DQNConfig(gamma=gamma, lr=3e-3, batch_size=64, target_update=25)
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr)
    eye = np.eye(n, dtype=np.float32)
    replay = Replay(5000, LatentStore(10_000, (n,)))
    for s in range(n - 1):  # every transition of the chain, as exploration would find them
        for a in (0, 1):
            s2 = min(s + 1, n - 1) if a == 1 else max(s - 1, 0)
            ids = replay.store.add(eye[[s, s2]], np.array([-1, -1]))
            replay.add(ids[:1], np.array([a]), np.array([float(s2 == n - 1)]), ids[1:], np.array([s2 == n - 1]))
    try:
        for step in range(600):
            update(net, target, opt, replay.sample(rng, cfg.batch_size), cfg)
            if (step + 1) % cfg.target_update == 0:
                target.load_state_dict(net.state_dict())
    finally:
        torch.set_num_threads(threads)
    q = net(torch.from_numpy(eye[: n - 1])).detach()
    assert (q.argmax(dim=1) == 1).all()
    expected = torch.tensor([gamma ** (n - 2 - s) for s in range(n - 1)])
    torch.testing.assert_close(q[:, 1], expected, atol=0.05, rtol=0.0)


def test_the_replay_ratio_is_an_exact_fraction_and_may_exceed_one():
    from latentdrive.rl.dqn import updates_owed

    assert [updates_owed(DQNConfig(learning_starts=10), t) for t in (0, 10, 17, 18, 26)] == [0, 0, 0, 1, 2]
    two = DQNConfig(learning_starts=0, updates_per_transition=2)
    assert updates_owed(two, 5) == 10
    third = DQNConfig(learning_starts=0, updates_per_transition=1 / 3)
    # Counted as 1/3 exactly, not as the float 0.333...: every 3rd transition, never one early or late.
    assert [updates_owed(third, t) for t in range(3, 3001, 3)] == list(range(1, 1001))
    assert updates_owed(third, 2999) == 999


def test_older_configs_name_the_ratio_train_every():
    from latentdrive.config import ConfigError, validate

    assert validate(DQNConfig, {"train_every": 8}).updates_per_transition == 0.125
    assert validate(DQNConfig, {"train_every": 3}).updates_per_transition == pytest.approx(1 / 3)
    with pytest.raises(ConfigError, match="not both"):
        validate(DQNConfig, {"train_every": 2, "updates_per_transition": 0.5})
    with pytest.raises(ConfigError, match="train_every"):
        validate(DQNConfig, {"train_every": 0})
    with pytest.raises(ConfigError, match="updates_per_transition"):
        validate(DQNConfig, {"updates_per_transition": 0.1234567})
    with pytest.raises(ConfigError, match="updates_per_transition"):
        validate(DQNConfig, {"updates_per_transition": 0})


def test_soft_updates_move_the_target_tau_of_the_way_and_leave_frozen_parameters():
    from latentdrive.rl.dqn import soft_update

    online, target = nn.Linear(2, 2), nn.Linear(2, 2)
    frozen_on, frozen_tg = nn.Linear(2, 1).requires_grad_(False), nn.Linear(2, 1).requires_grad_(False)
    a, b = nn.Sequential(online, frozen_on), nn.Sequential(target, frozen_tg)
    before = {k: v.clone() for k, v in b.state_dict().items()}
    soft_update(b, a, 0.25)
    torch.testing.assert_close(target.weight, before["0.weight"] + 0.25 * (online.weight - before["0.weight"]))
    assert torch.equal(frozen_tg.weight, before["1.weight"])


def test_importance_weights_scale_each_samples_loss():
    from latentdrive.rl.replay import Batch

    torch.manual_seed(0)
    net = nn.Linear(3, 2)
    target = nn.Linear(3, 2)
    obs = torch.rand(4, 3)
    base = Batch(obs, torch.tensor([0, 1, 0, 1]), torch.rand(4), torch.rand(4, 3), torch.ones(4))
    cfg = DQNConfig()
    losses = []
    for weight in (None, torch.tensor([1.0, 0.0, 0.0, 0.0])):
        opt = torch.optim.SGD(net.parameters(), lr=0.0)
        losses.append(update(net, target, opt, base._replace(weight=weight), cfg))
    plain, weighted = losses
    per_sample = torch.nn.functional.huber_loss(
        net(obs).gather(1, base.action[:, None]).squeeze(1),
        td_targets(base.reward, base.bootstrap, net(base.next_obs), target(base.next_obs), cfg.gamma, True),
        reduction="none").detach()
    assert plain.loss == pytest.approx(float(per_sample.mean()), rel=1e-5)
    assert weighted.loss == pytest.approx(float(per_sample[0] / 4), rel=1e-5)
    assert weighted.td_error.shape == (4,) and (weighted.td_error >= 0).all()


def test_the_target_moves_by_polyak_steps_or_hard_copies_every_target_update():
    from latentdrive.rl.dqn import target_step

    online, target = nn.Linear(1, 1, bias=False), nn.Linear(1, 1, bias=False)
    with torch.no_grad():
        online.weight.fill_(1.0)
        target.weight.fill_(0.0)
    hard = DQNConfig(target_update=3)
    target_step(target, online, hard, 2)
    assert float(target.weight) == 0.0  # not yet due
    target_step(target, online, hard, 3)
    assert float(target.weight) == 1.0
    with torch.no_grad():
        target.weight.fill_(0.0)
    target_step(target, online, DQNConfig(tau=0.25), 1)
    assert float(target.weight) == pytest.approx(0.25)
