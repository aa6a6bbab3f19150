"""Multi-channel VelocityMaps: from a :class:`~latentdrive.scene.Scene` to image tensors.

One frame per observer is a ``(4, H, W)`` float32 image in [0, 1] with channels
:data:`CHANNELS` = HV, AV, RL, MV (paper section V-A):

- HV, AV: footprints of human-driven and of the *other* autonomous vehicles, valued with
  :func:`velocity_log_map` of their Frenet longitudinal speed relative to the observer
  (paper eq. 13).
- RL: the drivable area of the road layout.
- MV: the observer's own footprint, valued with its absolute speed over
  ``ObservationConfig.max_speed``. With ``ObservationConfig.route`` > 0 (an option; the
  paper's map has none) the road the observer's route still takes is drawn under it at
  that value, from the raster's edge bits and the Scene's ``route``.

Grid geometry (the observer's local frame): ``x`` points along the observer's heading,
``y`` to its right (the world convention of :mod:`latentdrive.scene`, where y grows to the
right of a car heading along +x). Cell ``(i, j)`` has its centre at

    x_c = -behind + (j + 0.5) * resolution        (column j: longitudinal)
    y_c = (i + 0.5) * resolution - H * resolution / 2   (row i: lateral)

so column 0 is the farthest behind, row 0 the farthest to the observer's left, and the
observer's centre lies on the boundary between rows ``H/2 - 1`` and ``H/2`` (H even). A
vehicle covers the cells whose centres fall inside its rotated ``length x width``
rectangle; the rectangle is half-open along each of its own axes (``-L/2 <= u < L/2``), so
an axis-aligned vehicle whose sides are whole multiples of the cell size covers exactly
``(length / res) x (width / res)`` cells wherever it sits (up to rounding of positions).
Overlapping footprints take the maximum value.

Sensor noise q_D (:class:`~latentdrive.config.NoiseConfig`) perturbs, per observer, every
other vehicle's position, heading and Frenet speed and drops it with ``miss_prob``. The
draws come from the generator passed in, in a fixed order (see :func:`render_frame`), so
frames are reproducible for a seed.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Final, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from latentdrive.config import NoiseConfig, ObservationConfig
from latentdrive.scene import Kind, Scene

__all__ = [
    "AV",
    "CHANNELS",
    "HV",
    "MV",
    "RL",
    "FrameStack",
    "SensorNoise",
    "draw_noise",
    "render_agents",
    "render_frame",
    "velocity_log_map",
]

CHANNELS: Final = ("HV", "AV", "RL", "MV")
"""Channel order of every VelocityMap frame."""
HV: Final = 0
"""Index of the human-driven vehicle channel."""
AV: Final = 1
"""Index of the other autonomous vehicles channel."""
RL: Final = 2
"""Index of the road layout (drivable area) channel."""
MV: Final = 3
"""Index of the mission vehicle (the observer itself) channel."""

Float32Array = NDArray[np.float32]


def velocity_log_map(v: ArrayLike, alpha: float, beta: float, v0: float) -> Float32Array:
    """Clipped log mapping of relative speed to pixel value (paper eq. 13), elementwise.

    ``Z = clip(1 - beta * ln(alpha * |v|) * H(|v| - v0), 0, 1)`` with ``H`` the Heaviside
    step, ``H(0) = 1``. Below ``v0`` the value is 1; with ``v0 = 1/alpha`` the map is
    continuous there and decreases monotonically with ``|v|`` above it.

    Args:
        v: relative Frenet longitudinal speeds, m/s, any shape.
        alpha: 1/(m/s).
        beta: dimensionless slope.
        v0: threshold speed, m/s.

    Returns:
        float32 array of the shape of ``v``, values in [0, 1].
    """
    speed = np.abs(np.asarray(v, dtype=np.float64))
    on = speed >= v0
    # Only the cells at or above v0 reach the log; v0 > 0 keeps its argument positive, and
    # the floor merely avoids log(0) warnings on the cells that are masked out anyway.
    decay = beta * np.log(alpha * np.maximum(speed, np.finfo(np.float64).tiny))
    z = np.where(on, 1.0 - decay, 1.0)
    return np.clip(z, 0.0, 1.0).astype(np.float32)


class SensorNoise(NamedTuple):
    """The sensor-noise draws of one frame: every (observer, vehicle) pair, ``(n_obs, N)``.

    Attributes:
        position: ``(n_obs, N, 2)`` offsets added to x, y, metres.
        heading: ``(n_obs, N)`` offsets added to the heading, radians.
        speed: ``(n_obs, N)`` offsets added to the Frenet speed, m/s.
        missed: ``(n_obs, N)`` bool, True where the vehicle is not seen.

    Entries of an observer's own slot are drawn but never applied (it knows its state).
    """

    position: NDArray[np.float64]
    heading: NDArray[np.float64]
    speed: NDArray[np.float64]
    missed: NDArray[np.bool_]

    def rows(self, which: NDArray[np.bool_] | NDArray[np.integer]) -> SensorNoise:
        """The draws of the observers ``which`` (a mask or indices over ``n_obs``)."""
        return SensorNoise(self.position[which], self.heading[which], self.speed[which], self.missed[which])


def draw_noise(rng: np.random.Generator, n_obs: int, n_veh: int, noise: NoiseConfig) -> SensorNoise:
    """Draw one frame's sensor noise for ``n_obs`` observers of ``n_veh`` vehicles.

    The stream consumed depends only on ``(n_obs, n_veh)``, in this order: position
    ``(n_obs, N, 2)`` standard normals, heading ``(n_obs, N)`` standard normals, Frenet
    speed ``(n_obs, N)`` standard normals, miss ``(n_obs, N)`` uniforms; each scaled by
    its ``noise`` field.
    """
    shape, k = (n_obs, n_veh), n_obs * n_veh
    # One call draws the three normal arrays: the generator yields the same numbers in
    # the same order as three calls would, for a quarter of the calls' overhead.
    z = rng.standard_normal(4 * k)
    return SensorNoise(
        position=z[: 2 * k].reshape(*shape, 2) * noise.position_std,
        heading=z[2 * k : 3 * k].reshape(shape) * noise.heading_std,
        speed=z[3 * k :].reshape(shape) * noise.speed_std,
        missed=rng.random(shape) < noise.miss_prob,
    )


def _local_axes(cfg: ObservationConfig) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Cell-centre coordinates ``(x_c (W,), y_c (H,))`` in the observer frame, metres."""
    res = cfg.resolution
    xc = -cfg.behind + (np.arange(cfg.width, dtype=np.float64) + 0.5) * res
    yc = (np.arange(cfg.height, dtype=np.float64) + 0.5) * res - cfg.height * res / 2.0
    return xc, yc


def render_frame(
    scene: Scene,
    observers: Sequence[int] | NDArray[np.integer],
    cfg: ObservationConfig,
    rng: np.random.Generator | None = None,
    noise: SensorNoise | None = None,
) -> Float32Array:
    """Render one VelocityMap frame per observer.

    Args:
        scene: the vehicles and road at one instant.
        observers: ``(n_obs,)`` indices into the scene's vehicles, normally
            ``scene.agents``.
        cfg: grid geometry, eq. 13 coefficients and noise levels (``cfg.noise``).
        rng: when given, sensor noise ``cfg.noise`` is drawn from it with
            :func:`draw_noise` for every (observer, vehicle) pair, including masked
            slots and the observer itself. ``None`` (and no ``noise``) renders the clean
            scene.
        noise: draws made beforehand, ``(n_obs, N)`` (instead of ``rng``).

    Returns:
        ``(n_obs, 4, H, W)`` float32 in [0, 1], channels in :data:`CHANNELS` order.

    Masked-out vehicles (``scene.mask`` False) are never drawn, not even as an observer's
    own MV footprint; crashed vehicles are drawn as usual.
    """
    obs = np.asarray(observers, dtype=np.int64).reshape(-1)
    n_obs, n_veh = obs.shape[0], scene.n_vehicles
    h, w, res = cfg.height, cfg.width, cfg.resolution
    out = np.zeros((n_obs, 4, h, w), dtype=np.float32)
    if n_obs == 0:
        return out
    if obs.min() < 0 or obs.max() >= n_veh:
        raise IndexError(f"observer index outside the scene's {n_veh} vehicles")

    ego_pos = scene.position[obs]  # (n_obs, 2)
    ego_head = scene.heading[obs]
    cos_k, sin_k = np.cos(ego_head), np.sin(ego_head)
    xc, yc = _local_axes(cfg)

    # RL is sampled at the cell centres in the world frame, where the road raster lives.
    wx = ego_pos[:, 0, None, None] + cos_k[:, None, None] * xc - sin_k[:, None, None] * yc[:, None]
    wy = ego_pos[:, 1, None, None] + sin_k[:, None, None] * xc + cos_k[:, None, None] * yc[:, None]
    out[:, RL] = scene.road.sample(np.stack([wx, wy], axis=-1))
    if cfg.route > 0.0:
        # The route lies under the observer's footprint, which is drawn over it below.
        route_of = np.zeros(n_veh, dtype=np.uint64)
        assert scene.route is not None
        route_of[scene.agents] = scene.route
        on = (scene.road.sample_edges(np.stack([wx, wy], axis=-1)) & route_of[obs][:, None, None]) != 0
        out[:, MV] = np.where(on, np.float32(cfg.route), np.float32(0.0))

    if n_veh == 0:
        return out

    # Arrays are per (observer, vehicle) pair: each observer sees its own noisy copy.
    pos = np.broadcast_to(scene.position, (n_obs, n_veh, 2))
    head = np.broadcast_to(scene.heading, (n_obs, n_veh))
    fspeed = np.broadcast_to(scene.frenet_speed, (n_obs, n_veh))
    is_self = obs[:, None] == np.arange(n_veh)[None, :]
    visible = np.broadcast_to(scene.mask, (n_obs, n_veh)).copy()
    if rng is not None:
        if noise is not None:
            raise ValueError("give rng or noise draws, not both")
        noise = draw_noise(rng, n_obs, n_veh, cfg.noise)
    if noise is not None:
        if noise.heading.shape != (n_obs, n_veh):
            raise ValueError(f"noise draws are {noise.heading.shape}, the frame needs {(n_obs, n_veh)}")
        # The observer knows its own state exactly.
        keep = ~is_self
        pos = pos + noise.position * keep[..., None]
        head = head + noise.heading * keep
        fspeed = fspeed + noise.speed * keep
        visible &= ~(noise.missed & keep)

    rel = pos - ego_pos[:, None, :]
    lx = cos_k[:, None] * rel[..., 0] + sin_k[:, None] * rel[..., 1]  # (n_obs, N)
    ly = -sin_k[:, None] * rel[..., 0] + cos_k[:, None] * rel[..., 1]
    radius = 0.5 * np.hypot(scene.length, scene.width)  # (N,) footprint circumradius
    half_h = 0.5 * h * res
    # Culling by the footprint's bounding circle is conservative: no vehicle covering a
    # cell centre is dropped, and what survives is bounded by the view, not by N.
    visible &= (lx + radius >= -cfg.behind) & (lx - radius <= w * res - cfg.behind)
    visible &= np.abs(ly) - radius <= half_h
    k_idx, v_idx = np.nonzero(visible)
    if k_idx.size == 0:
        return out

    kind = scene.kind[v_idx]
    self_pair = is_self[k_idx, v_idx]
    channel = np.where(self_pair, MV, np.where(kind == Kind.HV, HV, AV))
    rel_speed = fspeed[k_idx, v_idx] - scene.frenet_speed[obs[k_idx]]
    value = velocity_log_map(rel_speed, cfg.alpha, cfg.beta, cfg.v0)
    mv_value = np.clip(np.abs(scene.speed[v_idx]) / cfg.max_speed, 0.0, 1.0)
    value = np.where(self_pair, mv_value, value).astype(np.float32)

    # Each pair tests a K x K window of cells around its nearest cell. A covered centre
    # lies within the circumradius r of the vehicle's centre, which lies within half a cell
    # of that nearest cell's centre: K = 2 * floor(r / res + 0.5) + 1 misses none.
    px, py = lx[k_idx, v_idx], ly[k_idx, v_idx]
    half_win = int(np.floor(radius[v_idx].max() / res + 0.5))
    offsets = np.arange(-half_win, half_win + 1)
    col = np.rint((px + cfg.behind) / res - 0.5).astype(np.int64)[:, None] + offsets  # (P, K)
    row = np.rint((py + half_h) / res - 0.5).astype(np.int64)[:, None] + offsets  # (P, K)
    dx = (-cfg.behind + (col + 0.5) * res) - px[:, None]  # (P, K)
    dy = ((row + 0.5) * res - half_h) - py[:, None]  # (P, K)

    rel_head = head[k_idx, v_idx] - ego_head[k_idx]
    cos_r, sin_r = np.cos(rel_head)[:, None, None], np.sin(rel_head)[:, None, None]
    # Cell offsets in the vehicle's own frame, (P, K rows, K cols).
    u = cos_r * dx[:, None, :] + sin_r * dy[:, :, None]
    v = cos_r * dy[:, :, None] - sin_r * dx[:, None, :]
    half_len = (0.5 * scene.length[v_idx])[:, None, None]
    half_wid = (0.5 * scene.width[v_idx])[:, None, None]
    inside = (u >= -half_len) & (u < half_len) & (v >= -half_wid) & (v < half_wid)
    inside &= ((col >= 0) & (col < w))[:, None, :]
    inside &= ((row >= 0) & (row < h))[:, :, None]

    p_idx, r_idx, c_idx = np.nonzero(inside)
    plane = k_idx[p_idx] * 4 + channel[p_idx]
    flat = (plane * h + row[p_idx, r_idx]) * w + col[p_idx, c_idx]
    own = self_pair[p_idx]
    np.maximum.at(out.reshape(-1), flat[~own], value[p_idx][~own])
    # An observer's own footprint replaces what lies under it (the route, when drawn):
    # it is the only vehicle of its MV plane.
    out.reshape(-1)[flat[own]] = value[p_idx][own]
    return out


def render_agents(
    scene: Scene,
    cfg: ObservationConfig,
    noise: SensorNoise | None,
    observing: NDArray[np.bool_],
) -> Float32Array:
    """Frames of the scene's agents where ``observing``, zeros for the others.

    Args:
        scene: the vehicles and road at one instant.
        cfg: as for :func:`render_frame`.
        noise: this frame's draws for every agent, ``(n_av, N)`` (the rows of agents
            that are not observing are drawn but unused); None renders the clean scene.
        observing: ``(n_av,)`` bool, the agents that get a frame.

    Returns:
        ``(n_av, 4, H, W)`` float32, agent order.
    """
    seen = np.asarray(observing, dtype=bool)
    out = np.zeros((scene.n_agents, 4, cfg.height, cfg.width), dtype=np.float32)
    out[seen] = render_frame(scene, scene.agents[seen], cfg, noise=None if noise is None else noise.rows(seen))
    return out


class FrameStack:
    """The last ``T`` frames of every observer, most recent last.

    :meth:`reset` fills all ``T`` slots with the first frame, so a stack is full-shaped
    from the first step and reads as "nothing has moved yet" rather than as empty frames
    the network never sees later in an episode.

    Args:
        frames: T, the number of frames kept.
        storage: where to keep the stack, ``(n_obs, C, T, H, W)`` float32 (a vector env
            keeps every environment's stack in one array and copies it once per step);
            by default an array of its own, allocated on :meth:`reset`.
    """

    def __init__(self, frames: int, storage: Float32Array | None = None) -> None:
        if frames < 1:
            raise ValueError(f"frames must be >= 1, got {frames}")
        if storage is not None and (storage.ndim != 5 or storage.shape[2] != frames or storage.dtype != np.float32):
            raise ValueError(f"storage must be float32 (n_obs, C, {frames}, H, W), got {storage.dtype} {storage.shape}")
        self.frames = int(frames)
        self._storage = storage
        self._buf: Float32Array | None = None

    def reset(self, first_frame: NDArray[np.floating]) -> None:
        """Start a new episode from ``first_frame`` of shape ``(n_obs, 4, H, W)``."""
        frame = np.asarray(first_frame, dtype=np.float32)
        if frame.ndim != 4:
            raise ValueError(f"a frame must be (n_obs, C, H, W), got shape {frame.shape}")
        n, c, h, w = frame.shape
        if self._storage is None:
            self._buf = np.empty((n, c, self.frames, h, w), dtype=np.float32)
        elif self._storage.shape != (n, c, self.frames, h, w):
            raise ValueError(f"frame shape {frame.shape} does not fit the storage {self._storage.shape}")
        else:
            self._buf = self._storage
        self._buf[...] = frame[:, :, None]

    def push(self, frame: NDArray[np.floating], rows: NDArray[np.bool_] | None = None) -> None:
        """Append ``frame`` ``(n_obs, 4, H, W)`` as the most recent, dropping the oldest.

        With ``rows`` ``(n_obs,)`` bool, only those observers' stacks move on; the others
        keep their last observation (their rows of ``frame`` are not read).
        """
        if self._buf is None:
            raise RuntimeError("FrameStack.push called before reset")
        buf = self._buf
        expected = (buf.shape[0], buf.shape[1], buf.shape[3], buf.shape[4])
        if np.shape(frame) != expected:
            raise ValueError(f"frame shape {np.shape(frame)} does not match {expected}")
        # One slot at a time, oldest first: each copy reads a slot not yet overwritten,
        # and slices that do not overlap spare numpy the temporary copy of the stack it
        # makes for an overlapping one.
        if rows is None or np.all(rows):
            for t in range(self.frames - 1):
                buf[:, :, t] = buf[:, :, t + 1]
            buf[:, :, -1] = frame
            return
        idx = np.flatnonzero(rows)
        for t in range(self.frames - 1):
            buf[idx, :, t] = buf[idx, :, t + 1]
        buf[idx, :, -1] = np.asarray(frame)[idx]

    @property
    def stack(self) -> Float32Array:
        """``(n_obs, 4, T, H, W)`` float32, oldest first; a copy, safe to keep."""
        if self._buf is None:
            raise RuntimeError("FrameStack.stack read before reset")
        return self._buf.copy()

    @property
    def view(self) -> Float32Array:
        """:attr:`stack` without the copy: it changes with the next push or reset."""
        if self._buf is None:
            raise RuntimeError("FrameStack.view read before reset")
        return self._buf
