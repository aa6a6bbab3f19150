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
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from latentdrive.scene import Kind, Scene

__all__ = ["PER_NEIGHBOUR", "ROUTE_BITS", "nearest", "state_features", "state_size"]

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
    near = nearest(scene, i, k, radius)
    rows = np.zeros((k, PER_NEIGHBOUR))
    if near.size:
        dx, dy = (scene.position[near] - scene.position[i]).T
        hv = scene.heading[near]
        vx = scene.speed[near] * np.cos(hv) - scene.speed[i] * c
        vy = scene.speed[near] * np.sin(hv) - scene.speed[i] * s
        # World offsets and velocity differences turned into the AV's frame.
        rows[: near.size] = np.stack([
            (c * dx + s * dy) / 50.0, (-s * dx + c * dy) / 50.0,
            (c * vx + s * vy) / 20.0, (-s * vx + c * vy) / 20.0,
            np.cos(hv - h), np.sin(hv - h),
            scene.kind[near] == Kind.AV, scene.crashed[near], np.ones(near.size),
        ], axis=1)
    return np.concatenate([np.asarray(ego, dtype=np.float64), rows.reshape(-1)]).astype(np.float32)
