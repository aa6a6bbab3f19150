"""``latentdrive bench --bottleneck``: one row per precision, rates from the run itself."""

from __future__ import annotations

import math

import pytest

from latentdrive.bnn.bench import bench_bottleneck, format_bottleneck_bench
from latentdrive.models.bottleneck import BottleneckConfig

pytestmark = pytest.mark.usefixtures("one_torch_thread")

TINY = BottleneckConfig(input_shape=(2, 16, 32), latent_dim=8, channels=(4, 8), head_hidden=16)


def test_one_row_per_precision_with_measured_rates() -> None:
    rows = bench_bottleneck(TINY, batch_size=4, steps=2)
    assert [r.precision for r in rows] == ["fp32", "bf16"]
    for r in rows:
        assert math.isfinite(r.network_samples_per_s) and r.network_samples_per_s > 0
        assert math.isfinite(r.loop_samples_per_s) and r.loop_samples_per_s > 0
    table = format_bottleneck_bench(rows, TINY, 1)
    assert "| fp32 |" in table and "| bf16 |" in table
    # The first row is the reference: its ratios are 1.
    assert table.splitlines()[3].count("| 1.00 |") == 2


def test_bad_sizes_are_refused() -> None:
    with pytest.raises(ValueError, match="steps and batch_size"):
        bench_bottleneck(TINY, batch_size=0, steps=2)


def test_auto_measures_bf16_only_where_it_is_native(monkeypatch) -> None:
    import torch

    from latentdrive.bnn import bench

    cpu = torch.device("cpu")
    monkeypatch.setattr("latentdrive.runtime.cpu_bf16_gradients_sound", lambda: True)
    monkeypatch.setattr("latentdrive.runtime.cpu_has_bf16", lambda: False)
    assert bench.bench_precisions("auto", cpu) == ("fp32",)
    assert bench.bench_precisions("bf16", cpu) == ("fp32", "bf16")
    assert bench.bench_precisions("fp32", cpu) == ("fp32",)
    monkeypatch.setattr("latentdrive.runtime.cpu_has_bf16", lambda: True)
    assert bench.bench_precisions("auto", cpu) == ("fp32", "bf16")
    assert bench.bench_precisions("fp32", cpu) == ("fp32",)
    with pytest.raises(ValueError, match="precision must be one of auto, fp32, bf16, got 'fp16'"):
        bench.bench_precisions("fp16", cpu)


def test_the_cli_refuses_an_unknown_precision(capsys) -> None:
    from latentdrive.cli import main

    assert main(["bench", "--bottleneck", "--set", "precision=fp16"]) != 0
    assert "precision must be one of auto, fp32, bf16, got 'fp16'" in capsys.readouterr().err
