"""The auxiliary loss (dqn.aux_scale): what it stores, what it moves, and when it is refused."""

import copy
import runpy
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from latentdrive.config import ConfigError, ObservationConfig
from latentdrive.models.vfan import QNetwork, VFANConfig
from latentdrive.observe.state import view_target_size
from latentdrive.rl.auxiliary import (
    FIELDS,
    AuxLearning,
    aux_head,
    aux_step,
    field_fit,
    gradient_share,
    scene_targets,
)
from latentdrive.rl.dqn import DQNConfig, td_targets, update, updates_owed
from latentdrive.rl.learner import Learner
from latentdrive.rl.policy import build_network, load_policy_network
from latentdrive.rl.replay import Batch
from latentdrive.rl.train import train_policy
from latentdrive.rollout import rollout
from latentdrive.vec import make_vec

AUX = {"aux_scale": 1.0, "aux_neighbours": 4, "n_step": 1}


def test_every_stored_observation_keeps_the_targets_of_the_scene_it_shows(tiny):
    cfg = tiny(mode="raw", dqn=AUX, vfan={"reader": "attention", "hidden": 32})
    net = build_network(cfg, None)
    vec = make_vec(cfg.scenario_specs(), cfg.envs, observation=cfg.observation.model_dump())
    learner = Learner(cfg, net, torch.device("cpu"), cfg.envs * vec.n_av)
    assert learner.aux is not None
    rng = np.random.default_rng(0)
    cur, ends = None, 0
    try:
        for step, rec in enumerate(rollout(vec, lambda inp: rng.integers(0, 5, inp.active.shape), seed=5)):
            if cur is None:
                assert rec.acted_scenes is not None
                cur = learner.start_segment(learner.cache(rec.obs), rec.acted_scenes)
                want = scene_targets(rec.acted_scenes, cfg.observation, 4)
                np.testing.assert_array_equal(learner.aux.store.get(cur.ravel()), want.reshape(cur.size, -1))
            ei, ai = np.nonzero(rec.agents.acting)
            cur = learner.record(rec, cur, learner.cache)
            # One-step transitions reach the replay at once: the step's are its newest.
            slots = (learner.replay.added - len(ei) + np.arange(len(ei))) % learner.replay.capacity
            # Each transition leads to the Scene next_obs shows: the ended episode's last one.
            np.testing.assert_array_equal(learner.aux.store.get(learner.replay.next_id[slots]),
                                          scene_targets(rec.scenes, cfg.observation, 4)[ei, ai])
            assert rec.scenes_after is not None
            for e in np.flatnonzero(rec.ended):
                # The new episode's first observations show its first Scene.
                np.testing.assert_array_equal(learner.aux.store.get(cur[e]),
                                              scene_targets(rec.scenes_after[e:e + 1], cfg.observation, 4)[0])
                assert not np.array_equal(scene_targets(rec.scenes[e:e + 1], cfg.observation, 4),
                                          scene_targets(rec.scenes_after[e:e + 1], cfg.observation, 4))
            ends += int(rec.ended.sum())
            if step == 60:
                break
    finally:
        vec.close()
    assert ends > 0  # both kinds of first observation were checked
    assert learner.aux.store.added == learner.replay.store.added


def test_the_auxiliary_step_fits_the_targets_and_leaves_the_q_head_alone():
    torch.manual_seed(0)
    net = QNetwork(VFANConfig(reader="attention", hidden=32, attention_width=16), "raw", (4, 2, 16, 32),
                   geometry=(1.5, 8.0))
    head = aux_head(net.summary_size, 32, 2)
    opt = torch.optim.Adam([*net.parameters(), *head.parameters()], lr=3e-3)
    obs = torch.rand(32, 4, 2, 16, 32)
    targets = torch.rand(32, 2 + 2 * 9)
    q_head = [p.detach().clone() for p in net.body.get_submodule("head").parameters()]
    stem = [p.detach().clone() for p in net.body.get_submodule("stem").parameters()]
    first = aux_step(net.summary, head, opt, obs, targets)
    for _ in range(150):
        last = aux_step(net.summary, head, opt, obs, targets)
    assert last < 0.3 * first
    assert all(torch.equal(a, b) for a, b in zip(q_head, net.body.get_submodule("head").parameters(), strict=True))
    assert not all(torch.equal(a, b) for a, b in zip(stem, net.body.get_submodule("stem").parameters(), strict=True))


def _net_and_batch(seed=0):
    torch.manual_seed(seed)
    net = QNetwork(VFANConfig(reader="attention", hidden=32, attention_width=16), "raw", (4, 2, 16, 32),
                   geometry=(1.5, 8.0))
    b = 16
    batch = Batch(torch.rand(b, 4, 2, 16, 32), torch.randint(0, 5, (b,)), torch.rand(b), torch.rand(b, 4, 2, 16, 32),
                  torch.ones(b))
    return net, batch


def test_a_joint_update_steps_on_the_sum_of_the_q_loss_and_the_term():
    cfg = DQNConfig(lr=1e-3)
    net, batch = _net_and_batch()
    target = copy.deepcopy(net)
    # A term of zero changes nothing: the Q-values read from the summary are forward()'s.
    plain, joint = copy.deepcopy(net), copy.deepcopy(net)
    opt_p, opt_j = (torch.optim.Adam(m.parameters(), lr=1e-3) for m in (plain, joint))
    a = update(plain, target, opt_p, batch, cfg)
    b = update(joint, target, opt_j, batch, cfg, joint=lambda z: 0.0 * z.sum())
    assert a.loss == b.loss
    assert all(torch.equal(p, q) for p, q in zip(plain.parameters(), joint.parameters(), strict=True))
    # With a term, the gradient is that of the sum, from one backward pass: SGD's step
    # shows it exactly.
    head = aux_head(net.summary_size, 8, 1)
    targets = torch.rand(16, view_target_size(1))
    by_hand = copy.deepcopy(net)
    sgd = torch.optim.SGD(net.parameters(), lr=0.1)
    stats = update(net, target, sgd, batch, cfg, joint=lambda z: 2.0 * F.mse_loss(head(z), targets))
    with torch.no_grad():
        y = td_targets(batch.reward, batch.bootstrap, by_hand(batch.next_obs), target(batch.next_obs), cfg.gamma, True)
    q = by_hand(batch.obs).gather(1, batch.action[:, None]).squeeze(1)
    total = F.huber_loss(q, y) + 2.0 * F.mse_loss(head(by_hand.summary(batch.obs)), targets)
    grads = torch.autograd.grad(total, list(by_hand.parameters()))
    assert stats.loss == pytest.approx(float(F.huber_loss(q, y).detach()), rel=1e-6)
    norm = float(torch.linalg.vector_norm(torch.stack([torch.linalg.vector_norm(g) for g in grads])))
    clip = min(1.0, cfg.grad_clip / (norm + 1e-6))
    for p, before, g in zip(net.parameters(), by_hand.parameters(), grads, strict=True):
        torch.testing.assert_close(p, before - 0.1 * clip * g, rtol=1e-4, atol=1e-6)


def test_the_joint_auxiliary_loss_fits_the_targets_through_the_q_update():
    cfg = DQNConfig(lr=3e-3, aux_scale=1.0, aux_joint=True, aux_neighbours=1)
    net, batch = _net_and_batch(1)
    target = copy.deepcopy(net)
    aux = AuxLearning(net, cfg, ObservationConfig(), 64, torch.device("cpu"))
    # Joint: the head's own optimizer moves the head alone; the reader moves with the Q-learner's.
    assert {id(p) for g in aux.optimizer.param_groups for p in g["params"]} == {id(p) for p in aux.head.parameters()}
    aux.store.add(np.random.default_rng(0).random((16, view_target_size(1)), dtype=np.float32), np.arange(16))
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr)
    stem = [p.detach().clone() for p in net.body.get_submodule("stem").parameters()]
    head = [p.detach().clone() for p in aux.head.parameters()]
    ids, cpu = np.arange(16), torch.device("cpu")
    targets = torch.from_numpy(aux.store.get(ids))
    for step in range(150):
        before = copy.deepcopy(net)
        update(net, target, opt, batch, cfg, joint=aux.joint_term(ids, cpu, torch.float32))
        if step < 2:
            # The head's gradient is this step's alone (cleared before the backward pass):
            # that of aux_scale × its squared error on the summary the update saw.
            with torch.no_grad():
                z = before.summary(batch.obs)
            want = torch.autograd.grad(cfg.aux_scale * F.mse_loss(aux.head(z), targets), list(aux.head.parameters()))
            for p, g in zip(aux.head.parameters(), want, strict=True):
                assert p.grad is not None
                torch.testing.assert_close(p.grad, g)
        aux.step_head()
    assert len(aux.losses) == 150
    assert aux.losses[-1] < 0.3 * aux.losses[0]
    assert not all(torch.equal(a, b) for a, b in zip(stem, net.body.get_submodule("stem").parameters(), strict=True))
    assert not any(torch.equal(a, b) for a, b in zip(head, aux.head.parameters(), strict=True))


@pytest.mark.parametrize("joint", [False, True])
def test_the_learner_takes_the_step_its_config_names(tmp_path, tiny, monkeypatch, joint):
    calls = {"separate": 0, "head": 0}
    separate, step_head = AuxLearning.step, AuxLearning.step_head

    def counted(name, fn):
        def wrapper(*args, **kwargs):
            calls[name] += 1
            return fn(*args, **kwargs)
        return wrapper

    monkeypatch.setattr(AuxLearning, "step", counted("separate", separate))
    monkeypatch.setattr(AuxLearning, "step_head", counted("head", step_head))
    cfg = tiny(mode="raw", steps=150, dqn={**AUX, "aux_joint": joint}, vfan={"reader": "attention", "hidden": 32})
    result = train_policy(cfg, tmp_path / "run", progress=False, say=lambda _line: None)
    assert result["updates"] > 0
    assert calls == ({"separate": 0, "head": result["updates"]} if joint else {"separate": result["updates"], "head": 0})


@pytest.mark.parametrize("joint", [False, True])
def test_pretraining_fits_the_reader_once_before_the_first_update(tmp_path, tiny, monkeypatch, joint):
    seen: list[dict[str, Any]] = []
    pretrain = Learner.pretrain

    def moved(before: list[torch.Tensor], module: torch.nn.Module) -> list[bool]:
        return [not torch.equal(a, b) for a, b in zip(before, module.parameters(), strict=True)]

    def spied(self):
        modules = {"stem": self.net.body.get_submodule("stem"), "q_head": self.net.body.get_submodule("head"),
                   "aux_head": self.aux.head}
        before = {k: [p.detach().clone() for p in m.parameters()] for k, m in modules.items()}
        pretrain(self)
        seen.append({
            "updates": self.updates, "transitions": self.transitions, "losses": list(self.aux.pretrain_losses),
            **{k: moved(before[k], m) for k, m in modules.items()},
            # Its Adam is its own: neither the Q-learner's nor the run's auxiliary one has taken a step.
            "optimizers_untouched": not self.optimizer.state and not self.aux.optimizer.state,
            "target_is_net": all(torch.equal(a, b) for a, b in zip(self.net.state_dict().values(),
                                                                   self.target.state_dict().values(), strict=True)),
        })

    monkeypatch.setattr(Learner, "pretrain", spied)
    # aux_scale 0.25: a step at the run's auxiliary rate (aux_scale × lr) would be another step.
    cfg = tiny(mode="raw", steps=200, dqn={**AUX, "aux_scale": 0.25, "lr": 3e-3, "aux_joint": joint, "aux_pretrain": 60,
                                           "learning_starts": 100}, vfan={"reader": "attention", "hidden": 32})
    result = train_policy(cfg, tmp_path / "run", progress=False, say=lambda _line: None)
    (at,) = seen
    # Right before the first update, in the call that owes it, and not counted as updates.
    assert at["updates"] == 0 and updates_owed(cfg.dqn, at["transitions"]) >= 1
    assert all(at["stem"]) and all(at["aux_head"]) and not any(at["q_head"])
    assert at["optimizers_untouched"] and at["target_is_net"]
    losses = at["losses"]
    assert len(losses) == 60 and np.mean(losses[-10:]) < 0.7 * np.mean(losses[:10])
    assert result["updates"] == updates_owed(cfg.dqn, result["transitions"])


@pytest.mark.parametrize(("changes", "match"), [({"aux_pretrain": 10}, r"aux_pretrain.*aux_scale"),
                                                 ({"aux_pretrain": 10, "aux_scale": 1.0, "learning_starts": 31},
                                                  r"aux_pretrain.*learning_starts ≥ batch_size \(32\), got 31")])
def test_pretraining_without_its_loss_or_its_maps_is_refused(changes, match):
    with pytest.raises(ValueError, match=match):
        DQNConfig(**changes)


def test_joint_without_the_auxiliary_loss_is_refused():
    with pytest.raises(ValueError, match=r"aux_joint.*aux_scale"):
        DQNConfig(aux_joint=True)


@pytest.mark.parametrize("changes", [{"vfan": {}}, {"vfan": {"reader": "attention"}, "learner": "dagger"}])
def test_the_auxiliary_loss_needs_the_attention_reader_and_q_learning(tiny, changes):
    with pytest.raises((ConfigError, ValueError), match=r"dqn\.aux_scale"):
        tiny(mode="raw", dqn={"aux_scale": 1.0}, **changes)


def test_a_run_with_the_auxiliary_loss_evaluates_from_its_folder(tmp_path, tiny):
    cfg = tiny(mode="raw", steps=150, dqn=AUX, vfan={"reader": "attention", "hidden": 32})
    result = train_policy(cfg, tmp_path / "run", progress=False, say=lambda _line: None)
    assert result["updates"] > 0
    net, _ = load_policy_network(tmp_path / "run")
    assert not any(name.startswith("aux") for name in net.state_dict())


def test_the_gradient_share_measures_each_loss_on_the_reader_and_moves_nothing():
    net, batch = _net_and_batch(2)
    target = copy.deepcopy(net)
    head = aux_head(net.summary_size, 8, 1)
    targets = torch.rand(16, view_target_size(1))
    before = [p.detach().clone() for p in [*net.parameters(), *head.parameters()]]
    one = gradient_share(net, target, head, batch, targets, DQNConfig(aux_scale=1.0))
    three = gradient_share(net, target, head, batch, targets, DQNConfig(aux_scale=3.0))
    assert all(torch.equal(a, b) for a, b in zip(before, [*net.parameters(), *head.parameters()], strict=True))
    assert three.q_norm == one.q_norm and three.q_loss == one.q_loss
    assert three.aux_norm == pytest.approx(3 * one.aux_norm, rel=1e-5)
    assert three.aux_loss == pytest.approx(3 * one.aux_loss, rel=1e-5)
    # The Q-loss's gradient on the reader only: the Q head is what the auxiliary loss never reaches.
    reader = [p for name, p in net.named_parameters() if not name.startswith("body.head.")]
    with torch.no_grad():
        y = td_targets(batch.reward, batch.bootstrap, net(batch.next_obs), target(batch.next_obs), 0.95, True)
    q = net(batch.obs).gather(1, batch.action[:, None]).squeeze(1)
    grads = torch.autograd.grad(F.huber_loss(q, y), reader)
    assert one.q_norm == pytest.approx(float(torch.linalg.vector_norm(torch.cat([g.flatten() for g in grads]))), rel=1e-5)


def test_the_share_script_reads_a_runs_checkpoint_and_refuses_a_run_without_the_loss(tmp_path, tiny, capsys):
    script = runpy.run_path(str(Path(__file__).resolve().parents[2] / "scripts" / "aux_share.py"), run_name="aux_share")
    cfg = tiny(mode="raw", steps=150, dqn={**AUX, "aux_joint": True}, vfan={"reader": "attention", "hidden": 32})
    train_policy(cfg, tmp_path / "run", progress=False, say=lambda _line: None)
    assert script["main"]([str(tmp_path / "run"), "--batches", "2"]) == 0
    out = capsys.readouterr().out
    assert "(joint)" in out and "aux / Q" in out
    ratio = float(out.split("aux / Q")[1].split()[0])
    assert np.isfinite(ratio) and ratio > 0
    # --fit: a row of R² per group of neighbour ranks (AUX keeps 4: "1" and "2-4").
    assert script["main"]([str(tmp_path / "run"), "--batches", "2", "--fit"]) == 0
    table = capsys.readouterr().out.split("R² of the auxiliary head's predictions: speed ")[1].splitlines()
    assert table[1].split() == ["neighbours", *FIELDS]
    assert [line.split()[0] for line in table[2:]] == ["1", "2-4"]
    assert float(table[0].split(",")[0]) <= 1.0
    train_policy(tiny(mode="raw", steps=100), tmp_path / "plain", progress=False, say=lambda _line: None)
    assert script["main"]([str(tmp_path / "plain")]) == 2
    err = capsys.readouterr().err
    assert "aux_scale is 0" in err and err.count("\n") == 1


def test_the_fit_of_each_target_is_its_share_of_variance_explained():
    # Two neighbours, four samples; the second neighbour is absent in the last two rows.
    k, n_f = 2, len(FIELDS)
    rng = np.random.default_rng(0)
    t = rng.normal(size=(4, 2 + k * n_f))
    rows = t[:, 2:].reshape(4, k, n_f)
    rows[:, :, -1] = 1.0
    rows[2:, 1] = 0.0  # absent: a zero row
    t[:, 2:] = rows.reshape(4, -1)
    fit = field_fit(t, t, k)
    assert fit["speed"] == fit["x 1"] == fit["vy 2"] == 1.0
    assert np.isnan(fit["present 1"])  # every nearest neighbour is there: nothing to explain
    assert fit["present 2"] == 1.0
    # Predicting the mean explains nothing; predicting the mean plus the error's size of
    # the spread, negative. Absent rows do not count: junk there leaves x 2 alone.
    mean = t.copy()
    mean[:, 0] = t[:, 0].mean()
    assert field_fit(mean, t, k)["speed"] == pytest.approx(0.0)
    junk = t.copy()
    junk[2:, 2 + n_f] = 99.0
    assert field_fit(junk, t, k)["x 2"] == 1.0
    worse = t.copy()
    worse[:, 2] = t[:, 2] + 2 * t[:, 2].std()
    assert field_fit(worse, t, k)["x 1"] == pytest.approx(-3.0)  # SSE = 4 SST
    with pytest.raises(ValueError, match=r"\(N, 20\)"):
        field_fit(t[:, :-1], t[:, :-1], k)


@pytest.mark.parametrize("readout", ["query", "queries", "self-attention"])
def test_the_reader_probe_fits_a_fresh_reader_to_a_runs_targets(tmp_path, tiny, capsys, readout):
    script = runpy.run_path(str(Path(__file__).resolve().parents[2] / "scripts" / "reader_probe.py"), run_name="probe")
    cfg = tiny(mode="raw", steps=150, dqn={**AUX, "aux_joint": True}, vfan={"reader": "attention", "hidden": 32})
    train_policy(cfg, tmp_path / "run", progress=False, say=lambda _line: None)
    args = [str(tmp_path / "run"), "--readout", readout, "--steps", "3", "--block", "10"]
    assert script["main"](args) == 0
    out = capsys.readouterr().out
    assert f"readout {readout}, stem conv; 3 steps" in out
    table = out.splitlines()[1:]
    assert table[0].split() == ["neighbours", *FIELDS]
    assert [line.split()[0] for line in table[1:]] == ["1", "2-4"]
    # Held out: every tenth block of 10 observation ids, so the ids ending 0-9 of 0-99 etc.
    train, held = script["split"](np.arange(250), 10)
    assert held.tolist() == [*range(0, 10), *range(100, 110), *range(200, 210)]
    assert len(train) == 220
    # Too few observations to hold any out in blocks of 10 000: refused in one line.
    assert script["main"]([str(tmp_path / "run"), "--block", "10000"]) == 2
    err = capsys.readouterr().err
    assert "too small to hold observations out" in err and err.count("\n") == 1
