"""Training a policy: multi-agent double DQN over a vector env, resumable bit for bit.

The run is cut into segments of ``cfg.segment`` agent-transitions. Each segment resets
every environment from a seed fixed by ``(seed, segment index)`` and ends with a
checkpoint: model, target network, optimizer, counters, the numpy generator and the
replay. The simulator's state is never saved: it is recreated from the segment's seed.
A run resumed from any checkpoint therefore takes exactly the steps an uninterrupted run
takes, and ends with the same weights. Episodes still running at a segment boundary are
cut off like a time limit (their last transitions bootstrap), which costs a little
experience per segment and nothing in correctness.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch

from latentdrive.bnn.runlog import RunLog
from latentdrive.config import ConfigError
from latentdrive.evaluate.policies import reference_policy
from latentdrive.evaluate.report import policy_report
from latentdrive.evaluate.run import evaluate_policy
from latentdrive.fileio import seconds_logged
from latentdrive.models.vfan import QNetwork
from latentdrive.outcome import EpisodeOutcome
from latentdrive.rl.config import PolicyTrainConfig, check_mission_pays
from latentdrive.rl.imitate import (
    ExpertLabels,
    dagger_policy,
    expert_policy,
)
from latentdrive.rl.learner import Learner
from latentdrive.rl.policy import (
    CHECKPOINT,
    build_network,
    encoder_config,
    epsilon_greedy,
    greedy_actions,
    greedy_policy,
)
from latentdrive.rl.runfolder import (
    EVALS,
    LOGS,
    METRICS,
    check_resume,
    init_weights,
    read_logs,
    stored_encoder,
    write_config,
)
from latentdrive.rollout import Policy, StepRecord, rollout
from latentdrive.runlock import dir_lock
from latentdrive.runtime import resolve_device, resolve_precision, torch_settings
from latentdrive.seeds import TRAINING_EVAL_OFFSET, train_reset_seed, validation_reset_seed
from latentdrive.vec import make_vec

__all__ = ["EvalCallback", "TrainResult", "learner_steps", "periodic_evaluation", "train_policy"]


#: Called after each periodic evaluation, once its checkpoint is saved, with the
#: agent-transitions so far and the mixed failure rate in [0, 1]. An exception it raises
#: (a search pruning the run) ends training there; the run resumes from that checkpoint.
EvalCallback = Callable[[int, float], None]


class TrainResult(dict[str, Any]):
    """Final counters, the last evaluation and ``resumed_s``, the training seconds of the
    sessions a resumed run continued from (a plain dict, JSON-serializable)."""



def learner_steps(learner: Learner, vec: Any, seed: int) -> Iterator[StepRecord]:
    """The training loop proper: act (ε-greedily, or under DAgger mixing in the planner's
    actions), store the step's transitions, learn; yields each step."""
    cache = learner.cache
    labels: ExpertLabels | None = None
    if learner.imitating:
        labels = ExpertLabels()
        net = learner.net
        expert = expert_policy(learner.cfg.imitation, learner.cfg.reward)
        policy = dagger_policy(expert, lambda inp: greedy_actions(net, cache, inp), learner.rng, learner.eps, labels)
    else:
        share = learner.cfg.dqn.explore_rule
        guide = reference_policy("rule")() if share > 0 else None
        policy = epsilon_greedy(learner.net, cache, learner.rng, learner.eps, guide, share)
    cur: np.ndarray | None = None
    for rec in rollout(vec, policy, seed=seed):
        if cur is None:
            cur = learner.start_segment(cache(rec.obs), rec.acted_scenes)
        cur = learner.record(rec, cur, cache, None if labels is None else labels.latest)
        learner.learn()
        yield rec


def periodic_evaluation(cfg: PolicyTrainConfig, make_policy: Callable[[], Policy]) -> list[EpisodeOutcome]:
    """``make_policy``'s outcomes on the episodes a run of ``cfg`` plays at each periodic
    evaluation (its eval.csv rows), so that a reference policy can be scored on them too."""
    # Validation episodes when a search scores this run, an evaluation set otherwise.
    reset_seed = validation_reset_seed(0) if cfg.eval_seeds == "validation" else None
    return evaluate_policy(make_policy, cfg.scenario_specs(), cfg.eval_episodes, envs=min(16, cfg.eval_episodes),
                           backend=cfg.backend, seed_offset=TRAINING_EVAL_OFFSET, reset_seed=reset_seed,
                           observation=cfg.observation.model_dump(), reward=cfg.reward.model_dump())


def _evaluate(cfg: PolicyTrainConfig, net: QNetwork, device: torch.device) -> dict[str, Any]:
    net.eval()
    outcomes = periodic_evaluation(cfg, greedy_policy(net, device))
    net.train()
    return policy_report(outcomes).as_dict()


def train_policy(cfg: PolicyTrainConfig, run_dir: str | Path, *, resume: bool = False,
                 progress: bool = True, say: Callable[[str], None] = print,
                 on_eval: EvalCallback | None = None) -> TrainResult:
    """Train (or, with ``resume``, continue) a policy run in ``run_dir``.

    ``on_eval`` is told each periodic evaluation's result (see :data:`EvalCallback`).
    """
    root = Path(run_dir)
    if not resume and (root / CHECKPOINT).exists():
        raise ConfigError(f"{root}: already holds a policy run; give --resume to continue it, or another directory")
    if resume and not (root / CHECKPOINT).exists():
        raise ConfigError(f"{root}: nothing to resume (no {CHECKPOINT})")
    device = resolve_device(cfg.device)
    # A resumed run's checkpoint holds its encoder's weights: it needs its BNN folder only
    # if that is still there (to check it), not when the run was moved without it.
    bnn_gone = resume and cfg.bnn is not None and not (Path(cfg.bnn) / CHECKPOINT).exists()
    enc = stored_encoder(root) if bnn_gone else encoder_config(cfg)  # checked before anything is written
    if resume:
        check_resume(root, cfg)
    else:
        check_mission_pays(cfg)
    init_state = init_weights(cfg) if cfg.init_from and not resume else None
    root.mkdir(parents=True, exist_ok=True)
    with (dir_lock(root, "train-policy"),
          torch_settings(True, device, cfg.threads, resolve_precision(cfg.precision, device))):
        net = build_network(cfg, enc, load_bnn_weights=not bnn_gone).to(device)
        if init_state is not None:
            try:
                net.load_state_dict(init_state)
            except RuntimeError:
                raise ConfigError(f"--init-from {cfg.init_from}: its network's architecture differs from this run's") from None
        vec = make_vec(cfg.scenario_specs(), cfg.envs, backend=cfg.backend,
                       observation=cfg.observation.model_dump(), reward=cfg.reward.model_dump())
        learner = Learner(cfg, net, device, cfg.envs * vec.n_av, progress=progress)
        # Everything a resumption reads is checked before anything is written.
        logs = read_logs(root) if resume else {}
        if not resume:
            learner.check_memory()  # a resumed run checks before it loads its replay
        segment = learner.load(root) if resume else 0
        elapsed_before = _elapsed_before(root, logs.get(METRICS, []), learner.transitions)
        write_config(root, cfg, net, enc)
        if not resume:
            say(f"{cfg.mode}: {net.parameter_count()} parameters")
        log = RunLog(root, {name: cols for name, (_, cols) in LOGS.items()}, "transitions",
                     learner.transitions if resume else None, logs)
        try:
            return _run(cfg, root, net, learner, vec, segment, device, log, progress, on_eval, elapsed_before)
        finally:
            log.close()
            vec.close()


def _elapsed_before(root: Path, metrics: list[dict[str, str]], transitions: int) -> float:
    """Training seconds logged up to the checkpoint a resumption starts from (0 for a new run).

    The clock restarts each session; elapsed_s continues from here, so it counts the whole
    run's training time, less what a killed session did after its last checkpoint (the
    resumption redoes it)."""
    kept = [r for r in metrics if int(r["transitions"]) <= transitions]
    if not kept:
        return 0.0
    return seconds_logged(kept[-1].get("elapsed_s", ""),
                          f"{root / METRICS} at {kept[-1]['transitions']} agent-transitions", ConfigError)


def _run(cfg: PolicyTrainConfig, root: Path, net: QNetwork, learner: Learner, vec: Any, segment: int,
         device: torch.device, log: RunLog, progress: bool, on_eval: EvalCallback | None,
         elapsed_before: float) -> TrainResult:
    from tqdm import tqdm

    bar = tqdm(total=cfg.steps, initial=min(learner.transitions, cfg.steps), unit="tr", disable=not progress,
               dynamic_ncols=True, desc=f"train {cfg.mode}")
    recent: list[EpisodeOutcome] = []
    last_eval: dict[str, Any] = {}
    t0 = time.perf_counter()
    start_transitions = learner.transitions
    net.train()
    while learner.transitions < cfg.steps:
        end = min(cfg.steps, (segment + 1) * cfg.segment)
        before = learner.transitions
        for rec in learner_steps(learner, vec, train_reset_seed(cfg.seed, segment)):
            recent = (recent + rec.outcomes)[-200:]
            bar.update(min(learner.transitions, cfg.steps) - min(before, cfg.steps))
            before = learner.transitions
            if learner.transitions >= end:
                break
        learner.end_segment()
        elapsed = time.perf_counter() - t0
        loss = float(np.mean(learner.losses)) if learner.losses else float("nan")
        learner.losses.clear()
        row = {
            "transitions": learner.transitions, "updates": learner.updates, "episodes": learner.episodes,
            "epsilon": round(learner.eps(), 4), "loss": loss,
            "train_failure_rate": float(np.mean([o.failed for o in recent])) if recent else float("nan"),
            "train_crash_rate": float(np.mean([o.crashed for o in recent])) if recent else float("nan"),
            "transitions_per_s": (learner.transitions - start_transitions) / max(elapsed, 1e-9),
            "elapsed_s": round(elapsed_before + elapsed, 2),
        }
        if learner.aux is not None:
            # TensorBoard's train/aux_loss; metrics.csv keeps the columns every run has.
            row["aux_loss"] = float(np.mean(learner.aux.losses)) if learner.aux.losses else float("nan")
            learner.aux.losses.clear()
            if learner.aux.pretrain_losses:
                # dqn.aux_pretrain: the last hundred steps' mean, where the reader starts Q-learning.
                row["aux_pretrain_loss"] = float(np.mean(learner.aux.pretrain_losses[-100:]))
                learner.aux.pretrain_losses.clear()
        log.write(METRICS, row, "train")
        final = learner.transitions >= cfg.steps
        evaluated = final or bool(cfg.eval_every and (segment + 1) % cfg.eval_every == 0)
        if evaluated:
            last_eval = _evaluate(cfg, net, device)
            for name, summary in [*last_eval["scenarios"].items(), ("mixed", last_eval["mixed"])]:
                log.write(EVALS, {"transitions": learner.transitions, "scenario": name, "episodes": summary["episodes"],
                                  "failure_rate": summary["failure_rate"]["rate"],
                                  "crash_rate": summary["crash_rate"]["rate"],
                                  "success_rate": summary["success_rate"]["rate"],
                                  "mean_return": summary["mean_return"]["mean"]}, f"eval/{name}")
            mixed = last_eval["mixed"]
            if cfg.keep == "best":
                learner.consider_best(float(mixed["failure_rate"]["rate"]))
            bar.set_postfix(fail=f"{mixed['failure_rate']['rate']:.2f}", crash=f"{mixed['crash_rate']['rate']:.2f}")
        learner.save(root, segment)
        segment += 1
        if evaluated and on_eval is not None:
            # After the checkpoint: whatever the callback raises, the run resumes from here.
            on_eval(learner.transitions, float(last_eval["mixed"]["failure_rate"]["rate"]))
    bar.close()
    kept = ({"kept": {"transitions": learner.best_transitions, "failure_rate": learner.best_failure}}
            if learner.best is not None else {})
    # resumed_s: the training seconds of the sessions this one resumed from, so that a run
    # cut off and resumed reports what it cost (less what the cut-off session redid).
    return TrainResult(transitions=learner.transitions, updates=learner.updates, episodes=learner.episodes,
                       evaluation=last_eval, parameters=net.parameter_count(), resumed_s=round(elapsed_before, 2),
                       **kept)
