import numpy as np
import pytest

from latentdrive.reward import agent_rewards
from latentdrive.scenarios import RewardConfig

F = np.array([False, False])


def test_speed_term_is_normalized_and_clipped():
    r = agent_rewards(np.array([20.0, 35.0]), F, F, F, F, (20.0, 30.0), RewardConfig(speed=0.2))
    np.testing.assert_allclose(r, [0.0, 0.2])
    r = agent_rewards(np.array([25.0, 10.0]), F, F, F, F, (20.0, 30.0), RewardConfig(speed=0.2))
    np.testing.assert_allclose(r, [0.1, 0.0])


def test_collision_and_mission_pay_once():
    cfg = RewardConfig(collision=-1.0, speed=0.0, mission=1.0)
    crashed = np.array([True, False])
    arrived = np.array([False, True])
    first = agent_rewards(np.zeros(2), crashed, arrived, F, F, (0.0, 1.0), cfg)
    again = agent_rewards(np.zeros(2), crashed, arrived, crashed, arrived, (0.0, 1.0), cfg)
    np.testing.assert_allclose(first, [-1.0, 1.0])
    np.testing.assert_allclose(again, [0.0, 0.0])


def test_crashed_car_earns_no_speed_reward():
    r = agent_rewards(np.array([30.0]), np.array([True]), np.array([False]), np.array([True]),
                      np.array([False]), (20.0, 30.0), RewardConfig())
    assert r[0] == pytest.approx(0.0)


def _scene(crashed, arrived):
    from latentdrive.scene import RoadRaster, Scene

    n = len(crashed) + 1  # one HV besides the agents
    raster = RoadRaster(mask=np.ones((2, 2), np.uint8), origin=np.zeros(2), resolution=1.0)
    return Scene(position=np.arange(2 * n, dtype=float).reshape(n, 2), heading=np.zeros(n), speed=np.zeros(n),
                 frenet_speed=np.zeros(n), length=np.full(n, 5.0), width=np.full(n, 2.0),
                 kind=np.array([1] * (n - 1) + [0], np.int8), mask=np.ones(n, bool),
                 crashed=np.array([*crashed, True]), arrived=np.array([*arrived, False]),
                 agents=np.arange(n - 1), road=raster)


def test_episode_end_rule():
    from latentdrive.reward import episode_end
    from latentdrive.scenarios import get_spec

    spec = get_spec("merge")  # 15 decisions
    # A crashed HV does not end the episode; a crashed AV does; all AVs arrived does.
    assert episode_end(_scene([False, False], [True, False]), 3, spec) == (False, False)
    assert episode_end(_scene([True, False], [False, False]), 3, spec) == (True, False)
    assert episode_end(_scene([False, False], [True, True]), 3, spec) == (True, False)
    assert episode_end(_scene([False, False], [False, False]), spec.max_steps, spec) == (False, True)
    assert episode_end(_scene([True, False], [False, False]), spec.max_steps, spec) == (True, False)


def test_a_crash_on_the_arrival_step_does_not_pay_the_mission():
    # Regression: collision -1 plus mission 5 paid +4 for a failed episode.
    cfg = RewardConfig(collision=-1.0, speed=0.2, mission=5.0)
    both = np.array([True])
    r = agent_rewards(np.array([30.0]), both, both, ~both, ~both, (20.0, 30.0), cfg)
    assert r[0] == pytest.approx(-1.0)
    # Arriving without a crash still pays the mission (and its speed term).
    r = agent_rewards(np.array([30.0]), ~both, both, ~both, ~both, (20.0, 30.0), cfg)
    assert r[0] == pytest.approx(5.2)
