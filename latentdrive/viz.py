"""Pictures a person would rather look at than read: the scene beside what an agent sees."""

from __future__ import annotations

import io
from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.axes import Axes
from matplotlib.patches import Polygon

from latentdrive.config import ObservationConfig
from latentdrive.fileio import atomic_write_bytes
from latentdrive.observe import CHANNELS
from latentdrive.scene import Kind, Scene

__all__ = ["draw_scene", "save_png", "save_show_figure"]

_COLORS = {"hv": "#3b75af", "av": "#2ca02c", "observer": "#d62728", "crashed": "#000000"}


def _rect(center: np.ndarray, heading: float, length: float, width: float) -> np.ndarray:
    """Corners ``(4, 2)`` of a rotated rectangle, metres."""
    c, s = np.cos(heading), np.sin(heading)
    local = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * [length / 2, width / 2]
    return center + local @ np.array([[c, s], [-s, c]])


def draw_scene(ax: Axes, scene: Scene, observer: int, cfg: ObservationConfig, view: float = 70.0) -> None:
    """Top-down world view around vehicle ``observer``: road, vehicles, the observed window.

    The y axis is drawn downwards, as the simulator does, so that a car heading along +x
    has its left at the top, like the VelocityMap rows.
    """
    road = scene.road
    rows, cols = road.mask.shape
    x0, y0 = road.origin - road.resolution / 2
    ax.imshow(
        road.mask, cmap="Greys", vmin=0, vmax=3, origin="upper", interpolation="nearest",
        extent=(x0, x0 + cols * road.resolution, y0 + rows * road.resolution, y0),
    )
    for i in np.flatnonzero(scene.mask):
        if i == observer:
            color = _COLORS["observer"]
        else:
            color = _COLORS["av"] if scene.kind[i] == Kind.AV else _COLORS["hv"]
        ax.add_patch(Polygon(_rect(scene.position[i], scene.heading[i], scene.length[i], scene.width[i]),
                             closed=True, facecolor=color, edgecolor="k" if scene.crashed[i] else color,
                             linewidth=2 if scene.crashed[i] else 0.5))
    # The VelocityMap window, in the observer's frame.
    ahead = cfg.width * cfg.resolution - cfg.behind
    half = cfg.height * cfg.resolution / 2
    corners_local = np.array([[-cfg.behind, -half], [ahead, -half], [ahead, half], [-cfg.behind, half]])
    h = scene.heading[observer]
    rot = np.array([[np.cos(h), np.sin(h)], [-np.sin(h), np.cos(h)]])
    ax.add_patch(Polygon(scene.position[observer] + corners_local @ rot, closed=True, fill=False,
                         edgecolor=_COLORS["observer"], linestyle="--", linewidth=1))
    cx, cy = scene.position[observer]
    ax.set_xlim(cx - view, cx + view)
    ax.set_ylim(cy + view, cy - view)
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])


def save_show_figure(
    path: str | Path,
    scenes: Sequence[Scene],
    observations: Sequence[np.ndarray],
    cfg: ObservationConfig,
    title: str,
    agent: int = 0,
) -> Path:
    """One row per step: the scene, then agent ``agent``'s four channels (latest frame).

    Args:
        scenes: the Scene at each shown step.
        observations: the matching ``(n_av, 4, T, H, W)`` observations.
    """
    n = len(scenes)
    fig, axes = plt.subplots(n, 5, figsize=(17, 2.6 * n + 0.6), squeeze=False,
                             gridspec_kw={"width_ratios": [1.2, 1, 1, 1, 1]})
    for r, (scene, obs) in enumerate(zip(scenes, observations, strict=True)):
        observer = int(scene.agents[agent])
        draw_scene(axes[r, 0], scene, observer, cfg)
        axes[r, 0].set_ylabel(f"t = {scene.time:.0f} s")
        for c, name in enumerate(CHANNELS):
            ax = axes[r, c + 1]
            ax.imshow(obs[agent, c, -1], cmap="viridis", vmin=0, vmax=1, origin="upper", interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(name)
    axes[0, 0].set_title("scene (red: observing AV, green: AVs, blue: HVs)", fontsize=9)
    fig.suptitle(title)
    return save_png(fig, path, dpi=80, tight_bbox=False)


def save_png(fig: plt.Figure, path: str | Path, dpi: int = 90, tight_bbox: bool = True) -> Path:
    """Write ``fig`` as a PNG atomically (a reader never sees half a figure) and close it."""
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight" if tight_bbox else None)
    plt.close(fig)
    return atomic_write_bytes(path, buf.getvalue())
