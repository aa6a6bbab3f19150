"""The BNN study's held-out samples: what its evaluation (:mod:`latentdrive.experiments.bnn`)
scores and its figures (:mod:`latentdrive.experiments.bnn_figures`) draw, kept apart from
both so that the figures need nothing of the study that draws them."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from latentdrive.data.dataset import ShardDataset

__all__ = ["HeldOut", "held_out"]


@dataclass
class HeldOut:
    """Held-out samples, at most ``per_scenario`` of each scenario, in dataset order.

    ``noisy``/``clean``: ``(n, 4, T, H, W)`` float32; ``scenario``: ``(n,)`` int64 indices
    into ``names``.
    """

    names: list[str]
    noisy: np.ndarray
    clean: np.ndarray
    scenario: np.ndarray

    def by_scenario(self, features: np.ndarray) -> dict[str, np.ndarray]:
        """Split ``(n, ...)`` features into one array per scenario present."""
        return {name: features[self.scenario == i] for i, name in enumerate(self.names) if np.any(self.scenario == i)}

    def first(self, name: str) -> int:
        """Index of the first held-out sample of scenario ``name`` (-1 when absent)."""
        if name not in self.names:
            return -1
        idx = np.flatnonzero(self.scenario == self.names.index(name))
        return int(idx[0]) if idx.size else -1


def held_out(ds: ShardDataset, episodes: np.ndarray, per_scenario: int, seed: int = 0) -> HeldOut:
    """Collect up to ``per_scenario`` samples of each scenario from ``episodes``.

    Samples are drawn from a shuffled pass (so they spread over episodes), then kept in
    their pass order; memory is ``per_scenario × scenarios × 2 × 4·T·H·W × 4`` bytes.
    """
    names = list(ds.scenario_names)
    keep: dict[str, list[np.ndarray]] = {"noisy": [], "clean": [], "scenario": []}
    counts = np.zeros(len(names), dtype=np.int64)
    for batch in ds.batches(256, episodes, seed=seed, epoch=0, mixed=False):
        s = batch.scenario.numpy()
        take = np.zeros(len(s), dtype=bool)
        for i in range(len(s)):  # per sample of a 256-batch, not a hot path
            if counts[s[i]] < per_scenario:
                take[i] = True
                counts[s[i]] += 1
        keep["noisy"].append(batch.noisy.numpy()[take])
        keep["clean"].append(batch.clean.numpy()[take])
        keep["scenario"].append(s[take])
        if np.all(counts[np.unique(ds.episode_scenario(episodes))] >= per_scenario):
            break
    return HeldOut(names, *(np.concatenate(keep[k]) for k in ("noisy", "clean", "scenario")))
