"""A sum tree over replay slots: proportional prioritized sampling (Schaul et al., 2016).

Every internal node is always recomputed as the sum of its two children, never adjusted
by a difference, so the tree is a pure function of its leaves: rebuilt from saved leaves
it is bitwise the tree it was, and a resumed run samples the same transitions.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = ["SumTree"]


class SumTree:
    """Non-negative priorities of ``capacity`` slots, sampled in proportion to their value."""

    def __init__(self, capacity: int) -> None:
        self.capacity = int(capacity)
        self.size = 1 << max(0, (self.capacity - 1).bit_length())  # leaves, a power of two
        self.tree = np.zeros(2 * self.size, dtype=np.float64)  # node i has children 2i, 2i+1; leaves at size+

    @property
    def total(self) -> float:
        return float(self.tree[1])

    def leaves(self, n: int) -> NDArray[np.float64]:
        """The priorities of slots ``0 .. n-1``."""
        return self.tree[self.size:self.size + n]

    def set(self, slots: NDArray[np.int64], values: NDArray[np.floating]) -> None:
        """Set slots' priorities (the last value wins for a repeated slot) and their ancestors' sums."""
        nodes = np.asarray(slots, dtype=np.int64) + self.size
        self.tree[nodes] = values
        nodes = np.unique(nodes // 2)
        while nodes[0] >= 1:
            self.tree[nodes] = self.tree[2 * nodes] + self.tree[2 * nodes + 1]
            if nodes[0] == 1:
                break
            nodes = np.unique(nodes // 2)

    def rebuild(self, leaves: NDArray[np.floating]) -> None:
        """Leaves ``0 .. len(leaves)-1`` from ``leaves`` (the rest 0) and every sum from them."""
        self.tree[:] = 0.0
        self.tree[self.size:self.size + len(leaves)] = leaves
        lo = self.size // 2
        while lo >= 1:
            nodes = np.arange(lo, 2 * lo)
            self.tree[nodes] = self.tree[2 * nodes] + self.tree[2 * nodes + 1]
            lo //= 2

    def sample(self, rng: np.random.Generator, k: int, filled: int) -> NDArray[np.int64]:
        """``k`` slots below ``filled``, one from each of ``k`` equal strata of the total mass."""
        total = self.total
        u = (np.arange(k) + rng.random(k)) * (total / k)
        u = np.minimum(u, np.nextafter(total, 0.0))
        node = np.ones(k, dtype=np.int64)
        while node[0] < self.size:
            left = 2 * node
            go_right = u >= self.tree[left]
            u = np.where(go_right, u - self.tree[left], u)
            node = np.where(go_right, left + 1, left)
        # Rounding can carry a draw past the last filled slot; it belongs to that slot.
        return np.minimum(node - self.size, filled - 1)
