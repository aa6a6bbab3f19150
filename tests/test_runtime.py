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
    monkeypatch.setattr(runtime, "cpu_bf16_gradients_sound", lambda: True)
    monkeypatch.setattr(runtime, "cpu_has_bf16", lambda: False)
    assert runtime.resolve_precision("auto", cpu) == torch.float32
    monkeypatch.setattr(runtime, "cpu_has_bf16", lambda: True)
    assert runtime.resolve_precision("auto", cpu) == torch.bfloat16
    # AMX whose kernels fail the probe: fp32.
    monkeypatch.setattr(runtime, "cpu_bf16_gradients_sound", lambda: False)
    assert runtime.resolve_precision("auto", cpu) == torch.float32
    # CUDA: fp32 whatever the host CPU (bf16 was no faster there for these networks).
    monkeypatch.setattr(runtime, "cpu_bf16_gradients_sound", lambda: True)
    assert runtime.resolve_precision("auto", torch.device("cuda")) == torch.float32
    assert runtime.resolve_precision("bf16", torch.device("cuda")) == torch.bfloat16


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


def test_only_amx_counts_as_bf16_units(monkeypatch: pytest.MonkeyPatch) -> None:
    """AVX512-BF16 without AMX gains little and its oneDNN kernels are unsound: not bf16 units."""
    caps = {"avx512_bf16": True, "amx_bf16": False}
    monkeypatch.setattr(torch.cpu, "get_capabilities", lambda: caps)
    assert not runtime.cpu_has_bf16()
    caps["amx_bf16"] = True
    assert runtime.cpu_has_bf16()


def test_the_bf16_probe_leaves_the_global_generator_alone() -> None:
    runtime.cpu_bf16_gradients_sound.cache_clear()
    torch.manual_seed(3)
    expected = torch.rand(4)
    torch.manual_seed(3)
    assert isinstance(runtime.cpu_bf16_gradients_sound(), bool)
    assert torch.equal(torch.rand(4), expected)


def test_bf16_where_the_kernels_are_unsound_runs_without_onednn(monkeypatch: pytest.MonkeyPatch) -> None:
    """Regression: on AVX512-BF16 without AMX, a bf16 BNN read NaN from its second step."""
    cpu = torch.device("cpu")
    before = torch.backends.mkldnn.enabled
    monkeypatch.setattr(runtime, "cpu_bf16_gradients_sound", lambda: False)
    with pytest.warns(RuntimeWarning, match="without oneDNN"), runtime.torch_settings(False, cpu, 0, torch.bfloat16):
        assert not torch.backends.mkldnn.enabled
        # The probe's convolution, where oneDNN on AVX512-BF16 returns inf: its bf16
        # gradient agrees with fp32's under these settings.
        assert runtime.bf16_conv_gradients_agree()
    assert torch.backends.mkldnn.enabled == before
    monkeypatch.setattr(runtime, "cpu_bf16_gradients_sound", lambda: True)
    with runtime.torch_settings(False, cpu, 0, torch.bfloat16):
        assert torch.backends.mkldnn.enabled == before
    with runtime.torch_settings(False, cpu, 0, torch.float32):
        assert torch.backends.mkldnn.enabled == before


def test_the_bf16_probe_runs_under_no_grad_and_inference_mode() -> None:
    runtime.cpu_bf16_gradients_sound.cache_clear()
    with torch.no_grad():
        a = runtime.cpu_bf16_gradients_sound()
    runtime.cpu_bf16_gradients_sound.cache_clear()
    with torch.inference_mode():
        b = runtime.cpu_bf16_gradients_sound()
    assert a == b


def test_onednn_toggles_only_whether_it_is_used() -> None:
    m = torch.backends.mkldnn
    before = (m.enabled, m.deterministic, m.allow_tf32, m.fp32_precision)
    with runtime.onednn(False):
        assert not m.enabled
        assert (m.deterministic, m.allow_tf32, m.fp32_precision) == before[1:]
    assert (m.enabled, m.deterministic, m.allow_tf32, m.fp32_precision) == before
