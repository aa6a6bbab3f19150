"""The Scene: the one boundary between simulators and everything downstream.

A :class:`Scene` is a struct of arrays describing every vehicle at one instant, plus a
handle to the road layout's drivable-area raster. Backends produce Scenes; observation,
data collection and learning consume them and never import a simulator.

Conventions: world frame in metres (x, y), headings in radians measured from +x towards
+y (highway-env's convention: y grows to the right of a car heading along +x), speeds in
m/s.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum
from typing import TypeVar

import numpy as np
from numpy.typing import NDArray

__all__ = ["Kind", "RoadRaster", "Scene", "rasterize_strips"]

FloatArray = NDArray[np.float64]
_Cell = TypeVar("_Cell", np.uint8, np.uint64)


class Kind(IntEnum):
    """What drives a vehicle. The mission vehicle (MV) is the observing AV itself."""

    HV = 0  # human-driven: IDM + MOBIL
    AV = 1  # autonomous: driven by the learned policy


@dataclass(frozen=True, eq=False)
class RoadRaster:
    """Drivable area of a road layout in the world frame, rasterized once per layout.

    Attributes:
        mask: ``(rows, cols)`` uint8, 1 where the road is drivable. Row index grows with
            world y, column index with world x.
        origin: ``(2,)`` world (x, y) of the centre of cell ``[0, 0]``, metres.
        resolution: cell size, metres.
        edges: ``(rows, cols)`` uint64 or None: bit ``e`` set where edge ``e`` of the
            layout's lane graph (highway-env's graph order) is drivable. It is what a
            route is drawn from (``ObservationConfig.route``); None where unknown.
    """

    mask: NDArray[np.uint8]
    origin: FloatArray
    resolution: float
    edges: NDArray[np.uint64] | None = None

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, RoadRaster):
            return NotImplemented
        return self is other or (
            self.resolution == other.resolution
            and np.array_equal(self.origin, other.origin)
            and np.array_equal(self.mask, other.mask)
            and (self.edges is None) == (other.edges is None)
            and (self.edges is None or other.edges is None or np.array_equal(self.edges, other.edges))
        )

    __hash__ = None  # type: ignore[assignment]

    def sample(self, xy: FloatArray) -> NDArray[np.uint8]:
        """Drivable flag at world points ``xy`` of shape ``(..., 2)`` (nearest cell; 0 outside)."""
        return self._sample(self.mask, xy)

    def sample_edges(self, xy: FloatArray) -> NDArray[np.uint64]:
        """Edge bits (:attr:`edges`) at world points ``xy`` of shape ``(..., 2)`` (nearest
        cell; 0 outside, and everywhere when the raster has no edges)."""
        if self.edges is None:
            return np.zeros(xy.shape[:-1], dtype=np.uint64)
        return self._sample(self.edges, xy)

    def _sample(self, grid: NDArray[_Cell], xy: FloatArray) -> NDArray[_Cell]:
        idx = np.rint((xy - self.origin) / self.resolution).astype(np.int64)
        col, row = idx[..., 0], idx[..., 1]
        rows, cols = grid.shape
        inside = (row >= 0) & (row < rows) & (col >= 0) & (col < cols)
        out = np.zeros(xy.shape[:-1], dtype=grid.dtype)
        out[inside] = grid[row[inside], col[inside]]
        return out


def rasterize_strips(
    centers: FloatArray,
    headings: FloatArray,
    half_widths: FloatArray,
    resolution: float = 0.5,
    margin: float = 5.0,
    edges: NDArray[np.integer] | None = None,
) -> RoadRaster:
    """Rasterize lanes given as densely sampled centreline points into a :class:`RoadRaster`.

    Each centreline sample marks the cells under a lateral segment of half-width
    ``half_widths[i]`` across its heading. Sample centrelines at most ``resolution`` apart
    so that consecutive segments leave no gaps.

    Args:
        centers: ``(P, 2)`` centreline points, metres.
        headings: ``(P,)`` lane heading at each point, radians.
        half_widths: ``(P,)`` half lane width at each point, metres.
        resolution: raster cell size, metres.
        margin: empty border around the road, metres.
        edges: ``(P,)`` the lane-graph edge id (0–63) of each sample; when given, the
            raster's :attr:`RoadRaster.edges` marks each cell with the edges drawn on it.
    """
    centers = np.asarray(centers, dtype=np.float64)
    lo = centers.min(axis=0) - half_widths.max() - margin
    hi = centers.max(axis=0) + half_widths.max() + margin
    shape = (int(np.ceil((hi[1] - lo[1]) / resolution)) + 1, int(np.ceil((hi[0] - lo[0]) / resolution)) + 1)
    mask = np.zeros(shape, dtype=np.uint8)
    # Lateral offsets at half-cell spacing: every cell a strip crosses gets at least one hit.
    n_off = int(np.ceil(half_widths.max() / (0.5 * resolution)))
    unit = np.linspace(-1.0, 1.0, 2 * n_off + 1)
    normals = np.stack([-np.sin(headings), np.cos(headings)], axis=-1)  # (P, 2)
    offsets = unit[None, :, None] * half_widths[:, None, None] * normals[:, None, :]  # (P, K, 2)
    pts = (centers[:, None, :] + offsets).reshape(-1, 2)
    idx = np.rint((pts - lo) / resolution).astype(np.int64)
    mask[idx[:, 1], idx[:, 0]] = 1
    if edges is None:
        return RoadRaster(mask=mask, origin=lo, resolution=float(resolution))
    ids = np.asarray(edges, dtype=np.int64)
    if ids.shape != (centers.shape[0],) or (ids.size and (ids.min() < 0 or ids.max() > 63)):
        raise ValueError("edges must give one edge id in [0, 63] per centreline sample")
    bits = np.zeros(shape, dtype=np.uint64)
    cell_bits = np.repeat(np.left_shift(np.uint64(1), ids.astype(np.uint64)), unit.size)
    np.bitwise_or.at(bits, (idx[:, 1], idx[:, 0]), cell_bits)
    return RoadRaster(mask=mask, origin=lo, resolution=float(resolution), edges=bits)


@dataclass(frozen=True, eq=False)
class Scene:
    """All vehicles of one environment at one instant, as arrays of length N.

    Attributes:
        position: ``(N, 2)`` world x, y of each vehicle's centre, metres.
        heading: ``(N,)`` yaw, radians.
        speed: ``(N,)`` speed along the heading, m/s.
        frenet_speed: ``(N,)`` longitudinal speed along the vehicle's current lane
            (Frenet ṡ), m/s. The VelocityMap encodes differences of these (eq. 13).
        length: ``(N,)`` metres.
        width: ``(N,)`` metres.
        kind: ``(N,)`` int8, a :class:`Kind` value.
        mask: ``(N,)`` bool, False for padding slots (batched backends pad to a fixed N).
        crashed: ``(N,)`` bool.
        agents: ``(n_av,)`` int64 indices of the AVs, in agent order: agent i of the env's
            actions, rewards and observations is vehicle ``agents[i]``.
        road: the layout's drivable-area raster (shared by every Scene of the layout).
        time: simulated time since reset, seconds.
        arrived: ``(N,)`` bool, True for AVs that have completed their mission (all False
            when omitted).
        route: ``(n_av,)`` uint64, agent order: the edges (bits, as in
            :attr:`RoadRaster.edges`) of the lane each AV steers along and of the rest of
            its planned route (all 0 when omitted).
    """

    position: FloatArray
    heading: FloatArray
    speed: FloatArray
    frenet_speed: FloatArray
    length: FloatArray
    width: FloatArray
    kind: NDArray[np.int8]
    mask: NDArray[np.bool_]
    crashed: NDArray[np.bool_]
    agents: NDArray[np.int64]
    road: RoadRaster
    time: float = 0.0
    arrived: NDArray[np.bool_] | None = None
    route: NDArray[np.uint64] | None = None

    def __post_init__(self) -> None:
        n = self.position.shape[0]
        if self.arrived is None:
            object.__setattr__(self, "arrived", np.zeros(n, dtype=bool))
        route = np.zeros(self.agents.shape[0], dtype=np.uint64) if self.route is None else self.route
        if route.shape != self.agents.shape or route.dtype != np.uint64:
            raise ValueError(f"Scene.route must be uint64 ({self.agents.shape[0]},), got {route.dtype} {route.shape}")
        object.__setattr__(self, "route", route)
        if self.position.shape != (n, 2):
            raise ValueError(f"Scene.position must be (N, 2), got {self.position.shape}")
        for name in ("heading", "speed", "frenet_speed", "length", "width", "kind", "mask", "crashed", "arrived"):
            if getattr(self, name).shape != (n,):
                raise ValueError(f"Scene.{name} must be ({n},), got {getattr(self, name).shape}")
        if self.agents.size and (self.agents.max() >= n or self.agents.min() < 0):
            raise ValueError("Scene.agents indexes outside the vehicle arrays")

    def __eq__(self, other: object) -> bool:
        """Equal when every array holds the same values (for determinism checks)."""
        if not isinstance(other, Scene):
            return NotImplemented
        return self.time == other.time and self.road == other.road and all(
            np.array_equal(getattr(self, f), getattr(other, f))
            for f in ("position", "heading", "speed", "frenet_speed", "length", "width",
                      "kind", "mask", "crashed", "arrived", "agents", "route")
        )

    __hash__ = None  # type: ignore[assignment]

    @property
    def n_vehicles(self) -> int:
        return int(self.position.shape[0])

    @property
    def n_agents(self) -> int:
        return int(self.agents.shape[0])
