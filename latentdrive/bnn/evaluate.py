"""Validation of a bottleneck network: reconstruction error, vehicle recovery, scenario distance."""

from __future__ import annotations

from collections.abc import Iterable
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from latentdrive.bnn.batch import BNNBatch
from latentdrive.bnn.distance import group_mmd2
from latentdrive.bnn.losses import (
    PAPER_WEIGHTS,
    CellWeights,
    LossKind,
    reconstruction_error,
    vehicle_cells_l2,
)
from latentdrive.bnn.vehicles import VehicleCounts, vehicle_counts
from latentdrive.models.bottleneck import BottleneckNetwork
from latentdrive.runtime import autocast

__all__ = ["VAL_KEYS", "Evaluation", "add_counts", "evaluate_bnn", "vehicle_counts_by_scenario"]

#: The metrics :func:`evaluate_bnn` returns, in the order they are logged.
VAL_KEYS: tuple[str, ...] = (
    "val_loss", "val_vehicle_l2", "val_vehicle_recall", "val_vehicle_precision", "val_mmd",
    "val_train_loss",
)


def vehicle_counts_by_scenario(
    recon: Tensor, clean: Tensor, scenario: Tensor
) -> dict[int, VehicleCounts]:
    """Vehicle counts of HV+AV pair reconstructions ``recon`` of ``clean`` (both
    ``(B, 2, T, H, W)``: every frame of both channels is scored), per scenario id of
    ``scenario`` ``(B,)``."""
    h, w = clean.shape[-2:]
    out: dict[int, VehicleCounts] = {}
    for s in torch.unique(scenario).tolist():
        keep = scenario == s
        out[s] = vehicle_counts(recon[keep].reshape(-1, h, w), clean[keep].reshape(-1, h, w))
    return out


def add_counts(
    a: dict[int, VehicleCounts], b: dict[int, VehicleCounts]
) -> dict[int, VehicleCounts]:
    """Per-scenario counts ``a`` plus ``b``, sorted by scenario id."""
    zero = VehicleCounts(0, 0, 0, 0)
    return {s: a.get(s, zero).plus(b.get(s, zero)) for s in sorted(a.keys() | b.keys())}


class Evaluation(NamedTuple):
    """:func:`evaluate_bnn`'s result."""

    metrics: dict[str, float]  #: the keys of :data:`VAL_KEYS`
    vehicles_by_scenario: dict[int, VehicleCounts]  #: scenario id → its vehicle counts


@torch.no_grad()
def evaluate_bnn(
    model: BottleneckNetwork,
    batches: Iterable[BNNBatch],
    device: torch.device,
    *,
    mmd_samples: int = 256,
    rng: np.random.Generator | None = None,
    dtype: torch.dtype = torch.float32,
    weights: CellWeights = PAPER_WEIGHTS,
    loss: LossKind = "l2",
    dice: float = 0.0,
) -> Evaluation:
    """Validation metrics, the keys of :data:`VAL_KEYS`, and vehicle counts per scenario.

    - ``val_loss``: the plain (unweighted) reconstruction MSE averaged over all samples,
      comparable across runs whatever their training weights.
    - ``val_vehicle_l2``: the MSE over vehicle cells only (:func:`vehicle_cells_l2`).
    - ``val_vehicle_recall`` / ``val_vehicle_precision``: vehicles recovered in the HV and
      AV channels of every frame, and how much of what is drawn bright lies on vehicles
      (:mod:`latentdrive.bnn.vehicles`, default thresholds).
    - ``val_mmd``: the mean pairwise MMD² between the scenarios' latent distributions
      (latents flattened to ``(3d,)``), each scenario subsampled to ``mmd_samples`` vectors
      with ``rng`` (all of them, first ones first, when ``rng`` is None); NaN with fewer
      than two scenarios.
    - ``val_train_loss``: the training objective's reconstruction term under ``weights``,
      ``loss`` and ``dice`` (:func:`~latentdrive.bnn.losses.reconstruction_error`), so that the
      held-out loss compares with the training loss.

    The network runs under autocast to ``dtype`` (:func:`latentdrive.runtime.autocast`);
    scores are computed in float32.
    """
    was_training = model.training
    model.eval()
    total, count, objective = 0.0, 0, 0.0
    veh_sum, veh_count = 0.0, 0
    per_scenario: dict[int, VehicleCounts] = {}
    lat: list[Tensor] = []
    lab: list[Tensor] = []
    for batch in batches:
        b = batch.to(device)
        with autocast(dtype, device):
            logits, z = model.forward_logits(b.noisy)
        logits, z = logits.float(), z.float()
        recon_x = torch.sigmoid(logits)
        target = model.pairs(b.clean)
        mse = torch.mean((recon_x - target) ** 2)
        objective += float(reconstruction_error(logits, target, weights, loss, dice)) * b.noisy.shape[0]
        v_sum, v_count = vehicle_cells_l2(recon_x, target)
        veh_sum += float(v_sum)
        veh_count += int(v_count)
        per_scenario = add_counts(
            per_scenario, vehicle_counts_by_scenario(recon_x[:, 0], target[:, 0], b.scenario)
        )
        n = b.noisy.shape[0]
        total += float(mse) * n
        count += n
        lat.append(z.flatten(1).cpu())
        lab.append(b.scenario.cpu())
    model.train(was_training)
    if count == 0:
        raise ValueError("the validation batches are empty")
    counts = VehicleCounts.total(per_scenario.values())
    metrics = {
        "val_loss": total / count,
        "val_vehicle_l2": veh_sum / veh_count if veh_count else float("nan"),
        "val_vehicle_recall": counts.recall,
        "val_vehicle_precision": counts.precision,
        "val_mmd": _mean_scenario_distance(torch.cat(lat), torch.cat(lab), mmd_samples, rng),
        "val_train_loss": objective / count,
    }
    return Evaluation(metrics, per_scenario)


def _mean_scenario_distance(
    latents: Tensor, labels: Tensor, mmd_samples: int, rng: np.random.Generator | None
) -> float:
    keep: list[np.ndarray] = []
    labels_np = labels.numpy()
    for s in np.unique(labels_np):
        idx = np.flatnonzero(labels_np == s)
        if idx.shape[0] > mmd_samples:
            if rng is None:
                idx = idx[:mmd_samples]
            else:
                idx = np.sort(rng.choice(idx, mmd_samples, replace=False))
        keep.append(idx)
    sel = torch.from_numpy(np.concatenate(keep))
    groups, d = group_mmd2(latents[sel].double(), labels[sel])
    s_count = groups.shape[0]
    if s_count < 2:
        return float("nan")
    iu = torch.triu_indices(s_count, s_count, offset=1)
    return float(d[iu[0], iu[1]].mean())
