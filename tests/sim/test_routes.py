"""``Scene.route``: the edges an AV's route still takes, alike on both backends."""

import numpy as np
import pytest

from latentdrive.scenarios import SCENARIOS, get_spec
from latentdrive.sim.fast import FastBackend, FastBatch
from latentdrive.sim.highway import HighwayBackend
from latentdrive.sim.roads import layout_edges

# Every meta-action, as in test_fidelity.
SCRIPT = [3, 3, 1, 0, 1, 2, 1, 4, 1, 3, 0, 1, 2, 1, 4, 1, 1, 3, 1, 1]


def _edges(bits: np.uint64, keys: list[tuple[str, str]]) -> set[tuple[str, str]]:
    return {k for e, k in enumerate(keys) if int(bits) >> e & 1}


@pytest.mark.parametrize("name", SCENARIOS)
def test_both_backends_report_the_same_route_along_an_episode(name):
    # AVs alone on the road, where both backends drive the same trajectories.
    spec = get_spec(name, n_hv=0)
    changed = 0
    for seed in (0, 1):
        hw, fast = HighwayBackend(spec), FastBackend(spec)
        a, b = hw.reset(seed), fast.reset(seed)
        assert a.route is not None and a.route.any()
        np.testing.assert_array_equal(a.route, b.route)
        for action in SCRIPT[: spec.max_steps]:
            actions = np.full(spec.n_av, action)
            before = a.route
            a, b = hw.step(actions), fast.step(actions)
            assert before is not None and a.route is not None
            np.testing.assert_array_equal(a.route, b.route)
            changed += not np.array_equal(before, a.route)
            if a.crashed.any():
                break
    # Edges are dropped from the route as the AVs drive past them (highway has one edge).
    assert changed > 0 or name == "highway"


@pytest.mark.parametrize("name", ["roundabout", "intersection"])
def test_route_leads_from_the_steered_edge_to_the_goal_all_episode_long(name):
    # Regression: the closest lane inside a junction can be another connector than the
    # route's; the route is drawn from the lane the AV steers along.
    spec = get_spec(name)
    keys = list(layout_edges(spec.layout, spec.lanes_count))
    batch = FastBatch([spec] * 8)
    scenes = batch.reset(list(range(3, 11)))
    script = np.random.default_rng(0)
    checked = 0
    for _ in range(spec.max_steps):
        for i, scene in enumerate(scenes):
            goals = batch.goal_nodes(i)
            assert scene.route is not None
            for k in range(scene.n_agents):
                if scene.crashed[k] or scene.arrived is None or scene.arrived[k]:
                    continue
                edges = _edges(scene.route[k], keys)
                # The edges chain, one successor each, from a start edge to a goal node.
                starts = [e for e in edges if not any(f[1] == e[0] for f in edges)]
                assert len(starts) == 1, edges
                node, chain = starts[0][1], {starts[0]}
                while nxt := [e for e in edges - chain if e[0] == node]:
                    assert len(nxt) == 1
                    chain.add(nxt[0])
                    node = nxt[0][1]
                assert chain == edges
                assert node in goals[k], (node, goals[k])
                checked += 1
        scenes = batch.step(script.integers(0, 5, (8, spec.n_av)))
    assert checked > 100


def test_an_av_without_a_planned_route_has_only_its_current_edge():
    # exit's AVs have a goal (the exit) but no planned route: taking the exit lane is the
    # mission itself, so only the edge they are on is theirs.
    spec = get_spec("exit")
    assert all(not region.destinations for region in spec.av_spawn)
    keys = list(layout_edges(spec.layout, spec.lanes_count))
    batch = FastBatch([spec])
    scene = batch.reset([0])[0]
    lanes = batch.lane_keys(0)
    assert scene.route is not None
    for k, agent in enumerate(scene.agents):
        assert _edges(scene.route[k], keys) == {lanes[int(agent)][:2]}
