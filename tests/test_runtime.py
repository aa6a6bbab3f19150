"""The one precision setting: resolution per device and the autocast block."""

from __future__ import annotations

import pytest
import torch

from latentdrive import runtime


def test_explicit_precisions_are_taken_as_given() -> None:
    cpu = torch.device("cpu")
    assert runtime.resolve_precision("fp32", cpu) == torch.float32
    assert runtime.resolve_precision("bf16", cpu) == torch.bfloat16


def test_auto_follows_the_cpu(monkeypatch: pytest.MonkeyPatch) -> None:
    cpu = torch.device("cpu")
    monkeypatch.setattr(runtime, "cpu_has_bf16", lambda: False)
    assert runtime.resolve_precision("auto", cpu) == torch.float32
    monkeypatch.setattr(runtime, "cpu_has_bf16", lambda: True)
    assert runtime.resolve_precision("auto", cpu) == torch.bfloat16
    # CUDA has bf16 whatever the host CPU.
    monkeypatch.setattr(runtime, "cpu_has_bf16", lambda: False)
    assert runtime.resolve_precision("auto", torch.device("cuda")) == torch.bfloat16


def test_unknown_precision_is_refused() -> None:
    with pytest.raises(ValueError, match="precision must be one of"):
        runtime.resolve_precision("fp16", torch.device("cpu"))


def test_autocast_runs_matmuls_in_the_dtype() -> None:
    cpu = torch.device("cpu")
    a = torch.ones(4, 4)
    with runtime.autocast(torch.bfloat16, cpu):
        assert (a @ a).dtype == torch.bfloat16
    with runtime.autocast(torch.float32, cpu):
        assert (a @ a).dtype == torch.float32
