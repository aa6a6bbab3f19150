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

import copy
import re
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors.numpy import save as np_save
from safetensors.torch import load_file as st_load_file

from latentdrive.bnn.checkpoint import (
    CheckpointError,
    load_checkpoint,
    save_checkpoint,
    section,
    tensors_digest,
)
from latentdrive.bnn.runlog import RunLog
from latentdrive.config import ConfigError
from latentdrive.errors import first_line
from latentdrive.evaluate.policies import reference_policy
from latentdrive.evaluate.report import policy_report
from latentdrive.evaluate.run import evaluate_policy
from latentdrive.fileio import atomic_write_bytes, confined
from latentdrive.models.vfan import LATENT_MODES, QNetwork
from latentdrive.outcome import EpisodeOutcome
from latentdrive.rl.augment import random_shift
from latentdrive.rl.auxiliary import AuxLearning
from latentdrive.rl.config import PolicyTrainConfig, check_mission_pays
from latentdrive.rl.dqn import epsilon, priority_beta, target_step, update, updates_owed
from latentdrive.rl.imitate import (
    ExpertLabels,
    dagger_policy,
    expert_policy,
    expert_share,
    imitation_update,
    label_weights,
)
from latentdrive.rl.nstep import NStepEntries, NStepWindow
from latentdrive.rl.policy import (
    CHECKPOINT,
    FeatureCache,
    build_network,
    encoder_config,
    epsilon_greedy,
    greedy_actions,
    greedy_policy,
)
from latentdrive.rl.replay import FrameStore, LatentStore, ObservationStore, Replay
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

__all__ = ["REPLAY_PATTERN", "EvalCallback", "Learner", "TrainResult", "learner_steps",
           "make_store", "periodic_evaluation", "train_policy"]

#: Replay of segment k: ``replay-<k>.safetensors``. A new name per segment, so that a kill
#: while saving never leaves a checkpoint beside a replay it does not belong to.
REPLAY_PATTERN = re.compile(r"replay-(\d{1,9})\.safetensors")


#: Called after each periodic evaluation, once its checkpoint is saved, with the
#: agent-transitions so far and the mixed failure rate in [0, 1]. An exception it raises
#: (a search pruning the run) ends training there; the run resumes from that checkpoint.
EvalCallback = Callable[[int, float], None]


class TrainResult(dict[str, Any]):
    """Final counters and the last evaluation (a plain dict, JSON-serializable)."""


def make_store(net: QNetwork, cfg: PolicyTrainConfig, n_slots: int) -> ObservationStore:
    cap = cfg.dqn.buffer_size
    # n-step entries reach the replay up to n-1 steps after their first observation was
    # stored: the store keeps 2·(n-1) more steps' worth of observations per agent slot.
    late = 2 * (cfg.dqn.n_step - 1) * n_slots
    if net.mode in LATENT_MODES:
        # Per step: one next observation per transition and n_av first observations per
        # ended environment; over the replay's span that is at most 2·cap + 3·n_slots.
        return LatentStore(2 * cap + 4 * n_slots + late, net.stored_shape)
    t = cfg.observation.frames
    return FrameStore(2 * cap + (2 * t + 1) * n_slots + late, cfg.observation.shape)


class Learner:
    """Replay writing and updates; one instance per run.

    Under ``learner: dagger`` the replay aggregates the planner's labels (its ``action``
    slot holds the label, rewards are kept but unused) and updates fit them
    (:mod:`latentdrive.rl.imitate`); the target network is kept but never read.
    """

    def __init__(self, cfg: PolicyTrainConfig, net: QNetwork, device: torch.device, n_slots: int) -> None:
        self.cfg, self.net, self.device = cfg, net, device
        self.dtype = resolve_precision(cfg.precision, device)
        self.target = copy.deepcopy(net).requires_grad_(False)
        self.optimizer = torch.optim.Adam(net.trainable_parameters(), lr=cfg.dqn.lr, eps=cfg.dqn.adam_eps)
        d = cfg.dqn
        self.replay = Replay(d.buffer_size, make_store(net, cfg, n_slots), prioritized=d.prioritized,
                             alpha=d.priority_alpha, priority_eps=d.priority_eps)
        self.window: NStepWindow | None = None  # sized by the first step's agent slots
        self.rng = np.random.default_rng(np.random.SeedSequence([cfg.seed, 0x51]))
        self.transitions = 0
        self.updates = 0
        self.episodes = 0
        self.losses: list[float] = []
        self.learn_seconds = 0.0  # wall time in updates (for the benchmark)
        self.cache = FeatureCache(net, device, self.dtype)
        # dqn.aux_scale: targets of every stored observation, beside the store (rl.auxiliary).
        self.aux = (AuxLearning(net, d, cfg.observation, self.replay.store.capacity, device)
                    if d.aux_scale > 0 else None)
        self._weights = torch.ones(0)  # DAgger's class weights, as of replay.added == _weights_at
        self._weights_at = -1
        # keep 'best': the weights that failed least at a periodic evaluation so far.
        self.best: dict[str, torch.Tensor] | None = None
        self.best_failure = float("inf")
        self.best_transitions = -1

    @property
    def imitating(self) -> bool:
        return self.cfg.learner == "dagger"

    def eps(self) -> float:
        """The share of actions that are not the network's greedy choice: ε of ε-greedy,
        or under DAgger β, the planner's share."""
        if self.imitating:
            return expert_share(self.cfg.imitation, self.transitions, self.cfg.steps)
        return epsilon(self.cfg.dqn, self.transitions, self.cfg.steps)

    def start_segment(self, obs_feats: torch.Tensor, scenes: np.ndarray | None = None) -> np.ndarray:
        """Store every agent's first observation (``scenes``: the Scenes they show, which
        the auxiliary loss needs); ids ``(num_envs, n_av)``."""
        e, a = obs_feats.shape[:2]
        flat = obs_feats.reshape(e * a, *obs_feats.shape[2:]).cpu().numpy()
        ids = self.replay.store.add(flat, np.full(e * a, -1, dtype=np.int64))
        if self.aux is not None:
            assert scenes is not None
            self.aux.add(self.aux.targets(scenes).reshape(e * a, -1), ids)
        return ids.reshape(e, a)

    def record(self, rec: StepRecord, cur: np.ndarray, cache: FeatureCache,
               labels: np.ndarray | None = None) -> np.ndarray:
        """Store the step's transitions; returns the agents' current observation ids.

        ``labels`` ``(num_envs, n_av)``: the expert's actions (DAgger), stored in place of
        the actions taken, one step each."""
        ag = rec.agents
        ei, ai = np.nonzero(ag.acting)
        # Encoded once: the policy reuses it on the next step. Needed: where a transition
        # leads, and every agent of a new episode; not the AVs already done.
        after = cache(rec.obs_after, ag.acting | rec.ended[:, None])
        nxt = after[ei, ai]
        ended_rows = rec.ended[ei]
        if ended_rows.any():
            # An ended episode's transitions lead to its final observation, not the new
            # episode's first one.
            nxt = nxt.clone()
            nxt[torch.from_numpy(ended_rows)] = cache.encode(rec.next_obs[ei[ended_rows], ai[ended_rows]])
        store = self.replay.store
        next_ids = store.add(nxt.cpu().numpy(), cur[ei, ai])
        if self.aux is not None:
            # rec.scenes are those next_obs shows: the ended episode's last where it ended.
            self.aux.add(self.aux.targets(rec.scenes)[ei, ai], next_ids)
        # terminated (crash, mission done) does not bootstrap; cut-off agents (another AV
        # crashed, time ran out, the segment ended) do: see rl.dqn.td_targets. The window
        # turns the one-step transitions into n-step ones (rl.nstep).
        if labels is not None:
            self.replay.add(cur[ei, ai], labels[ei, ai], ag.reward[ei, ai], next_ids, ag.terminated[ei, ai])
        else:
            if self.window is None:
                self.window = NStepWindow(self.cfg.dqn.n_step, self.cfg.dqn.gamma, cur.shape)
            self._store(self.window.push(ei, ai, cur[ei, ai], rec.actions[ei, ai], ag.reward[ei, ai], next_ids,
                                         ag.terminated[ei, ai], ag.truncated[ei, ai]))
        cur = cur.copy()
        cur[ei, ai] = next_ids
        for e in np.flatnonzero(rec.ended):
            flat = after[e].cpu().numpy()
            cur[e] = store.add(flat, np.full(len(flat), -1, dtype=np.int64))
            if self.aux is not None:
                assert rec.scenes_after is not None
                self.aux.add(self.aux.targets(rec.scenes_after[e:e + 1])[0], cur[e])
        self.transitions += len(ei)
        self.episodes += len(rec.outcomes)
        return cur

    def _store(self, entries: NStepEntries) -> None:
        self.replay.add(entries.obs_id, entries.action, entries.reward, entries.next_id, entries.terminated,
                        entries.steps)

    def end_segment(self) -> None:
        """Store the n-step transitions still pending: the segment's end cuts every agent
        off, and they bootstrap from their latest observation. Called before each checkpoint,
        which therefore holds no pending state."""
        if self.window is not None:
            self._store(self.window.flush())
            self.window = None

    def learn(self) -> None:
        """The updates the transitions collected so far are owed (``dqn.updates_per_transition``)."""
        t0 = time.perf_counter()
        owed = updates_owed(self.cfg.dqn, self.transitions) - self.updates
        for _ in range(max(0, owed)):
            self.update_step()
        self.learn_seconds += time.perf_counter() - t0

    def update_step(self) -> None:
        """One sampled minibatch, one gradient step, and the target update when it is due."""
        d = self.cfg.dqn
        if self.imitating:
            batch = self.replay.sample(self.rng, d.batch_size, self.device)
            weights = self._label_weights() if self.cfg.imitation.class_weighted else None
            self.losses.append(imitation_update(self.net, self.optimizer, batch, weights, d.grad_clip, self.dtype))
            self.updates += 1
            return
        beta = priority_beta(d, self.transitions, self.cfg.steps)
        batch = self.replay.sample(self.rng, d.batch_size, self.device, beta=beta)
        if d.augment_shift:
            batch = batch._replace(obs=random_shift(batch.obs, d.augment_shift, self.rng),
                                   next_obs=random_shift(batch.next_obs, d.augment_shift, self.rng))
        stats = update(self.net, self.target, self.optimizer, batch, d, self.dtype)
        self.losses.append(stats.loss)
        if self.aux is not None:
            assert batch.slots is not None
            self.aux.step(self.net, batch.obs, self.replay.obs_id[batch.slots], self.dtype)
        if batch.slots is not None and d.prioritized:
            self.replay.update_priorities(batch.slots, stats.td_error.cpu().numpy())
        self.updates += 1
        target_step(self.target, self.net, d, self.updates)

    def _label_weights(self) -> torch.Tensor:
        """The class weights of the labels in the replay, recounted only when it changed
        (once per environment step, not once per update)."""
        if self._weights_at != self.replay.added:
            labels = self.replay.action[:len(self.replay)]
            self._weights = torch.from_numpy(label_weights(labels)).to(self.device)
            self._weights_at = self.replay.added
        return self._weights

    def consider_best(self, failure: float) -> None:
        """Keep the current weights as the run's best if they failed (mixed failure rate in
        [0, 1] at a periodic evaluation) no more often than the best so far; ties go to the
        later weights, trained on more data."""
        if failure <= self.best_failure:
            self.best = {k: v.detach().cpu().clone() for k, v in self.net.state_dict().items()}
            self.best_failure, self.best_transitions = failure, self.transitions

    # ---- checkpoints ---------------------------------------------------------------

    def save(self, run_dir: Path, segment: int) -> None:
        state = {**self.replay.state(), **({} if self.aux is None else self.aux.arrays())}
        arrays = {k: np.ascontiguousarray(v) for k, v in state.items()}
        # The replay first, under a new name; then the checkpoint that names it (atomic);
        # only then are older replays removed. A kill anywhere leaves a consistent pair.
        # The checkpoint keeps the replay's digest: a damaged replay is refused on
        # resumption rather than silently training on other transitions.
        name = f"replay-{segment}.safetensors"
        # The best weights travel in the checkpoint itself, so they and the counters that
        # chose them are written together.
        best = {} if self.best is None else {f"best/{k}": v for k, v in self.best.items()}
        kept = {} if self.best is None else {"best_failure": self.best_failure, "best_transitions": self.best_transitions}
        aux = {} if self.aux is None else {f"aux_head/{k}": v for k, v in self.aux.head.state_dict().items()}
        atomic_write_bytes(run_dir / name, np_save(arrays, metadata={"replay_added": str(self.replay.added)}))
        save_checkpoint(
            run_dir / CHECKPOINT, self.net, self.optimizer, step=self.updates, epoch=segment,
            config=self.cfg.model_dump(mode="json"), numpy_generator=self.rng,
            extra={"transitions": self.transitions, "updates": self.updates, "episodes": self.episodes,
                   "segment": segment, "replay_added": self.replay.added, "replay": name,
                   "replay_digest": tensors_digest({k: torch.from_numpy(v) for k, v in arrays.items()}), **kept},
            extra_tensors={**{f"target/{k}": v for k, v in self.target.state_dict().items()}, **best, **aux},
            extra_optimizers=None if self.aux is None else {"aux": self.aux.optimizer},
        )
        for old in run_dir.iterdir():
            if REPLAY_PATTERN.fullmatch(old.name) and old.name != name:
                old.unlink(missing_ok=True)

    def load(self, run_dir: Path) -> int:
        """Restore from the run's checkpoint; returns the next segment index.

        The replay is restored only when there is training left to do: a finished run
        resumes to nothing and needs none.
        """
        info = load_checkpoint(run_dir / CHECKPOINT, self.net, self.optimizer, numpy_generator=self.rng,
                               extra_optimizers=None if self.aux is None else {"aux": self.aux.optimizer})
        target_sd = section(info.extra_tensors, "target/")
        try:
            self.target.load_state_dict(target_sd, strict=True)
            if self.aux is not None:
                self.aux.head.load_state_dict(section(info.extra_tensors, "aux_head/"), strict=True)
        except RuntimeError:
            raise CheckpointError(f"{run_dir / CHECKPOINT}: target network or auxiliary head does not match the "
                                  "model") from None
        try:
            self.transitions = int(info.extra["transitions"])
            self.updates = int(info.extra["updates"])
            self.episodes = int(info.extra["episodes"])
            segment = int(info.extra["segment"])
            replay_added = int(info.extra.get("replay_added", -1))
            best = section(info.extra_tensors, "best/")
            if best:
                self.best = best
                self.best_failure = float(info.extra["best_failure"])
                self.best_transitions = int(info.extra["best_transitions"])
        except (KeyError, TypeError, ValueError):
            raise CheckpointError(f"{run_dir / CHECKPOINT}: not a policy run's checkpoint (no training counters)") from None
        if self.transitions >= self.cfg.steps:
            return segment + 1
        # Checkpoints written before replays were named per segment used one fixed name.
        name = info.extra.get("replay", "replay.safetensors")
        path = confined(run_dir, name, source=run_dir / CHECKPOINT, error=CheckpointError)
        if not (REPLAY_PATTERN.fullmatch(str(name)) or name == "replay.safetensors"):
            raise CheckpointError(f"{run_dir / CHECKPOINT}: names no valid replay file ({name!r})")
        try:
            tensors = st_load_file(str(path))
        except FileNotFoundError:
            raise CheckpointError(f"{path}: missing; the run cannot resume without its replay") from None
        except Exception as exc:  # the safetensors parser raises its own error types
            raise CheckpointError(f"{path}: unusable replay ({first_line(exc)})") from None
        # Checkpoints written before replays were digested have none to compare.
        digest = info.extra.get("replay_digest")
        if digest is not None and tensors_digest(tensors) != digest:
            raise CheckpointError(f"{path}: corrupt replay (checksum mismatch with {CHECKPOINT})")
        try:
            arrays = {k: t.numpy() for k, t in tensors.items()}
            if self.aux is not None:
                self.aux.load_arrays(arrays)
            self.replay.load_state(arrays)
        except (KeyError, TypeError, ValueError) as exc:
            raise CheckpointError(f"{path}: unusable replay ({first_line(exc)})") from None
        if self.replay.added != replay_added:
            raise CheckpointError(f"{path}: replay does not belong to the checkpoint (written by another save)")
        return segment + 1


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
        learner = Learner(cfg, net, device, cfg.envs * vec.n_av)
        # Everything a resumption reads is checked before anything is written.
        logs = read_logs(root) if resume else {}
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
    text = kept[-1].get("elapsed_s", "") if kept else ""
    try:
        return float(text) if text else 0.0
    except ValueError:
        raise ConfigError(f"{root / METRICS}: elapsed_s {text!r} at {kept[-1]['transitions']} "
                          "agent-transitions is not a number") from None


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
    return TrainResult(transitions=learner.transitions, updates=learner.updates, episodes=learner.episodes,
                       evaluation=last_eval, parameters=net.parameter_count(), **kept)
