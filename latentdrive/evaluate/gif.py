"""An episode as an animated GIF: the scene beside what the observing agent sees.

Each frame shows one policy step: the top-down scene (as :func:`latentdrive.viz.draw_scene`
draws it) beside the observing agent's four VelocityMap channels (HV, AV, RL, MV) of the
most recent stacked frame; when reconstructions are given, a second row shows a BNN's
reconstruction of the same channels.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import imageio.v3 as iio
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from latentdrive.config import ObservationConfig
from latentdrive.fileio import atomic_write_bytes
from latentdrive.observe import CHANNELS
from latentdrive.scene import Scene
from latentdrive.viz import draw_scene

__all__ = ["save_episode_gif", "save_side_by_side_gif"]

_DPI = 80
_WIDTH_IN = 14.0
_BODY_IN = {1: 2.6, 2: 4.0}  # height below the title, by rows of channel images, inches
_TITLE_IN = 0.5
_PANEL_IN = 4.2  # a side-by-side panel's width and height below its title, inches


def _check(
    scenes: Sequence[Scene],
    observations: Sequence[np.ndarray],
    agent: int,
    reconstructions: Sequence[np.ndarray] | None,
    fps: float,
) -> None:
    n = len(scenes)
    if n == 0:
        raise ValueError("save_episode_gif: the episode is empty (no scenes)")
    if len(observations) != n:
        raise ValueError(f"save_episode_gif: {n} scenes but {len(observations)} observations")
    if reconstructions is not None and len(reconstructions) != n:
        raise ValueError(f"save_episode_gif: {n} scenes but {len(reconstructions)} reconstructions")
    if not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"save_episode_gif: fps must be positive, got {fps}")
    for i, (scene, obs) in enumerate(zip(scenes, observations, strict=True)):
        shape = np.shape(obs)
        if len(shape) != 5 or shape[1] != len(CHANNELS):
            raise ValueError(f"save_episode_gif: observations[{i}] must be (n_av, {len(CHANNELS)}, T, H, W), got {shape}")
        if not 0 <= agent < min(shape[0], scene.n_agents):
            raise ValueError(f"save_episode_gif: agent {agent} is out of range: step {i} has "
                             f"{min(shape[0], scene.n_agents)} agents")
        if reconstructions is not None and np.shape(reconstructions[i]) != shape[1:]:
            raise ValueError(f"save_episode_gif: reconstructions[{i}] must be {shape[1:]} like the "
                             f"agent's observation, got {np.shape(reconstructions[i])}")


def _render_frame(
    scene: Scene,
    obs: np.ndarray,
    recon: np.ndarray | None,
    obs_cfg: ObservationConfig,
    agent: int,
    heading: str,
) -> np.ndarray:
    """One frame as ``(H, W, 3)`` uint8; the pixel size depends only on whether ``recon`` is given."""
    rows = 1 if recon is None else 2
    height = _BODY_IN[rows] + _TITLE_IN
    fig = Figure(figsize=(_WIDTH_IN, height), dpi=_DPI)
    canvas = FigureCanvasAgg(fig)
    grid = fig.add_gridspec(rows, 5, width_ratios=[1.2, 1, 1, 1, 1], left=0.02, right=0.98,
                            bottom=0.03, top=1 - _TITLE_IN / height,
                            wspace=0.08, hspace=0.2)
    observer = int(scene.agents[agent])
    ax = fig.add_subplot(grid[:, 0])
    draw_scene(ax, scene, observer, obs_cfg)
    ax.set_title("scene (red: observing AV, green: AVs, blue: HVs)", fontsize=8)
    images = [("observation", np.asarray(obs[agent]))]
    if recon is not None:
        images.append(("reconstruction", np.asarray(recon)))
    for r, (label, x) in enumerate(images):
        for c, name in enumerate(CHANNELS):
            ax = fig.add_subplot(grid[r, c + 1])
            ax.imshow(x[c, -1], cmap="viridis", vmin=0, vmax=1, origin="upper", interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_title(f"{name} ({label})" if rows > 1 else name, fontsize=9)
    fig.suptitle(heading, fontsize=11)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()


def save_episode_gif(
    path: str | Path,
    scenes: Sequence[Scene],
    observations: Sequence[np.ndarray],
    obs_cfg: ObservationConfig,
    *,
    agent: int = 0,
    reconstructions: Sequence[np.ndarray] | None = None,
    title: str = "",
    fps: float = 2.0,
) -> Path:
    """Write an episode as an animated GIF, one frame per step, and return its path.

    Args:
        path: the GIF to write; its folder is created. Written atomically (a temporary
            file in the same folder, then renamed), so a reader never sees half a GIF.
        scenes: the Scene at each step.
        observations: the matching ``(n_av, 4, T, H, W)`` observations in [0, 1].
        obs_cfg: the observation settings (to draw the observed window on the scene).
        agent: which AV's view to show (an index into the env's agents).
        reconstructions: optionally, the observing agent's reconstruction at each step,
            ``(4, T, H, W)``, shown as a second row.
        title: appended to each frame's heading, after the step index.
        fps: frames per second.

    Raises:
        ValueError: an empty episode, sequences of different lengths, badly shaped arrays,
            ``agent`` out of range, or a non-positive ``fps``.
    """
    _check(scenes, observations, agent, reconstructions, fps)
    n = len(scenes)
    frames = []
    for i, (scene, obs) in enumerate(zip(scenes, observations, strict=True)):
        heading = f"step {i}/{n - 1}, t = {scene.time:.1f} s"
        if title:
            heading += f" — {title}"
        recon = None if reconstructions is None else reconstructions[i]
        frames.append(_render_frame(scene, obs, recon, obs_cfg, agent, heading))
    return _write_gif(path, frames, fps)


def save_side_by_side_gif(
    path: str | Path,
    episodes: Sequence[tuple[str, Sequence[Scene], ObservationConfig]],
    *,
    agent: int = 0,
    title: str = "",
    fps: float = 2.0,
) -> Path:
    """Write several policies' runs of one episode side by side as an animated GIF.

    Args:
        path: the GIF to write, atomically; its folder is created.
        episodes: ``(label, scenes, observation settings)`` per policy: the Scene at every
            step of the same episode (same seed), and what the policy observes (to draw
            its window). A policy whose episode ended sooner keeps its last scene, marked
            as ended, while the others go on.
        agent: which AV the panels follow (an index into the env's agents).
        title: appended to each frame's heading, after the step index.
        fps: frames per second.

    Raises:
        ValueError: no policy, an empty episode, ``agent`` out of range, or a
            non-positive ``fps``.
    """
    if not episodes or any(not scenes for _, scenes, _ in episodes):
        raise ValueError("save_side_by_side_gif: every policy needs a non-empty episode")
    if not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"save_side_by_side_gif: fps must be positive, got {fps}")
    for label, scenes, _ in episodes:
        if not all(0 <= agent < s.n_agents for s in scenes):
            raise ValueError(f"save_side_by_side_gif: agent {agent} is out of range in {label}'s episode")
    n = max(len(scenes) for _, scenes, _ in episodes)
    frames = []
    for i in range(n):
        heading = f"step {i}/{n - 1}" + (f" — {title}" if title else "")
        fig = Figure(figsize=(_PANEL_IN * len(episodes), _PANEL_IN + _TITLE_IN + 0.4), dpi=_DPI)
        canvas = FigureCanvasAgg(fig)
        grid = fig.add_gridspec(1, len(episodes), left=0.01, right=0.99, bottom=0.02, top=0.82, wspace=0.05)
        for c, (label, scenes, obs_cfg) in enumerate(episodes):
            scene = scenes[min(i, len(scenes) - 1)]
            ax = fig.add_subplot(grid[0, c])
            draw_scene(ax, scene, int(scene.agents[agent]), obs_cfg)
            ax.set_title(label + ("" if i < len(scenes) else "\n(episode over)"), fontsize=9)
        fig.suptitle(heading, fontsize=11)
        canvas.draw()
        frames.append(np.asarray(canvas.buffer_rgba())[..., :3].copy())
    return _write_gif(path, frames, fps)


def _write_gif(path: str | Path, frames: Sequence[np.ndarray], fps: float) -> Path:
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    data = iio.imwrite("<bytes>", np.stack(frames), extension=".gif", duration=1000.0 / fps, loop=0)
    atomic_write_bytes(out, data)
    return out
