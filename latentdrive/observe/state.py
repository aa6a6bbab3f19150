"""An exact-state vector of one AV and its nearest vehicles: what a map draws, without the map.

A diagnostic observation, not the paper's: it reads the Scene's own values (no raster, no
sensor noise, no field-of-view edge), so a policy fed it tells whether the VelocityMap's
picture is what limits a policy that reads the map (``scripts/state_copy.py``). It holds
neither where a human driver will turn nor its driving parameters.

Layout, scaled to order one (positions in metres, speeds in m/s, headings in radians):

- the AV: speed / 20, lane speed / 20, cos and sin of its heading, world x / 100, y / 100,
  the share of the episode's time gone, and, with ``route``, bits 0 to
  :data:`ROUTE_BITS` − 1 of its planned route (``Scene.route``);
- its ``k`` nearest other vehicles within ``radius``, nearest first, :data:`PER_NEIGHBOUR`
  values each: x, y / 50 and velocity differences vx, vy / 20 in the AV's frame (x ahead, y
  to its right, as the world's y is to the right of a car heading along +x); cos and sin
  of the heading relative to the AV's; 1 if an AV; 1 if crashed; 1 (present). Absent
  neighbours are zero rows.

:func:`view_targets` gives, for every AV of a Scene at once, the AV's two speeds and the
same neighbour rows for the vehicles inside its VelocityMap's view: what its map draws,
exactly. They are the targets of the learner's auxiliary loss (``dqn.aux_scale``).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from latentdrive.config import ObservationConfig
from latentdrive.scene import Kind, Scene

__all__ = ["PER_NEIGHBOUR", "ROUTE_BITS", "nearest", "neighbour_rows", "state_features", "state_size", "view_box",
           "view_target_size", "view_targets"]

#: Route bits kept: the preset layouts' lane graphs have at most 24 edges (roundabout).
ROUTE_BITS = 32
#: Values per neighbour (module docstring).
PER_NEIGHBOUR = 9
_EGO = 7


def state_size(k: int, route: bool) -> int:
    """Length of :func:`state_features`' vector."""
    return _EGO + (ROUTE_BITS if route else 0) + k * PER_NEIGHBOUR


def nearest(scene: Scene, vehicle: int, k: int, radius: float) -> NDArray[np.intp]:
    """Indices of the at most ``k`` other vehicles of ``scene`` whose centres lie within
    ``radius`` metres of ``vehicle``'s, nearest first (ties in index order)."""
    others = np.flatnonzero(scene.mask & (np.arange(scene.n_vehicles) != vehicle))
    dist = np.hypot(*(scene.position[others] - scene.position[vehicle]).T)
    inside = dist <= radius
    return others[inside][np.argsort(dist[inside], kind="stable")][:k]


def state_features(scene: Scene, agent: int, duration: float, k: int, radius: float, route: bool) -> NDArray[np.float32]:
    """The exact-state vector ``(state_size(k, route),)`` float32 of agent ``agent`` of
    ``scene`` in an episode of ``duration`` seconds (module docstring)."""
    i = int(scene.agents[agent])
    h = float(scene.heading[i])
    c, s = math.cos(h), math.sin(h)
    ego = [scene.speed[i] / 20.0, scene.frenet_speed[i] / 20.0, c, s,
           scene.position[i, 0] / 100.0, scene.position[i, 1] / 100.0, scene.time / duration]
    if route:
        assert scene.route is not None  # Scene fills it in
        bits = int(scene.route[agent])
        if bits >> ROUTE_BITS:
            raise ValueError(f"the route uses lane-graph edges beyond the {ROUTE_BITS} the state vector holds")
        ego += [float((bits >> b) & 1) for b in range(ROUTE_BITS)]
    rows = np.zeros((k, PER_NEIGHBOUR))
    near = nearest(scene, i, k, radius)
    rows[: near.size] = neighbour_rows(scene, np.array([i]), near[None])[0]
    return np.concatenate([np.asarray(ego, dtype=np.float64), rows.reshape(-1)]).astype(np.float32)


def neighbour_rows(scene: Scene, observers: NDArray[np.intp], others: NDArray[np.intp]) -> NDArray[np.float64]:
    """Rows ``(A, k, PER_NEIGHBOUR)`` of vehicles ``others`` ``(A, k)`` seen by vehicles
    ``observers`` ``(A,)`` of ``scene`` (module docstring), in each observer's frame."""
    i = observers[:, None]
    h = scene.heading[i]
    c, s = np.cos(h), np.sin(h)
    dx = scene.position[others, 0] - scene.position[i, 0]
    dy = scene.position[others, 1] - scene.position[i, 1]
    hv = scene.heading[others]
    vx = scene.speed[others] * np.cos(hv) - scene.speed[i] * c
    vy = scene.speed[others] * np.sin(hv) - scene.speed[i] * s
    # World offsets and velocity differences turned into the observer's frame.
    return np.stack([
        (c * dx + s * dy) / 50.0, (-s * dx + c * dy) / 50.0,
        (c * vx + s * vy) / 20.0, (-s * vx + c * vy) / 20.0,
        np.cos(hv - h), np.sin(hv - h),
        scene.kind[others] == Kind.AV, scene.crashed[others], np.ones(others.shape),
    ], axis=-1)


def view_box(obs: ObservationConfig) -> tuple[float, float, float]:
    """The VelocityMap's view in the observer's frame, metres: how far it sees behind, ahead
    and to each side (a centre inside the box may still be drawn only in part)."""
    return obs.behind, obs.width * obs.resolution - obs.behind, obs.height * obs.resolution / 2.0


def view_target_size(k: int) -> int:
    """Length of a :func:`view_targets` row."""
    return 2 + k * PER_NEIGHBOUR


def view_targets(scene: Scene, obs: ObservationConfig, k: int) -> NDArray[np.float32]:
    """What each AV's map of ``scene`` draws, as exact values: ``(n_agents, view_target_size(k))``
    float32. Per AV: its speed / 20 and lane speed / 20, then the rows (module docstring) of
    the ``k`` nearest other vehicles whose centres lie in :func:`view_box`, nearest first
    (ties in index order), zero rows when fewer are there. Sensor noise is not applied: the
    targets are what the map would show without it."""
    agents = np.asarray(scene.agents, dtype=np.intp)
    behind, ahead, side = view_box(obs)
    h = scene.heading[agents][:, None]
    dx = scene.position[None, :, 0] - scene.position[agents][:, None, 0]
    dy = scene.position[None, :, 1] - scene.position[agents][:, None, 1]
    along, across = np.cos(h) * dx + np.sin(h) * dy, -np.sin(h) * dx + np.cos(h) * dy
    inside = ((along >= -behind) & (along < ahead) & (np.abs(across) <= side) & scene.mask[None]
              & (np.arange(scene.n_vehicles)[None] != agents[:, None]))
    dist = np.where(inside, np.hypot(dx, dy), np.inf)
    order = np.argsort(dist, axis=1, kind="stable")[:, :k]
    present = np.take_along_axis(inside, order, axis=1)
    rows = np.zeros((len(agents), k, PER_NEIGHBOUR))
    if order.shape[1]:
        rows[:, : order.shape[1]] = neighbour_rows(scene, agents, order) * present[..., None]
    own = np.stack([scene.speed[agents], scene.frenet_speed[agents]], axis=1) / 20.0
    return np.concatenate([own, rows.reshape(len(agents), -1)], axis=1).astype(np.float32)
