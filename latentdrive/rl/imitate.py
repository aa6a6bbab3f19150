"""DAgger: the lookahead planner's decisions imitated through the policy's own observation.

The imitation reference answers a question the Q-learner cannot: how well can a policy
that reads the VelocityMap drive at all? The planner (:mod:`latentdrive.evaluate.planner`)
sees the simulator's state; a policy sees the map. A network with the same input mode and
VFAN body as the DQN policy is trained to predict the planner's action from the map, on
the states it visits itself (dataset aggregation, Ross, Gordon and Bagnell, AISTATS 2011):

- at every step the planner labels every acting AV's observation with its own action;
- the AV plays the planner's action with probability β, else the network's greedy one.
  β falls linearly from ``beta_start`` to ``beta_end`` over ``beta_fraction`` of the
  budget, so the data move from the planner's states to the policy's;
- the labelled observations go into the run's replay (its ``action`` slot holds the
  label), aggregated up to ``dqn.buffer_size``; updates minimize the cross-entropy of
  the network's outputs, read as logits, at ``dqn.updates_per_transition`` updates per
  labelled decision, with ``dqn.lr``, ``dqn.batch_size`` and ``dqn.grad_clip``.

The expert can also be the rule driver (``expert: rule``): its decisions follow from what
the map shows, so a copy that matches it shows that the network reads the map, and a gap
to the planner is then about what the planner alone knows.

The greedy action of the trained network (argmax of its outputs) is the policy, so every
tool that reads a policy run (``evaluate``, the study) reads an imitation run too. It is a
reference, not the paper's method: it needs the planner, hence the fast backend, while
training, and a planner that knows every driver's next move while labelling.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Literal

import numpy as np
import torch
import torch.nn.functional as F
from numpy.typing import NDArray
from pydantic import Field, model_validator
from torch import nn

from latentdrive.actions import N_ACTIONS
from latentdrive.config import Config
from latentdrive.evaluate.planner import PlannerConfig, planner_policy
from latentdrive.evaluate.policies import reference_policy
from latentdrive.rl.dqn import linear_decay
from latentdrive.rl.replay import Batch
from latentdrive.rollout import Policy, PolicyInput
from latentdrive.runtime import autocast
from latentdrive.scenarios import RewardConfig

__all__ = ["ExpertLabels", "ImitationConfig", "dagger_policy", "expert_policy", "expert_share", "imitation_update", "label_weights"]


class ImitationConfig(Config):
    """Settings of a DAgger run (``train-policy --learner dagger``)."""

    expert: Literal["plan", "rule"] = Field("plan", description="Whose actions the network learns: 'plan', the lookahead planner (the imitation reference: it knows every driver's next move); 'rule', the rule driver of evaluate --policy rule, which decides from the gap to the vehicle ahead and the AV's own speed, both drawn in the map (up to sensor noise and the map's reach), so imitating it tests whether the network reads the map at all.")
    beta_start: float = Field(1.0, ge=0.0, le=1.0, description="Probability that an AV plays the expert's action rather than the network's at the first labelled decision.")
    beta_end: float = Field(0.0, ge=0.0, le=1.0, description="That probability after the decay (0: the policy drives alone, every later label is on its own states).")
    beta_fraction: float = Field(0.5, gt=0.0, le=1.0, description="Share of the budget over which the probability falls linearly from beta_start to beta_end.")
    class_weighted: bool = Field(True, description="Weight each label's cross-entropy by the inverse frequency of its action among the aggregated labels (the experts mostly play Idle; unweighted, the rare lane changes and brakings hardly count).")
    planner: PlannerConfig = Field(default_factory=PlannerConfig, description="The lookahead planner's settings (expert 'plan').")

    @model_validator(mode="after")
    def _check(self) -> ImitationConfig:
        if self.beta_end > self.beta_start:
            raise ValueError(f"beta_end={self.beta_end} exceeds beta_start={self.beta_start}")
        return self


def expert_policy(cfg: ImitationConfig, reward: RewardConfig) -> Policy:
    """The expert that labels the decisions: the planner (under the run's reward) or the rule driver."""
    if cfg.expert == "rule":
        # The rule driver of the evaluation tables: no random lane changes, so every decision
        # follows from the scene and its random stream is never drawn from.
        return reference_policy("rule")()
    return planner_policy(cfg.planner, reward)


def expert_share(cfg: ImitationConfig, transitions: int, budget: int) -> float:
    """β after ``transitions`` labelled decisions of a ``budget``: linear, then flat."""
    return linear_decay(cfg.beta_start, cfg.beta_end, cfg.beta_fraction, transitions, budget)


class ExpertLabels:
    """The expert's actions ``(num_envs, n_av)`` at the latest step the policy acted on."""

    def __init__(self) -> None:
        self.latest: NDArray[np.int64] | None = None


def dagger_policy(expert: Policy, greedy: Callable[[PolicyInput], NDArray[np.int64]], rng: np.random.Generator,
                  beta: Callable[[], float], labels: ExpertLabels) -> Policy:
    """The DAgger behaviour policy: per AV, the expert's action with probability ``beta()``,
    else ``greedy``'s. Every step records the expert's actions in ``labels`` (the caller
    stores them with the step's observations), and draws the same random numbers whoever
    acts, so the stream does not depend on the episodes' course."""

    def policy(inp: PolicyInput) -> NDArray[np.int64]:
        planned = np.asarray(expert(inp), dtype=np.int64)
        labels.latest = planned
        own = greedy(inp)
        follow = rng.random(planned.shape) < beta()
        return np.where(follow, planned, own).astype(np.int64)

    return policy


def label_weights(labels: NDArray[np.int64], n_actions: int = N_ACTIONS) -> NDArray[np.float32]:
    """Per-action weights ``(n_actions,)`` inversely proportional to each action's count in
    ``labels``, scaled so that the labelled data's mean weight is 1. An action never seen
    gets weight 0 (it has nothing to weight)."""
    counts = np.bincount(labels, minlength=n_actions).astype(np.float64)
    seen = counts > 0
    w = np.zeros(n_actions)
    w[seen] = counts.sum() / (seen.sum() * counts[seen])
    return w.astype(np.float32)


def imitation_update(net: nn.Module, optimizer: torch.optim.Optimizer, batch: Batch, weights: torch.Tensor | None,
                     grad_clip: float, dtype: torch.dtype = torch.float32) -> float:
    """One gradient step of cross-entropy between ``net(batch.obs)`` (logits ``(B, A)``) and the
    labels ``batch.action`` ``(B,)``, each weighted by ``weights[label]`` when given
    (a weighted mean). The forward pass runs in ``dtype``; the loss in fp32."""
    with autocast(dtype, batch.obs.device):
        logits = net(batch.obs)
    loss = F.cross_entropy(logits.float(), batch.action, weight=weights)
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    params = [p for g in optimizer.param_groups for p in g["params"]]
    nn.utils.clip_grad_norm_(params, grad_clip)
    optimizer.step()
    return float(loss.detach())
