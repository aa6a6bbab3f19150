from __future__ import annotations

import hashlib
import io
import json
import re
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import torch

from latentdrive.bnn.batch import BNNBatch
from latentdrive.data.dataset import ShardDataset, _quotas
from latentdrive.data.shards import MANIFEST, DatasetError, dequantize, write_shard

_UNPICKLED: list[str] = []


class _Bomb:
    """Records it if anything ever unpickles it."""

    def __reduce__(self) -> tuple[object, tuple[str]]:
        return (_UNPICKLED.append, ("unpickled",))


def first_shard(root: Path) -> Path:
    return root / json.loads((root / MANIFEST).read_text())["units"][0]["name"]


def replace_shard(path: Path, data: bytes) -> None:
    """Overwrite a shard and record the new file in the manifest, as a forger would."""
    path.write_bytes(data)
    m = json.loads((path.parent / MANIFEST).read_text())
    m["shards"][path.name].update(sha256=hashlib.sha256(data).hexdigest(), bytes=len(data))
    (path.parent / MANIFEST).write_text(json.dumps(m))


def npz_bytes(**arrays: object) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)  # type: ignore[arg-type]
    return buf.getvalue()


def sample_keys(noisy: torch.Tensor, clean: torch.Tensor) -> list[bytes]:
    """One identity per sample: its quantized noisy and clean bytes."""
    qn = torch.round(noisy * 255).to(torch.uint8).numpy()
    qc = torch.round(clean * 255).to(torch.uint8).numpy()
    return [hashlib.sha1(a.tobytes() + b.tobytes()).digest() for a, b in zip(qn, qc, strict=True)]


def stored_keys(ds: ShardDataset, episodes: np.ndarray | None = None) -> Counter[bytes]:
    keys: Counter[bytes] = Counter()
    for name in ds.shard_names:
        a = ds.load_shard(name)
        keep = np.ones(a["episode"].shape, bool) if episodes is None else np.isin(a["episode"], episodes)
        keys.update(sample_keys(torch.from_numpy(dequantize(a["noisy"][keep])),
                                torch.from_numpy(dequantize(a["clean"][keep]))))
    return keys


def test_open_reports_size_shape_and_scenarios(collected: Path) -> None:
    ds = ShardDataset(collected, verify=True)
    m = json.loads((collected / MANIFEST).read_text())
    assert len(ds) == sum(e["samples"] for e in m["shards"].values()) == ds.num_samples() > 0
    assert ds.sample_shape == (4, 2, 16, 32)
    assert ds.scenario_names == ("merge", "highway")
    assert ds.episode_ids.tolist() == list(range(12))
    assert ds.verify() == len(ds)


def test_missing_or_corrupt_manifest(dataset_copy: Path, tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match=f"{tmp_path / 'nowhere' / MANIFEST}: no dataset manifest"):
        ShardDataset(tmp_path / "nowhere")
    (dataset_copy / MANIFEST).write_text("{ not json")
    with pytest.raises(DatasetError, match=f"{dataset_copy / MANIFEST}: dataset manifest is not valid JSON"):
        ShardDataset(dataset_copy)
    (dataset_copy / MANIFEST).write_text(json.dumps({"format": "something else"}))
    with pytest.raises(DatasetError, match="not a latentdrive dataset manifest"):
        ShardDataset(dataset_copy)


@pytest.mark.parametrize(("unit_key", "shard_key", "value", "needle"), [
    ("first_episode", None, 10**30, "first_episode must be an integer >= 0 and < 2**62, got 1000000000000000000000000000000"),
    ("first_episode", None, 2**62, "first_episode must be an integer >= 0 and < 2**62"),
    ("episodes", None, 10**30, "episodes must be an integer >= 1 and < 2**62"),
    (None, "episode_samples", 10**30, "an episode's samples must be an integer >= 0 and < 2**62"),
])
def test_counts_beyond_int64_are_one_line(dataset_copy: Path, unit_key: str | None, shard_key: str | None,
                                           value: object, needle: str) -> None:
    # Regression: a huge first episode id was an OverflowError from numpy, not a DatasetError.
    m = json.loads((dataset_copy / MANIFEST).read_text())
    unit = m["units"][0]
    if unit_key is not None:
        unit[unit_key] = value
    else:
        m["shards"][unit["name"]][shard_key][0] = value  # the first episode's count
    (dataset_copy / MANIFEST).write_text(json.dumps(m))
    with pytest.raises(DatasetError, match=re.escape(needle)) as exc:
        ShardDataset(dataset_copy)
    assert str(exc.value).startswith(str(dataset_copy / MANIFEST)) and "\n" not in str(exc.value)


def test_missing_shard_is_named(dataset_copy: Path) -> None:
    victim = first_shard(dataset_copy)
    victim.unlink()
    with pytest.raises(DatasetError, match=f"{victim}: shard listed in the manifest is missing"):
        ShardDataset(dataset_copy)


def test_unfinished_collection(dataset_copy: Path) -> None:
    m = json.loads((dataset_copy / MANIFEST).read_text())
    name = m["units"][0]["name"]
    del m["shards"][name]
    (dataset_copy / MANIFEST).write_text(json.dumps(m))
    with pytest.raises(DatasetError, match="unfinished"):
        ShardDataset(dataset_copy)
    ds = ShardDataset(dataset_copy, allow_incomplete=True)
    assert name not in ds.shard_names and len(ds) > 0


def test_truncated_and_flipped_shards_are_named(dataset_copy: Path) -> None:
    victim = first_shard(dataset_copy)
    data = victim.read_bytes()
    victim.write_bytes(data[: len(data) // 2])
    with pytest.raises(DatasetError, match=f"{victim}: shard is corrupt \\(size"):
        ShardDataset(dataset_copy)
    flipped = bytearray(data)
    flipped[len(data) // 2] ^= 0xFF
    victim.write_bytes(bytes(flipped))
    ds = ShardDataset(dataset_copy)  # same size: found when the shard is read
    with pytest.raises(DatasetError, match=f"{victim}: shard is corrupt \\(sha256"):
        ds.verify()
    with pytest.raises(DatasetError, match=str(victim)):
        list(ds.batches(8))
    with pytest.raises(DatasetError, match=str(victim)):
        ShardDataset(dataset_copy, verify=True)


def test_bad_zip_is_named(dataset_copy: Path) -> None:
    victim = first_shard(dataset_copy)
    replace_shard(victim, b"this is not a zip file at all")
    with pytest.raises(DatasetError, match=f"{victim}: shard is corrupt"):
        ShardDataset(dataset_copy, verify=True)


def test_foreign_npz_is_refused(dataset_copy: Path) -> None:
    victim = first_shard(dataset_copy)
    replace_shard(victim, npz_bytes(weights=np.zeros(3), bias=np.ones(2)))
    with pytest.raises(DatasetError, match=f"{victim}: not a shard of this format"):
        ShardDataset(dataset_copy, verify=True)


def test_pickled_arrays_are_never_unpickled(dataset_copy: Path) -> None:
    victim = first_shard(dataset_copy)
    ds = ShardDataset(dataset_copy)
    arrays = dict(ds.load_shard(victim.name))
    arrays["noisy"] = np.array([_Bomb()], dtype=object)
    buf = io.BytesIO()
    np.savez(buf, allow_pickle=True, **arrays)
    replace_shard(victim, buf.getvalue())
    with pytest.raises(DatasetError, match=str(victim)):
        ShardDataset(dataset_copy, verify=True)
    assert _UNPICKLED == []


@pytest.mark.parametrize("change", ["shape", "dtype", "config", "episodes"])
def test_wrong_arrays_are_named(dataset_copy: Path, change: str) -> None:
    victim = first_shard(dataset_copy)
    arrays = dict(ShardDataset(dataset_copy).load_shard(victim.name))
    if change == "shape":
        arrays["clean"] = arrays["clean"][:, :, :, :8]
        match = "array 'clean'"
    elif change == "dtype":
        arrays["noisy"] = dequantize(arrays["noisy"])
        match = "array 'noisy' is float32"
    elif change == "config":  # a shard from another dataset
        arrays["config_hash"] = np.array("0123456789abcdef")
        match = "belongs to config '0123456789abcdef'"
    else:
        arrays["episode"] = arrays["episode"] + 1
        match = "do not match the manifest"
    write_shard(victim, arrays)
    replace_shard(victim, victim.read_bytes())
    with pytest.raises(DatasetError, match=f"{victim}: .*{match}"):
        ShardDataset(dataset_copy, verify=True)


def test_split_by_episode(collected: Path) -> None:
    ds = ShardDataset(collected)
    train, val = ds.split_by_episode(0.34, seed=0)
    assert not set(train.tolist()) & set(val.tolist())
    assert sorted([*train.tolist(), *val.tolist()]) == ds.episode_ids.tolist()
    assert set(ds.episode_scenario(val).tolist()) == {0, 1}  # every scenario validated
    assert len(val) == 4  # round(0.34 · 6) per scenario
    again = ds.split_by_episode(0.34, seed=0)
    assert np.array_equal(train, again[0]) and np.array_equal(val, again[1])
    others = {tuple(ds.split_by_episode(0.34, seed=s)[1].tolist()) for s in range(10)}
    assert len(others) > 1
    assert len(ds.split_by_episode(0.0)[1]) == 0
    with pytest.raises(ValueError, match="val_fraction"):
        ds.split_by_episode(1.0)


def test_batches_are_mixed_shuffled_and_cover_every_sample_once(collected: Path) -> None:
    ds = ShardDataset(collected)
    batches = list(ds.batches(16, seed=0, epoch=0))
    assert all(isinstance(b, BNNBatch) for b in batches)
    assert sum(len(b.scenario) for b in batches) == len(ds)
    assert len(batches) == -(-len(ds) // 16)
    for b in batches:
        assert b.noisy.dtype == b.clean.dtype == torch.float32 and b.scenario.dtype == torch.int64
        assert b.noisy.shape[1:] == (4, 2, 16, 32) and b.clean.shape == b.noisy.shape
        assert 0.0 <= float(b.noisy.min()) and float(b.noisy.max()) <= 1.0
        assert set(b.scenario.tolist()) == {0, 1}  # every batch holds both scenarios
    got = [k for b in batches for k in sample_keys(b.noisy, b.clean)]
    assert Counter(got) == stored_keys(ds)
    in_storage_order = [k for name in ds.shard_names for k in sample_keys(
        torch.from_numpy(dequantize(ds.load_shard(name)["noisy"])),
        torch.from_numpy(dequantize(ds.load_shard(name)["clean"])))]
    assert got != in_storage_order


def test_batches_are_deterministic_per_seed_and_epoch(collected: Path) -> None:
    ds = ShardDataset(collected)

    def keys(seed: int, epoch: int) -> list[bytes]:
        return [k for b in ds.batches(16, seed=seed, epoch=epoch) for k in sample_keys(b.noisy, b.clean)]

    a = list(ds.batches(16, seed=3, epoch=1))
    b = list(ds.batches(16, seed=3, epoch=1))
    assert all(torch.equal(x.noisy, y.noisy) and torch.equal(x.clean, y.clean)
               and torch.equal(x.scenario, y.scenario) for x, y in zip(a, b, strict=True))
    assert keys(3, 1) != keys(3, 2) and keys(3, 1) != keys(4, 1)
    fn = ds.batches_fn(16, seed=3)
    assert [k for x in fn(1) for k in sample_keys(x.noisy, x.clean)] == keys(3, 1)


def test_batches_of_an_episode_subset(collected: Path) -> None:
    ds = ShardDataset(collected)
    train, val = ds.split_by_episode(0.34, seed=0)
    for ids in (train, val):
        got = Counter(k for b in ds.batches(7, ids, seed=1) for k in sample_keys(b.noisy, b.clean))
        assert got == stored_keys(ds, ids)
        assert sum(got.values()) == ds.num_samples(ids)
    with pytest.raises(ValueError, match="not in"):
        next(ds.batches(8, [999]))


@pytest.mark.parametrize(("mixed", "buffer", "drop_last"), [(False, 2048, False), (True, 1, False), (True, 5, True)])
def test_batch_options_keep_exact_coverage(collected: Path, mixed: bool, buffer: int, drop_last: bool) -> None:
    ds = ShardDataset(collected)
    batches = list(ds.batches(10, seed=2, mixed=mixed, shuffle_buffer=buffer, drop_last=drop_last, device="cpu"))
    sizes = [len(b.scenario) for b in batches]
    if drop_last:
        assert set(sizes) == {10} and len(batches) == len(ds) // 10
    else:
        assert sum(sizes) == len(ds)
        got = Counter(k for b in batches for k in sample_keys(b.noisy, b.clean))
        assert got == stored_keys(ds)


def test_quotas_are_proportional_exact_and_mixed() -> None:
    rng = np.random.default_rng(0)
    for _ in range(500):
        remaining = rng.integers(0, 50, size=int(rng.integers(1, 6)))
        if remaining.sum() == 0:
            continue
        b = int(rng.integers(1, remaining.sum() + 1))
        q = _quotas(b, remaining.copy())
        assert q.sum() == b and (q <= remaining).all() and (q >= 0).all()
        if b >= (remaining > 0).sum():
            assert (q[remaining > 0] >= 1).all()
    assert _quotas(10, np.array([30, 10, 0, 60])).tolist() == [3, 1, 0, 6]
