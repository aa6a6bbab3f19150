"""Every preset's mission can be completed in time at the AVs' top speed, with room to spare."""

from __future__ import annotations

from pathlib import Path

import pytest

from latentdrive.config import ConfigError
from latentdrive.scenarios import SCENARIOS, get_spec
from latentdrive.sim.reach import mission_routes


@pytest.mark.parametrize("name", SCENARIOS)
def test_every_spawn_reaches_its_goal_within_70_percent_of_the_duration(name: str) -> None:
    spec = get_spec(name)
    routes = mission_routes(spec)
    # Every spawn region, lane and goal is covered.
    assert {r.region for r in routes} == set(range(len(spec.av_spawn)))
    for r in routes:
        assert 0 < r.distance
        assert r.share(spec.duration) <= 0.70, r


def test_route_lengths_are_the_merge_geometry() -> None:
    # highway-env's merge: a-b 0..230 m, b-c 230..310 m, c-d from 310 m; the ramp j-k is
    # 150 m long, then k-b converges over 80 m. Goal: 20 m into c-d.
    spec = get_spec("merge")
    by_region = {r.region: r for r in mission_routes(spec)}
    assert by_region[0].distance == pytest.approx(230 - (50 - 20) + 80 + 20)
    assert by_region[1].distance == pytest.approx(150 - (85 - 15) + 80 + 80 + 20, abs=0.5)
    assert by_region[0].seconds == pytest.approx(by_region[0].distance / 30.0)


def test_a_goal_on_the_spawn_edge_counts_from_the_start() -> None:
    spec = get_spec("highway")
    (route, *_) = mission_routes(spec)
    assert route.distance == pytest.approx(450 - (100 - 30))


def test_an_unreachable_or_impossible_goal_is_named() -> None:
    with pytest.raises(ConfigError, match="unreachable"):
        mission_routes(get_spec("merge", goal={"nodes": ["a"]}))
    with pytest.raises(ConfigError, match="beyond the end"):
        mission_routes(get_spec("merge", goal={"nodes": ["d"], "longitudinal": 5000.0}))


def test_the_old_highway_goal_was_too_far() -> None:
    # Regression: the 550 m highway goal needed 80% of the duration at top speed.
    spec = get_spec(str(Path(__file__).parents[2] / "docs" / "calibration" / "highway-550m.yaml"))
    assert max(r.share(spec.duration) for r in mission_routes(spec)) == pytest.approx(0.8)
