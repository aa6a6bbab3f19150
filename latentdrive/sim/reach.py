"""How far each AV must drive to complete its mission: a static check of a scenario spec.

For every AV spawn region, lane and destination, the route distance from the region's
farthest-back start to the point that completes the mission, and the time that takes at
the AVs' top target speed. A scenario whose missions cannot be completed in time at top
speed measures nothing with its failure rate, so the presets keep that time within ~70%
of the duration (tested), which leaves time for traffic, lane changes and acceleration.
:func:`distance_to_goal` measures the same route length from any point of the road.
"""

from __future__ import annotations

import itertools
from typing import NamedTuple

from latentdrive.config import ConfigError
from latentdrive.scenarios.spec import ScenarioSpec
from latentdrive.sim.fast.network import LENGTH, Network, get_network

__all__ = ["MissionRoute", "distance_to_goal", "mission_routes"]


class MissionRoute(NamedTuple):
    """One way an AV can start and what its mission then asks."""

    region: int  # index into spec.av_spawn
    lane: int  # lane id on the region's edge
    goal: str  # the node the route must reach
    distance: float  # metres from the farthest-back start to mission completion
    seconds: float  # that distance at the top target speed

    def share(self, duration: float) -> float:
        """``seconds`` as a fraction of the episode ``duration``."""
        return self.seconds / duration


def _edge_length(net: Network, edge: tuple[str, str], lane: int | None = None) -> float:
    e = net.edge(edge)
    first, count = int(net.table.edges[2, e]), int(net.table.edges[3, e])
    lanes = range(first, first + count) if lane is None else [first + min(lane, count - 1)]
    # Lanes of one edge differ in length on curves: take the longest, so the check errs
    # on the side of "too far".
    return max(float(net.table.geo[LENGTH, k]) for k in lanes)


def distance_to_goal(net: Network, edge: tuple[str, str], lane: int, s: float, goal: str,
                     goal_longitudinal: float) -> float | None:
    """Metres a vehicle ``s`` metres along lane id ``lane`` of ``edge`` drives until a mission to
    ``goal`` completes: the rest of its lane, the edges of the planned path between (their
    longest lane), and ``goal_longitudinal`` metres along the edge that ends at ``goal``.

    Negative once the vehicle is past the completion point on a goal edge; None when no
    path leads from the end of ``edge`` to ``goal``.
    """
    if edge[1] == goal:  # already on the goal edge
        return goal_longitudinal - s
    path = net.paths.get((edge[1], goal))
    if not path or len(path) < 2:
        return None
    edges = list(itertools.pairwise(path))
    return (_edge_length(net, edge, lane) - s
            + sum(_edge_length(net, e) for e in edges[:-1]) + goal_longitudinal)


def mission_routes(spec: ScenarioSpec) -> list[MissionRoute]:
    """Every (spawn region, lane, goal) route of ``spec``'s AVs, with its worst-case length.

    An AV with destinations must reach one of them; one without follows the road to a goal
    node (``spec.goal.nodes``). The mission completes ``spec.goal.longitudinal`` metres
    along the last edge of the route (the edge that ends at the goal node).

    Raises:
        ConfigError: a goal the spawn region cannot reach at all, or a goal distance longer
            than the goal edge.
    """
    net = get_network(spec.layout, spec.lanes_count)
    top = max(spec.av_target_speeds)
    out = []
    for r, region in enumerate(spec.av_spawn):
        start = region.longitudinal.mean - region.longitudinal.clip
        goals = region.destinations or spec.goal.nodes
        for lane, goal in itertools.product(region.lanes, goals):
            dist = distance_to_goal(net, region.edge, lane, start, goal, spec.goal.longitudinal)
            if dist is None:
                raise ConfigError(f"{spec.name}: goal {goal!r} is unreachable from spawn edge {region.edge}")
            last = region.edge
            if region.edge[1] != goal:
                path = net.paths[(region.edge[1], goal)]
                last = (path[-2], path[-1])
            if spec.goal.longitudinal > _edge_length(net, last):
                raise ConfigError(f"{spec.name}: goal.longitudinal {spec.goal.longitudinal:g} m is beyond the end of "
                                  f"goal edge {last} ({_edge_length(net, last):.0f} m)")
            out.append(MissionRoute(r, lane, goal, dist, dist / top))
    return out
