"""The seed ranges: training, evaluation, validation and probes never share an environment seed."""

import itertools
from typing import Any

import pytest

from latentdrive.config import ConfigError
from latentdrive.seeds import (
    EVAL_RESET_SEEDS,
    MAX_ENVS,
    PROBE_RESET_SEEDS,
    TRAIN_RESET_SEEDS,
    VALIDATION_RESET_SEEDS,
    VALIDATION_SETS,
    eval_reset_seed,
    train_reset_seed,
    validation_reset_seed,
)


def test_validation_seeds_are_disjoint_from_training_evaluation_and_probes():
    ranges = sorted([TRAIN_RESET_SEEDS, EVAL_RESET_SEEDS, VALIDATION_RESET_SEEDS, PROBE_RESET_SEEDS],
                    key=lambda r: r.start)
    # Each range ends MAX_ENVS before the next begins, so s + i (i < MAX_ENVS) stays inside.
    for lower, upper in itertools.pairwise(ranges):
        assert lower.stop + MAX_ENVS <= upper.start
    assert validation_reset_seed(0) == VALIDATION_RESET_SEEDS.start
    assert validation_reset_seed(VALIDATION_SETS - 1) in VALIDATION_RESET_SEEDS
    last_eval = EVAL_RESET_SEEDS.start + (len(EVAL_RESET_SEEDS) // MAX_ENVS - 1) * MAX_ENVS
    assert last_eval + MAX_ENVS <= VALIDATION_RESET_SEEDS.start
    for seed in range(20):
        for segment in range(20):
            assert train_reset_seed(seed, segment) + MAX_ENVS <= VALIDATION_RESET_SEEDS.start
    # The evaluation sets used so far keep their seeds.
    assert eval_reset_seed(0) == 2**30 and eval_reset_seed(1) == 2**30 + MAX_ENVS
    with pytest.raises(ConfigError, match="validation set"):
        validation_reset_seed(VALIDATION_SETS)
    with pytest.raises(ConfigError, match="validation set"):
        validation_reset_seed(-1)


def test_periodic_evaluations_play_validation_episodes_when_asked(tmp_path):
    from latentdrive.evaluate.run import evaluate_policy

    def idle():
        return lambda inp: inp.active.astype("int64")

    kw: dict[str, Any] = {"envs": 2, "observation": {"height": 16, "width": 32, "frames": 2}}
    seeds = {name: {o.seed for o in evaluate_policy(idle, ["intersection"], 4, reset_seed=first, **kw)}
             for name, first in (("evaluation", eval_reset_seed(1)), ("validation", validation_reset_seed(0)))}
    default = {o.seed for o in evaluate_policy(idle, ["intersection"], 4, seed_offset=1, **kw)}
    assert seeds["evaluation"] == default and not seeds["evaluation"] & seeds["validation"]
