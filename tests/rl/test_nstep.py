"""n-step returns: literal windows for a full horizon, a terminal step, a cut-off and a segment end."""

import numpy as np
import pytest
import torch

from latentdrive.rl.dqn import td_targets
from latentdrive.rl.nstep import NStepWindow

G = 0.5
ONE = np.array([0]), np.array([0])  # one agent slot (env 0, AV 0)
NO, YES = np.array([False]), np.array([True])


def _step(w, t, r, terminated=NO, truncated=NO):
    """Agent (0, 0) acts on observation t (action 10+t) and reaches observation t+1."""
    return w.push(*ONE, np.array([t]), np.array([10 + t]), np.array([r]), np.array([t + 1]), terminated, truncated)


def _rows(entries):
    return [(int(o), int(a), float(r), int(nx), bool(term), int(k))
            for o, a, r, nx, term, k in zip(*entries, strict=True)]


def test_a_full_window_sums_n_rewards_and_bootstraps_n_steps_later():
    w = NStepWindow(3, G, (1, 1))
    assert _rows(_step(w, 0, 1.0)) == [] and _rows(_step(w, 1, 2.0)) == []
    # obs 0: 1 + 0.5·2 + 0.25·4 = 3, bootstrapping from obs 3, discounted by γ^3.
    assert _rows(_step(w, 2, 4.0)) == [(0, 10, 3.0, 3, False, 3)]
    # obs 1: 2 + 0.5·4 + 0.25·8 = 6, from obs 4.
    assert _rows(_step(w, 3, 8.0)) == [(1, 11, 6.0, 4, False, 3)]
    assert len(w) == 2


def test_the_agents_own_terminal_step_inside_the_window_stops_every_return_there():
    w = NStepWindow(3, G, (1, 1))
    _step(w, 0, 1.0)
    # Crash (or mission done) on the second step: no bootstrap, k = steps actually taken.
    got = _rows(_step(w, 1, -4.0, terminated=YES))
    assert got == [(0, 10, 1.0 - 2.0, 2, True, 2), (1, 11, -4.0, 2, True, 1)]
    assert len(w) == 0


def test_a_cut_off_inside_the_window_bootstraps_from_the_observation_at_the_cut():
    w = NStepWindow(4, G, (1, 1))
    _step(w, 0, 1.0)
    _step(w, 1, 2.0)
    # Another AV crashed or time ran out: cut off at obs 3, discounted by γ^k.
    got = _rows(_step(w, 2, 4.0, truncated=YES))
    assert got == [(0, 10, 3.0, 3, False, 3), (1, 11, 4.0, 3, False, 2), (2, 12, 4.0, 3, False, 1)]
    assert len(w) == 0


def test_a_segment_end_cuts_every_pending_return_at_the_latest_observation():
    w = NStepWindow(3, G, (2, 1))
    both = np.array([0, 1]), np.array([0, 0])
    w.push(*both, np.array([0, 100]), np.array([1, 2]), np.array([1.0, 3.0]), np.array([1, 101]), ~YES.repeat(2),
           ~YES.repeat(2))
    w.push(*both, np.array([1, 101]), np.array([1, 2]), np.array([2.0, 5.0]), np.array([2, 102]), ~YES.repeat(2),
           ~YES.repeat(2))
    got = _rows(w.flush())
    assert got == [(0, 1, 2.0, 2, False, 2), (1, 1, 2.0, 2, False, 1),
                   (100, 2, 5.5, 102, False, 2), (101, 2, 5.0, 102, False, 1)]
    assert len(w) == 0 and _rows(w.flush()) == []


def test_agents_keep_their_own_windows_and_n1_is_one_step():
    w = NStepWindow(2, G, (1, 2))
    two = np.array([0, 0]), np.array([0, 1])
    # Agent 1 crashes on the first step; agent 0 drives on.
    got = _rows(w.push(*two, np.array([0, 50]), np.array([3, 4]), np.array([1.0, -1.0]), np.array([1, 51]),
                       np.array([False, True]), np.array([False, False])))
    assert got == [(50, 4, -1.0, 51, True, 1)]
    got = _rows(w.push(np.array([0]), np.array([0]), np.array([1]), np.array([3]), np.array([2.0]), np.array([2]),
                       NO, NO))
    assert got == [(0, 3, 2.0, 2, False, 2)]
    one = NStepWindow(1, G, (1, 1))
    assert _rows(_step(one, 0, 7.0)) == [(0, 10, 7.0, 1, False, 1)]


def test_window_needs_a_positive_horizon():
    with pytest.raises(ValueError, match="at least 1"):
        NStepWindow(0, G, (1, 1))


def test_td_targets_discount_the_bootstrap_by_gamma_to_the_steps_taken():
    reward = torch.tensor([3.0, 3.0, -1.0])
    bootstrap = torch.tensor([1.0, 1.0, 0.0])
    steps = torch.tensor([3.0, 1.0, 2.0])
    q = torch.tensor([[8.0, 0.0], [8.0, 0.0], [8.0, 0.0]])
    y = td_targets(reward, bootstrap, q, q, gamma=0.5, double=True, steps=steps)
    torch.testing.assert_close(y, torch.tensor([3.0 + 0.125 * 8.0, 3.0 + 0.5 * 8.0, -1.0]))
