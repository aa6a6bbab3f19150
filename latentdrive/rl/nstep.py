"""n-step returns, assembled per agent as its transitions arrive.

Each agent slot keeps a window of the transitions it started in the last ``n`` steps.
Position ``j`` of the window holds the transition started ``j`` steps ago, with its
discounted return so far ``Σ_{i≤j} γ^i r_{t+i}``. A transition leaves the window, as one
replay entry ``(obs_t, a_t, R, obs_{t+k}, terminated, k)``, when

- it has gathered ``n`` rewards (``k = n``, bootstraps from ``obs_{t+n}``);
- its agent terminated (crash or mission completed): ``k`` is the steps actually taken
  and the entry does not bootstrap;
- its agent was cut off (another AV crashed, time ran out): ``k`` steps, bootstrapping
  from the observation at the cut, discounted by ``γ^k``;
- the segment ends (:meth:`NStepWindow.flush`): likewise cut off, at the agent's latest
  observation.

With ``n = 1`` every transition leaves on the step it was made, as one-step DQN stores it.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

__all__ = ["NStepEntries", "NStepWindow"]

IntArray = NDArray[np.int64]


class NStepEntries(NamedTuple):
    """Replay entries ready to store; every field ``(k,)``."""

    obs_id: IntArray
    action: IntArray
    reward: NDArray[np.float64]  # discounted sum of the k rewards
    next_id: IntArray  # the observation k steps later (the final or cut-off one)
    terminated: NDArray[np.bool_]  # the agent's own terminal step is inside: no bootstrap
    steps: IntArray  # k, 1 ≤ k ≤ n: the bootstrap is discounted by γ^k


class NStepWindow:
    """Per-agent windows of pending transitions for ``(num_envs, n_av)`` agent slots.

    Args:
        n: the return's horizon, in policy steps.
        gamma: discount per policy step.
        slots: ``(num_envs, n_av)``.
    """

    def __init__(self, n: int, gamma: float, slots: tuple[int, int]) -> None:
        if n < 1:
            raise ValueError(f"n must be at least 1, got {n}")
        self.n = int(n)
        self.powers = float(gamma) ** np.arange(self.n, dtype=np.float64)  # γ^j of position j
        self.obs_id = np.full((*slots, self.n), -1, dtype=np.int64)
        self.action = np.zeros((*slots, self.n), dtype=np.int64)
        self.ret = np.zeros((*slots, self.n), dtype=np.float64)
        self.valid = np.zeros((*slots, self.n), dtype=bool)
        self.last = np.full(slots, -1, dtype=np.int64)  # each slot's latest observation id

    def __len__(self) -> int:
        """Transitions pending."""
        return int(self.valid.sum())

    def push(self, ei: IntArray, ai: IntArray, obs_id: IntArray, action: IntArray, reward: NDArray[np.floating],
             next_id: IntArray, terminated: NDArray[np.bool_], truncated: NDArray[np.bool_]) -> NStepEntries:
        """One step of the acting agents ``(ei[i], ai[i])``; returns the entries it completes.

        Every argument is ``(k,)``: the agents' transitions ``obs_id --action--> next_id``
        with ``reward``; ``terminated`` (crash, mission done) and ``truncated`` (cut off)
        end the agent's episode, and with it every transition in its window.
        """
        old_ret, old_valid = self.ret[ei, ai], self.valid[ei, ai]
        # The oldest position left on the step it filled; shifting drops nothing pending.
        assert not old_valid[:, -1].any()
        o = np.concatenate([obs_id[:, None], self.obs_id[ei, ai, :-1]], axis=1)
        a = np.concatenate([action[:, None], self.action[ei, ai, :-1]], axis=1)
        v = np.concatenate([np.ones((len(ei), 1), dtype=bool), old_valid[:, :-1]], axis=1)
        r = np.concatenate([np.zeros((len(ei), 1)), old_ret[:, :-1]], axis=1)
        r = np.where(v, r + self.powers * np.asarray(reward, dtype=np.float64)[:, None], 0.0)
        ends = np.asarray(terminated) | np.asarray(truncated)
        emit = v & (ends[:, None] | (np.arange(self.n) == self.n - 1))
        # Oldest first within an agent, agents in the given order: a fixed replay order.
        rows, pos = np.nonzero(emit[:, ::-1])
        pos = self.n - 1 - pos
        out = NStepEntries(o[rows, pos], a[rows, pos], r[rows, pos], next_id[rows],
                           np.asarray(terminated, dtype=bool)[rows], (pos + 1).astype(np.int64))
        v &= ~emit
        self.obs_id[ei, ai], self.action[ei, ai], self.ret[ei, ai], self.valid[ei, ai] = o, a, r, v
        self.last[ei, ai] = next_id
        return out

    def flush(self) -> NStepEntries:
        """Every pending transition, cut off at its agent's latest observation (segment end)."""
        e, a, pos = np.nonzero(self.valid)
        order = np.lexsort((-pos, a, e))  # slot by slot, oldest first
        e, a, pos = e[order], a[order], pos[order]
        out = NStepEntries(self.obs_id[e, a, pos], self.action[e, a, pos], self.ret[e, a, pos], self.last[e, a],
                           np.zeros(len(e), dtype=bool), (pos + 1).astype(np.int64))
        self.valid[:] = False
        return out
