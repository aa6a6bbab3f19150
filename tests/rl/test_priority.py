"""Prioritized replay: the sum tree, proportional sampling, importance weights, exact restore."""

import numpy as np
import pytest

from latentdrive.rl.priority import SumTree
from latentdrive.rl.replay import LatentStore, Replay


def test_the_tree_samples_in_proportion_to_priorities():
    tree = SumTree(5)
    tree.set(np.arange(4), np.array([1.0, 0.0, 3.0, 4.0]))
    assert tree.total == 8.0 and tree.size == 8
    idx = tree.sample(np.random.default_rng(0), 8000, filled=4)
    freq = np.bincount(idx, minlength=4) / len(idx)
    np.testing.assert_allclose(freq, [1 / 8, 0.0, 3 / 8, 4 / 8], atol=0.01)
    # Stratified: with k equal to the total mass, one draw falls in each unit of it.
    assert sorted(tree.sample(np.random.default_rng(1), 8, filled=4).tolist()) == [0, 2, 2, 2, 3, 3, 3, 3]


def test_a_tree_rebuilt_from_its_leaves_is_bitwise_the_same():
    rng = np.random.default_rng(0)
    tree = SumTree(100)
    for _ in range(200):
        slots = rng.integers(0, 100, size=7)
        tree.set(slots, rng.random(7) ** 3 * 10)
    again = SumTree(100)
    again.rebuild(tree.leaves(100).copy())
    assert np.array_equal(tree.tree, again.tree)


def _replay(prioritized, n=4):
    replay = Replay(8, LatentStore(32, (2,)), prioritized=prioritized, alpha=1.0, priority_eps=1e-9)
    ids = replay.store.add(np.zeros((2 * n, 2), np.float32), np.full(2 * n, -1))
    replay.add(ids[:n], np.arange(n), np.ones(n, np.float32), ids[n:], np.zeros(n, bool))
    return replay


def test_importance_weights_undo_the_sampling_bias():
    replay = _replay(True)
    # Every new transition gets the largest priority so far: 1 (the first one).
    np.testing.assert_array_equal(replay.tree.leaves(4), np.ones(4))
    replay.update_priorities(np.array([0, 1, 2, 3]), np.array([1.0, 1.0, 2.0, -4.0]))
    assert replay.max_priority == pytest.approx(4.0)
    batch = replay.sample(np.random.default_rng(0), 8, beta=1.0)
    assert batch.weight is not None and batch.slots is not None
    p = np.array([1.0, 1.0, 2.0, 4.0])[batch.slots] / 8.0
    want = (4 * p) ** -1.0
    np.testing.assert_allclose(batch.weight.numpy(), want / want.max(), rtol=1e-6)
    # beta 0: no correction.
    assert (replay.sample(np.random.default_rng(0), 8, beta=0.0).weight.numpy() == 1.0).all()
    # A new transition is sampled first in line: it gets the largest priority seen (4).
    ids = replay.store.add(np.zeros((2, 2), np.float32), np.full(2, -1))
    replay.add(ids[:1], np.array([0]), np.ones(1, np.float32), ids[1:], np.zeros(1, bool))
    assert replay.tree.leaves(5)[4] == pytest.approx(4.0)


def test_uniform_replay_has_no_weights_and_prioritized_state_restores_exactly():
    assert _replay(False).sample(np.random.default_rng(0), 4).weight is None
    replay = _replay(True)
    replay.update_priorities(np.array([1, 3]), np.array([0.3, 2.5]))
    fresh = _replay(True, n=0)
    fresh.load_state({k: v.copy() for k, v in replay.state().items()})
    assert np.array_equal(fresh.tree.tree, replay.tree.tree) and fresh.max_priority == replay.max_priority
    a, b = (r.sample(np.random.default_rng(3), 16) for r in (replay, fresh))
    assert np.array_equal(a.slots, b.slots)
    state = replay.state()
    del state["replay/priority"]
    with pytest.raises(KeyError):
        _replay(True, n=0).load_state(state)
