from __future__ import annotations

import numpy as np
import pytest

from latentdrive.actions import ACTION_NAMES, N_ACTIONS
from latentdrive.data.policies import episode_policy, random_policy, rule_policy
from latentdrive.scene import Kind, RoadRaster, Scene

LEFT, IDLE, RIGHT, FASTER, SLOWER = range(5)


def test_action_indices_match_names() -> None:
    assert ACTION_NAMES == ("Left", "Idle", "Right", "Accelerate", "Decelerate")


def make_scene(positions: list[tuple[float, float]], headings: list[float], speeds: list[float],
               agents: list[int], mask: list[bool] | None = None) -> Scene:
    n = len(positions)
    kind = np.full(n, Kind.HV, dtype=np.int8)
    kind[agents] = Kind.AV
    return Scene(
        position=np.asarray(positions, dtype=np.float64),
        heading=np.asarray(headings, dtype=np.float64),
        speed=np.asarray(speeds, dtype=np.float64),
        frenet_speed=np.asarray(speeds, dtype=np.float64),
        length=np.full(n, 5.0), width=np.full(n, 2.0), kind=kind,
        mask=np.ones(n, dtype=bool) if mask is None else np.asarray(mask),
        crashed=np.zeros(n, dtype=bool), agents=np.asarray(agents, dtype=np.int64),
        road=RoadRaster(mask=np.ones((1, 1), np.uint8), origin=np.zeros(2), resolution=1.0),
    )


def no_lane_change(scene: Scene) -> np.ndarray:
    return rule_policy(scene, np.random.default_rng(0), lane_change_prob=0.0)


def test_random_policy_shape_range_and_determinism() -> None:
    scene = make_scene([(0, 0), (10, 0), (20, 0)], [0, 0, 0], [20, 20, 20], agents=[0, 2])
    a = random_policy(scene, np.random.default_rng(3))
    assert a.shape == (2,) and a.dtype == np.int64
    draws = np.concatenate([random_policy(scene, np.random.default_rng(s)) for s in range(200)])
    assert set(draws.tolist()) == set(range(N_ACTIONS))
    assert np.array_equal(a, random_policy(scene, np.random.default_rng(3)))


def test_rule_brakes_for_a_close_leader_only() -> None:
    # AV at cruise speed 25 m/s: safe distance 8 + 1.5·25 = 45.5 m bumper to bumper.
    ahead = make_scene([(0, 0), (20, 0)], [0, 0], [25, 25], agents=[0])
    assert no_lane_change(ahead).tolist() == [SLOWER]
    far = make_scene([(0, 0), (80, 0)], [0, 0], [25, 25], agents=[0])
    assert no_lane_change(far).tolist() == [IDLE]
    behind = make_scene([(0, 0), (-10, 0)], [0, 0], [25, 25], agents=[0])
    assert no_lane_change(behind).tolist() == [IDLE]
    next_lane = make_scene([(0, 0), (20, 4.0)], [0, 0], [25, 25], agents=[0])
    assert no_lane_change(next_lane).tolist() == [IDLE]
    padding = make_scene([(0, 0), (20, 0)], [0, 0], [25, 25], agents=[0], mask=[True, False])
    assert no_lane_change(padding).tolist() == [IDLE]


def test_rule_uses_the_heading_of_each_agent() -> None:
    # Agent 0 heads along -x with a car 15 m in front of it; agent 1 heads along +y
    # (downwards in world y) with nobody ahead and is slow, so it accelerates.
    scene = make_scene([(0, 0), (-15, 0), (100, 0)], [np.pi, np.pi, np.pi / 2], [25, 20, 15], agents=[0, 2])
    assert no_lane_change(scene).tolist() == [SLOWER, FASTER]


def test_rule_tracks_the_cruise_speed() -> None:
    scene = make_scene([(0, 0), (0, 50), (0, 100)], [0, 0, 0], [15, 25, 30], agents=[0, 1, 2])
    assert no_lane_change(scene).tolist() == [FASTER, IDLE, SLOWER]
    assert rule_policy(scene, np.random.default_rng(0), cruise_speed=30, lane_change_prob=0).tolist() == [FASTER, FASTER, IDLE]


def test_rule_changes_lane_at_random_but_never_instead_of_braking() -> None:
    scene = make_scene([(0, 0), (20, 0), (0, 50)], [0, 0, 0], [25, 25, 25], agents=[0, 2])
    acts = np.stack([rule_policy(scene, np.random.default_rng(s), lane_change_prob=1.0) for s in range(50)])
    assert (acts[:, 0] == SLOWER).all()
    assert set(acts[:, 1].tolist()) == {LEFT, RIGHT}


@pytest.mark.parametrize(("behaviour", "fraction", "expected"), [
    ("rule", 0.0, {"rule"}), ("random", 1.0, {"random"}),
    ("mixed", 0.0, {"random"}), ("mixed", 1.0, {"rule"}), ("mixed", 0.5, {"random", "rule"}),
])
def test_episode_policy_choice(behaviour: str, fraction: float, expected: set[str]) -> None:
    names = {episode_policy(behaviour, np.random.default_rng(s), rule_fraction=fraction)[0]  # type: ignore[arg-type]
             for s in range(40)}
    assert names == expected


def test_episode_policy_rejects_unknown_behaviour() -> None:
    with pytest.raises(ValueError, match="unknown behaviour"):
        episode_policy("greedy", np.random.default_rng(0))  # type: ignore[arg-type]
