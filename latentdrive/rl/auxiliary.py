"""An auxiliary loss that teaches the map reader to see the vehicles (``dqn.aux_scale``).

The Q-loss alone teaches the attention reader little of where the other vehicles are: a
reader fed the same map learns to drive far better when it is also asked to say, from
the map, what the map shows (docs/readers.md, "The attention reader told its place, or
taught to see the vehicles"). The targets are exact values read from the Scene each
observation was rendered from (:func:`latentdrive.observe.state.view_targets`): the AV's
speed and lane speed and its ``aux_neighbours`` nearest vehicles inside its map's view,
each as offsets, velocity differences and heading in the AV's frame, kind and crashed flag.

After each Q update, one Adam step of its own (at ``aux_scale`` × ``dqn.lr``; Adam's steps
do not scale with the loss, so the scale goes into the rate) moves the reader and a small
head by the squared error of that head's prediction, on the same sampled observations.
The Q-learner's update and its optimizer's moments stay those of :func:`~latentdrive.rl.dqn.update`.

With ``aux_joint`` the squared error, times ``aux_scale``, is added to the Q update's loss
instead: the reader's summary of the sampled maps is computed once and one backward pass
serves both losses, about 1.01 times a Q update's arithmetic instead of about 1.56 times.
The reader then moves by the Q-learner's gradient clip and Adam step on the summed
gradient, so the scale is a weight on the loss, not on the rate, and the two losses share
the optimizer's moments; the head has an Adam of its own at ``dqn.lr``.

With ``aux_pretrain`` the reader and the head first take that many steps of the
auxiliary loss alone, on the maps the replay holds when Q-learning starts, so that the
Q-learner starts from a reader that already sees the vehicles
(:meth:`AuxLearning.pretrain`).

The head is used in training only: the policy reads the map and nothing else.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
from numpy.typing import NDArray
from torch import Tensor, nn

from latentdrive.config import ObservationConfig
from latentdrive.models.vfan import QNetwork
from latentdrive.observe.state import view_target_size, view_targets
from latentdrive.rl.dqn import DQNConfig, losses
from latentdrive.rl.replay import Batch, LatentStore
from latentdrive.runtime import autocast

__all__ = ["FIELDS", "RANKS", "AuxLearning", "GradientShare", "aux_error", "aux_head", "aux_step", "field_fit",
           "fit_table", "gradient_share", "scene_targets"]

#: The values of a neighbour's target row (latentdrive.observe.state), in order.
FIELDS = ("x", "y", "vx", "vy", "cos", "sin", "av", "crashed", "present")
#: Groups of neighbour ranks (nearest first, 0-based, end exclusive) :func:`field_fit` reports.
RANKS = ((0, 1), (1, 4), (4, None))


def aux_head(features: int, hidden: int, k: int) -> nn.Sequential:
    """The head that predicts the targets of ``k`` neighbours from ``features`` values of
    what the Q head reads."""
    return nn.Sequential(nn.Linear(features, hidden), nn.ReLU(), nn.Linear(hidden, view_target_size(k)))


def scene_targets(scenes: NDArray[np.object_], obs: ObservationConfig, k: int) -> NDArray[np.float32]:
    """:func:`~latentdrive.observe.state.view_targets` of every environment's Scene
    ``(num_envs,)``: ``(num_envs, n_av, view_target_size(k))`` float32."""
    return np.stack([view_targets(s, obs, k) for s in scenes])


def aux_error(head: nn.Module, z: Tensor, targets: Tensor, dtype: torch.dtype = torch.float32) -> Tensor:
    """The auxiliary loss: the mean squared error of ``head(z)`` ``(B, n)`` against
    ``targets`` ``(B, n)``, ``z`` the reader's summary; the head's forward pass in ``dtype``
    (bf16 autocast or fp32), the error in fp32. Every form of the loss (the separate step,
    the joint term, :func:`gradient_share`) computes it here."""
    with autocast(dtype, z.device):
        pred = head(z)
    return F.mse_loss(pred.float(), targets)


def aux_step(summary: Callable[[Tensor], Tensor], head: nn.Module, optimizer: torch.optim.Optimizer, obs: Tensor, targets: Tensor,
             dtype: torch.dtype = torch.float32) -> float:
    """One step of the auxiliary loss (:func:`aux_error` of ``summary(obs)``), the reader's
    forward pass in ``dtype`` too. Returns the loss."""
    with autocast(dtype, obs.device):
        z = summary(obs)
    loss = aux_error(head, z, targets, dtype)
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    optimizer.step()
    return float(loss.detach())


def field_fit(pred: NDArray[np.floating], targets: NDArray[np.floating], k: int) -> dict[str, float]:
    """How much of each target the head's predictions explain: R² = 1 − SSE / SST per value.

    ``pred`` and ``targets`` are ``(N, view_target_size(k))`` rows: the AV's two speeds,
    then ``k`` neighbour rows of :data:`FIELDS`. Keys: ``"speed"``, ``"lane speed"``, and
    ``"FIELD RANKS"`` for each field and group of neighbour ranks in :data:`RANKS` (``"x
    1"``, ``"vx 2-4"``, ``"present 5-k"``), pooled over the group's rows where a vehicle
    is present (every row for ``present``). NaN where a group holds no such rows or its
    target does not vary. 1 is a perfect fit, 0 no better than the target's mean."""
    n_f = len(FIELDS)
    if pred.shape != targets.shape or pred.ndim != 2 or pred.shape[1] != 2 + k * n_f:
        raise ValueError(f"pred and targets must both be (N, {2 + k * n_f}), got {pred.shape} and {targets.shape}")

    def r2(p: NDArray[np.floating], t: NDArray[np.floating]) -> float:
        sst = float(((t - t.mean()) ** 2).sum()) if t.size else 0.0
        return 1.0 - float(((p - t) ** 2).sum()) / sst if sst > 0 else float("nan")

    out = {"speed": r2(pred[:, 0], targets[:, 0]), "lane speed": r2(pred[:, 1], targets[:, 1])}
    p_rows = pred[:, 2:].reshape(len(pred), k, n_f).astype(np.float64)
    t_rows = targets[:, 2:].reshape(len(targets), k, n_f).astype(np.float64)
    for lo, hi in RANKS:
        end = k if hi is None else min(hi, k)
        if lo >= end:
            continue
        label = f"{lo + 1}" if end == lo + 1 else f"{lo + 1}-{end}"
        p_g, t_g = p_rows[:, lo:end].reshape(-1, n_f), t_rows[:, lo:end].reshape(-1, n_f)
        here = t_g[:, -1] > 0.5
        for j, name in enumerate(FIELDS):
            rows = slice(None) if name == "present" else here
            out[f"{name} {label}"] = r2(p_g[rows, j], t_g[rows, j])
    return out


def fit_table(fit: dict[str, float]) -> list[str]:
    """:func:`field_fit`'s neighbour values as text lines: a header of :data:`FIELDS`, then
    a row of R² per group of ranks."""
    groups = sorted({key.split(" ", 1)[1] for key in fit if key.startswith("x ")}, key=lambda g: int(g.split("-")[0]))
    return ["neighbours  " + "".join(f"{f:>9}" for f in FIELDS),
            *(f"{g:<10}  " + "".join(f"{fit[f'{f} {g}']:>9.2f}" for f in FIELDS) for g in groups)]


class GradientShare(NamedTuple):
    """:func:`gradient_share`'s result for one minibatch."""

    q_loss: float  #: the Huber Q-loss
    aux_loss: float  #: aux_scale × the auxiliary squared error (the joint term)
    q_norm: float  #: L2 norm of the Q-loss's gradient on the parameters both losses reach
    aux_norm: float  #: L2 norm of the joint term's gradient on the same parameters


def gradient_share(net: QNetwork, target: nn.Module, head: nn.Module, batch: Batch, targets: Tensor,
                   cfg: DQNConfig) -> GradientShare:
    """How much of a joint update's (``aux_joint``) step on the reader the auxiliary loss
    takes: the norms of the gradients of the Q-loss and of ``aux_scale`` × the head's
    squared error against ``targets`` ``(B, n)``, on ``batch``, over the parameters both
    reach (the reader; not the Q head, not the auxiliary head). Adam steps the sum, so the
    ratio ``aux_norm / q_norm`` is the auxiliary loss's weight in the reader's direction.
    In fp32; moves nothing."""
    parts = losses(net, target, batch, cfg, joint=lambda z: cfg.aux_scale * aux_error(head, z, targets))
    assert parts.joint is not None
    params = net.trainable_parameters()
    g_aux = torch.autograd.grad(parts.joint, params, retain_graph=True, allow_unused=True)
    reader = [i for i, g in enumerate(g_aux) if g is not None]
    g_q = torch.autograd.grad(parts.q, [params[i] for i in reader])

    def norm(gs: list[Tensor]) -> float:
        return float(torch.linalg.vector_norm(torch.cat([g.float().flatten() for g in gs])))

    aux = [g for g in g_aux if g is not None]
    return GradientShare(float(parts.q.detach()), float(parts.joint.detach()), norm(list(g_q)), norm(aux))


class AuxLearning:
    """A training run's auxiliary loss: its head, its optimizer, and the targets of every
    observation the replay's store holds, kept in a store of the same capacity that is
    added to whenever that one is, so that an observation's id names its targets too.

    Args:
        net: the Q-network (reader 'attention'); its trainable parameters and the head's
            are what the auxiliary optimizer moves (with ``aux_joint``, the head's alone:
            the reader moves with the Q-learner's optimizer).
        cfg: ``aux_scale``, ``aux_joint``, ``aux_neighbours``, ``lr``, ``adam_eps``.
        obs: the VelocityMap's settings (its view box).
        capacity: the observation store's capacity.
    """

    def __init__(self, net: QNetwork, cfg: DQNConfig, obs: ObservationConfig, capacity: int,
                 device: torch.device) -> None:
        self.k, self.obs = cfg.aux_neighbours, obs
        self.head = aux_head(net.summary_size, net.cfg.hidden, self.k).to(device)
        self.scale, self.joint = cfg.aux_scale, cfg.aux_joint
        # Joint: the reader moves with the Q-learner's optimizer; this one moves the head.
        moved = [*self.head.parameters()] if self.joint else [*net.trainable_parameters(), *self.head.parameters()]
        self.optimizer = torch.optim.Adam(moved, lr=cfg.lr if self.joint else cfg.aux_scale * cfg.lr,
                                          eps=cfg.adam_eps)
        self.store = LatentStore(capacity, (view_target_size(self.k),))
        self.losses: list[float] = []
        self.pretrain_losses: list[float] = []  # dqn.aux_pretrain's, until the run's log takes them
        self._pending: Tensor | None = None

    def pretrain(self, net: QNetwork, batches: Iterable[tuple[Tensor, NDArray[np.int64]]], lr: float, adam_eps: float,
                 dtype: torch.dtype) -> None:
        """One :func:`aux_step` of the reader and the head together per batch of ``batches``
        (observations and their store ids), under an Adam of their own at ``lr`` that is
        dropped afterwards: there is no Q-loss to weigh against, so ``aux_scale`` plays no
        part, and neither the Q-learner's moments nor the run's auxiliary ones see these
        steps. Their losses go to :attr:`pretrain_losses`."""
        optimizer = torch.optim.Adam([*net.trainable_parameters(), *self.head.parameters()], lr=lr, eps=adam_eps)
        for obs, ids in batches:
            self.pretrain_losses.append(aux_step(net.summary, self.head, optimizer, obs, self.stored(ids, obs.device), dtype))

    def stored(self, ids: NDArray[np.int64], device: torch.device) -> Tensor:
        """The stored targets ``(len(ids), n)`` of the observations whose ids are ``ids``."""
        return torch.from_numpy(self.store.get(ids)).to(device)

    def targets(self, scenes: NDArray[np.object_]) -> NDArray[np.float32]:
        """:func:`scene_targets` of ``scenes`` ``(num_envs,)`` → ``(num_envs, n_av, n)``."""
        return scene_targets(scenes, self.obs, self.k)

    def add(self, targets: NDArray[np.float32], ids: NDArray[np.int64]) -> None:
        """Store ``targets`` ``(k, n)`` of the observations the observation store just gave
        ``ids`` ``(k,)``."""
        mine = self.store.add(targets, ids)
        if not np.array_equal(mine, ids):
            raise RuntimeError("auxiliary targets out of step with the observation store")

    def step(self, net: QNetwork, obs: Tensor, ids: NDArray[np.int64], dtype: torch.dtype) -> None:
        """One :func:`aux_step` on sampled observations ``obs`` whose ids are ``ids``."""
        self.losses.append(aux_step(net.summary, self.head, self.optimizer, obs, self.stored(ids, obs.device), dtype))

    def joint_term(self, ids: NDArray[np.int64], device: torch.device, dtype: torch.dtype) -> Callable[[Tensor], Tensor]:
        """The term :func:`~latentdrive.rl.dqn.update` adds to its Q-loss (``aux_joint``)
        for sampled observations whose ids are ``ids`` ``(B,)``: ``aux_scale`` × the squared
        error of the head's prediction from the summary ``z`` ``(B, summary_size)`` against
        their targets (forward in ``dtype``, loss in fp32). Clears the head's gradients now;
        :meth:`step_head` steps it after the backward pass."""
        targets = self.stored(ids, device)
        self.optimizer.zero_grad(set_to_none=True)

        def term(z: Tensor) -> Tensor:
            loss = aux_error(self.head, z, targets, dtype)
            # Read after the step: a float() here would make a GPU wait between the passes.
            self._pending = loss.detach()
            return self.scale * loss

        return term

    def step_head(self) -> None:
        """The head's Adam step after a joint update's backward pass."""
        self.optimizer.step()
        if self._pending is not None:
            self.losses.append(float(self._pending))
            self._pending = None

    def arrays(self) -> dict[str, np.ndarray]:
        """The stored targets, for the replay's file (keys ``aux/...``)."""
        return {f"aux/{k}": v for k, v in self.store.state().items()}

    def load_arrays(self, arrays: dict[str, np.ndarray], observations_added: int) -> None:
        """Restore :meth:`arrays` from the replay's file ``arrays``, checked against the
        count of observations the restored store holds; raises ``KeyError``/``ValueError``
        when they do not fit."""
        self.store.load_state({k.removeprefix("aux/"): v for k, v in arrays.items() if k.startswith("aux/")})
        if self.store.added != observations_added:
            raise ValueError("auxiliary targets out of step with the stored observations")
