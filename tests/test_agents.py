"""Per-agent episode semantics, on hand-made Scenes: who terminates, who is cut off, who earns."""

import dataclasses
from typing import Any

import numpy as np
import pytest

from latentdrive.env import Episode, EpisodeEnded, make_env, make_env_config
from latentdrive.scene import Kind, RoadRaster, Scene

SMALL: dict[str, Any] = {"observation": {"height": 16, "width": 32, "frames": 2}}
ROAD = RoadRaster(mask=np.ones((40, 400), np.uint8), origin=np.zeros(2), resolution=1.0)


def scene(speed=(28.0, 28.0), crashed=(False, False), arrived=(False, False), t=0.0) -> Scene:
    """Two AVs driving along +x, 30 m apart."""
    n = 2
    return Scene(
        position=np.array([[10.0, 4.0], [40.0, 4.0]]), heading=np.zeros(n), speed=np.asarray(speed),
        frenet_speed=np.asarray(speed), length=np.full(n, 5.0), width=np.full(n, 2.0),
        kind=np.full(n, Kind.AV, np.int8), mask=np.ones(n, bool), crashed=np.asarray(crashed),
        agents=np.arange(n), road=ROAD, time=t, arrived=np.asarray(arrived),
    )


def episode(**overrides: Any) -> Episode:
    ep = Episode(make_env_config("merge", **SMALL, **overrides))
    ep.start(scene(), episode_seed=1)
    return ep


def test_an_arrived_av_terminates_alone_and_then_earns_nothing():
    ep = episode()
    mission = ep.config.reward.mission
    _, _, term, trunc, info = ep.advance(scene(arrived=(True, False)))
    a = info["agents"]
    assert not term and not trunc
    assert a.acting.tolist() == [True, True]
    assert a.terminated.tolist() == [True, False] and a.truncated.tolist() == [False, False]
    assert a.active.tolist() == [False, True] and a.active.dtype == bool
    assert a.reward[0] >= mission and a.reward[0] == pytest.approx(mission + a.reward[1])
    # It drives on in the simulation, at speed, but it is no longer an agent of the episode.
    np.testing.assert_array_equal(ep.check_actions(np.array([3, 3])), [1, 3])
    _, reward, term, _, info = ep.advance(scene(arrived=(True, False)))
    a = info["agents"]
    assert not term and a.acting.tolist() == [False, True] and a.reward[0] == 0.0 and a.reward[1] > 0
    assert reward == pytest.approx(a.reward.mean())
    _, _, term, trunc, info = ep.advance(scene(arrived=(True, True)))
    a = info["agents"]
    assert term and not trunc
    assert a.terminated.tolist() == [False, True] and not a.active.any() and not a.truncated.any()
    with pytest.raises(EpisodeEnded, match="reset"):
        ep.check_actions(np.array([1, 1]))


def test_an_av_done_on_an_earlier_step_gets_no_new_frames():
    ep = episode()
    first, *_ = ep.advance(scene(arrived=(True, False)))
    assert ep.observing.tolist() == [True, True]  # its last transition leads to this frame
    before = scene(arrived=(True, False))
    moved = dataclasses.replace(before, position=before.position + np.array([[6.0, 0.0], [3.0, 0.0]]))
    later, *_ = ep.advance(moved)
    assert ep.observing.tolist() == [False, True]
    np.testing.assert_array_equal(later[0], first[0])
    assert not np.array_equal(later[1], first[1])


def test_a_crash_terminates_the_crasher_and_cuts_off_the_others():
    ep = episode()
    _, _, term, trunc, info = ep.advance(scene(crashed=(False, True)))
    a = info["agents"]
    assert term and not trunc
    assert a.terminated.tolist() == [False, True]
    assert a.truncated.tolist() == [True, False]  # bootstraps: nothing ended for agent 0 itself
    assert not a.active.any()
    assert a.reward[1] == pytest.approx(ep.config.reward.collision)  # speed term off when crashed


def test_time_out_cuts_off_every_driving_av():
    ep = episode(duration=2)  # two policy steps at 1 Hz
    ep.advance(scene())
    _, _, term, trunc, info = ep.advance(scene())
    a = info["agents"]
    assert trunc and not term
    assert a.truncated.tolist() == [True, True] and not a.terminated.any() and not a.active.any()


def test_failure_reward_pays_and_ends_the_partner_of_a_crashed_av():
    plain, paid = episode(), episode(reward={"failure": -3.0})
    _, _, _, _, info = plain.advance(scene(crashed=(False, True)))
    _, _, term, trunc, info_paid = paid.advance(scene(crashed=(False, True)))
    a, b = info["agents"], info_paid["agents"]
    assert term and not trunc
    # Agent 0 was cut off by agent 1's crash: now paid the failure, and not bootstrapped.
    assert b.reward[0] == pytest.approx(a.reward[0] - 3.0)
    assert b.terminated.tolist() == [True, True] and not b.truncated.any() and not b.active.any()
    # The crasher's own reward is the collision as before, with no failure on top.
    assert b.reward[1] == pytest.approx(a.reward[1]) == pytest.approx(paid.config.reward.collision)


def test_failure_reward_at_the_time_limit_reaches_only_the_avs_short_of_their_goal():
    ep = episode(duration=2, reward={"failure": -3.0})
    ep.advance(scene(arrived=(True, False)))  # agent 0 arrives on the first step
    _, _, term, trunc, info = ep.advance(scene(arrived=(True, False)))
    a = info["agents"]
    assert trunc and not term
    assert a.acting.tolist() == [False, True]
    assert a.terminated.tolist() == [False, True] and not a.truncated.any()
    speed_term = info["agents"].reward[1] + 3.0
    assert 0.0 < speed_term <= ep.config.reward.speed
    assert a.reward[0] == 0.0


def test_failure_reward_reaches_the_partner_of_an_av_that_crashes_on_arrival():
    # Agent 1 arrives and crashes on the same step: a failure, so agent 0 is paid it.
    ep = episode(reward={"failure": -3.0})
    _, _, term, _, info = ep.advance(scene(crashed=(False, True), arrived=(False, True)))
    a = info["agents"]
    assert term and a.terminated.tolist() == [True, True]
    assert a.reward[0] < 0 and a.reward[1] == pytest.approx(ep.config.reward.collision)


def test_step_after_the_end_raises_and_reset_starts_over():
    env = make_env("merge", backend="fast", **SMALL)
    _obs, info = env.reset(seed=3)
    assert info["agents"].active.all() and not info["agents"].acting.any()
    done = False
    while not done:
        _, _, term, trunc, info = env.step(np.full(2, 3))
        done = term or trunc
    with pytest.raises(EpisodeEnded):
        env.step(np.full(2, 1))
    env.reset()
    env.step(np.full(2, 1))
