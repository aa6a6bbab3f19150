"""Batches for bottleneck-network training, and a batch source over in-memory arrays.

A :class:`BNNBatch` pairs noisy observations (the input) with the clean ones they were
made from (the denoising target) and the scenario id of each sample.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

__all__ = ["BNNBatch", "array_batches_fn", "iterate_batches", "synthetic_dataset"]


class BNNBatch(NamedTuple):
    """One training batch.

    - ``noisy``: ``(B, 4, T, H, W)`` float32 in [0, 1], observations with sensor noise q_D;
      the network's input.
    - ``clean``: ``(B, 4, T, H, W)`` float32 in [0, 1], the same observations without
      noise; the reconstruction target.
    - ``scenario``: ``(B,)`` int64 scenario ids (used by the latent regularizer).
    """

    noisy: Tensor
    clean: Tensor
    scenario: Tensor

    def to(self, device: torch.device | str) -> BNNBatch:
        """The batch on ``device`` (non-blocking copies)."""
        return BNNBatch(
            self.noisy.to(device, non_blocking=True),
            self.clean.to(device, non_blocking=True),
            self.scenario.to(device, non_blocking=True),
        )


def _order(scenario: np.ndarray, rng: np.random.Generator, stratified: bool) -> np.ndarray:
    n = scenario.shape[0]
    if not stratified:
        return rng.permutation(n)
    # Spread each scenario evenly over the epoch: its k-th (shuffled) sample gets the key
    # (k + u) / n_s with u ~ U(0, 1); sorting all keys interleaves the scenarios so that any
    # window of B samples holds about B·n_s/N of scenario s.
    keys = np.empty(n)
    idx_all = np.arange(n)
    for s in np.unique(scenario):
        idx = rng.permutation(idx_all[scenario == s])
        keys[idx] = (np.arange(idx.shape[0]) + rng.random(idx.shape[0])) / idx.shape[0]
    return np.argsort(keys, kind="stable")


def iterate_batches(
    clean: np.ndarray,
    noisy: np.ndarray,
    scenario: np.ndarray,
    batch_size: int,
    rng: np.random.Generator,
    *,
    stratified: bool = False,
    drop_last: bool = False,
) -> Iterator[BNNBatch]:
    """Shuffled batches over ``clean``, ``noisy`` ``(N, 4, T, H, W)`` and ``scenario`` ``(N,)``.

    ``stratified=True`` spreads every scenario evenly over the epoch, so each batch holds
    every scenario whenever ``batch_size · n_s / N ≥ 1`` (the "mixed" training phase).
    """
    if clean.shape != noisy.shape or clean.shape[0] != scenario.shape[0]:
        raise ValueError(
            f"inconsistent arrays: clean {clean.shape}, noisy {noisy.shape}, "
            f"scenario {scenario.shape}"
        )
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    order = _order(np.asarray(scenario), rng, stratified)
    n = order.shape[0]
    stop = n - n % batch_size if drop_last else n
    for start in range(0, stop, batch_size):
        idx = np.sort(order[start : start + batch_size])
        yield BNNBatch(
            torch.from_numpy(np.ascontiguousarray(noisy[idx], dtype=np.float32)),
            torch.from_numpy(np.ascontiguousarray(clean[idx], dtype=np.float32)),
            torch.from_numpy(np.asarray(scenario[idx], dtype=np.int64)),
        )


def array_batches_fn(
    clean: np.ndarray,
    noisy: np.ndarray,
    scenario: np.ndarray,
    *,
    batch_size: int,
    seed: int,
    stratify_from_epoch: int | None = 0,
    drop_last: bool = False,
) -> Callable[[int], Iterator[BNNBatch]]:
    """A ``batches_fn(epoch)`` for :func:`latentdrive.bnn.train.train_bnn` over in-memory arrays.

    Epoch ``e`` is shuffled by ``numpy.random.default_rng((seed, e))``, so each epoch's
    batches depend only on ``(seed, e)`` and a resumed run sees the same batches as an
    uninterrupted one. Batches are stratified from epoch ``stratify_from_epoch`` on
    (``None``: never), e.g. the first epoch of the mixed phase.
    """

    def batches(epoch: int) -> Iterator[BNNBatch]:
        rng = np.random.default_rng((seed, epoch))
        strat = stratify_from_epoch is not None and epoch >= stratify_from_epoch
        return iterate_batches(
            clean, noisy, scenario, batch_size, rng, stratified=strat, drop_last=drop_last
        )

    return batches


def synthetic_dataset(
    n: int,
    shape: tuple[int, int, int, int] = (4, 2, 16, 32),
    n_scenarios: int = 3,
    *,
    seed: int = 0,
    noise_std: float = 0.1,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Toy VelocityMap-like data for smoke tests and benchmarks (not driving data).

    Returns ``(clean, noisy, scenario)``: ``(n, 4, T, H, W)`` float32 in [0, 1] twice and
    ``(n,)`` int64. Each scenario has its own road layout in RL (a horizontal band at a
    scenario-specific row, plus a vertical band for odd scenarios); HV and AV hold a few
    rectangles (vehicles) with values in [0.3, 1] that move one column per frame; MV holds
    the ego at a fixed cell. ``noisy`` adds Gaussian noise of std ``noise_std`` to every
    cell and clips to [0, 1].
    """
    c, t, h, w = shape
    if c != 4 or h < 8 or w < 8 or t < 1:
        raise ValueError(f"shape must be (4, T>=1, H>=8, W>=8), got {shape}")
    rng = np.random.default_rng(seed)
    clean = np.zeros((n, c, t, h, w), dtype=np.float32)
    scenario = rng.integers(0, n_scenarios, size=n).astype(np.int64)
    band = max(2, h // 4)
    for i in range(n):
        s = int(scenario[i])
        row0 = (s * h // max(n_scenarios, 1)) % (h - band + 1)
        clean[i, 2, :, row0 : row0 + band, :] = 1.0
        if s % 2 == 1:
            col0 = w // 2 - band // 2
            clean[i, 2, :, :, col0 : col0 + band] = 1.0
        clean[i, 3, :, row0 + band // 2 - 1 : row0 + band // 2 + 1, w // 3 : w // 3 + 3] = 0.6
        for ch, count in ((0, int(rng.integers(1, 4))), (1, int(rng.integers(0, 3)))):
            for _ in range(count):
                r = int(rng.integers(row0, row0 + band - 1))
                col = int(rng.integers(0, w - 3 - t))
                val = float(rng.uniform(0.3, 1.0))
                for f in range(t):
                    clean[i, ch, f, r : r + 2, col + f : col + f + 3] = val
    noise = rng.normal(0.0, noise_std, size=clean.shape)
    noisy = np.clip(clean + noise, 0.0, 1.0).astype(np.float32)
    return clean, noisy, scenario
