"""A layout's lane network as flat arrays, read once from highway-env's own road builders.

Geometry is extracted rather than re-derived: every lane parameter (start, direction,
radius, phases, widths, speed limits, priorities, the graph's edge order) is copied from
the :class:`highway_env.road.road.Road` that :func:`latentdrive.sim.roads.build_road`
builds, so both backends drive on the same numbers by construction. highway-env is only
touched here, once per ``(layout, lanes_count)``; the arrays are what the compiled
kernels read.

Conventions: lanes are numbered in highway-env's graph iteration order (that order breaks
ties in closest-lane searches), edges likewise, nodes in order of first appearance.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from functools import cache, cached_property
from typing import NamedTuple

import numpy as np
from highway_env.road.lane import CircularLane, SineLane, StraightLane
from highway_env.road.regulation import RegulatedRoad
from highway_env.vehicle.objects import Landmark, Obstacle
from numpy.typing import NDArray

from latentdrive.sim.roads import build_road, layout_edges

__all__ = ["CIRCULAR", "GEO_ROWS", "INT_ROWS", "SINE", "STRAIGHT", "LaneTable", "Network", "get_network"]

STRAIGHT, SINE, CIRCULAR = 0, 1, 2

FArr = NDArray[np.float64]
IArr = NDArray[np.int64]

# Rows of LaneTable.geo (metres, radians, m/s; parameters a lane kind does not use are 0).
GEO_ROWS = (
    "start_x", "start_y",  # straight / sine: start of the (base) segment
    "dir_x", "dir_y",  # straight / sine: unit direction of the base segment
    "lat_x", "lat_y",  # straight / sine: unit lateral direction (+90° from direction)
    "base_heading",  # straight / sine: heading of the base segment
    "length", "width",
    "amplitude", "pulsation", "phase",  # sine: metres, rad/m, rad
    "center_x", "center_y", "radius", "start_phase",  # circular
    "cdir",  # circular: +1 for increasing phase, -1 otherwise
    "speed_limit",  # NaN where the lane has none
)
(START_X, START_Y, DIR_X, DIR_Y, LAT_X, LAT_Y, BASE_HEADING, LENGTH, WIDTH, AMPLITUDE, PULSATION,
 PHASE, CENTER_X, CENTER_Y, RADIUS, START_PHASE, CDIR, SPEED_LIMIT) = range(len(GEO_ROWS))
# Rows of LaneTable.ints.
INT_ROWS = ("kind", "forbidden", "priority", "edge", "index_in_edge")
KIND, FORBIDDEN, PRIORITY, EDGE, INDEX_IN_EDGE = range(len(INT_ROWS))
# Rows of LaneTable.edges: from node, to node, lane id of the edge's lane 0, lane count.
EDGE_FROM, EDGE_TO, EDGE_FIRST_LANE, EDGE_N_LANES = range(4)
# Planes of LaneTable.boxes.
CURVE_BOX, REGION_BOX = 0, 1


class LaneTable(NamedTuple):
    """A lane network packed into a few arrays (few arguments keep compilation quick).

    Attributes:
        geo: ``(len(GEO_ROWS), L)`` float lane parameters, rows named by ``GEO_ROWS``.
        ints: ``(len(INT_ROWS), L)`` kind (STRAIGHT/SINE/CIRCULAR), forbidden flag,
            right-of-way priority, edge id, highway-env's lane id on its edge.
        boxes: ``(2, L, 4)`` boxes ``(xmin, ymin, xmax, ymax)``: CURVE_BOX bounds the lane's
            distance function from below, REGION_BOX every point on the lane (1 m margin,
            ±5 m beyond its ends).
        edges: ``(4, E)`` per edge: from node, to node, first lane id, lane count.
        node_out_start: ``(V + 1,)`` CSR offsets into ``node_out_edges``.
        node_out_edges: successor edges of each node, in highway-env's dict order.
    """

    geo: FArr
    ints: IArr
    boxes: FArr
    edges: IArr
    node_out_start: IArr
    node_out_edges: IArr


@dataclass(frozen=True, eq=False)
class Network:
    """A layout's lanes, edges and nodes: arrays for the kernels, names for people.

    Attributes:
        layout, lanes_count: what was built.
        table: the arrays.
        lane_keys: highway-env lane index ``(from, to, id)`` of each lane.
        node_names: name of each node id.
        edge_keys: ``(from, to)`` of each edge id.
        obstacles: ``(n_obj, 5)`` static road objects: x, y, heading, length, width.
        regulated: whether the road enforces right of way (highway-env's RegulatedRoad).
        paths: shortest node paths between node pairs, as highway-env's BFS finds them.
    """

    layout: str
    lanes_count: int
    table: LaneTable
    lane_keys: tuple[tuple[str, str, int], ...]
    node_names: tuple[str, ...]
    edge_keys: tuple[tuple[str, str], ...]
    obstacles: FArr
    regulated: bool
    paths: dict[tuple[str, str], tuple[str, ...]]

    @property
    def n_lanes(self) -> int:
        return len(self.lane_keys)

    @property
    def n_nodes(self) -> int:
        return len(self.node_names)

    def node(self, name: str) -> int:
        """Node id of a node name (KeyError when the layout has no such node)."""
        return self.node_names.index(name)

    def edge(self, key: tuple[str, str]) -> int:
        """Edge id of ``(from, to)`` (ValueError when the layout has no such edge)."""
        return self.edge_keys.index((key[0], key[1]))

    def lane(self, key: tuple[str, str, int]) -> int:
        """Lane id of a highway-env lane index."""
        e = self.edge((key[0], key[1]))
        return int(self.table.edges[EDGE_FIRST_LANE, e] + key[2])

    def route_edges(self, lane: int, destination: str | None) -> list[int]:
        """Edge ids of the route a vehicle on ``lane`` plans to ``destination``.

        The first entry is the lane's own edge; an unreachable or missing destination
        leaves only it, as highway-env's planner does.
        """
        edge = int(self.table.ints[EDGE, lane])
        if destination is None:
            return [edge]
        path = self.paths.get((self.edge_keys[edge][1], destination), ())
        return [edge] + [self.edge(pair) for pair in itertools.pairwise(path)]

    def destination_id(self, destination: str) -> int:
        """Column of ``destination`` in :attr:`route_table` (``n_nodes`` when unknown)."""
        return self.node_names.index(destination) if destination in self.node_names else self.n_nodes

    @cached_property
    def route_table(self) -> tuple[IArr, IArr]:
        """Every planned route: ``(routes, lengths)``, ``routes[lane, dest, :lengths[lane,
        dest]]`` the edge ids from ``lane`` to node ``dest`` (:meth:`route_edges`); the
        extra last column is for destinations the layout does not have."""
        rows = [[self.route_edges(k, d) for d in (*self.node_names, None)] for k in range(self.n_lanes)]
        width = max(len(r) for row in rows for r in row)
        routes = np.full((self.n_lanes, self.n_nodes + 1, width), -1, dtype=np.int64)
        lengths = np.zeros((self.n_lanes, self.n_nodes + 1), dtype=np.int64)
        for k, row in enumerate(rows):
            for d, r in enumerate(row):
                routes[k, d, : len(r)] = r
                lengths[k, d] = len(r)
        return routes, lengths


def _curve_samples(lane: object, s: FArr, lateral: float) -> FArr:
    """World points of ``lane`` at longitudinal ``s`` and lateral ±``lateral`` (P, 2)."""
    pts = [lane.position(si, r) for si in s for r in (-lateral, 0.0, lateral)]  # type: ignore[attr-defined]
    return np.asarray(pts, dtype=np.float64)


def _box(points: FArr, pad: float) -> FArr:
    return np.array([*(points.min(axis=0) - pad), *(points.max(axis=0) + pad)])


def _lane_row(lane: object) -> dict[str, float]:
    row = dict.fromkeys(("kind", *GEO_ROWS), 0.0)
    if isinstance(lane, CircularLane):
        row.update(kind=CIRCULAR, center_x=lane.center[0], center_y=lane.center[1], radius=lane.radius,
                   start_phase=lane.start_phase, cdir=float(lane.direction))
    elif isinstance(lane, StraightLane):
        row.update(kind=SINE if isinstance(lane, SineLane) else STRAIGHT,
                   start_x=lane.start[0], start_y=lane.start[1], dir_x=lane.direction[0],
                   dir_y=lane.direction[1], lat_x=lane.direction_lateral[0],
                   lat_y=lane.direction_lateral[1], base_heading=lane.heading)
        if isinstance(lane, SineLane):
            row.update(amplitude=lane.amplitude, pulsation=lane.pulsation, phase=lane.phase)
    else:
        raise TypeError(f"lane type {type(lane).__name__} is not supported by the fast backend")
    limit = lane.speed_limit
    row.update(length=lane.length, width=lane.width,
               speed_limit=np.nan if limit is None else float(limit))
    return row


def _boxes(lane: object, kind: int, amplitude: float) -> tuple[FArr, FArr]:
    """Boxes for pruning: the curve box bounds the lane's distance function from below
    (for a sine lane, its base band of half-width ``amplitude``, because the distance is
    measured from the base segment beyond the lane's ends); the region box bounds every
    point highway-env counts as on the lane with a 1 m margin."""
    length = float(lane.length)  # type: ignore[attr-defined]
    half = float(lane.width) / 2 + 1.0  # type: ignore[attr-defined]
    # Straight lanes are spanned by their ends; curves are sampled every 0.25 m.
    n = 2 if kind == STRAIGHT else max(int(np.ceil((length + 10.0) / 0.25)), 2)
    pad = 0.05  # covers the chord error of sampling arcs every 0.25 m
    curve = _curve_samples(lane, np.linspace(0.0, length, n), 0.0)
    if kind == SINE:
        base = np.array([lane.start, lane.end], dtype=np.float64)  # type: ignore[attr-defined]
        lat = np.asarray(lane.direction_lateral)  # type: ignore[attr-defined]
        curve = np.concatenate([base + amplitude * lat, base - amplitude * lat])
    region = _curve_samples(lane, np.linspace(-5.0, length + 5.0, n), half)
    return _box(curve, pad), _box(region, pad)


def _all_paths(network: object, nodes: tuple[str, ...]) -> dict[tuple[str, str], tuple[str, ...]]:
    paths = {}
    for a in nodes:
        for b in nodes:
            path = network.shortest_path(a, b)  # type: ignore[attr-defined]
            if path:
                paths[(a, b)] = tuple(path)
    return paths


@cache
def get_network(layout: str, lanes_count: int) -> Network:
    """The lane network of a layout, built once per ``(layout, lanes_count)``."""
    road = build_road(layout, lanes_count, np.random.default_rng(0))
    graph = road.network.graph
    nodes: list[str] = []
    for a, tos in graph.items():
        for b in (a, *tos):
            if b not in nodes:
                nodes.append(b)
    rows: list[dict[str, float]] = []
    lane_keys: list[tuple[str, str, int]] = []
    edge_keys: list[tuple[str, str]] = []
    boxes: list[tuple[FArr, FArr]] = []
    edge_of, index_in_edge, edge_first, edge_n = [], [], [], []
    priority, forbidden = [], []
    # Edge ids are the raster's (layout_edges): graph order, as the loops below visit them.
    edge_ids = layout_edges(layout, lanes_count)
    for a, tos in graph.items():
        for b, lanes in tos.items():
            assert edge_ids[(a, b)] == len(edge_keys)
            edge_first.append(len(rows))
            edge_n.append(len(lanes))
            for i, lane in enumerate(lanes):
                row = _lane_row(lane)
                rows.append(row)
                boxes.append(_boxes(lane, int(row["kind"]), row["amplitude"]))
                lane_keys.append((a, b, i))
                edge_of.append(len(edge_keys))
                index_in_edge.append(i)
                priority.append(int(lane.priority))
                forbidden.append(bool(lane.forbidden))
            edge_keys.append((a, b))
    node_out_start, node_out_edges = [0], []
    for name in nodes:
        node_out_edges += [edge_keys.index((name, b)) for b in graph.get(name, {})]
        node_out_start.append(len(node_out_edges))
    ints = np.array([[r["kind"] for r in rows], forbidden, priority, edge_of, index_in_edge], dtype=np.int64)
    table = LaneTable(
        geo=np.array([[r[f] for r in rows] for f in GEO_ROWS], dtype=np.float64),
        ints=ints,
        boxes=np.array([[b[0] for b in boxes], [b[1] for b in boxes]], dtype=np.float64),
        edges=np.array([[nodes.index(a) for a, _ in edge_keys], [nodes.index(b) for _, b in edge_keys],
                        edge_first, edge_n], dtype=np.int64),
        node_out_start=np.asarray(node_out_start, dtype=np.int64),
        node_out_edges=np.asarray(node_out_edges, dtype=np.int64),
    )
    objects = [o for o in road.objects if not isinstance(o, Landmark)]
    if any(not isinstance(o, Obstacle) for o in objects):
        raise TypeError("the fast backend supports static obstacles only")
    obstacles = np.array([[o.position[0], o.position[1], o.heading, o.LENGTH, o.WIDTH] for o in objects],
                         dtype=np.float64).reshape(-1, 5)
    for arr in (*table, obstacles):
        arr.flags.writeable = False
    return Network(
        layout=layout, lanes_count=lanes_count, table=table, lane_keys=tuple(lane_keys),
        node_names=tuple(nodes), edge_keys=tuple(edge_keys), obstacles=obstacles,
        regulated=isinstance(road, RegulatedRoad), paths=_all_paths(road.network, tuple(nodes)),
    )
