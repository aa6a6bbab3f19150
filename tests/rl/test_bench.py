"""`latentdrive bench --train`: the real training loop, timed per mode, repeatable."""

from typing import Any

import pytest
import torch

from latentdrive.rl.bench import bench_training, format_train_bench

# fp32 unless a test says otherwise: ``auto`` would add a bf16 row on CPUs with AMX-BF16.
SMALL: dict[str, Any] = {"precision": "fp32", "observation": {"height": 16, "width": 32, "frames": 2},
         "dqn": {"learning_starts": 16, "batch_size": 4, "buffer_size": 200}}


def test_a_repeated_bench_reports_its_median_run_and_range():
    rows = bench_training(["latent"], ["merge"], transitions=24, updates=2, envs=2, overrides=SMALL, repeat=3)
    (row,) = rows
    assert row.gflop_per_encode > 0 and row.arithmetic_cap < row.learning_cap  # latent modes encode
    assert row.mode == "latent (untrained encoder)" and row.runs == 3
    lo, hi = row.transitions_per_s_min, row.transitions_per_s_max
    assert lo is not None and hi is not None and lo <= row.transitions_per_s <= hi
    assert row.updates_per_s > 0 and row.trainable_parameters > 0
    shares = (row.simulate, row.render, row.encode, row.learn, row.other)
    assert all(0 <= x <= 1 for x in shares) and row.encode > 0  # latent mode encodes
    text = format_train_bench(rows, envs=2, threads=1)
    assert "the median of 3 runs" in text and f"{lo:.0f}-{hi:.0f}" in text


def test_a_single_run_prints_no_range():
    (row,) = bench_training(["raw"], ["merge"], transitions=24, updates=2, envs=2, overrides=SMALL)
    assert row.runs == 1 and row.encode < 0.05  # raw mode stores observations as they are
    assert row.gflop_per_encode == 0 and row.arithmetic_cap == row.learning_cap
    assert "median" not in format_train_bench([row], envs=2, threads=1)


def test_a_bf16_run_is_measured_beside_fp32_in_the_same_run():
    rows = bench_training(["raw"], ["merge"], transitions=24, updates=2, envs=2,
                          overrides={**SMALL, "precision": "bf16"})
    assert [r.precision for r in rows] == ["fp32", "bf16"]
    assert all(r.updates_per_s > 0 and r.transitions_per_s > 0 for r in rows)
    text = format_train_bench(rows, envs=2, threads=1)
    assert "raw: bf16 over fp32 in this run" in text
    fp32_only = bench_training(["raw"], ["merge"], transitions=24, updates=2, envs=2,
                               overrides={**SMALL, "precision": "fp32"})
    assert [r.precision for r in fp32_only] == ["fp32"]
    assert "fp32 only" in format_train_bench(fp32_only, envs=2, threads=1)


def test_the_learners_arithmetic_is_counted_per_update_and_set_against_a_matrix_product():
    small, = bench_training(["raw"], ["merge"], transitions=24, updates=2, envs=2, overrides=SMALL)
    big = {**SMALL, "dqn": {**SMALL["dqn"], "batch_size": 8, "updates_per_transition": 0.25}}
    double, = bench_training(["raw"], ["merge"], transitions=24, updates=2, envs=2, overrides=big)
    # Every counted operation (convolutions, linear layers, on the batch) scales with it.
    assert double.gflop_per_update == pytest.approx(2 * small.gflop_per_update, rel=0.01)
    assert small.gflop_per_update > 0 and small.matmul_gflops > 0
    assert double.learning_cap == pytest.approx(double.matmul_gflops / (double.gflop_per_update * 0.25))
    text = format_train_bench([small], envs=2, threads=1)
    assert f"{small.gflop_per_update:.3g} GFLOP per update" in text and "would allow at most" in text


def test_an_update_counts_the_batchs_backward_and_both_passes_on_the_next_observations():
    """Forward on the batch, its backward (about twice the forward), the target's and the
    online network's passes on the next observations: at least 4 forwards of the batch."""
    from torch.utils.flop_counter import FlopCounterMode

    from latentdrive.config import merge_overrides, validate
    from latentdrive.rl.config import PolicyTrainConfig
    from latentdrive.rl.policy import build_network, encoder_config

    (row,) = bench_training(["raw"], ["merge"], transitions=24, updates=2, envs=2, overrides=SMALL)
    cfg = validate(PolicyTrainConfig, merge_overrides({"mode": "raw", "scenarios": ["merge"]}, SMALL))
    net = build_network(cfg, encoder_config(cfg))
    with FlopCounterMode(display=False) as counter:
        net(torch.zeros(SMALL["dqn"]["batch_size"], *cfg.observation.shape))
    forward = counter.get_total_flops() / 1e9
    assert 4 * forward <= row.gflop_per_update <= 6 * forward
