"""The learner of a policy run: its replay, its updates and its checkpoint.

One :class:`Learner` per run. It stores each step's transitions (through the n-step window,
:mod:`latentdrive.rl.nstep`), takes the updates they are owed (double DQN,
:mod:`latentdrive.rl.dqn`, or DAgger's supervised fit, :mod:`latentdrive.rl.imitate`), and
writes and restores everything a resumed run needs to continue bit for bit: the networks,
the optimizers, the counters, the generator and the replay. :mod:`latentdrive.rl.train`
drives it through segments, evaluations and the run folder.
"""

from __future__ import annotations

import copy
import re
import time
from pathlib import Path

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
from latentdrive.config import ConfigError, validate
from latentdrive.errors import first_line
from latentdrive.fileio import atomic_write_bytes, confined
from latentdrive.models.vfan import QNetwork
from latentdrive.rl.augment import random_shift
from latentdrive.rl.auxiliary import AuxLearning
from latentdrive.rl.config import PolicyTrainConfig
from latentdrive.rl.dqn import epsilon, priority_beta, target_step, update, updates_owed
from latentdrive.rl.imitate import expert_share, imitation_update, label_weights
from latentdrive.rl.nstep import NStepEntries, NStepWindow
from latentdrive.rl.policy import CHECKPOINT, FeatureCache, build_network, read_run_config
from latentdrive.rl.replay import FrameStore, LatentStore, ObservationStore, Replay
from latentdrive.rollout import StepRecord
from latentdrive.runtime import available_memory, resolve_precision

__all__ = ["REPLAY_PATTERN", "Learner", "make_store", "restore_with_targets"]

#: Replay of segment k: ``replay-<k>.safetensors``. A new name per segment, so that a kill
#: while saving never leaves a checkpoint beside a replay it does not belong to.
REPLAY_PATTERN = re.compile(r"replay-(\d{1,9})\.safetensors")


def make_store(net: QNetwork, cfg: PolicyTrainConfig, n_slots: int) -> ObservationStore:
    cap = cfg.dqn.buffer_size
    # n-step entries reach the replay up to n-1 steps after their first observation was
    # stored: the store keeps 2·(n-1) more steps' worth of observations per agent slot.
    late = 2 * (cfg.dqn.n_step - 1) * n_slots
    if net.stores_features:
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

    def __init__(self, cfg: PolicyTrainConfig, net: QNetwork, device: torch.device, n_slots: int,
                 progress: bool = False) -> None:
        self.cfg, self.net, self.device = cfg, net, device
        self.dtype = resolve_precision(cfg.precision, device)
        self.target = copy.deepcopy(net).requires_grad_(False)
        # One fused kernel for every parameter instead of a loop of small ops: the Q-networks are
        # small enough that the loop's per-op overhead shows (1.10-1.14x agent-transitions/s by
        # `latentdrive bench --train`, docs/performance.md). A checkpoint keeps its optimizer's
        # setting, so a run written before resumes as it began.
        self.optimizer = torch.optim.Adam(net.trainable_parameters(), lr=cfg.dqn.lr, eps=cfg.dqn.adam_eps,
                                          fused=device.type in ("cpu", "cuda"))
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
        self.progress = progress  # a progress bar for long steps inside learn() (the pretraining)
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
        """The updates the transitions collected so far are owed (``dqn.updates_per_transition``),
        the first of them preceded by the reader's pretraining (``dqn.aux_pretrain``)."""
        t0 = time.perf_counter()
        owed = updates_owed(self.cfg.dqn, self.transitions) - self.updates
        # updates travels in the checkpoint and the pretraining is followed by an update in
        # this same call, so updates == 0 means "not pretrained yet", across resumes too.
        if owed > 0 and self.updates == 0 and self.aux is not None and self.cfg.dqn.aux_pretrain:
            self.pretrain()
        for _ in range(max(0, owed)):
            self.update_step()
        self.learn_seconds += time.perf_counter() - t0

    def pretrain(self) -> None:
        """``dqn.aux_pretrain``: the reader's steps on the auxiliary loss alone, once, right
        before the first update (so a resumed run repeats them only if its checkpoint came
        before that), then the target network set to the whole pretrained network: the
        first targets are read by the pretrained reader, not by the random one a hard
        copy (``target_update`` updates later) or Polyak's steps (``tau``) would replace
        only gradually."""
        from tqdm import tqdm

        assert self.aux is not None
        d = self.cfg.dqn
        batches = (self.replay.sample_observations(self.rng, d.batch_size, self.device)
                   for _ in tqdm(range(d.aux_pretrain), desc="pretrain reader", unit="step", leave=False,
                                 disable=not self.progress))
        self.aux.pretrain(self.net, batches, d.lr, d.adam_eps, self.dtype)
        self.target.load_state_dict(self.net.state_dict())

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
        joint = None
        if self.aux is not None and self.aux.joint:
            assert batch.slots is not None
            joint = self.aux.joint_term(self.replay.obs_id[batch.slots], self.device, self.dtype)
        stats = update(self.net, self.target, self.optimizer, batch, d, self.dtype, joint=joint)
        self.losses.append(stats.loss)
        if self.aux is not None:
            assert batch.slots is not None
            if self.aux.joint:
                self.aux.step_head()
            else:
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

    def check_memory(self) -> None:
        """Refuse, before training starts or resumes, a replay that would outgrow the memory
        available once it holds ``min(steps, buffer_size)`` transitions (its arrays are
        reserved whole and fill as the run goes: without this a run fails hours in, or
        drives the machine into swap). Runs going at once are not counted together."""
        held = min(self.cfg.steps, self.replay.capacity)
        need, have = self.replay.nbytes_at(held), available_memory()
        if have is not None and need > have:
            raise ConfigError(f"the replay would take {need / 2**30:.1f} GiB at {held:,} transitions (dqn.buffer_size "
                              f"{self.replay.capacity:,}) and {have / 2**30:.1f} GiB of memory is available: lower "
                              "dqn.buffer_size, or the observation's size (vfan.objects_k, observation.frames)")

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
        self.check_memory()
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
            self.replay.load_state(arrays)
            if self.aux is not None:
                self.aux.load_arrays(arrays, self.replay.store.added)
        except (KeyError, TypeError, ValueError) as exc:
            raise CheckpointError(f"{path}: unusable replay ({first_line(exc)})") from None
        if self.replay.added != replay_added:
            raise CheckpointError(f"{path}: replay does not belong to the checkpoint (written by another save)")
        return segment + 1


def restore_with_targets(run: Path) -> tuple[PolicyTrainConfig, QNetwork, Learner]:
    """A run trained with the auxiliary loss, restored on the CPU for inspection: its config,
    network and learner (replay and auxiliary targets included). Raises ConfigError for a
    run without the loss (its replay holds no targets), CheckpointError for a damaged one."""
    cfg = validate(PolicyTrainConfig, read_run_config(run)["train"])
    if cfg.dqn.aux_scale == 0:
        raise ConfigError(f"{run}: trained without the auxiliary loss (dqn.aux_scale is 0): its replay holds no targets")
    # A finished run restores its replay only with training left: ask for one more step.
    cfg = cfg.model_copy(update={"steps": 10**12})
    net = build_network(cfg, None)
    learner = Learner(cfg, net, torch.device("cpu"), cfg.envs * cfg.scenario_specs()[0].n_av)
    learner.load(run)
    return cfg, net, learner
