"""The BNN's training objective: the denoising reconstruction error (the paper's L2, eq. 11,
or a binary cross-entropy), optionally with vehicle cells weighted up, plus the λ-weighted
scenario-distance regularizer.

Reconstructions and targets are channel pairs ``(B, 3, 2, T, H, W)`` (pairs HV+AV, RL+AV,
MV+AV; see :mod:`latentdrive.models.bottleneck`). The error is averaged over all elements
rather than summed, so that its scale does not depend on batch or grid size (the sum is
this mean times a constant; only the effective learning rate differs).
"""

from __future__ import annotations

from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor

from latentdrive.bnn.batch import BNNBatch
from latentdrive.bnn.distance import latent_regularizer
from latentdrive.models.bottleneck import BottleneckNetwork

__all__ = [
    "LossKind",
    "reconstruction_error",
    "reconstruction_loss",
    "step_losses",
    "vehicle_cells_l2",
    "weighted_l2",
]

#: Per-cell reconstruction error: squared error (the paper's) or binary cross-entropy.
LossKind = Literal["l2", "bce"]

# Which (pair, channel) of the (B, 3, 2, T, H, W) reconstruction shows vehicles: all but
# the road layout (RL, pair RL+AV channel 0), which is dense and needs no up-weighting.
_VEHICLE_CHANNELS = torch.tensor([[1.0, 1.0], [0.0, 1.0], [1.0, 1.0]]).view(1, 3, 2, 1, 1, 1)


def reconstruction_error(
    recon: Tensor, target: Tensor, foreground_weight: float = 1.0, loss: LossKind = "l2"
) -> Tensor:
    """Per-cell error of pair reconstructions ``(B, 3, 2, T, H, W)`` (both in [0, 1]),
    averaged with weight ``foreground_weight`` on vehicle cells (non-zero target cells of
    the HV, AV and MV channels) and 1 elsewhere, normalized by the total weight.

    ``loss="l2"``: the squared error, the paper's eq. 11 (plain MSE when the weight is 1).
    ``loss="bce"``: the binary cross-entropy of the cell values, treating the targets as
    soft labels (its minimum is the targets' own entropy, not 0). Through the output
    sigmoid the L2 gradient of a cell is ``(r - t)·r·(1 - r)``, which is tiny while the
    decoder still draws near-empty maps (r ≈ 0.05); the cross-entropy's is ``r - t``, so
    vehicle cells are learned without that damping.
    """
    if loss == "l2":
        err = (recon - target) ** 2
    elif loss == "bce":
        # binary_cross_entropy bounds log(0) at -100, so saturated outputs stay finite.
        err = F.binary_cross_entropy(recon, target, reduction="none")
    else:
        raise ValueError(f"unknown loss {loss!r}; expected 'l2' or 'bce'")
    if foreground_weight == 1.0:
        return torch.mean(err)
    vehicle = (target > 0).to(err.dtype) * _VEHICLE_CHANNELS.to(err.device, err.dtype)
    w = 1.0 + (foreground_weight - 1.0) * vehicle
    return torch.sum(w * err) / torch.sum(w)


def weighted_l2(recon: Tensor, target: Tensor, foreground_weight: float = 1.0) -> Tensor:
    """:func:`reconstruction_error` with the squared error (the paper's loss)."""
    return reconstruction_error(recon, target, foreground_weight, "l2")


def vehicle_cells_l2(recon: Tensor, target: Tensor) -> tuple[Tensor, Tensor]:
    """Sum of squared errors and count over vehicle cells: the HV and AV channels of the
    HV+AV pair (``[:, 0]`` of ``(B, 3, 2, T, H, W)``) where the clean target is non-zero."""
    r, t = recon[:, 0], target[:, 0]
    mask = t > 0
    return torch.sum(((r - t) ** 2)[mask]), mask.sum()


def step_losses(
    model: BottleneckNetwork,
    batch: BNNBatch,
    lambda_distance: float = 0.0,
    foreground_weight: float = 1.0,
    loss: LossKind = "l2",
) -> tuple[Tensor, Tensor, Tensor]:
    """The training objective of one batch: ``(total, recon, reg)`` scalar tensors.

    ``recon`` is the (foreground-weighted, see :func:`reconstruction_error`) error between
    ``model(batch.noisy)``'s reconstruction ``(B, 3, 2, T, H, W)`` and
    ``model.pairs(batch.clean)``: the denoising target is the clean observation. ``reg``
    is :func:`latent_regularizer` of the latents ``(B, 3, d)`` grouped by
    ``batch.scenario``, computed only when ``lambda_distance > 0`` (else 0).
    ``total = recon + lambda_distance · reg``.
    """
    recon_x, latents = model(batch.noisy)
    recon = reconstruction_error(recon_x, model.pairs(batch.clean), foreground_weight, loss)
    if lambda_distance > 0.0:
        reg = latent_regularizer(latents, batch.scenario)
        return recon + lambda_distance * reg, recon, reg
    zero = recon.new_zeros(())
    return recon, recon, zero


def reconstruction_loss(model: BottleneckNetwork, batch: BNNBatch) -> Tensor:
    """Mean squared error between the reconstruction of ``batch.noisy`` and the clean pairs."""
    return step_losses(model, batch, 0.0)[1]


