"""Read a collected observation dataset and stream shuffled, scenario-mixed training batches.

:class:`ShardDataset` checks a dataset directory written by
:func:`latentdrive.data.collect.collect` and streams its shards: a few at a time, never the
whole set, through shuffle buffers, into :class:`~latentdrive.bnn.batch.BNNBatch` es of
float32 tensors in [0, 1].

This module imports neither the simulator nor the env, so training processes that only
read data do not load highway-env.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from numpy.typing import NDArray

from latentdrive.bnn.batch import BNNBatch
from latentdrive.data.shards import MANIFEST, DatasetError, read_manifest, read_shard
from latentdrive.fileio import confined

__all__ = ["DatasetError", "ShardDataset"]

IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class _Shard:
    name: str
    path: Path
    scenario: int
    first_episode: int
    episode_samples: IntArray  # (episodes,) samples of each episode, in episode order
    samples: int
    sha256: str
    size: int  # bytes, as recorded in the manifest

    @property
    def episode_ids(self) -> IntArray:
        return self.first_episode + np.arange(self.episode_samples.shape[0], dtype=np.int64)


class ShardDataset:
    """A collected dataset: ``root/manifest.json`` plus its shards.

    Opening checks the manifest (present, parseable, this format), that every shard it
    lists exists with the recorded size, and, unless ``allow_incomplete``, that collection
    finished. ``verify=True`` also loads every shard once and checks its contents (see
    :meth:`verify`); otherwise each shard is checked (sha256, arrays, dtypes, shapes,
    config hash, episode counts) every time it is loaded. Every failure is a
    :class:`DatasetError` whose message names the file.

    Attributes:
        root: the dataset directory.
        config_hash: hash of the collect config that wrote it.
        scenario_names: scenario labels: a sample's ``scenario`` id indexes this tuple.
        sample_shape: ``(4, T, H, W)`` of one observation.
    """

    def __init__(self, root: str | Path, *, allow_incomplete: bool = False, verify: bool = False) -> None:
        self.root = Path(root)
        m = read_manifest(self.root)
        self.manifest: dict[str, Any] = m
        self.config_hash: str = str(m["config_hash"])
        self.scenario_names: tuple[str, ...] = tuple(m["scenarios"])
        self.sample_shape: tuple[int, int, int, int] = tuple(int(v) for v in m["sample_shape"])  # type: ignore[assignment]
        done = m["shards"]
        pending = [u["name"] for u in m["units"] if u["name"] not in done]
        if pending and not allow_incomplete:
            raise DatasetError(
                f"{self.root}: collection is unfinished ({len(pending)} of {len(m['units'])} "
                "shards missing); rerun the same collect command to finish it")
        self._shards: list[_Shard] = []
        for u in m["units"]:
            entry = done.get(u["name"])
            if entry is None:
                continue
            path = confined(self.root, u["name"], source=self.root / MANIFEST, error=DatasetError)
            try:
                size = path.stat().st_size
            except FileNotFoundError:
                raise DatasetError(f"{path}: shard listed in the manifest is missing") from None
            if size != int(entry["bytes"]):
                raise DatasetError(f"{path}: shard is corrupt (size {size} bytes, the manifest says {entry['bytes']})")
            self._shards.append(_Shard(
                name=u["name"], path=path, scenario=int(u["scenario"]),
                first_episode=int(u["first_episode"]),
                episode_samples=np.asarray(entry["episode_samples"], dtype=np.int64),
                samples=int(entry["samples"]), sha256=str(entry["sha256"]), size=int(entry["bytes"])))
        self._episode_scenario: dict[int, int] = {}
        for sh in self._shards:
            for ep in sh.episode_ids.tolist():
                self._episode_scenario[ep] = sh.scenario
        if verify:
            self.verify()

    def __len__(self) -> int:
        """Number of samples (one per AV per recorded step)."""
        return sum(s.samples for s in self._shards)

    def __repr__(self) -> str:
        return (f"ShardDataset({str(self.root)!r}: {len(self)} samples of {self.sample_shape}, "
                f"{len(self._episode_scenario)} episodes, {len(self._shards)} shards, "
                f"scenarios {list(self.scenario_names)})")

    @property
    def shard_names(self) -> list[str]:
        """File names of the shards, in manifest order."""
        return [s.name for s in self._shards]

    @property
    def observation(self) -> dict[str, Any] | None:
        """The observation settings (an :class:`~latentdrive.config.ObservationConfig`
        dump, as the manifest's ``env_configs`` hold it) every scenario's maps were drawn
        with; None when they differ between scenarios."""
        dumps = [e.get("observation") for e in self.manifest["env_configs"]]
        first = dumps[0] if dumps else None
        return first if isinstance(first, dict) and all(d == first for d in dumps) else None

    @property
    def episode_ids(self) -> IntArray:
        """``(n_episodes,)`` sorted global episode ids."""
        return np.array(sorted(self._episode_scenario), dtype=np.int64)

    def episode_scenario(self, episodes: Iterable[int]) -> IntArray:
        """Scenario id of each episode id, ``(len(episodes),)`` int64."""
        return np.array([self._episode_scenario[int(e)] for e in episodes], dtype=np.int64)

    def num_samples(self, episodes: Iterable[int] | None = None) -> int:
        """Samples in ``episodes`` (all when None), from the manifest without loading shards."""
        sel = self._selection(episodes)
        return sum(int(s.episode_samples[self._shard_mask(s, sel)].sum()) for s in self._shards)

    def split_by_episode(self, val_fraction: float, seed: int = 0) -> tuple[IntArray, IntArray]:
        """Split episode ids into ``(train_ids, val_ids)``, sorted int64 arrays.

        Whole episodes go to one side, so consecutive, nearly identical frames never
        straddle the split. The split is drawn per scenario (``round(val_fraction · n)`` of
        its ``n`` episodes, at least one on each side when ``0 < val_fraction`` and
        ``n ≥ 2``), so validation holds every scenario; it depends only on ``seed``.
        """
        if not 0.0 <= val_fraction < 1.0:
            raise ValueError(f"val_fraction must be in [0, 1), got {val_fraction}")
        rng = np.random.default_rng(seed)
        ids = self.episode_ids
        scen = self.episode_scenario(ids)
        train, val = [], []
        for s in range(len(self.scenario_names)):
            own = rng.permutation(ids[scen == s])
            n = own.shape[0]
            n_val = round(val_fraction * n)
            if val_fraction > 0 and n >= 2:
                n_val = min(max(n_val, 1), n - 1)
            val.append(own[:n_val])
            train.append(own[n_val:])
        return (np.sort(np.concatenate(train)).astype(np.int64),
                np.sort(np.concatenate(val)).astype(np.int64))

    def load_shard(self, name: str) -> dict[str, np.ndarray]:
        """The arrays of one shard (uint8 images, int64 indices), fully checked."""
        for s in self._shards:
            if s.name == name:
                return self._load(s)
        raise KeyError(f"no shard {name!r} in {self.root}")

    def verify(self) -> int:
        """Load every shard once and check it; returns the number of samples checked."""
        return sum(int(self._load(s)["noisy"].shape[0]) for s in self._shards)

    def _load(self, s: _Shard) -> dict[str, np.ndarray]:
        arrays = read_shard(s.path, sha256=s.sha256, config_hash=self.config_hash,
                            sample_shape=self.sample_shape, samples=s.samples, size=s.size)
        n_ep = s.episode_samples.shape[0]
        local = arrays["episode"] - s.first_episode
        if (arrays["scenario"] != s.scenario).any() or local.min(initial=0) < 0 or local.max(initial=0) >= max(n_ep, 1):
            raise DatasetError(f"{s.path}: scenario or episode ids do not match the manifest")
        if not np.array_equal(np.bincount(local, minlength=n_ep), s.episode_samples):
            raise DatasetError(f"{s.path}: per-episode sample counts do not match the manifest")
        return arrays

    def _selection(self, episodes: Iterable[int] | None) -> IntArray | None:
        if episodes is None:
            return None
        raw = episodes if isinstance(episodes, np.ndarray) else list(episodes)
        sel = np.unique(np.asarray(raw, dtype=np.int64))
        unknown = [int(e) for e in sel if int(e) not in self._episode_scenario]
        if unknown:
            raise ValueError(f"{len(unknown)} episode ids are not in {self.root} (first: {unknown[0]})")
        return sel

    @staticmethod
    def _shard_mask(s: _Shard, sel: IntArray | None) -> NDArray[np.bool_]:
        ids = s.episode_ids
        return np.ones(ids.shape[0], dtype=bool) if sel is None else np.isin(ids, sel)

    def batches(
        self,
        batch_size: int,
        episodes: Iterable[int] | None = None,
        *,
        seed: int = 0,
        epoch: int = 0,
        mixed: bool = True,
        device: torch.device | str | None = None,
        shuffle_buffer: int = 2048,
        drop_last: bool = False,
    ) -> Iterator[BNNBatch]:
        """One epoch of shuffled batches over the samples of ``episodes`` (all when None).

        Every selected sample appears exactly once per epoch (the last batch is smaller
        unless ``drop_last``, which drops it). The order depends only on ``(seed, epoch)``.

        Shuffling: the shards of a stream are read in a random order, one at a time, into a
        shuffle buffer of about ``shuffle_buffer`` samples (split evenly among the
        streams) from which batches draw uniformly at random; consecutive samples of a
        shard (the steps of one episode) are thereby scattered over roughly
        ``shuffle_buffer`` samples' worth of batches.

        ``mixed=True`` keeps one stream per scenario and fills each batch from all of
        them in proportion to the samples each has left (largest remainder, and at least
        one per scenario that still has samples when ``batch_size`` allows). The streams
        thus run out together: every batch holds every scenario as long as each scenario
        has at least as many samples as there are batches. ``mixed=False`` uses a single
        stream over all shards, so a batch may hold one scenario only.

        Memory: the buffers hold at most ``(shuffle_buffer + S·batch_size + S·shard)``
        samples of ``2·4·T·H·W`` bytes (uint8 noisy and clean), for ``S`` streams and the
        largest shard's sample count; loading a shard adds that shard once more while
        it is copied in, and a batch takes ``batch_size · 2·4·T·H·W · 4`` bytes as float32.

        Yields:
            :class:`BNNBatch` ``(noisy, clean, scenario)``: ``(B, 4, T, H, W)`` float32 in
            [0, 1] (dequantized uint8, so within 1/510 of the collected values) twice and
            ``(B,)`` int64, on ``device`` when given.
        """
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        if shuffle_buffer < 1:
            raise ValueError(f"shuffle_buffer must be >= 1, got {shuffle_buffer}")
        sel = self._selection(episodes)
        groups: list[list[tuple[_Shard, NDArray[np.bool_]]]] = []
        keys = range(len(self.scenario_names)) if mixed else [None]
        for key in keys:
            group = []
            for s in self._shards:
                if key is not None and s.scenario != key:
                    continue
                ep_mask = self._shard_mask(s, sel)
                if s.episode_samples[ep_mask].sum() > 0:
                    group.append((s, ep_mask))
            if group:
                groups.append(group)
        if not groups:
            return
        seeds = np.random.SeedSequence([seed, epoch]).spawn(len(groups) + 1)
        rng = np.random.default_rng(seeds[0])
        per_stream = max(1, shuffle_buffer // len(groups))
        streams = [_ShuffleStream(self, g, np.random.default_rng(ss), per_stream, batch_size)
                   for g, ss in zip(groups, seeds[1:], strict=True)]
        remaining = np.array([st.remaining for st in streams], dtype=np.int64)
        while remaining.sum() > 0:
            b = int(min(batch_size, remaining.sum()))
            if drop_last and b < batch_size:
                return
            quota = _quotas(b, remaining)
            parts = [st.take(int(q)) for st, q in zip(streams, quota, strict=True) if q > 0]
            remaining -= quota
            noisy = np.concatenate([p[0] for p in parts])
            clean = np.concatenate([p[1] for p in parts])
            scen = np.concatenate([p[2] for p in parts])
            # Streams fill the batch one after the other; permute so that no position in
            # the batch is tied to a scenario.
            perm = rng.permutation(b)
            batch = BNNBatch(_to_float(noisy[perm]), _to_float(clean[perm]), torch.from_numpy(scen[perm]))
            yield batch.to(device) if device is not None else batch

    def batches_fn(
        self,
        batch_size: int,
        episodes: Iterable[int] | None = None,
        *,
        seed: int = 0,
        mixed: bool = True,
        device: torch.device | str | None = None,
        shuffle_buffer: int = 2048,
        drop_last: bool = False,
    ) -> Callable[[int], Iterator[BNNBatch]]:
        """``batches_fn(epoch)`` for :func:`latentdrive.bnn.train.train_bnn`: :meth:`batches` of that epoch."""
        ids = None if episodes is None else np.asarray(list(episodes), dtype=np.int64)

        def fn(epoch: int) -> Iterator[BNNBatch]:
            return self.batches(batch_size, ids, seed=seed, epoch=epoch, mixed=mixed, device=device,
                                shuffle_buffer=shuffle_buffer, drop_last=drop_last)

        return fn


def _to_float(q: NDArray[np.uint8]) -> torch.Tensor:
    """uint8 ``q`` as float32 ``q / 255`` (the inverse of the collector's quantization)."""
    # One numpy pass; torch's uint8→float32 cast followed by an in-place divide measured
    # about 2.5× slower on CPU.
    return torch.from_numpy(np.divide(q, np.float32(255.0), dtype=np.float32))


def _quotas(b: int, remaining: IntArray) -> IntArray:
    """Split ``b`` batch slots among streams in proportion to their ``remaining`` samples.

    Largest-remainder rounding (ties to the lower index); then, when ``b`` is at least the
    number of streams with samples left, every such stream gets at least one slot. The
    result never exceeds ``remaining`` and sums to ``b`` (``b ≤ remaining.sum()``).
    """
    total = int(remaining.sum())
    q = (b * remaining) // total
    frac = (b * remaining) % total
    left = b - int(q.sum())
    order = np.lexsort((np.arange(remaining.shape[0]), -frac))
    q[order[:left]] += 1
    active = remaining > 0
    if b >= int(active.sum()):
        for s in np.flatnonzero(active & (q == 0)):
            donor = int(np.argmax(q))  # holds >= 2: b >= #active slots with some stream at 0
            q[donor] -= 1
            q[s] += 1
    return q


class _ShuffleStream:
    """Samples of some shards in random order, through a bounded shuffle buffer."""

    def __init__(self, ds: ShardDataset, shards: list[tuple[_Shard, NDArray[np.bool_]]],
                 rng: np.random.Generator, capacity: int, batch_size: int) -> None:
        self._ds = ds
        self._rng = rng
        self._queue = [shards[i] for i in rng.permutation(len(shards))]
        self._next = 0
        self.remaining = int(sum(int(s.episode_samples[m].sum()) for s, m in shards))
        self._capacity = capacity
        # Room for the buffer, a batch's worth beyond it, and one more shard loaded in.
        largest = max(int(s.episode_samples[m].sum()) for s, m in shards)
        self._size = max(capacity, batch_size) + largest
        self._noisy: NDArray[np.uint8] | None = None
        self._clean: NDArray[np.uint8] | None = None
        self._scen = np.zeros(self._size, dtype=np.int64)
        self._n = 0

    def _fill(self, want: int) -> None:
        while self._n < max(self._capacity, want) and self._next < len(self._queue):
            s, ep_mask = self._queue[self._next]
            self._next += 1
            arrays = self._ds._load(s)
            keep = np.isin(arrays["episode"], s.episode_ids[ep_mask])
            k = int(keep.sum())
            if self._noisy is None or self._clean is None:
                self._noisy = np.empty((self._size, *self._ds.sample_shape), dtype=np.uint8)
                self._clean = np.empty_like(self._noisy)
            end = self._n + k
            self._noisy[self._n:end] = arrays["noisy"][keep]
            self._clean[self._n:end] = arrays["clean"][keep]
            self._scen[self._n:end] = arrays["scenario"][keep]
            self._n = end

    def take(self, k: int) -> tuple[NDArray[np.uint8], NDArray[np.uint8], IntArray]:
        """``k`` samples drawn uniformly from the buffer (``k`` ≤ samples left)."""
        self._fill(k)
        assert self._noisy is not None and self._clean is not None and k <= self._n
        n = self._n
        idx = self._rng.choice(n, size=k, replace=False)
        out = (self._noisy[idx], self._clean[idx], self._scen[idx])
        # Close the holes with the surviving samples from the end of the buffer.
        holes = np.sort(idx[idx < n - k])
        tail = np.setdiff1d(np.arange(n - k, n), idx, assume_unique=True)
        self._noisy[holes] = self._noisy[tail]
        self._clean[holes] = self._clean[tail]
        self._scen[holes] = self._scen[tail]
        self._n = n - k
        self.remaining -= k
        return out
