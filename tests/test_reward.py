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
