"""Double DQN: targets, loss and one learner update, as small functions.

Parameter sharing: every acting AV's transition goes into one replay and one Q-network,
as the paper's authors did, so a step of ``num_envs`` environments with ``n_av`` AVs
yields up to ``num_envs · n_av`` transitions.
"""

from __future__ import annotations

from collections.abc import Callable
from fractions import Fraction
from typing import Any, NamedTuple

import torch
import torch.nn.functional as F
from pydantic import Field, model_validator
from torch import Tensor, nn

from latentdrive.config import Config
from latentdrive.models.vfan import QNetwork
from latentdrive.rl.replay import Batch
from latentdrive.runtime import autocast

__all__ = ["DQNConfig", "Losses", "UpdateStats", "epsilon", "linear_decay", "losses", "priority_beta", "soft_update",
           "target_step", "td_targets", "update", "updates_owed"]

#: Largest denominator of ``updates_per_transition`` (the ratio is kept as an exact fraction).
MAX_RATIO_DENOMINATOR = 1024


class DQNConfig(Config):
    """Q-learning hyperparameters, the same for every input mode."""

    gamma: float = Field(0.95, gt=0.0, lt=1.0, description="Discount per policy step (1 s at 1 Hz); the authors' 0.95.")
    lr: float = Field(5e-4, gt=0.0, le=1.0, description="Adam learning rate (the authors' 5e-4).")
    adam_eps: float = Field(1e-8, gt=0.0, le=1.0, description="Adam's ε, added to the root of the squared-gradient average before dividing by it. PyTorch's 1e-8 is the default; sample-efficient DQNs on pixels (data-efficient Rainbow) use about 1.5e-4, which bounds the step of a weight whose gradients are rare and small, as they are for the many weights that read mostly empty map cells.")
    batch_size: int = Field(32, ge=1, le=4096, description="Transitions per update (the authors' 32).")
    buffer_size: int = Field(100_000, ge=100, le=5_000_000, description="Transitions kept in replay.")
    learning_starts: int = Field(2_000, ge=0, description="Agent-transitions collected before the first update.")
    updates_per_transition: float = Field(0.125, gt=0.0, le=64.0, description=f"Learner updates per agent-transition (the replay ratio is batch_size × this): 0.125 is one update per 8 agent-transitions, 2 two updates per agent-transition. Kept as an exact fraction with a denominator up to {MAX_RATIO_DENOMINATOR}. Older configs' train_every: k means 1/k.")
    n_step: int = Field(1, ge=1, le=64, description="Policy steps per return: the target sums n discounted rewards and bootstraps from the observation n steps later, discounted by γ^n. It stops at the agent's own terminal step (crash, mission completed: no bootstrap); where the agent is cut off (another AV crashed, time ran out, the segment ended) it bootstraps from the observation at the cut, discounted by γ^k for the k steps taken.")
    target_update: int = Field(500, ge=1, description="Learner updates between hard copies of the online network into the target network (used when tau is 0).")
    tau: float = Field(0.0, ge=0.0, le=1.0, description="Polyak rate of soft target updates: after every learner update the target network moves this share of the way to the online one (0: hard copies every target_update updates instead).")
    double: bool = Field(True, description="Double DQN: the online network picks the next action, the target network values it.")
    dueling: bool = Field(False, description="Dueling head: separate value and advantage streams (each as wide as vfan.hidden), Q = V + A − mean(A).")
    prioritized: bool = Field(False, description="Proportional prioritized replay: sample transitions in proportion to (|TD error| + priority_eps)^priority_alpha, with importance weights.")
    priority_alpha: float = Field(0.6, ge=0.0, le=1.0, description="Priority exponent of prioritized replay (0: uniform).")
    priority_beta: float = Field(0.4, ge=0.0, le=1.0, description="Importance-weight exponent at the first update; annealed linearly to 1 over the transition budget.")
    priority_eps: float = Field(1e-6, gt=0.0, le=1.0, description="Added to |TD error| (reward units) so that no transition's priority is 0.")
    huber_delta: float = Field(1.0, gt=0.0, description="Huber loss threshold (TD error units).")
    grad_clip: float = Field(10.0, gt=0.0, description="Maximum global gradient norm.")
    eps_start: float = Field(1.0, ge=0.0, le=1.0, description="ε of ε-greedy exploration at the first transition.")
    eps_end: float = Field(0.05, ge=0.0, le=1.0, description="ε after the decay.")
    eps_fraction: float = Field(0.3, gt=0.0, le=1.0, description="Share of the transition budget over which ε decays linearly.")
    augment_shift: int = Field(0, ge=0, le=8, description="Random-shift augmentation (DrQ): every sampled map and next map is moved by up to this many cells along each axis (edge cells repeated), independently per sample, before the update. Modes that read the map only (raw, end-to-end); 0, the default, is off.")
    aux_scale: float = Field(0.0, ge=0.0, le=100.0, description="Auxiliary loss that teaches the map reader to see the vehicles (latentdrive.rl.auxiliary): after each Q update, an Adam step of its own at aux_scale × lr (or, with aux_joint, a term weighted aux_scale in the Q update's loss) trains the reader and a small head to predict, from the map, the AV's speed and lane speed and its aux_neighbours nearest vehicles inside the map's view, read exactly from the Scene. Training only: the policy reads the map alone. vfan.reader 'attention' only; 0, the default, is off.")
    aux_joint: bool = Field(False, description="How the auxiliary loss (aux_scale > 0) trains the reader. False: after each Q update, an Adam step of its own at aux_scale × lr, with its own forward and backward pass of the sampled maps (about 1.56 times a Q update's arithmetic). True: aux_scale × its squared error is added to the Q update's loss, so one forward and one backward pass of the maps, the Q-learner's gradient clip and its Adam step serve both (about 1.01 times); the head keeps an Adam of its own at lr. Needs aux_scale > 0.")
    aux_pretrain: int = Field(0, ge=0, le=1_000_000, description="Steps of the auxiliary loss alone taken before the first Q update (aux_scale > 0): minibatches of the first observations of the transitions the replay holds at the first update (about learning_starts), one Adam of their own at lr moving the reader and the auxiliary head, after which the target network is set to the whole pretrained network. The reader then starts Q-learning already trained to see the vehicles, rather than learning it alongside. Raise learning_starts with it, so that the replay holds enough maps for the steps (each step draws batch_size of them; learning_starts below batch_size is refused). The steps run inside one learner call, with no checkpoint among them: a run killed during them repeats them on resume. 0, the default, is off.")
    aux_neighbours: int = Field(12, ge=1, le=64, description="Vehicles whose offsets, velocity differences, headings, kinds and crashed flags the auxiliary loss asks for (aux_scale > 0), nearest first.")
    explore_rule: float = Field(0.0, ge=0.0, le=1.0, description="Share of the exploratory actions (those ε-greedy plays instead of the greedy one) that the rule driver of evaluate --policy rule chooses instead of a uniform random action. Exploration guided toward the states a car follower reaches; one-step Q-learning, off-policy, still learns the greedy policy's values, while n-step returns (no off-policy correction) also follow the guide's later actions. 0, the default, is plain ε-greedy.")

    @model_validator(mode="before")
    @classmethod
    def _train_every(cls, data: Any) -> Any:
        """Configs written before the replay ratio was a fraction name ``train_every``
        (agent-transitions per update): ``train_every: k`` is ``updates_per_transition: 1/k``."""
        if isinstance(data, dict) and "train_every" in data:
            data = dict(data)
            k = data.pop("train_every")
            if "updates_per_transition" in data:
                raise ValueError("give updates_per_transition or the older train_every, not both")
            if not isinstance(k, int) or isinstance(k, bool) or not 1 <= k <= 4096:
                raise ValueError(f"train_every must be a whole number of agent-transitions in [1, 4096], got {k!r}")
            data["updates_per_transition"] = 1.0 / k
        return data

    @model_validator(mode="after")
    def _check(self) -> DQNConfig:
        if self.aux_joint and self.aux_scale == 0:
            raise ValueError("aux_joint shapes the auxiliary loss: it needs aux_scale > 0")
        if self.aux_pretrain and self.aux_scale == 0:
            raise ValueError("aux_pretrain takes steps of the auxiliary loss: it needs aux_scale > 0")
        if self.aux_pretrain and self.learning_starts < self.batch_size:
            raise ValueError(f"aux_pretrain trains on the maps stored before the first update: it needs learning_starts "
                             f"≥ batch_size ({self.batch_size}), got {self.learning_starts}")
        if self.eps_end > self.eps_start:
            raise ValueError(f"eps_end={self.eps_end} exceeds eps_start={self.eps_start}")
        ratio = Fraction(self.updates_per_transition).limit_denominator(MAX_RATIO_DENOMINATOR)
        if abs(float(ratio) - self.updates_per_transition) > 1e-9 * self.updates_per_transition:
            raise ValueError(f"updates_per_transition={self.updates_per_transition} is no fraction p/q with "
                             f"q ≤ {MAX_RATIO_DENOMINATOR} (e.g. 0.125, 0.5, 1, 2)")
        return self


def updates_owed(cfg: DQNConfig, transitions: int) -> int:
    """Learner updates due after ``transitions`` agent-transitions: none before
    ``learning_starts``, then ``updates_per_transition`` per transition, counted exactly."""
    ratio = Fraction(cfg.updates_per_transition).limit_denominator(MAX_RATIO_DENOMINATOR)
    return max(0, (transitions - cfg.learning_starts) * ratio.numerator // ratio.denominator)


def linear_decay(start: float, end: float, fraction: float, transitions: int, budget: int) -> float:
    """From ``start`` at 0 linearly to ``end`` after ``fraction · budget`` transitions, then flat."""
    frac = min(1.0, transitions / max(1.0, fraction * budget))
    return start + frac * (end - start)


def epsilon(cfg: DQNConfig, transitions: int, budget: int) -> float:
    """ε after ``transitions`` agent-transitions of a ``budget``: linear, then flat."""
    return linear_decay(cfg.eps_start, cfg.eps_end, cfg.eps_fraction, transitions, budget)


def priority_beta(cfg: DQNConfig, transitions: int, budget: int) -> float:
    """The importance-weight exponent after ``transitions`` of a ``budget``: from
    ``priority_beta`` linearly to 1 at the end of the budget."""
    frac = min(1.0, transitions / max(1, budget))
    return cfg.priority_beta + frac * (1.0 - cfg.priority_beta)


def td_targets(reward: Tensor, bootstrap: Tensor, q_next_online: Tensor, q_next_target: Tensor,
               gamma: float, double: bool, steps: Tensor | None = None) -> Tensor:
    """TD targets ``(B,)``: ``reward + γ^steps · bootstrap · Q_target(next, a*)``.

    ``bootstrap`` is 0 only where the agent itself terminated (crashed or completed its
    mission). An agent cut off because the episode ended for someone else, or because
    time ran out, keeps bootstrap 1: the time limit is not part of its state, and
    treating it as terminal would teach it that the world ends at the limit (the common
    truncation bug).

    Args:
        reward, bootstrap: ``(B,)``; ``reward`` is the discounted sum over ``steps``.
        q_next_online, q_next_target: ``(B, n_actions)`` Q-values of the next observation
            under the online and target networks.
        steps: ``(B,)`` policy steps from the observation to the next one (n-step
            returns); 1 everywhere when None.
    """
    if double:
        best = q_next_online.argmax(dim=1, keepdim=True)
        q_next = q_next_target.gather(1, best).squeeze(1)
    else:
        q_next = q_next_target.max(dim=1).values
    discount = gamma if steps is None else torch.pow(torch.tensor(gamma, dtype=q_next.dtype), steps)
    return reward + discount * bootstrap * q_next


class UpdateStats(NamedTuple):
    loss: float
    #: (B,) |TD error| of each sampled transition (for prioritized replay), fp32, detached.
    td_error: Tensor


class Losses(NamedTuple):
    """What one minibatch's update descends (:func:`losses`)."""

    q: Tensor  #: the Huber Q-loss, fp32 scalar
    joint: Tensor | None  #: the joint term (``joint``), fp32 scalar, or None
    q_taken: Tensor  #: (B,) Q-values of the actions taken, fp32
    target: Tensor  #: (B,) their TD targets, fp32, no gradient


def losses(online: nn.Module, target: nn.Module, batch: Batch, cfg: DQNConfig, dtype: torch.dtype = torch.float32,
           joint: Callable[[Tensor], Tensor] | None = None) -> Losses:
    """The Q-loss of ``batch`` (and a joint term) with their graphs, before any step.

    Forward passes run in ``dtype`` (bf16 autocast, or fp32); targets, TD errors and the
    loss are computed in fp32. With importance weights (``batch.weight``) each sample's
    Huber loss is weighted before the mean.

    ``joint``, when given, maps the online network's summary of ``batch.obs``
    ``(B, 2·attention_width)`` (:meth:`~latentdrive.models.vfan.QNetwork.summary`,
    attention reader) to a scalar loss: the Q-values are read from the same summary
    (:meth:`~latentdrive.models.vfan.QNetwork.q_from_summary`), so one forward pass of the
    observations serves both.
    """
    device = batch.obs.device
    with torch.no_grad(), autocast(dtype, device):
        q_target_next = target(batch.next_obs).float()
        q_online_next = online(batch.next_obs).float() if cfg.double else q_target_next
    y = td_targets(batch.reward, batch.bootstrap, q_online_next, q_target_next, cfg.gamma, cfg.double, batch.steps)
    z: Tensor | None = None
    with autocast(dtype, device):
        if joint is None:
            q_all = online(batch.obs)
        else:
            if not isinstance(online, QNetwork):
                raise TypeError("a joint loss reads a QNetwork's summary")
            z = online.summary(batch.obs)
            q_all = online.q_from_summary(z)
    q = q_all.float().gather(1, batch.action[:, None]).squeeze(1)
    if batch.weight is None:
        loss = F.huber_loss(q, y, delta=cfg.huber_delta)
    else:
        loss = (F.huber_loss(q, y, delta=cfg.huber_delta, reduction="none") * batch.weight).mean()
    return Losses(loss, None if joint is None or z is None else joint(z), q, y)


def update(online: nn.Module, target: nn.Module, optimizer: torch.optim.Optimizer, batch: Batch,
           cfg: DQNConfig, dtype: torch.dtype = torch.float32,
           joint: Callable[[Tensor], Tensor] | None = None) -> UpdateStats:
    """One gradient step on ``batch``'s :func:`losses`.

    With ``joint`` (``dqn.aux_joint``) the term is added to the Q-loss: one backward pass
    serves both, and the gradient clip applies to their summed gradient. The term's own
    parameters (a head) get their gradients from the same backward pass; stepping them is
    the caller's. The returned loss is the Q-loss alone.
    """
    parts = losses(online, target, batch, cfg, dtype, joint)
    total = parts.q if parts.joint is None else parts.q + parts.joint
    optimizer.zero_grad(set_to_none=True)
    total.backward()
    params = [p for g in optimizer.param_groups for p in g["params"]]
    nn.utils.clip_grad_norm_(params, cfg.grad_clip)
    optimizer.step()
    return UpdateStats(float(parts.q.detach()), (parts.q_taken.detach() - parts.target).abs())


def target_step(target: nn.Module, online: nn.Module, cfg: DQNConfig, updates: int) -> None:
    """The target network's move after learner update number ``updates`` (counted from 1):
    a Polyak step when ``cfg.tau`` > 0, else a hard copy every ``cfg.target_update`` updates."""
    if cfg.tau > 0:
        soft_update(target, online, cfg.tau)
    elif updates % cfg.target_update == 0:
        target.load_state_dict(online.state_dict())


@torch.no_grad()
def soft_update(target: nn.Module, online: nn.Module, tau: float) -> None:
    """Polyak averaging: every trainable parameter of ``target`` moves ``tau`` of the way to
    ``online``'s; frozen parameters (a frozen encoder) are equal in both and stay."""
    theirs = dict(online.named_parameters())
    for name, p in target.named_parameters():
        src = theirs[name]
        if src.requires_grad:
            p.lerp_(src, tau)
