"""Double DQN: targets, loss and one learner update, as small functions.

Parameter sharing: every acting AV's transition goes into one replay and one Q-network,
as the paper's authors did, so a step of ``num_envs`` environments with ``n_av`` AVs
yields up to ``num_envs · n_av`` transitions.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from pydantic import Field, model_validator
from torch import Tensor, nn

from latentdrive.config import Config
from latentdrive.rl.replay import Batch

__all__ = ["DQNConfig", "epsilon", "td_targets", "update"]


class DQNConfig(Config):
    """Q-learning hyperparameters, the same for every input mode."""

    gamma: float = Field(0.95, gt=0.0, lt=1.0, description="Discount per policy step (1 s at 1 Hz); the authors' 0.95.")
    lr: float = Field(5e-4, gt=0.0, le=1.0, description="Adam learning rate (the authors' 5e-4).")
    batch_size: int = Field(32, ge=1, le=4096, description="Transitions per update (the authors' 32).")
    buffer_size: int = Field(100_000, ge=100, le=5_000_000, description="Transitions kept in replay.")
    learning_starts: int = Field(2_000, ge=0, description="Agent-transitions collected before the first update.")
    train_every: int = Field(8, ge=1, le=4096, description="Agent-transitions per learner update (the replay ratio is batch_size / train_every).")
    target_update: int = Field(500, ge=1, description="Learner updates between hard copies of the online network into the target network.")
    double: bool = Field(True, description="Double DQN: the online network picks the next action, the target network values it.")
    huber_delta: float = Field(1.0, gt=0.0, description="Huber loss threshold (TD error units).")
    grad_clip: float = Field(10.0, gt=0.0, description="Maximum global gradient norm.")
    eps_start: float = Field(1.0, ge=0.0, le=1.0, description="ε of ε-greedy exploration at the first transition.")
    eps_end: float = Field(0.05, ge=0.0, le=1.0, description="ε after the decay.")
    eps_fraction: float = Field(0.3, gt=0.0, le=1.0, description="Share of the transition budget over which ε decays linearly.")

    @model_validator(mode="after")
    def _check_eps(self) -> DQNConfig:
        if self.eps_end > self.eps_start:
            raise ValueError(f"eps_end={self.eps_end} exceeds eps_start={self.eps_start}")
        return self


def epsilon(cfg: DQNConfig, transitions: int, budget: int) -> float:
    """ε after ``transitions`` agent-transitions of a ``budget``: linear, then flat."""
    frac = min(1.0, transitions / max(1.0, cfg.eps_fraction * budget))
    return cfg.eps_start + frac * (cfg.eps_end - cfg.eps_start)


def td_targets(reward: Tensor, bootstrap: Tensor, q_next_online: Tensor, q_next_target: Tensor,
               gamma: float, double: bool) -> Tensor:
    """One-step TD targets ``(B,)``.

    ``bootstrap`` is 0 only where the agent itself terminated (crashed or completed its
    mission). An agent cut off because the episode ended for someone else, or because
    time ran out, keeps bootstrap 1: the time limit is not part of its state, and
    treating it as terminal would teach it that the world ends at the limit (the common
    truncation bug).

    Args:
        reward, bootstrap: ``(B,)``.
        q_next_online, q_next_target: ``(B, n_actions)`` Q-values of the next observation
            under the online and target networks.
    """
    if double:
        best = q_next_online.argmax(dim=1, keepdim=True)
        q_next = q_next_target.gather(1, best).squeeze(1)
    else:
        q_next = q_next_target.max(dim=1).values
    return reward + gamma * bootstrap * q_next


def update(online: nn.Module, target: nn.Module, optimizer: torch.optim.Optimizer, batch: Batch,
           cfg: DQNConfig) -> float:
    """One gradient step on ``batch``; returns the loss."""
    with torch.no_grad():
        q_target_next = target(batch.next_obs)
        q_online_next = online(batch.next_obs) if cfg.double else q_target_next
        y = td_targets(batch.reward, batch.bootstrap, q_online_next, q_target_next, cfg.gamma, cfg.double)
    q = online(batch.obs).gather(1, batch.action[:, None]).squeeze(1)
    loss = F.huber_loss(q, y, delta=cfg.huber_delta)
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    params = [p for g in optimizer.param_groups for p in g["params"]]
    nn.utils.clip_grad_norm_(params, cfg.grad_clip)
    optimizer.step()
    return float(loss.detach())
