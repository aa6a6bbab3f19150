"""Disjoint seed ranges for training and evaluation environments.

A vector env reset with seed ``s`` gives environment ``i`` the seed ``s + i``; every later
episode seed of that environment comes from a generator seeded with it. Training resets
draw ``s`` from :data:`TRAIN_RESET_SEEDS` and evaluation from :data:`EVAL_RESET_SEEDS`,
ranges that do not overlap even after adding environment indices (below
:data:`MAX_ENVS`), so no evaluation environment is ever seeded like a training one.
"""

from __future__ import annotations

import numpy as np

__all__ = ["EVAL_RESET_SEEDS", "MAX_ENVS", "TRAIN_RESET_SEEDS", "eval_reset_seed", "train_reset_seed"]

#: Environments per vector env that the ranges leave room for.
MAX_ENVS = 4096
TRAIN_RESET_SEEDS = range(0, 2**30 - MAX_ENVS)
EVAL_RESET_SEEDS = range(2**30, 2**31 - MAX_ENVS)


def train_reset_seed(seed: int, segment: int) -> int:
    """The reset seed of a training run's ``segment`` (see :mod:`latentdrive.rl.train`)."""
    state = np.random.SeedSequence([seed, segment, 0x7A41]).generate_state(1, np.uint64)[0]
    return TRAIN_RESET_SEEDS.start + int(state % np.uint64(len(TRAIN_RESET_SEEDS)))


def eval_reset_seed(offset: int = 0) -> int:
    """The reset seed of an evaluation; ``offset`` picks another fixed evaluation set."""
    if not 0 <= offset < len(EVAL_RESET_SEEDS):
        raise ValueError(f"evaluation seed offset must be in [0, {len(EVAL_RESET_SEEDS)}), got {offset}")
    return EVAL_RESET_SEEDS.start + offset
