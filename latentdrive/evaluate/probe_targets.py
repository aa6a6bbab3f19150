"""What the linear probes read out: driving-relevant quantities of each AV at one instant.

Targets, one value per AV (metres, m/s, booleans):

- ``gap_ahead``: longitudinal distance, centre to centre, from the AV to the nearest
  vehicle ahead in its lane, capped at the VelocityMap's forward range
  (:func:`forward_range`: 64 m at the default grid), which is also the value when no
  vehicle is that close. Every vehicle is 5 m long, so the bumper-to-bumper gap is this
  minus 5 m, the same target for a linear read-out.
- ``relative_speed_ahead``: that vehicle's Frenet longitudinal speed (the speed the
  VelocityMap encodes, paper eq. 13) minus the AV's; 0 when none is within range.
- ``left_free``, ``right_free``: the adjacent lane on that side exists on the AV's road
  edge, may be changed into (highway-env's forbidden lanes, such as merge's on-ramp and
  the exit ramp, may not), and no vehicle's centre lies in it within :data:`FREE_WINDOW`
  metres ahead of or behind the AV.
- ``goal_distance``: metres the AV still drives until its mission completes, along the
  planned route to the nearest goal it can still reach
  (:func:`latentdrive.sim.reach.distance_to_goal`); NaN when it can reach none (it took
  another exit), and such samples are left out of that target's probe.

"The AV's lane" is its current lane and, past the lane's end, the lanes its route to the
goal continues on (the same lane index when the next road has as many lanes, else the lane
that starts nearest the end of this one, as highway-env's route follower picks). A vehicle
is in it when its centre lies within half a lane width of the centreline, measured in the
Frenet frame of one of those lanes. Where no goal is reachable the current lane is
extended along its own geometry. At the intersection, a vehicle crossing in front of the
AV counts as ahead only while its centre is inside the AV's lane, and every road edge has
one lane, so both free flags are False throughout: a probe reads nothing from them there.

Lane geometry comes from :mod:`latentdrive.sim.fast.network` (highway-env's lanes as
arrays) and :mod:`latentdrive.sim.fast.lanes` (its Frenet formulas); which lane each AV
is on, and its goals, from the fast simulator. The read-out functions
(:func:`gap_ahead`, :func:`relative_speed_ahead`, :func:`lane_free`,
:func:`goal_distance`) are pure and vectorized over AVs.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from latentdrive.config import ObservationConfig
from latentdrive.scene import Scene
from latentdrive.sim.fast.lanes import local_coordinates, position
from latentdrive.sim.fast.network import (
    EDGE,
    EDGE_FIRST_LANE,
    EDGE_N_LANES,
    FORBIDDEN,
    INDEX_IN_EDGE,
    LENGTH,
    WIDTH,
    Network,
)
from latentdrive.sim.reach import distance_to_goal

__all__ = [
    "BOOLEAN_TARGETS",
    "FREE_WINDOW",
    "TARGETS",
    "forward_range",
    "gap_ahead",
    "goal_distance",
    "lane_free",
    "relative_speed_ahead",
    "scene_targets",
]

FArr = NDArray[np.float64]
BArr = NDArray[np.bool_]

TARGETS: tuple[str, ...] = ("gap_ahead", "relative_speed_ahead", "left_free", "right_free", "goal_distance")
BOOLEAN_TARGETS: tuple[str, ...] = ("left_free", "right_free")
#: Half-length of the stretch of an adjacent lane that must be empty for it to count as
#: free, metres centre to centre: a car length (5 m) plus 10 m (half a second at 20 m/s)
#: either side of the AV.
FREE_WINDOW = 15.0


def forward_range(cfg: ObservationConfig) -> float:
    """How far ahead of its centre an AV's VelocityMap reaches, metres."""
    return cfg.width * cfg.resolution - cfg.behind


def _in_lane(along: FArr, lateral: FArr, half_width: FArr) -> BArr:
    # NaN offsets (vehicles off the lane's extent, the AV itself, padding) compare False.
    return np.abs(lateral) <= np.asarray(half_width, dtype=np.float64)[..., None]


def _leader(along: FArr, lateral: FArr, half_width: FArr, reach: float) -> tuple[FArr, NDArray[np.intp]]:
    """``(distance, index)`` of each AV's nearest vehicle ahead in the lane; ``(reach, -1)``
    when there is none within ``reach``."""
    ahead = _in_lane(along, lateral, half_width) & (along >= 0.0) & (along <= reach)
    dist = np.where(ahead, along, np.inf)
    # A column of "nobody" keeps argmin defined for AVs alone on the road.
    dist = np.concatenate([dist, np.full((*dist.shape[:-1], 1), np.inf)], axis=-1)
    idx = dist.argmin(axis=-1)
    best = np.take_along_axis(dist, idx[..., None], axis=-1)[..., 0]
    found = np.isfinite(best)
    return np.where(found, best, reach), np.where(found, idx, -1)


def gap_ahead(along: FArr, lateral: FArr, half_width: FArr, reach: float) -> FArr:
    """Distance to the nearest vehicle ahead in the lane, capped at ``reach``.

    Args:
        along: ``(n, N)`` metres along the lane from each AV's centre to each vehicle's
            centre (NaN for vehicles not on it, and for the AV itself).
        lateral: ``(n, N)`` metres from the lane's centreline to each vehicle's centre.
        half_width: ``(n,)`` half the lane's width, metres.
        reach: the cap, metres (:func:`forward_range`).

    Returns:
        ``(n,)`` metres in ``[0, reach]``; ``reach`` when no vehicle is that close.
    """
    return _leader(along, lateral, half_width, reach)[0]


def relative_speed_ahead(along: FArr, lateral: FArr, half_width: FArr, reach: float,
                         speed: FArr, ego_speed: FArr) -> FArr:
    """Speed of the vehicle :func:`gap_ahead` finds minus the AV's, m/s; 0 when none.

    Args:
        along, lateral, half_width, reach: as for :func:`gap_ahead`.
        speed: ``(N,)`` or ``(n, N)`` every vehicle's speed, m/s.
        ego_speed: ``(n,)`` each AV's speed, m/s.

    Returns:
        ``(n,)`` m/s, negative when the leader is slower.
    """
    _, idx = _leader(along, lateral, half_width, reach)
    v = np.broadcast_to(np.asarray(speed, dtype=np.float64), np.shape(along))
    lead = np.take_along_axis(v, np.maximum(idx, 0)[..., None], axis=-1)[..., 0] if v.shape[-1] else np.zeros(idx.shape)
    return np.where(idx >= 0, lead - np.asarray(ego_speed, dtype=np.float64), 0.0)


def lane_free(along: FArr, lateral: FArr, half_width: FArr, exists: BArr, window: float = FREE_WINDOW) -> BArr:
    """Whether an adjacent lane exists and holds no vehicle within ``window`` of the AV.

    Args:
        along: ``(n, N)`` metres along the adjacent lane from each AV's projection on it to
            each vehicle's centre (NaN for the AV itself and for lanes that do not exist).
        lateral: ``(n, N)`` metres from that lane's centreline to each vehicle's centre.
        half_width: ``(n,)`` half that lane's width, metres.
        exists: ``(n,)`` the lane exists and may be changed into.
        window: metres ahead and behind, centre to centre.

    Returns:
        ``(n,)`` bool.
    """
    blocked = (_in_lane(along, lateral, half_width) & (np.abs(along) <= window)).any(axis=-1)
    return np.asarray(exists, dtype=bool) & ~blocked


def goal_distance(route_lengths: FArr) -> FArr:
    """Distance left to the nearest reachable goal, metres, floored at 0.

    Args:
        route_lengths: ``(n, G)`` metres from each AV to each of its goals' completion
            points (negative once past one; NaN where a goal is unreachable or absent).

    Returns:
        ``(n,)`` metres; NaN for AVs with no reachable goal.
    """
    d = np.asarray(route_lengths, dtype=np.float64)
    reachable = np.isfinite(d)
    nearest = np.where(reachable, d, np.inf).min(axis=-1, initial=np.inf)
    return np.where(reachable.any(axis=-1), np.maximum(nearest, 0.0), np.nan)


# ---------------------------------------------------------------------------------------
# From the simulator's state to the arrays the read-outs take.


def _frenet(net: Network, lane: int, xy: FArr) -> tuple[FArr, FArr]:
    """``(s, r)`` of points ``xy`` ``(N, 2)`` in ``lane``'s Frenet frame, metres."""
    sr = np.array([local_coordinates(net.table, lane, float(x), float(y)) for x, y in xy], dtype=np.float64)
    return sr.reshape(-1, 2)[:, 0], sr.reshape(-1, 2)[:, 1]


def _edge_lanes(net: Network, edge: int) -> range:
    first = int(net.table.edges[EDGE_FIRST_LANE, edge])
    return range(first, first + int(net.table.edges[EDGE_N_LANES, edge]))


def _continuation(net: Network, lane: int, next_edge: int) -> int:
    """The lane of ``next_edge`` a vehicle on ``lane`` drives on after its end."""
    lanes = _edge_lanes(net, next_edge)
    index = int(net.table.ints[INDEX_IN_EDGE, lane])
    if len(lanes) == len(_edge_lanes(net, int(net.table.ints[EDGE, lane]))):
        return lanes[index]
    x, y = position(net.table, lane, float(net.table.geo[LENGTH, lane]), 0.0)

    def distance(k: int) -> float:
        s, r = local_coordinates(net.table, k, x, y)
        return abs(r) + max(s - float(net.table.geo[LENGTH, k]), 0.0) + max(-s, 0.0)

    return min(lanes, key=distance)


def _route_lanes(net: Network, lane: int, path: Sequence[str], reach: float, s: float) -> list[int]:
    """The AV's lane followed by its continuations along node ``path``, until ``reach``
    metres past the AV's position ``s`` are covered."""
    lanes = [lane]
    covered = float(net.table.geo[LENGTH, lane]) - s
    for a, b in itertools.pairwise(path):
        if covered >= reach:
            break
        lanes.append(_continuation(net, lanes[-1], net.edge((a, b))))
        covered += float(net.table.geo[LENGTH, lanes[-1]])
    return lanes


def _route_frame(net: Network, lanes: list[int], s_ego: float, xy: FArr) -> tuple[FArr, FArr]:
    """Every point's ``(along, lateral)`` on the chain of ``lanes``: along measured from
    ``s_ego`` on the first lane, NaN for points beside no lane of the chain. A point
    within the extent of several lanes takes the one whose centreline is nearest."""
    n = xy.shape[0]
    along, lateral = np.full(n, np.nan), np.full(n, np.nan)
    offset = -s_ego
    for k, lane in enumerate(lanes):
        s, r = _frenet(net, lane, xy)
        length = float(net.table.geo[LENGTH, lane])
        # The first lane reaches back behind the AV; the last one on past its end.
        inside = np.ones(n, dtype=bool) if k == 0 else s >= 0.0
        if k < len(lanes) - 1:
            inside &= s < length
        better = inside & ~(np.abs(r) >= np.abs(lateral))
        along = np.where(better, offset + s, along)
        lateral = np.where(better, r, lateral)
        offset += length
    return along, lateral


def _side_lanes(net: Network, lane: int, xy_ego: FArr) -> tuple[int, int]:
    """The adjacent lanes ``(left, right)`` of ``lane`` on its edge that may be changed
    into (-1 for none). Sides are found geometrically: the AV lies right of a lane on its
    left (Frenet ``r > 0``, highway-env's lateral axis points right)."""
    out = [-1, -1]
    lanes = _edge_lanes(net, int(net.table.ints[EDGE, lane]))
    index = int(net.table.ints[INDEX_IN_EDGE, lane])
    for j in (index - 1, index + 1):
        if 0 <= j < len(lanes) and not net.table.ints[FORBIDDEN, lanes[j]]:
            _, r = local_coordinates(net.table, lanes[j], float(xy_ego[0]), float(xy_ego[1]))
            out[0 if r > 0 else 1] = lanes[j]
    return out[0], out[1]


def scene_targets(scene: Scene, net: Network, lanes: Sequence[int], goals: Sequence[Sequence[str]],
                  goal_longitudinal: float, reach: float,
                  agents: Sequence[int] | NDArray[np.integer] | None = None) -> dict[str, NDArray[np.generic]]:
    """Every target of :data:`TARGETS` for some AVs of one Scene.

    Args:
        scene: the instant.
        net: the layout's lane network.
        lanes: ``(n_av,)`` lane id each AV is on (the simulator's closest lane).
        goals: per AV, the nodes its mission may complete at.
        goal_longitudinal: metres along a goal edge that complete the mission.
        reach: the forward range, metres (:func:`forward_range`).
        agents: which AVs (agent indices), all by default.

    Returns:
        ``{target: (len(agents),) array}``, float64 (booleans for :data:`BOOLEAN_TARGETS`).
    """
    who = list(range(scene.n_agents)) if agents is None else [int(a) for a in agents]
    n, n_veh = len(who), scene.n_vehicles
    along, lateral, half = np.full((n, n_veh), np.nan), np.full((n, n_veh), np.nan), np.zeros(n)
    side_along = np.full((2, n, n_veh), np.nan)
    side_lateral = np.full((2, n, n_veh), np.nan)
    side_half, side_exists = np.zeros((2, n)), np.zeros((2, n), dtype=bool)
    routes = np.full((n, max((len(goals[a]) for a in who), default=0)), np.nan)
    xy = np.where(scene.mask[:, None], scene.position, np.nan)
    for k, a in enumerate(who):
        v, lane = int(scene.agents[a]), int(lanes[a])
        s_ego, _ = local_coordinates(net.table, lane, float(xy[v, 0]), float(xy[v, 1]))
        edge = net.edge_keys[int(net.table.ints[EDGE, lane])]
        index = int(net.table.ints[INDEX_IN_EDGE, lane])
        best: tuple[float, str] | None = None
        for g, goal in enumerate(goals[a]):
            d = distance_to_goal(net, edge, index, s_ego, goal, goal_longitudinal)
            if d is not None:
                routes[k, g] = d
                best = min(best, (d, goal)) if best else (d, goal)
        path: Sequence[str] = (edge[1], *net.paths.get((edge[1], best[1]), ())[1:]) if best else ()
        along[k], lateral[k] = _route_frame(net, _route_lanes(net, lane, path, reach, s_ego), s_ego, xy)
        half[k] = float(net.table.geo[WIDTH, lane]) / 2
        for side, adj in enumerate(_side_lanes(net, lane, xy[v])):
            if adj < 0:
                continue
            s, r = _frenet(net, adj, xy)
            side_along[side, k], side_lateral[side, k] = s - s[v], r
            side_half[side, k], side_exists[side, k] = float(net.table.geo[WIDTH, adj]) / 2, True
        # The AV is no obstacle to itself.
        along[k, v] = lateral[k, v] = side_along[:, k, v] = side_lateral[:, k, v] = np.nan
    ego = scene.agents[who]
    return {
        "gap_ahead": gap_ahead(along, lateral, half, reach),
        "relative_speed_ahead": relative_speed_ahead(along, lateral, half, reach, scene.frenet_speed,
                                                     scene.frenet_speed[ego]),
        "left_free": lane_free(side_along[0], side_lateral[0], side_half[0], side_exists[0]),
        "right_free": lane_free(side_along[1], side_lateral[1], side_half[1], side_exists[1]),
        "goal_distance": goal_distance(routes),
    }
