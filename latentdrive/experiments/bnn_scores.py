"""Scoring a BNN study's trained runs on its held-out episodes.

Reconstruction error, vehicles recovered (:mod:`latentdrive.bnn.vehicles`) per scenario,
where drawn vehicle cells lie, and the scenario distances in each latent space and in a
raw-input baseline space. What :func:`latentdrive.experiments.bnn.report_bnn_runs` puts
in ``report.json``; the Markdown of it is :func:`latentdrive.experiments.bnn_report.format_report`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from latentdrive.bnn.batch import BNNBatch
from latentdrive.bnn.distance import distance_matrix
from latentdrive.bnn.evaluate import add_counts, evaluate_bnn, vehicle_counts_by_scenario
from latentdrive.bnn.train import load_trained_bottleneck
from latentdrive.bnn.vehicles import REACH_CELLS, VehicleCounts, bright_cell_reach
from latentdrive.data.dataset import ShardDataset
from latentdrive.experiments.heldout import HeldOut
from latentdrive.models.bottleneck import BottleneckNetwork, channel_pairs

__all__ = ["drawn_cell_reach", "encode", "evaluate_run", "finite_or_none", "input_vehicle_recovery",
           "mean_offdiag", "raw_features", "reach_references", "reconstruct"]


@torch.no_grad()
def encode(model: BottleneckNetwork, x: np.ndarray, batch: int = 128) -> np.ndarray:
    """Latents ``(n, 3·d)`` of observations ``x`` ``(n, 4, T, H, W)``."""
    out = [model.encode(torch.from_numpy(x[i:i + batch])).flatten(1).numpy() for i in range(0, len(x), batch)]
    return np.concatenate(out) if out else np.zeros((0, model.latent_size), np.float32)


@torch.no_grad()
def reconstruct(model: BottleneckNetwork, x: np.ndarray) -> np.ndarray:
    """Reconstructions ``(n, 3, 2, T, H, W)`` of noisy observations ``x``."""
    return model(torch.from_numpy(x))[0].numpy()


def raw_features(x: np.ndarray, pool: int) -> np.ndarray:
    """The raw-input baseline space: ``x`` average-pooled by ``pool`` over H, W and flattened."""
    t = torch.from_numpy(x)
    n, _c, _tt, _h, _w = t.shape
    pooled = F.avg_pool3d(t, kernel_size=(1, pool, pool), ceil_mode=True) if pool > 1 else t
    return pooled.reshape(n, -1).numpy()


def mean_offdiag(m: np.ndarray) -> float:
    s = m.shape[0]
    return float(m[~np.eye(s, dtype=bool)].mean()) if s > 1 else float("nan")


def finite_or_none(v: float) -> float | None:
    return v if math.isfinite(v) else None


def _recall_by_name(ds: ShardDataset, per: dict[int, VehicleCounts]) -> dict[str, float | None]:
    return {ds.scenario_names[s]: finite_or_none(c.recall) for s, c in per.items() if c.vehicles}


def input_vehicle_recovery(ds: ShardDataset, batches: Callable[[], Iterable[BNNBatch]]) -> dict[str, Any]:
    """The noisy input scored as if it were a reconstruction of the clean target, over the
    held-out samples of ``batches()``: the reference for the runs' vehicle scores
    (:mod:`latentdrive.bnn.vehicles`). Returns ``vehicle_recall``, ``vehicle_precision``,
    ``vehicles`` and ``by_scenario`` (name → recall); undefined values are None.
    """
    per: dict[int, VehicleCounts] = {}
    for b in batches():
        per = add_counts(per, vehicle_counts_by_scenario(channel_pairs(b.noisy)[:, 0], channel_pairs(b.clean)[:, 0],
                                                         b.scenario))
    total = VehicleCounts.total(per.values())
    return {"vehicle_recall": finite_or_none(total.recall),
            "vehicle_precision": finite_or_none(total.precision), "vehicles": total.vehicles,
            "by_scenario": _recall_by_name(ds, per)}


@torch.no_grad()
def drawn_cell_reach(data: HeldOut, draw: Callable[[Tensor], Tensor], batch: int = 128) -> dict[str, float | None]:
    """Share of drawn vehicle cells within k cells of a real vehicle of their frame and
    channel, for each k of :data:`~latentdrive.bnn.vehicles.REACH_CELLS`, over the samples
    of ``data``: ``{"1": share, "2": share, ...}`` (None when nothing is drawn).

    ``draw`` maps noisy observations ``(B, 4, T, H, W)`` to the HV+AV pair it draws,
    ``(B, 2, T, H, W)`` in [0, 1]; cells ≥ 0.25 count as drawn. See :func:`reach_references`
    for the noisy input and chance.
    """
    bright, within = 0, np.zeros(len(REACH_CELLS), np.int64)
    h, w = data.clean.shape[-2:]
    for i in range(0, len(data.scenario), batch):
        noisy, clean = torch.from_numpy(data.noisy[i:i + batch]), torch.from_numpy(data.clean[i:i + batch])
        b, k = bright_cell_reach(draw(noisy).reshape(-1, h, w), channel_pairs(clean)[:, 0].reshape(-1, h, w))
        bright += b
        within += np.asarray(k)
    return {str(k): (float(n) / bright if bright else None) for k, n in zip(REACH_CELLS, within.tolist(), strict=True)}


def reach_references(data: HeldOut) -> dict[str, dict[str, float | None]]:
    """:func:`drawn_cell_reach` of two references: the noisy input itself (``"input"``) and
    a map drawn bright everywhere (``"every cell"``: the share of all HV and AV cells within
    k cells of a vehicle, what drawing at random would score)."""
    def pair(x: Tensor) -> Tensor:
        return channel_pairs(x)[:, 0]

    return {"input": drawn_cell_reach(data, pair),
            "every cell": drawn_cell_reach(data, lambda x: torch.ones_like(pair(x)))}


def evaluate_run(run_dir: Path, data: HeldOut, ds: ShardDataset, batches: Callable[[], Iterable[BNNBatch]]) -> dict[str, Any]:
    """Held-out reconstruction error (over the samples of ``batches()``) and latent scenario
    distances (over ``data``) of one trained run."""
    model = load_trained_bottleneck(run_dir)
    metrics, per = evaluate_bnn(model, batches(), torch.device("cpu"), mmd_samples=2)
    names, lat = distance_matrix(data.by_scenario(encode(model, data.noisy)))
    return {"val_recon": metrics["val_loss"], "val_vehicle_l2": metrics["val_vehicle_l2"],
            # None, not NaN, when undefined (no vehicles, nothing drawn): JSON has no NaN.
            "vehicle_recall": finite_or_none(metrics["val_vehicle_recall"]),
            "vehicle_precision": finite_or_none(metrics["val_vehicle_precision"]),
            "vehicle_recall_by_scenario": _recall_by_name(ds, per),
            "drawn_cells_within": drawn_cell_reach(data, lambda x: model(x)[0][:, 0]),
            "latent_scenarios": names, "latent_distance": lat.tolist(),
            "mean_between_scenario_distance": mean_offdiag(lat)}
