"""``scripts/state_dqn.py``: its settings and its ε-greedy policy over exact states."""

import runpy
from pathlib import Path

import numpy as np
import pytest
import torch

from latentdrive.config import ConfigError
from latentdrive.evaluate.run import evaluate_policy

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "state_dqn.py"
MOD = runpy.run_path(str(SCRIPT), run_name="state_dqn")


def test_settings_reach_the_learner_and_the_reward_and_map_only_ones_are_refused():
    dqn, reward = MOD["configs"](["dqn.n_step=3", "reward.speed=0.05", "dqn.updates_per_transition=1"])
    assert (dqn.n_step, dqn.updates_per_transition, reward.speed) == (3, 1.0, 0.05)
    with pytest.raises(ConfigError, match="augment_shift"):
        MOD["configs"](["dqn.augment_shift=2"])
    with pytest.raises(ConfigError, match=r"expected dqn\.KEY=VALUE"):
        MOD["configs"](["planner.depth=1"])
    with pytest.raises(ConfigError, match="prioritized"):
        MOD["configs"](["dqn.prioritized=true"])
    with pytest.raises(ConfigError, match=r"dqn\.n_step"):
        MOD["configs"](["dqn.n_step=0"])


class _Prefers:
    """A 'network' whose Q-values always rank action ``a`` first."""

    def __init__(self, a: int) -> None:
        self.a = a

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        q = torch.zeros(x.shape[0], 5)
        q[:, self.a] = 1.0
        return q


def _played(eps: float) -> np.ndarray:
    seen: list[np.ndarray] = []
    policy = MOD["StatePolicy"](_Prefers(3), 4, 80.0, True, np.random.default_rng(0), lambda: eps)

    def make():
        def act(inp):
            a = policy(inp)
            seen.append(a[inp.active])
            assert policy.latest is not None and policy.latest.shape[:2] == a.shape
            return a
        return act

    evaluate_policy(make, ["roundabout"], 4, envs=4, observation=MOD["TINY_MAP"])
    return np.concatenate(seen)


def test_the_greedy_policy_takes_the_best_action_and_exploration_all_of_them():
    assert set(_played(0.0)) == {3}
    assert set(_played(1.0)) == {0, 1, 2, 3, 4}


def _input_after(scenario: str, envs: int, seed: int, steps: int):
    """What a policy sees after ``steps`` Idle steps of ``envs`` environments of ``scenario``
    (off the start, so that time, speeds and positions are not those of a reset)."""
    from latentdrive.rollout import rollout
    from latentdrive.vec import make_vec

    seen = []

    def idle(inp):
        seen.append(inp)
        return np.zeros(inp.active.shape, dtype=np.int64)

    for k, _ in enumerate(rollout(make_vec(scenario, envs, observation=MOD["TINY_MAP"]), idle, seed=seed)):
        if k == steps:
            break
    return seen[-1]


def test_no_pose_zeroes_the_avs_world_heading_position_and_time_only():
    from latentdrive.observe.state import state_features
    from latentdrive.scenarios import get_spec

    inp, spec = _input_after("roundabout", 2, 3, 3), get_spec("roundabout")
    full = MOD["features"](inp, [spec, spec], 12, 80.0, True, True)
    bare = MOD["features"](inp, [spec, spec], 12, 80.0, True, False)
    assert np.array_equal(full[0, 0], state_features(inp.scenes[0], 0, spec.duration, 12, 80.0, True))
    pose = np.zeros(full.shape[-1], dtype=bool)
    pose[2:7] = True  # cos, sin of the heading, world x, y, share of the episode gone
    assert np.all(np.any(full[..., pose] != 0, axis=-1)) and np.all(bare[..., pose] == 0)
    assert np.array_equal(full[..., ~pose], bare[..., ~pose])
    # --no-time: the share of the episode gone (3 decisions of 1 s) alone.
    timeless = MOD["features"](inp, [spec, spec], 12, 80.0, True, True, show_time=False)
    assert full[0, 0, 6] == pytest.approx(3 / spec.duration) and np.all(timeless[..., 6] == 0)
    assert np.array_equal(np.delete(full, 6, axis=-1), np.delete(timeless, 6, axis=-1))


def test_a_view_box_drops_the_neighbours_outside_it_and_keeps_the_others():
    from latentdrive.observe.state import PER_NEIGHBOUR
    from latentdrive.scenarios import get_spec

    inp, spec = _input_after("intersection", 4, 5, 4), get_spec("intersection")
    k = 12
    full = MOD["features"](inp, [spec] * 4, k, 80.0, True, True)
    boxed = MOD["features"](inp, [spec] * 4, k, 80.0, True, True, (10.0, 20.0, 5.0))
    start = full.shape[-1] - k * PER_NEIGHBOUR
    rows = full[..., start:].reshape(-1, k, PER_NEIGHBOUR)
    kept = boxed[..., start:].reshape(-1, k, PER_NEIGHBOUR)
    ahead, right = rows[..., 0] * 50, rows[..., 1] * 50
    inside = (ahead >= -10) & (ahead <= 20) & (np.abs(right) <= 5) & (rows[..., -1] == 1)
    outside = (rows[..., -1] == 1) & ~inside
    assert inside.any() and outside.any()  # the case is tested both ways
    assert np.array_equal(kept[inside], rows[inside]) and np.all(kept[outside] == 0)
    assert np.array_equal(boxed[..., :start], full[..., :start])


def test_each_stored_transition_leads_one_decision_on_across_auto_resets():
    # A short run of 4 roundabout environments through many episode ends. The share of the
    # episode gone (feature 6) of every stored transition's next state must be one decision
    # (1 s) later than its state's, and the AV must not jump: a next state taken from the
    # episode that followed, or from another agent, would break both.
    import argparse

    from latentdrive.rl.dqn import DQNConfig
    from latentdrive.scenarios import get_spec
    from latentdrive.scenarios.spec import RewardConfig

    args = argparse.Namespace(seed=0, arch="attention", neighbours=4, hidden=16, envs=4, steps=300, radius=80.0,
                              no_route=False, no_pose=False, no_time=False, view_box=None, out=None,
                              eval_every=0, eval_episodes=1)
    cfg = DQNConfig(n_step=1, learning_starts=100, batch_size=8)
    _, replay = MOD["train"](args, ["roundabout"], cfg, RewardConfig())
    n = replay.added
    assert n >= 300 and np.all(replay.steps[:n] == 1)
    ended = replay.terminated[:n]
    assert 0 < ended.sum() < n  # crashes and arrivals happened: the run crossed episode ends
    before, after = replay.store.get(replay.obs_id[:n]), replay.store.get(replay.next_id[:n])
    np.testing.assert_allclose(after[:, 6] - before[:, 6], 1.0 / get_spec("roundabout").duration, atol=1e-6)
    moved = np.hypot(*(100.0 * (after[:, 4:6] - before[:, 4:6])).T)
    assert moved.max() < 40.0
