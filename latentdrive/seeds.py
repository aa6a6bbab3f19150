"""Disjoint seed ranges for training, evaluation, validation and probing environments.

A vector env reset with seed ``s`` gives environment ``i`` the seed ``s + i``; every later
episode seed of that environment comes from a generator seeded with it. Training resets
draw ``s`` from :data:`TRAIN_RESET_SEEDS`, evaluation from :data:`EVAL_RESET_SEEDS`,
hyperparameter search (``latentdrive tune``) scores on :data:`VALIDATION_RESET_SEEDS` and
the linear probes of :mod:`latentdrive.evaluate.probes` draw from :data:`PROBE_RESET_SEEDS`,
ranges that do not overlap even after adding environment indices (below
:data:`MAX_ENVS`), so no evaluation, validation or probe environment is ever seeded like a
training one, a tuned setting is never scored on an evaluation set, and probing never looks
at either.
"""

from __future__ import annotations

import numpy as np

from latentdrive.config import ConfigError

__all__ = ["EVAL_OFFSETS", "EVAL_RESET_SEEDS", "MAX_ENVS", "PROBE_RESET_SEEDS", "PROBE_SETS", "TRAINING_EVAL_OFFSET",
           "TRAIN_RESET_SEEDS", "VALIDATION_RESET_SEEDS", "VALIDATION_SETS", "eval_reset_seed", "probe_reset_seed",
           "train_reset_seed", "validation_reset_seed"]

#: Environments per vector env that the ranges leave room for.
MAX_ENVS = 4096
TRAIN_RESET_SEEDS = range(0, 2**30 - MAX_ENVS)
# The lower three quarters of [2**30, 2**31) evaluate, the top quarter validates: both stay
# below 2**31, and every evaluation set used before validation had a range of its own keeps
# its seeds (offset k starts at 2**30 + k·MAX_ENVS as before).
EVAL_RESET_SEEDS = range(2**30, 2**31 - 2**28 - MAX_ENVS)
VALIDATION_RESET_SEEDS = range(2**31 - 2**28, 2**31 - MAX_ENVS)
PROBE_RESET_SEEDS = range(2**31, 2**32 - MAX_ENVS)


def train_reset_seed(seed: int, segment: int) -> int:
    """The reset seed of a training run's ``segment`` (see :mod:`latentdrive.rl.train`)."""
    state = np.random.SeedSequence([seed, segment, 0x7A41]).generate_state(1, np.uint64)[0]
    return TRAIN_RESET_SEEDS.start + int(state % np.uint64(len(TRAIN_RESET_SEEDS)))


#: Evaluation sets available: offset k uses reset seeds ``start + k·MAX_ENVS + i``, so two
#: offsets share no environment seed.
EVAL_OFFSETS = len(EVAL_RESET_SEEDS) // MAX_ENVS
#: The offset of the evaluation run during training (a validation set): the final
#: evaluation's default set (offset 0) is never looked at while training.
TRAINING_EVAL_OFFSET = 1


def eval_reset_seed(offset: int = 0) -> int:
    """The reset seed of an evaluation; ``offset`` picks another, disjoint, fixed evaluation set."""
    if not 0 <= offset < EVAL_OFFSETS:
        raise ConfigError(f"evaluation seed offset must be in [0, {EVAL_OFFSETS}), got {offset}")
    return EVAL_RESET_SEEDS.start + offset * MAX_ENVS


#: Validation sets available: set k uses reset seeds ``start + k·MAX_ENVS + i``.
VALIDATION_SETS = len(VALIDATION_RESET_SEEDS) // MAX_ENVS


def validation_reset_seed(k: int = 0) -> int:
    """The reset seed of validation set ``k``: what hyperparameter search scores a setting on
    (``latentdrive tune``), never an evaluation set, so a tuned number is never a test number."""
    if not 0 <= k < VALIDATION_SETS:
        raise ConfigError(f"validation set must be in [0, {VALIDATION_SETS}), got {k}")
    return VALIDATION_RESET_SEEDS.start + k * MAX_ENVS


#: Probe data sets available: set k uses reset seeds ``start + k·MAX_ENVS + i``.
PROBE_SETS = len(PROBE_RESET_SEEDS) // MAX_ENVS


def probe_reset_seed(seed: int = 0) -> int:
    """The reset seed of probe data set ``seed`` (:mod:`latentdrive.evaluate.probes`)."""
    if not 0 <= seed < PROBE_SETS:
        raise ConfigError(f"probe seed must be in [0, {PROBE_SETS}), got {seed}")
    return PROBE_RESET_SEEDS.start + seed * MAX_ENVS
