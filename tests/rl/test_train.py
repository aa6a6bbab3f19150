"""Training runs: frozen encoders, determinism, bitwise resumption, evaluation seeds."""

import csv
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
from safetensors.numpy import load_file

from latentdrive.rl.policy import CHECKPOINT, load_policy_network
from latentdrive.rl.train import train_policy
from latentdrive.seeds import EVAL_RESET_SEEDS, TRAIN_RESET_SEEDS, eval_reset_seed, train_reset_seed


def _model_tensors(run_dir):
    return {k: v for k, v in load_file(str(run_dir / CHECKPOINT)).items() if k.startswith(("model/", "target/"))}


def _quiet(**kw):
    return {"progress": False, "say": lambda _line: None, **kw}


@pytest.mark.parametrize("mode, encoder_trains", [("latent-random", False), ("end-to-end", True)])
def test_the_encoder_changes_only_in_end_to_end_mode(tmp_path, tiny, mode, encoder_trains):
    cfg = tiny(mode=mode, steps=200)
    train_policy(cfg, tmp_path / "run", **_quiet())
    from latentdrive.rl.policy import build_network, encoder_config

    start = build_network(cfg, encoder_config(cfg)).state_dict()  # the seeded initial weights
    trained, _ = load_policy_network(tmp_path / "run")
    end = trained.state_dict()
    enc_same = all(np.array_equal(start[k].numpy(), end[k].numpy()) for k in start if k.startswith("encoder."))
    body_same = all(np.array_equal(start[k].numpy(), end[k].numpy()) for k in start if k.startswith("body."))
    assert enc_same != encoder_trains
    assert not body_same


def test_same_config_and_seed_give_the_same_weights_and_evaluation(tmp_path, tiny):
    cfg = tiny(mode="raw")
    a = train_policy(cfg, tmp_path / "a", **_quiet())
    b = train_policy(cfg, tmp_path / "b", **_quiet())
    ta, tb = _model_tensors(tmp_path / "a"), _model_tensors(tmp_path / "b")
    assert ta.keys() == tb.keys() and all(np.array_equal(ta[k], tb[k]) for k in ta)
    assert a["evaluation"] == b["evaluation"] and a["updates"] == b["updates"] > 0
    c = train_policy(tiny(mode="raw", seed=1), tmp_path / "c", **_quiet())
    tc = _model_tensors(tmp_path / "c")
    assert not all(np.array_equal(ta[k], tc[k]) for k in ta)
    assert c["transitions"] >= 300


def test_a_killed_run_resumes_to_the_weights_of_an_uninterrupted_one(tmp_path, tiny):
    cfg = tiny(mode="latent-random", steps=500)
    assert train_policy(cfg, tmp_path / "whole", **_quiet())["resumed_s"] == 0
    script = textwrap.dedent(f"""
        import json, sys
        from latentdrive.rl.config import PolicyTrainConfig
        from latentdrive.rl.train import train_policy
        cfg = PolicyTrainConfig.model_validate(json.loads({cfg.model_dump_json()!r}))
        train_policy(cfg, sys.argv[1], progress=False, say=lambda _l: None)
    """)
    run = tmp_path / "killed"
    proc = subprocess.Popen([sys.executable, "-c", script, str(run)])
    deadline = time.time() + 120
    while not (run / CHECKPOINT).exists() and time.time() < deadline and proc.poll() is None:
        time.sleep(0.05)
    assert proc.poll() is None, "the run finished before it could be interrupted"
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    from latentdrive.bnn.checkpoint import read_checkpoint

    done = read_checkpoint(run / CHECKPOINT)[1]["extra"]["transitions"]
    assert done < cfg.steps
    logged = {int(r["transitions"]): float(r["elapsed_s"]) for r in csv.DictReader(open(run / "metrics.csv"))}
    result = train_policy(cfg, run, resume=True, **_quiet())
    # What the killed session had done by its checkpoint is part of the run's cost.
    assert result["resumed_s"] == round(logged[done], 2) > 0
    whole, resumed = _model_tensors(tmp_path / "whole"), _model_tensors(run)
    assert all(np.array_equal(whole[k], resumed[k]) for k in whole)
    lines = (run / "metrics.csv").read_text().splitlines()
    assert len(lines) == len((tmp_path / "whole" / "metrics.csv").read_text().splitlines())


def test_training_and_evaluation_seeds_are_disjoint(tmp_path, tiny):
    assert TRAIN_RESET_SEEDS.stop + 4096 <= EVAL_RESET_SEEDS.start
    for seed in range(50):
        for segment in range(50):
            s = train_reset_seed(seed, segment)
            assert s in TRAIN_RESET_SEEDS and s + 4095 < EVAL_RESET_SEEDS.start
    assert eval_reset_seed(0) in EVAL_RESET_SEEDS
    # The episodes themselves: a short run's training episodes never appear in evaluation.
    import latentdrive
    from latentdrive.rollout import rollout

    def episode_seeds(reset_seed, steps=40):
        vec = latentdrive.make_vec("intersection", 4, observation={"height": 16, "width": 32, "frames": 2})
        seeds = set()
        for t, rec in enumerate(rollout(vec, lambda inp: np.full(inp.active.shape, 4), seed=reset_seed)):
            seeds |= {o.seed for o in rec.outcomes}
            if t == steps:
                return seeds
        return seeds

    train = episode_seeds(train_reset_seed(0, 0)) | episode_seeds(train_reset_seed(0, 1))
    assert train and not train & episode_seeds(eval_reset_seed(0))


def test_each_checkpoint_names_its_own_replay_and_older_ones_go(tmp_path, tiny):
    cfg = tiny(mode="raw", steps=250)
    train_policy(cfg, tmp_path / "r", **_quiet())
    replays = sorted(p.name for p in (tmp_path / "r").glob("replay-*.safetensors"))
    from latentdrive.bnn.checkpoint import read_checkpoint

    extra = read_checkpoint(tmp_path / "r" / CHECKPOINT)[1]["extra"]
    assert replays == [extra["replay"]] == ["replay-2.safetensors"]
    # A kill after the next replay was written but before its checkpoint: the run still
    # resumes from the pair that belongs together.
    (tmp_path / "r" / "replay-3.safetensors").write_bytes(b"half-written")
    result = train_policy(tiny(mode="raw", steps=350), tmp_path / "r", resume=True, **_quiet())
    assert result["transitions"] >= 350
    assert [p.name for p in (tmp_path / "r").glob("replay-*.safetensors")] == ["replay-3.safetensors"]


def _files(root):
    return {p: p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_a_damaged_replay_is_refused_on_resumption(tmp_path, tiny):
    from latentdrive.bnn.checkpoint import CheckpointError

    run = tmp_path / "r"
    train_policy(tiny(mode="raw", steps=100), run, **_quiet())
    (replay,) = run.glob("replay-*.safetensors")
    data = bytearray(replay.read_bytes())
    data[-3] ^= 0x01  # one bit of its tensor data: the safetensors header still parses
    replay.write_bytes(bytes(data))
    before = _files(run)
    with pytest.raises(CheckpointError, match="corrupt replay") as exc:
        train_policy(tiny(mode="raw", steps=200), run, resume=True, **_quiet())
    assert str(exc.value).startswith(str(replay)) and "\n" not in str(exc.value)
    assert _files(run) == before


class _Stop(Exception):
    pass


#: Every learner option away from its default at once.
LEARNER_OPTIONS = {"n_step": 3, "prioritized": True, "dueling": True, "tau": 0.05, "updates_per_transition": 1,
                   "augment_shift": 1, "explore_rule": 0.5, "adam_eps": 1.5e-4}


@pytest.mark.parametrize(("options", "vfan"), [({}, {}), (LEARNER_OPTIONS, {}), ({**LEARNER_OPTIONS, "augment_shift": 0}, {"reader": "attention"}),
                                               ({**LEARNER_OPTIONS, "augment_shift": 0, "dueling": False}, {"reader": "objects", "objects_frames": 2, "objects_layers": 1}),
                                               ({**LEARNER_OPTIONS, "augment_shift": 0, "aux_scale": 1.0}, {"reader": "attention"}),
                                               ({**LEARNER_OPTIONS, "augment_shift": 0, "aux_scale": 1.0, "aux_joint": True},
                                                {"reader": "attention"}),
                                               # The first checkpoint (at about 100) before the pretraining (120), then after it (50).
                                               ({**LEARNER_OPTIONS, "augment_shift": 0, "aux_scale": 1.0, "aux_pretrain": 5,
                                                 "learning_starts": 120}, {"reader": "attention"}),
                                               ({**LEARNER_OPTIONS, "augment_shift": 0, "aux_scale": 1.0, "aux_pretrain": 5,
                                                 "learning_starts": 50}, {"reader": "attention"})],
                         ids=["defaults", "options", "attention-reader", "objects-reader", "auxiliary-loss", "joint-auxiliary-loss",
                              "resumed-before-pretraining", "resumed-after-pretraining"])
def test_a_short_runs_replay_takes_the_room_of_its_transitions_and_resumes(tmp_path, tiny, monkeypatch, options, vfan):
    # The default buffer holds 100k transitions: saved whole, a raw replay takes 400 MB
    # at this tiny grid (1.6 GB at the default one) whatever the run's length.
    from latentdrive.bnn.checkpoint import read_checkpoint
    from latentdrive.rl.learner import Learner

    cfg = tiny(mode="raw", steps=200, dqn={"buffer_size": 100_000, **options}, vfan=vfan)
    train_policy(cfg, tmp_path / "whole", **_quiet())
    save = Learner.save

    def save_then_stop(self, run_dir, segment):
        save(self, run_dir, segment)
        raise _Stop  # as if killed after the first checkpoint

    with monkeypatch.context() as m:
        m.setattr(Learner, "save", save_then_stop)
        with pytest.raises(_Stop):
            train_policy(cfg, tmp_path / "r", **_quiet())
    (replay,) = (tmp_path / "r").glob("replay-*.safetensors")
    assert replay.stat().st_size < 2 << 20
    # Every agent-transition starts one replay entry, n-step or not: none is pending at a
    # checkpoint, and the n-step returns are stored with their horizons.
    extra = read_checkpoint(tmp_path / "r" / CHECKPOINT)[1]["extra"]
    assert extra["replay_added"] == extra["transitions"] > 0
    if options.get("aux_pretrain"):
        # The checkpoint the run resumes from comes before the pretraining (learning_starts 120)
        # or after it (50), as the case's name says: no updates yet means not pretrained yet.
        assert (extra["updates"] == 0) is (options["learning_starts"] == 120)
    steps = load_file(str(replay))["replay/steps"]
    assert set(np.unique(steps)) <= set(range(1, cfg.dqn.n_step + 1))
    assert (steps.max() == 3) == bool(options)
    train_policy(cfg, tmp_path / "r", resume=True, **_quiet())
    whole, resumed = _model_tensors(tmp_path / "whole"), _model_tensors(tmp_path / "r")
    assert all(np.array_equal(whole[k], resumed[k]) for k in whole)


def test_evaluation_offsets_are_disjoint_sets():
    from latentdrive.seeds import MAX_ENVS, TRAINING_EVAL_OFFSET

    assert eval_reset_seed(1) - eval_reset_seed(0) == MAX_ENVS
    assert TRAINING_EVAL_OFFSET != 0
    from latentdrive.config import ConfigError

    with pytest.raises(ConfigError, match="offset"):
        eval_reset_seed(-1)


def test_a_reward_that_pays_more_for_never_arriving_is_refused(tmp_path):
    from latentdrive.config import ConfigError, validate
    from latentdrive.rl.config import PolicyTrainConfig, check_mission_pays
    from latentdrive.rl.train import train_policy

    # Regression: with mission 1 and speed 0.2 at γ = 0.95, cruising forever (worth 4)
    # beat arriving, and no learned policy completed a merge.
    old = validate(PolicyTrainConfig, {"mode": "raw", "reward": {"mission": 1.0}, "steps": 10})
    with pytest.raises(ConfigError, match="mission"):
        check_mission_pays(old)
    with pytest.raises(ConfigError, match="mission"):
        train_policy(old, tmp_path / "run", **_quiet())
    assert not (tmp_path / "run").exists()
    check_mission_pays(old.replace(dqn={"gamma": 0.5}))
    check_mission_pays(validate(PolicyTrainConfig, {"mode": "raw"}))


def test_a_run_trained_under_an_older_reward_still_loads(tmp_path, tiny):
    import json

    from latentdrive.rl.policy import load_policy_network
    from latentdrive.rl.train import train_policy

    train_policy(tiny(mode="raw", steps=100), tmp_path / "run", **_quiet())
    path = tmp_path / "run" / "config.json"
    data = json.loads(path.read_text())
    data["train"]["reward"]["mission"] = 1.0
    path.write_text(json.dumps(data))
    _, cfg = load_policy_network(tmp_path / "run")
    assert cfg.reward.mission == 1.0


def test_a_run_whose_config_predates_the_learner_options_still_loads(tmp_path, tiny):
    import json

    train_policy(tiny(mode="raw", steps=100), tmp_path / "run", **_quiet())
    path = tmp_path / "run" / "config.json"
    data = json.loads(path.read_text())
    dqn = data["train"]["dqn"]
    for key in ("n_step", "tau", "dueling", "prioritized", "priority_alpha", "priority_beta", "priority_eps",
                "updates_per_transition"):
        del dqn[key]
    del data["train"]["precision"]
    dqn["train_every"] = 4
    path.write_text(json.dumps(data))
    _, cfg = load_policy_network(tmp_path / "run")
    assert cfg.dqn.updates_per_transition == 0.25 and cfg.dqn.n_step == 1 and not cfg.dqn.dueling
    assert cfg.precision == "auto"


def test_the_optimizer_takes_the_configured_adam_eps(tiny):
    import torch

    from latentdrive.rl.learner import Learner
    from latentdrive.rl.policy import build_network

    for eps in (1e-8, 1.5e-4):
        cfg = tiny(mode="raw", dqn={"adam_eps": eps})
        learner = Learner(cfg, build_network(cfg, None), torch.device("cpu"), 8)
        assert [g["eps"] for g in learner.optimizer.param_groups] == [eps]


def test_the_optimizer_is_fused_and_a_checkpoint_keeps_the_setting_it_was_written_with(tmp_path, tiny):
    import torch

    from latentdrive.rl.learner import Learner
    from latentdrive.rl.policy import build_network

    cfg = tiny(mode="raw", steps=300)
    train_policy(cfg, tmp_path / "run", **_quiet())
    learner = Learner(cfg, build_network(cfg, None), torch.device("cpu"), 8)
    assert [g["fused"] for g in learner.optimizer.param_groups] == [True]
    learner.load(tmp_path / "run")
    assert [g["fused"] for g in learner.optimizer.param_groups] == [True]
    # A run written with the loop of small ops (before the fused kernel) resumes with it,
    # so that it continues as it began.
    learner.optimizer.param_groups[0]["fused"] = None
    learner.save(tmp_path / "run", 0)
    again = Learner(cfg, build_network(cfg, None), torch.device("cpu"), 8)
    again.load(tmp_path / "run")
    assert [g["fused"] for g in again.optimizer.param_groups] == [None]


def _scripted_evaluations(rates, seen):
    """A stand-in for the periodic evaluation: reports ``rates`` in turn (mixed failure rate)
    and records the weights each one scored."""
    def evaluate(cfg, net, device):
        seen.append({k: v.detach().clone() for k, v in net.state_dict().items()})
        rate = rates[len(seen) - 1]
        summary = {"episodes": 4, "failure_rate": {"rate": rate}, "crash_rate": {"rate": rate},
                   "success_rate": {"rate": 1 - rate}, "mean_return": {"mean": 0.0}}
        return {"scenarios": {}, "mixed": summary}

    return evaluate


def _same(a, b):
    return a.keys() == b.keys() and all(np.array_equal(a[k].numpy(), b[k].numpy()) for k in a)


@pytest.mark.parametrize("keep", ["best", "last"])
def test_keep_best_makes_the_least_failing_evaluated_weights_the_runs_policy(tmp_path, tiny, monkeypatch, keep):
    import latentdrive.rl.train as train_module

    seen: list[dict] = []
    # Ties go to the later weights: the second and fourth evaluation tie, the fourth is kept.
    monkeypatch.setattr(train_module, "_evaluate", _scripted_evaluations([0.5, 0.25, 0.75, 0.25, 0.5], seen))
    cfg = tiny(mode="raw", steps=500, eval_every=1, keep=keep)
    result = train_policy(cfg, tmp_path / "run", **_quiet())
    assert len(seen) == 5
    net, _ = load_policy_network(tmp_path / "run")
    if keep == "best":
        assert _same(net.state_dict(), seen[3]) and not _same(seen[3], seen[4])
        assert result["kept"]["failure_rate"] == 0.25 and 400 <= result["kept"]["transitions"] < 500
    else:
        assert _same(net.state_dict(), seen[4]) and "kept" not in result
        assert not any(k.startswith("best/") for k in load_file(str(tmp_path / "run" / CHECKPOINT)))


def test_a_resumed_run_keeps_the_best_weights_chosen_before_it_was_stopped(tmp_path, tiny, monkeypatch):
    import latentdrive.rl.train as train_module
    from latentdrive.rl.learner import Learner

    rates = [0.25, 0.5, 0.75, 0.5]  # the best comes before the interruption, and stays best
    cfg = tiny(mode="raw", steps=400, eval_every=1, keep="best")
    whole: list[dict] = []
    monkeypatch.setattr(train_module, "_evaluate", _scripted_evaluations(rates, whole))
    train_policy(cfg, tmp_path / "whole", **_quiet())
    save, saves = Learner.save, []

    def save_then_stop(self, run_dir, segment):
        save(self, run_dir, segment)
        saves.append(segment)
        if len(saves) == 2:
            raise _Stop  # as if killed after the second checkpoint

    before: list[dict] = []
    monkeypatch.setattr(train_module, "_evaluate", _scripted_evaluations(rates, before))
    with monkeypatch.context() as m:
        m.setattr(Learner, "save", save_then_stop)
        with pytest.raises(_Stop):
            train_policy(cfg, tmp_path / "r", **_quiet())
    after: list[dict] = []
    monkeypatch.setattr(train_module, "_evaluate", _scripted_evaluations(rates[2:], after))
    result = train_policy(cfg, tmp_path / "r", resume=True, **_quiet())
    assert len(before) == len(after) == 2
    net, _ = load_policy_network(tmp_path / "r")
    assert _same(net.state_dict(), whole[0]) and _same(whole[0], before[0])
    assert result["kept"]["failure_rate"] == 0.25


def test_a_run_that_keeps_its_best_weights_refuses_to_load_before_any_evaluation(tmp_path, tiny, monkeypatch):
    from latentdrive.bnn.checkpoint import CheckpointError
    from latentdrive.rl.learner import Learner

    save = Learner.save

    def save_then_stop(self, run_dir, segment):
        save(self, run_dir, segment)
        raise _Stop  # killed after the first checkpoint, which no evaluation preceded

    monkeypatch.setattr(Learner, "save", save_then_stop)
    with pytest.raises(_Stop):
        train_policy(tiny(mode="raw", steps=300, eval_every=2, keep="best"), tmp_path / "r", **_quiet())
    with pytest.raises(CheckpointError, match="no evaluated weights yet"):
        load_policy_network(tmp_path / "r")


@pytest.mark.parametrize("bad", ["nan", "-5", "inf", "soon"])
def test_a_resumption_refuses_a_logged_time_that_is_not_seconds(tmp_path, tiny, bad):
    from latentdrive.config import ConfigError

    run = tmp_path / "r"
    train_policy(tiny(mode="latent-random", steps=200), run, **_quiet())
    metrics = run / "metrics.csv"
    rows = list(csv.DictReader(open(metrics)))
    rows[-1]["elapsed_s"] = bad
    with open(metrics, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    before = metrics.read_bytes()
    with pytest.raises(ConfigError, match=r"elapsed_s .* is not a number of seconds") as info:
        train_policy(tiny(mode="latent-random", steps=300), run, resume=True, **_quiet())
    assert "\n" not in str(info.value) and metrics.read_bytes() == before
