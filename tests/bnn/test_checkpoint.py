"""Checkpoints: exact round trips, atomic writes, and one-line errors for unusable files."""

from __future__ import annotations

import io
import json
import os
import pickle
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import examples
from hypothesis import given, settings
from hypothesis import strategies as st
from safetensors.torch import save_file

from latentdrive import fileio
from latentdrive.bnn import checkpoint as ckpt_mod
from latentdrive.bnn.checkpoint import (
    CheckpointError,
    load_checkpoint,
    read_checkpoint,
    save_checkpoint,
)
from latentdrive.models.bottleneck import BottleneckConfig, BottleneckNetwork

CFG = BottleneckConfig(input_shape=(2, 8, 16), latent_dim=8, channels=(4, 8))


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _trained(cfg: BottleneckConfig = CFG, steps: int = 3, seed: int = 0):
    torch.manual_seed(seed)
    model = BottleneckNetwork(cfg)
    opt = torch.optim.AdamW(model.parameters(), lr=1e-2, weight_decay=0.01)
    g = torch.Generator().manual_seed(seed)
    for _ in range(steps):
        x = torch.rand(4, 4, *cfg.input_shape, generator=g)
        loss = ((model(x)[0] - model.pairs(x)) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    return model, opt


def _one_more_step(model: BottleneckNetwork, opt: torch.optim.Optimizer) -> None:
    x = torch.full((2, 4, *model.cfg.input_shape), 0.3)
    loss = ((model(x)[0] - model.pairs(x)) ** 2).mean()
    opt.zero_grad()
    loss.backward()
    opt.step()


def _assert_one_line_naming(exc: pytest.ExceptionInfo[CheckpointError], path: Path) -> None:
    msg = str(exc.value)
    assert msg.startswith(str(path)), msg
    assert "\n" not in msg
    assert isinstance(exc.value, ValueError)


def test_round_trip_restores_everything(tmp_path: Path) -> None:
    model, opt = _trained()
    tgen = torch.Generator().manual_seed(123)
    tgen.manual_seed(5)
    torch.rand(3, generator=tgen)
    ngen = np.random.default_rng(99)
    ngen.random(7)
    path = save_checkpoint(
        tmp_path / "c.safetensors", model, opt, step=3, epoch=1,
        config={"model": CFG.model_dump(mode="json")},
        torch_generator=tgen, numpy_generator=ngen,
        extra={"metrics": {"loss": 0.5}}, extra_tensors={"ema": torch.ones(2)},
    )
    torch.manual_seed(1)
    model2 = BottleneckNetwork(CFG)
    opt2 = torch.optim.AdamW(model2.parameters(), lr=1.0)
    tgen2, ngen2 = torch.Generator(), np.random.default_rng(0)
    info = load_checkpoint(path, model2, opt2, torch_generator=tgen2, numpy_generator=ngen2)

    assert (info.step, info.epoch) == (3, 1)
    assert info.config == {"model": CFG.model_dump(mode="json")}
    assert info.extra == {"metrics": {"loss": 0.5}}
    assert torch.equal(info.extra_tensors["ema"], torch.ones(2))
    sd1, sd2 = model.state_dict(), model2.state_dict()
    assert sd1.keys() == sd2.keys()
    assert all(torch.equal(sd1[k], sd2[k]) for k in sd1)
    assert opt2.param_groups[0]["lr"] == 1e-2
    assert torch.equal(torch.rand(5, generator=tgen), torch.rand(5, generator=tgen2))
    assert np.array_equal(ngen.random(5), ngen2.random(5))
    # Continuing from the copy gives bitwise the same parameters as continuing the original.
    _one_more_step(model, opt)
    _one_more_step(model2, opt2)
    for t1, t2 in zip(model.parameters(), model2.parameters(), strict=True):
        assert torch.equal(t1, t2)


def test_numpy_generators_with_array_state(tmp_path: Path) -> None:
    model, _ = _trained(steps=0)
    gen = np.random.Generator(np.random.MT19937(3))
    gen.random(10)
    path = save_checkpoint(tmp_path / "c.safetensors", model, step=0, epoch=0, numpy_generator=gen)
    gen2 = np.random.Generator(np.random.MT19937(0))
    load_checkpoint(path, model, numpy_generator=gen2)
    assert np.array_equal(gen.integers(0, 1 << 30, 20), gen2.integers(0, 1 << 30, 20))


def test_other_architecture_is_rejected_and_nothing_changes(tmp_path: Path) -> None:
    model, opt = _trained()
    path = save_checkpoint(tmp_path / "c.safetensors", model, opt, step=3, epoch=1)
    other = BottleneckNetwork(CFG.replace(latent_dim=16))
    before = {k: v.clone() for k, v in other.state_dict().items()}
    with pytest.raises(CheckpointError, match="architecture differs") as exc:
        load_checkpoint(path, other)
    _assert_one_line_naming(exc, path)
    assert all(torch.equal(before[k], v) for k, v in other.state_dict().items())

    deeper = BottleneckNetwork(CFG.replace(channels=(4, 8, 8)))
    with pytest.raises(CheckpointError, match="architecture differs") as exc:
        load_checkpoint(path, deeper)
    _assert_one_line_naming(exc, path)

    # Same model, another optimizer: refused before the model is touched.
    fresh = BottleneckNetwork(CFG)
    before = {k: v.clone() for k, v in fresh.state_dict().items()}
    with pytest.raises(CheckpointError, match="SGD") as exc:
        load_checkpoint(path, fresh, torch.optim.SGD(fresh.parameters(), lr=0.1))
    _assert_one_line_naming(exc, path)
    assert all(torch.equal(before[k], v) for k, v in fresh.state_dict().items())


@pytest.mark.parametrize("damage", ["truncate", "flip_data", "garbage", "empty", "header_json"])
def test_corrupt_files_are_rejected(tmp_path: Path, damage: str) -> None:
    model, opt = _trained()
    path = save_checkpoint(tmp_path / "c.safetensors", model, opt, step=3, epoch=1)
    data = bytearray(path.read_bytes())
    if damage == "truncate":
        data = data[: len(data) // 2]
    elif damage == "flip_data":
        data[-10] ^= 0xFF
    elif damage == "garbage":
        data = bytearray(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    elif damage == "empty":
        data = bytearray()
    elif damage == "header_json":
        data[9] = ord("!")
    path.write_bytes(bytes(data))
    with pytest.raises(CheckpointError) as exc:
        load_checkpoint(path, BottleneckNetwork(CFG))
    _assert_one_line_naming(exc, path)


def test_foreign_and_missing_files_are_rejected(tmp_path: Path) -> None:
    foreign = tmp_path / "foreign.safetensors"
    save_file({"w": torch.zeros(3)}, str(foreign))
    with pytest.raises(CheckpointError, match="not a latentdrive checkpoint") as exc:
        load_checkpoint(foreign, BottleneckNetwork(CFG))
    _assert_one_line_naming(exc, foreign)
    missing = tmp_path / "missing.safetensors"
    with pytest.raises(CheckpointError, match="cannot read") as exc:
        load_checkpoint(missing, BottleneckNetwork(CFG))
    _assert_one_line_naming(exc, missing)


def test_missing_optimizer_or_rng_state_is_an_error(tmp_path: Path) -> None:
    model, _ = _trained(steps=0)
    path = save_checkpoint(tmp_path / "c.safetensors", model, step=0, epoch=0)
    with pytest.raises(CheckpointError, match="no optimizer state"):
        load_checkpoint(path, model, torch.optim.AdamW(model.parameters()))
    with pytest.raises(CheckpointError, match="no torch generator state"):
        load_checkpoint(path, model, torch_generator=torch.Generator())


def test_writes_are_atomic(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    model, opt = _trained()
    path = save_checkpoint(tmp_path / "c.safetensors", model, opt, step=3, epoch=1)
    original = path.read_bytes()
    assert os.listdir(tmp_path) == ["c.safetensors"]

    def broken_replace(src: str, dst: str) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(fileio.os, "replace", broken_replace)
    _one_more_step(model, opt)
    with pytest.raises(OSError, match="disk full"):
        save_checkpoint(path, model, opt, step=4, epoch=2)
    # The old checkpoint is intact and no temporary file is left behind.
    assert path.read_bytes() == original
    assert os.listdir(tmp_path) == ["c.safetensors"]


def test_loading_never_unpickles(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    model, opt = _trained()
    path = save_checkpoint(tmp_path / "c.safetensors", model, opt, step=3, epoch=1)
    data = path.read_bytes()
    # The file is safetensors (a header length, then a JSON header, then raw tensor bytes),
    # neither torch.save's zip archive nor a pickle stream.
    n = int.from_bytes(data[:8], "little")
    assert data[8:9] == b"{" and isinstance(json.loads(data[8 : 8 + n]), dict)
    assert not data.startswith((b"PK", b"\x80"))

    calls: list[str] = []

    def forbidden(name: str):
        def call(*args: object, **kwargs: object) -> None:
            calls.append(name)
            raise AssertionError(f"{name} must not be used")

        return call

    class NoUnpickler:
        def __init__(self, *args: object, **kwargs: object) -> None:
            calls.append("pickle.Unpickler")
            raise AssertionError("pickle.Unpickler must not be used")

    pickle_load = torch.load
    monkeypatch.setattr(torch, "load", forbidden("torch.load"))
    monkeypatch.setattr(pickle, "load", forbidden("pickle.load"))
    monkeypatch.setattr(pickle, "loads", forbidden("pickle.loads"))
    monkeypatch.setattr(pickle, "Unpickler", NoUnpickler)
    # The trap catches a pickle-based load ...
    buf = io.BytesIO()
    torch.save(model.state_dict(), buf)
    with pytest.raises(AssertionError):
        pickle_load(io.BytesIO(buf.getvalue()), weights_only=False)
    assert calls == ["pickle.Unpickler"]
    calls.clear()
    # ... and loading a checkpoint springs none of it, yet restores the weights.
    fresh = BottleneckNetwork(CFG)
    info = load_checkpoint(path, fresh, torch.optim.AdamW(fresh.parameters()))
    assert calls == []
    assert info.step == 3 and info.epoch == 1
    for name, value in model.state_dict().items():
        assert torch.equal(fresh.state_dict()[name], value), name


def _rewrite_metadata(path: Path, change: Callable[[dict[str, str]], None]) -> None:
    """Rewrite a safetensors file's metadata through ``change``, keeping its tensors."""
    data = path.read_bytes()
    n = int.from_bytes(data[:8], "little")
    header = json.loads(data[8 : 8 + n])
    change(header["__metadata__"])
    raw = json.dumps(header, separators=(",", ":")).encode()
    raw += b" " * (-len(raw) % 8)
    path.write_bytes(len(raw).to_bytes(8, "little") + raw + data[8 + n :])


def _set_state(key: str, value: object) -> Callable[[dict[str, str]], None]:
    def change(meta: dict[str, str]) -> None:
        state = json.loads(meta["state"])
        state[key] = value
        meta["state"] = json.dumps(state, sort_keys=True)

    return change


@pytest.mark.parametrize(("key", "value"), [("step", 4), ("epoch", 0), ("config", {"lr": 1.0})])
def test_tampering_with_the_json_state_is_detected(tmp_path: Path, key: str, value: object) -> None:
    model, opt = _trained()
    path = save_checkpoint(tmp_path / "c.safetensors", model, opt, step=3, epoch=1, config={"lr": 0.01})
    # Rewriting the metadata unchanged keeps the file loadable: what follows is the change.
    _rewrite_metadata(path, lambda meta: None)
    assert load_checkpoint(path, BottleneckNetwork(CFG)).step == 3
    _rewrite_metadata(path, _set_state(key, value))
    with pytest.raises(CheckpointError, match="checksum mismatch") as exc:
        load_checkpoint(path, BottleneckNetwork(CFG))
    _assert_one_line_naming(exc, path)


def test_version_1_files_are_still_read(tmp_path: Path) -> None:
    """Files written before the digest covered the state (version 1) load as before."""
    model, opt = _trained()
    path = save_checkpoint(tmp_path / "c.safetensors", model, opt, step=3, epoch=1)
    tensors, _ = read_checkpoint(path)

    def to_v1(meta: dict[str, str]) -> None:
        meta["version"] = "1"
        meta["digest"] = ckpt_mod._digest(tensors, None)

    _rewrite_metadata(path, to_v1)
    fresh = BottleneckNetwork(CFG)
    assert load_checkpoint(path, fresh, torch.optim.AdamW(fresh.parameters())).step == 3
    _rewrite_metadata(path, lambda meta: meta.update(version="3"))
    with pytest.raises(CheckpointError, match="format version '3'"):
        load_checkpoint(path, fresh)


def test_an_oversized_header_is_refused_before_reading_on(tmp_path: Path) -> None:
    path = tmp_path / "c.safetensors"
    path.write_bytes((200_000_000).to_bytes(8, "little") + b"{" + b" " * 1000)
    with pytest.raises(CheckpointError, match="bad header length") as exc:
        read_checkpoint(path)
    _assert_one_line_naming(exc, path)


@pytest.fixture(scope="module")
def saved(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("saved") / "c.safetensors"
    return save_checkpoint(path, *_trained(steps=1), step=1, epoch=1, config={"a": 1}, extra={"b": [1, 2]})


@settings(max_examples=examples(40), deadline=None)
@given(data=st.data())
def test_any_damage_is_an_error_or_changes_nothing(saved: Path, data: st.DataObject) -> None:
    """Flipped bytes anywhere in the file: a CheckpointError, or (a flip that turns header
    padding into other whitespace) exactly the saved tensors and state."""
    original = saved.read_bytes()
    damaged = bytearray(original)
    for _ in range(data.draw(st.integers(1, 3), label="flips")):
        i = data.draw(st.integers(0, len(damaged) - 1), label="offset")
        damaged[i] ^= data.draw(st.integers(1, 255), label="mask")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "c.safetensors"
        path.write_bytes(bytes(damaged))
        try:
            tensors, state = read_checkpoint(path)
        except CheckpointError as exc:
            assert "\n" not in str(exc) and str(exc).startswith(str(path))
            return
    want_tensors, want_state = read_checkpoint(saved)
    assert state == want_state
    assert tensors.keys() == want_tensors.keys()
    assert all(torch.equal(tensors[k], want_tensors[k]) for k in tensors)



def test_a_second_optimizer_over_the_same_weights_round_trips_by_name(tmp_path: Path) -> None:
    model, opt = _trained()
    aux = torch.optim.Adam(model.parameters(), lr=3e-3)
    _one_more_step(model, aux)
    path = save_checkpoint(tmp_path / "c.safetensors", model, opt, step=3, epoch=0, extra_optimizers={"aux": aux})
    model2 = BottleneckNetwork(CFG)
    opt2 = torch.optim.AdamW(model2.parameters(), lr=1.0)
    aux2 = torch.optim.Adam(model2.parameters(), lr=1.0)
    load_checkpoint(path, model2, opt2, extra_optimizers={"aux": aux2})
    assert aux2.param_groups[0]["lr"] == 3e-3 and opt2.param_groups[0]["lr"] == 1e-2
    # Each optimizer continues as its original does: the moments were not mixed up.
    for o, m in ((aux, model), (opt, model)):
        _one_more_step(m, o)
    for o, m in ((aux2, model2), (opt2, model2)):
        _one_more_step(m, o)
    for t1, t2 in zip(model.parameters(), model2.parameters(), strict=True):
        assert torch.equal(t1, t2)


def test_an_optimizer_the_checkpoint_lacks_is_named(tmp_path: Path) -> None:
    model, opt = _trained(steps=1)
    path = save_checkpoint(tmp_path / "c.safetensors", model, opt, step=1, epoch=0)
    aux = torch.optim.Adam(model.parameters())
    with pytest.raises(CheckpointError, match="no state of optimizer 'aux'") as exc:
        load_checkpoint(path, model, opt, extra_optimizers={"aux": aux})
    _assert_one_line_naming(exc, path)
    with pytest.raises(ValueError, match="letters, digits"):
        save_checkpoint(tmp_path / "d.safetensors", model, opt, step=1, epoch=0, extra_optimizers={"a/b": aux})
