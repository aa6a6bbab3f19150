"""The study's figures, drawn from ``results.json`` alone (no model is loaded)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from latentdrive.viz import save_png

__all__ = ["write_study_figures"]

COLORS = {"raw": "C0", "latent": "C1", "latent-random": "C2", "end-to-end": "C3", "latent-lam": "C4"}


def _err(entry: dict[str, Any]) -> tuple[float, float]:
    """Error-bar lengths below and above the mean (zero without an interval over seeds)."""
    if entry["lo"] is None:
        return 0.0, 0.0
    return entry["mean"] - entry["lo"], entry["hi"] - entry["mean"]


def headline(res: dict[str, Any], path: Path) -> Path:
    """Failure and crash rate of raw and latent policies per test set, references as marks."""
    rows = res["headline"]
    labels = [r["test"] for r in rows]
    x = np.arange(len(rows))
    fig, axes = plt.subplots(1, 2, figsize=(12, 4), sharey=True)
    for ax, what in zip(axes, ("failure", "crash"), strict=True):
        for i, rep in enumerate(("raw", "latent")):
            means = [r[rep][what]["mean"] for r in rows]
            errs = np.array([_err(r[rep][what]) for r in rows]).T
            ax.bar(x + (i - 0.5) * 0.38, means, 0.38, yerr=errs, capsize=3, color=COLORS[rep], label=rep)
            for j, r in enumerate(rows):
                ax.plot([x[j] + (i - 0.5) * 0.38] * len(r[rep][what]["per_seed"]), r[rep][what]["per_seed"], "k.",
                        markersize=3)
        for ref, marker in (("random", "v"), ("rule", "s"), ("plan", "*")):
            if ref in res["references"]:
                ax.plot(x, [res["references"][ref][t][what]["rate"] for t in labels], marker, color="grey",
                        linestyle="none", label=ref if ref != "plan" else "planner (floor)")
        ax.set_xticks(x, labels, rotation=20)
        ax.set_ylim(0, 1.02)
        ax.set_title(f"{what} rate (bars: mean over seeds, 95% bootstrap CI; dots: seeds)", fontsize=9)
    axes[0].set_ylabel("share of episodes")
    axes[0].legend(fontsize=7)
    fig.suptitle("Bottleneck (latent) vs baseline (raw): each scenario's own policy, and the mix policy on the mix")
    return save_png(fig, path)


def matrices(res: dict[str, Any], path: Path) -> Path:
    """Train × test failure rate for raw, latent, and latent − raw."""
    tests = res["tests"]
    trains = list(res["matrix"]["raw"])
    m = {rep: np.array([[res["matrix"][rep][tr][te] for te in tests] for tr in trains]) for rep in ("raw", "latent")}
    panels = [("raw", m["raw"], "Reds", 0.0, 1.0), ("latent", m["latent"], "Reds", 0.0, 1.0),
              ("latent − raw", m["latent"] - m["raw"], "RdBu_r", -1.0, 1.0)]
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    for ax, (title, a, cmap, lo, hi) in zip(axes, panels, strict=True):
        ax.imshow(a, cmap=cmap, vmin=lo, vmax=hi)
        for (i, j), v in np.ndenumerate(a):
            ax.text(j, i, f"{v:+.2f}" if lo < 0 else f"{v:.2f}", ha="center", va="center", fontsize=7)
        ax.set_xticks(range(len(tests)), [t[:6] for t in tests], rotation=30, fontsize=8)
        ax.set_yticks(range(len(trains)), [t[:6] for t in trains], fontsize=8)
        ax.set_xlabel("tested on")
        ax.set_ylabel("trained on")
        ax.set_title(f"failure rate: {title}", fontsize=10)
    fig.suptitle("Train × test (mean over training seeds); below zero on the right: the bottleneck fails less")
    return save_png(fig, path)


def transfer(res: dict[str, Any], path: Path) -> Path:
    """Learning curves on the transfer target: fine-tuned after pretraining vs from scratch."""
    tr = res["transfer"]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
    for ax, rep in zip(axes, ("raw", "latent"), strict=True):
        for kind, style in (("scratch", "--"), ("finetuned", "-")):
            for k, curve in enumerate(tr[rep]["curves"][kind]):
                if curve:
                    c = np.array(curve)
                    ax.plot(c[:, 0], c[:, 1], style, color=COLORS[rep], alpha=0.8,
                            label=kind if k == 0 else None, marker=".")
        ax.set_xlabel("agent-transitions on the target")
        ax.set_title(f"{rep}: {tr['target']}", fontsize=10)
        ax.set_ylim(0, 1.02)
        ax.legend(fontsize=8)
    axes[0].set_ylabel("failure rate (periodic held-out evaluation)")
    fig.suptitle("Transfer learning: pretrained on the other scenarios, then fine-tuned (solid), vs from scratch (dashed)")
    return save_png(fig, path)


def leave_one_out(res: dict[str, Any], path: Path) -> Path:
    """Zero-shot failure on each left-out scenario against its distance to the training scenarios."""
    loo = res["leave_one_out"]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for ax, space in zip(axes, ("latent", "raw"), strict=True):
        for rep in ("raw", "latent"):
            rows = loo[rep]["scenarios"]
            pts = [(v.get(f"distance_{space}"), v["zero_shot"]["mean"], s) for s, v in rows.items()]
            pts = [p for p in pts if p[0] is not None]
            ax.scatter([p[0] for p in pts], [p[1] for p in pts], color=COLORS[rep], label=f"{rep} policy")
            for d, f, s in pts:
                ax.annotate(s[:5], (d, f), fontsize=7)
        ax.set_xlabel(f"mean MMD² to the training scenarios ({space} space)")
        ax.set_ylabel("zero-shot failure rate")
        ax.set_ylim(0, 1.02)
        ax.legend(fontsize=8)
    fig.suptitle("Leave one scenario out: does a smaller scenario distance predict better transfer?")
    return save_png(fig, path)


def ablations(res: dict[str, Any], path: Path) -> Path:
    """Mixed-set failure rate of every representation trained on the mix."""
    ab = res["ablations"]
    names = list(ab)
    fig, ax = plt.subplots(figsize=(8, 3.8))
    means = [ab[n]["failure"]["mean"] for n in names]
    errs = np.array([_err(ab[n]["failure"]) for n in names]).T
    ax.bar(range(len(names)), means, yerr=errs, capsize=3, color=[COLORS.get(n, "grey") for n in names])
    for ref, style in (("random", ":"), ("plan", "--")):
        if ref in res["references"]:
            ax.axhline(res["references"][ref]["mixed"]["failure"]["rate"], color="grey", linestyle=style, label=ref)
    ax.set_xticks(range(len(names)), names)
    ax.set_ylim(0, 1.02)
    ax.set_ylabel("failure rate on the mixed test set")
    ax.legend(fontsize=8)
    ax.set_title("Ablations on the mix: is the gain the representation or the architecture?")
    return save_png(fig, path)


def write_study_figures(res: dict[str, Any], figures: Path) -> list[Path]:
    """Every figure the results support, into ``figures``."""
    paths = [headline(res, figures / "headline.png"), matrices(res, figures / "matrix.png")]
    if "transfer" in res:
        paths.append(transfer(res, figures / "transfer.png"))
    if "leave_one_out" in res:
        paths.append(leave_one_out(res, figures / "leave_one_out.png"))
    if "ablations" in res:
        paths.append(ablations(res, figures / "ablations.png"))
    return paths
