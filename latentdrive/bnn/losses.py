"""The BNN's training objective: a per-cell reconstruction error of the decoder's logits
(the paper's L2 through the sigmoid, eq. 11, or binary cross-entropy with logits), weighted
per channel and up on vehicle cells, plus the λ-weighted scenario-distance regularizer.

Reconstructions and targets are channel pairs ``(B, 3, 2, T, H, W)`` (pairs HV+AV, RL+AV,
MV+AV; see :mod:`latentdrive.models.bottleneck`). The error is a weighted mean over all
elements, so that its scale does not depend on batch or grid size.

Why the weights (docs/bnn-notes.md): vehicles cover about 1% of the cells. Under a plain
mean, the noise-free road layout is most of the loss and the vehicle cells about 2% of it,
so the cheapest reconstruction draws the road and no car. The road channel is therefore
weighted down, the AV channel (present in all three pairs) counts 1/3 in each so that it
weighs as much as one channel in all, and vehicle cells are weighted up.
"""

from __future__ import annotations

from typing import Literal, NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor

from latentdrive.bnn.batch import BNNBatch
from latentdrive.bnn.distance import latent_regularizer
from latentdrive.models.bottleneck import BottleneckNetwork

__all__ = [
    "PAPER_WEIGHTS",
    "CellWeights",
    "LossKind",
    "cell_weights",
    "reconstruction_error",
    "reconstruction_loss",
    "step_losses",
    "vehicle_cells_l2",
    "vehicle_dice_loss",
]

#: Per-cell reconstruction error: squared error of the sigmoid output (the paper's) or
#: binary cross-entropy with logits.
LossKind = Literal["l2", "bce"]

# Which (pair, channel) of the (B, 3, 2, T, H, W) reconstruction shows vehicles: all but
# the road layout (RL, pair RL+AV channel 0), which is dense and needs no up-weighting.
_VEHICLE_CHANNELS = torch.tensor([[1.0, 1.0], [0.0, 1.0], [1.0, 1.0]]).view(1, 3, 2, 1, 1, 1)
# Where each channel sits: (pair, member) of the road and of the three AV copies.
_ROAD = (1, 0)
_AV_COPIES = ((0, 1), (1, 1), (2, 1))


class CellWeights(NamedTuple):
    """Weights of the per-cell error.

    - ``foreground``: multiplies vehicle cells (non-zero clean target in the HV, AV and MV
      channels); other cells weigh 1 before the channel weights.
    - ``road``: the road-layout channel's weight.
    - ``av_share``: each of the three AV-channel copies' weight (1/3: the AV channel weighs
      as one channel in all; 1: the paper's plain mean, where it counts three times).
    """

    foreground: float = 1.0
    road: float = 1.0
    av_share: float = 1.0


#: The paper's plain mean (eq. 11): every cell of every pair weighs 1.
PAPER_WEIGHTS = CellWeights()


def _channel_weights(w: CellWeights, device: torch.device, dtype: torch.dtype) -> Tensor:
    ch = torch.ones(3, 2, dtype=dtype)
    ch[_ROAD] = w.road
    for p in _AV_COPIES:
        ch[p] = w.av_share
    return ch.view(1, 3, 2, 1, 1, 1).to(device)


def cell_weights(target: Tensor, w: CellWeights) -> Tensor:
    """Per-cell weights ``(B, 3, 2, T, H, W)`` of clean pair targets of that shape (see :class:`CellWeights`)."""
    vehicle = (target > 0).to(target.dtype) * _VEHICLE_CHANNELS.to(target.device, target.dtype)
    return (1.0 + (w.foreground - 1.0) * vehicle) * _channel_weights(w, target.device, target.dtype)


def vehicle_dice_loss(logits: Tensor, target: Tensor) -> Tensor:
    """``1 − Dice`` of the vehicle channels (HV, AV, MV) of pair ``logits`` ``(B, 3, 2, T, H, W)``
    against clean targets in [0, 1], over the whole batch: ``Dice = 2·Σ r·t / (Σ r² + Σ t²)``
    with ``r = sigmoid(logits)`` (the squared form: 1 exactly where ``r = t``, soft targets
    included).

    Unlike a per-cell error, its denominator grows with everything drawn, wherever it lies:
    faint mass spread around a car (the halo that costs precision) lowers Dice even where
    each cell's error is small. Computed in float32.
    """
    r = torch.sigmoid(logits.float())
    t = target.float()
    mask = _VEHICLE_CHANNELS.to(r.device, r.dtype)
    num = 2.0 * torch.sum(mask * r * t)
    den = torch.sum(mask * r * r) + torch.sum(mask * t * t)
    # A batch without vehicles and with nothing drawn is a perfect reconstruction.
    return 1.0 - (num + 1e-6) / (den + 1e-6)


def reconstruction_error(
    logits: Tensor, target: Tensor, weights: CellWeights = PAPER_WEIGHTS, loss: LossKind = "l2",
    dice: float = 0.0,
) -> Tensor:
    """Weighted mean per-cell error of pair reconstruction ``logits`` ``(B, 3, 2, T, H, W)``
    against clean targets in [0, 1] of the same shape: ``Σ w·err / Σ w`` with the weights
    of :func:`cell_weights` (a plain mean under :data:`PAPER_WEIGHTS`).

    ``loss="l2"``: the squared error of ``sigmoid(logits)``, the paper's eq. 11.
    ``loss="bce"``: binary cross-entropy with logits, the targets taken as soft labels (its
    minimum is the targets' own entropy, not 0). Through the sigmoid the L2 gradient of a
    cell is ``(r - t)·r·(1 - r)``, tiny while the decoder still draws near-empty maps
    (r ≈ 0.05); the cross-entropy's is ``r - t``, so vehicle cells are learned from the
    first steps. Computed in float32 whatever the dtype of ``logits`` (bf16 autocast).

    ``dice > 0`` adds ``dice ·`` :func:`vehicle_dice_loss`.
    """
    if dice < 0.0:
        raise ValueError(f"the Dice weight must be at least 0, got {dice}")
    logits, target = logits.float(), target.float()
    if loss == "l2":
        err = (torch.sigmoid(logits) - target) ** 2
    elif loss == "bce":
        err = F.binary_cross_entropy_with_logits(logits, target, reduction="none")
    else:
        raise ValueError(f"unknown loss {loss!r}; expected 'l2' or 'bce'")
    if weights == PAPER_WEIGHTS:
        out = torch.mean(err)
    else:
        w = cell_weights(target, weights)
        out = torch.sum(w * err) / torch.sum(w)
    return out + dice * vehicle_dice_loss(logits, target) if dice > 0.0 else out


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
    weights: CellWeights = PAPER_WEIGHTS,
    loss: LossKind = "l2",
    dice: float = 0.0,
) -> tuple[Tensor, Tensor, Tensor]:
    """The training objective of one batch: ``(total, recon, reg)`` scalar float32 tensors.

    ``recon`` is :func:`reconstruction_error` (with its ``dice`` term) between the logits of ``batch.noisy``'s
    reconstruction ``(B, 3, 2, T, H, W)`` and ``model.pairs(batch.clean)``: the denoising
    target is the clean observation. ``reg`` is :func:`latent_regularizer` of the latents
    ``(B, 3, d)`` grouped by ``batch.scenario``, computed only when ``lambda_distance > 0``
    (else 0). ``total = recon + lambda_distance · reg``.
    """
    logits, latents = model.forward_logits(batch.noisy)
    recon = reconstruction_error(logits, model.pairs(batch.clean), weights, loss, dice)
    if lambda_distance > 0.0:
        reg = latent_regularizer(latents.float(), batch.scenario)
        return recon + lambda_distance * reg, recon, reg
    zero = recon.new_zeros(())
    return recon, recon, zero


def reconstruction_loss(model: BottleneckNetwork, batch: BNNBatch) -> Tensor:
    """Mean squared error between the reconstruction of ``batch.noisy`` and the clean pairs."""
    return step_losses(model, batch, 0.0)[1]
