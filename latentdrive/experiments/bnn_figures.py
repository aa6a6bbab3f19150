"""Figures of the bottleneck-network study (the paper's ae_loss, reconstruction_fullpage,
latent_rep), plus the scenario distance matrices the paper names but never shows."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import torch

from latentdrive.bnn.train import load_trained_bottleneck
from latentdrive.experiments.bnn_report import epoch_rows
from latentdrive.experiments.heldout import HeldOut
from latentdrive.models.bottleneck import BottleneckNetwork
from latentdrive.observe import CHANNELS
from latentdrive.viz import save_png

__all__ = ["write_bnn_figures"]

SHOWN = ("roundabout", "intersection")


def loss_curves(figures: Path, runs: Mapping[str, Path], input_recall: float | None = None) -> Path:
    """Per epoch and run: training and held-out reconstruction loss (left), and the share of
    held-out vehicles recovered (right; ``input_recall``, the noisy input's own, as a line)."""
    fig, (ax, ax_r) = plt.subplots(1, 2, figsize=(12, 4))
    for i, (name, run) in enumerate(runs.items()):
        rows = epoch_rows(run)
        epochs = [int(r["epoch"]) + 1 for r in rows]
        color = f"C{i}"
        ax.plot(epochs, [float(r["recon"]) for r in rows], color=color, label=f"{name} train")
        ax.plot(epochs, [float(r["val_loss"]) for r in rows], color=color, linestyle="--", label=f"{name} held-out")
        recall = [float(r.get("val_vehicle_recall") or "nan") for r in rows]
        ax_r.plot(epochs, recall, color=color, label=name)
    ax.set_xlabel("epoch")
    ax.set_ylabel("reconstruction loss (train: as trained; held-out: plain MSE)")
    ax.set_yscale("log")
    ax.legend(fontsize=7, ncol=2)
    ax.set_title("BNN training (dashed: held-out episodes)")
    if input_recall is not None:
        ax_r.axhline(input_recall, color="grey", linestyle=":", label="noisy input (reference)")
    ax_r.set_xlabel("epoch")
    ax_r.set_ylabel("held-out vehicles recovered")
    ax_r.set_ylim(0, 1)
    ax_r.legend(fontsize=7)
    ax_r.set_title("Vehicles recovered: half their peak value within one cell")
    return save_png(fig, figures / "bnn_loss.png")


def _channels_of(recon: np.ndarray) -> np.ndarray:
    """Per-channel maps ``(4, H, W)`` (latest frame) from pair reconstructions ``(3, 2, T, H, W)``."""
    return np.stack([recon[0, 0, -1], recon[0, 1, -1], recon[1, 0, -1], recon[2, 0, -1]])


def reconstructions(figures: Path, data: HeldOut, runs: Mapping[str, Path], notes: dict[str, str] | None = None) -> Path:
    """Ground truth, noisy input and each run's reconstruction for a roundabout and an
    intersection; ``notes`` adds a line under a row's name (e.g. its vehicle recall)."""
    shown = [s for s in SHOWN if data.first(s) >= 0] or [data.names[int(data.scenario[0])]]
    notes = notes or {}
    run_names = list(runs)
    rows = ["ground truth", *(f"{n}\n{notes[n]}" if n in notes else n for n in ["noisy input", *run_names])]
    fig, axes = plt.subplots(len(rows), 4 * len(shown), figsize=(3.2 * 4 * len(shown), 1.9 * len(rows)), squeeze=False)
    models = {name: load_trained_bottleneck(run) for name, run in runs.items()}
    for k, scen in enumerate(shown):
        i = data.first(scen)
        images = [data.clean[i, :, -1], data.noisy[i, :, -1]]
        with torch.no_grad():
            for name in run_names:
                images.append(_channels_of(models[name](torch.from_numpy(data.noisy[i:i + 1]))[0][0].numpy()))
        for r, img in enumerate(images):
            for c in range(4):
                ax = axes[r, 4 * k + c]
                ax.imshow(img[c], vmin=0, vmax=1, cmap="viridis", interpolation="nearest")
                ax.set_xticks([])
                ax.set_yticks([])
                if r == 0:
                    ax.set_title(f"{scen}: {CHANNELS[c]}", fontsize=9)
                if 4 * k + c == 0:
                    ax.set_ylabel(rows[r], fontsize=9)
    fig.suptitle("Reconstruction from held-out noisy input, latest frame (the paper's reconstruction figure)")
    return save_png(fig, figures / "bnn_reconstruction.png")


def latents_before_after(figures: Path, data: HeldOut, run_name: str, run: Path, train_seed: int) -> Path:
    """Latents (3 pairs × d) of a roundabout and an intersection, at initialization and
    after training; ``train_seed`` is the seed the run was trained with."""
    trained = load_trained_bottleneck(run)
    # The initial weights are those train_bnn drew: the same seed, the same constructor.
    torch.manual_seed(train_seed)
    initial = BottleneckNetwork(trained.cfg).eval()
    shown = [s for s in SHOWN if data.first(s) >= 0]
    fig, axes = plt.subplots(len(shown), 2, figsize=(12, 2.4 * len(shown) + 0.8), squeeze=False)
    with torch.no_grad():
        for r, scen in enumerate(shown):
            x = torch.from_numpy(data.noisy[data.first(scen):data.first(scen) + 1])
            for c, (label, model) in enumerate((("before training", initial), ("after training", trained))):
                z = model.encode(x)[0].numpy()
                ax = axes[r, c]
                im = ax.imshow(z, aspect="auto", cmap="magma", interpolation="nearest")
                ax.set_yticks(range(3), ["HV+AV", "RL+AV", "MV+AV"], fontsize=8)
                ax.set_title(f"{scen}, {label}", fontsize=9)
                fig.colorbar(im, ax=ax, fraction=0.03)
    axes[-1, 0].set_xlabel("latent unit")
    axes[-1, 1].set_xlabel("latent unit")
    fig.suptitle(f"Latent representation ({run_name})")
    return save_png(fig, figures / "bnn_latents.png")


def distance_matrices(figures: Path, report: dict[str, Any]) -> Path:
    """The 5×5 scenario distance (MMD²) in the raw-input space and in each run's latent space."""
    panels = [("raw input (pooled)", report["raw_scenarios"], np.array(report["raw_distance"]))]
    panels += [(f"latent {n}", r["latent_scenarios"], np.array(r["latent_distance"])) for n, r in report["runs"].items()]
    fig, axes = plt.subplots(1, len(panels), figsize=(3.6 * len(panels), 3.6), squeeze=False)
    # One colour scale for every panel, so that shades compare across spaces.
    vmax = max(max(float(m.max()) for _, _, m in panels), 1e-9)
    for ax, (title, names, m) in zip(axes[0], panels, strict=True):
        ax.imshow(m, cmap="Blues", vmin=0, vmax=vmax)
        for (i, j), v in np.ndenumerate(m):
            ax.text(j, i, f"{v:.2f}", ha="center", va="center", fontsize=7)
        ax.set_xticks(range(len(names)), [n[:5] for n in names], fontsize=7, rotation=45)
        ax.set_yticks(range(len(names)), [n[:5] for n in names], fontsize=7)
        off = m[~np.eye(len(m), dtype=bool)].mean() if len(m) > 1 else float("nan")
        ax.set_title(f"{title}\nmean off-diagonal {off:.3f}", fontsize=9)
    fig.suptitle("Scenario distance: MMD² between scenarios' distributions")
    return save_png(fig, figures / "bnn_distance.png")


def _recall_notes(report: dict[str, Any]) -> dict[str, str]:
    """Row notes "NN% of vehicles" from the report's held-out vehicle recall, where known."""
    notes: dict[str, str] = {}
    entries = {"noisy input": report.get("noisy_input_vehicles") or {}, **report["runs"]}
    for name, entry in entries.items():
        recall = entry.get("vehicle_recall")
        if recall is not None:
            notes[name] = f"{recall:.0%} of vehicles"
    return notes


def write_bnn_figures(figures: str | Path, runs: Mapping[str, Path], data: HeldOut, report: dict[str, Any],
                      train_seed: int) -> list[Path]:
    """Every figure of the study, into ``figures``; ``runs`` maps each of the report's runs
    to its directory (``train_seed``: the seed its runs were trained with, which drew their
    initial weights)."""
    figures = Path(figures)
    names = list(report["runs"])
    plain = [n for n in names if report["runs"][n]["lambda"] == 0]
    largest = max(plain, key=lambda n: report["runs"][n]["latent_dim"])
    return [
        loss_curves(figures, {n: runs[n] for n in names}, (report.get("noisy_input_vehicles") or {}).get("vehicle_recall")),
        reconstructions(figures, data, {n: runs[n] for n in plain}, _recall_notes(report)),
        latents_before_after(figures, data, largest, runs[largest], train_seed),
        distance_matrices(figures, report),
    ]
