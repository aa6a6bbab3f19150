"""Does a BNN generalize? Vehicle recall and precision on the episodes it trained on beside
those on its held-out episodes.

Scores the run's kept weights (``best.safetensors``) with the same function validation uses
(:func:`latentdrive.bnn.evaluate.evaluate_bnn`) on the first ``--batches`` batches of its
training episodes and of its held-out episodes (the episodes of ``split.json``), in the
order training's validation reads them. A wide gap between the two says the network
memorizes its episodes rather than learning to draw vehicles, and that more episodes, not
more steps, are the lever. Usage::

    python scripts/bnn_gap.py BNN_RUN [--batches 30]
"""

from __future__ import annotations

import argparse
import itertools
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch

from latentdrive.bnn.evaluate import evaluate_bnn
from latentdrive.bnn.resume import saved_configs
from latentdrive.bnn.train import load_trained_bottleneck
from latentdrive.bnn.train_config import BNNTrainConfig
from latentdrive.config import validate
from latentdrive.data.dataset import ShardDataset
from latentdrive.fileio import read_json
from latentdrive.models.bottleneck import BottleneckNetwork
from latentdrive.runtime import resolve_precision


class BNNRun(NamedTuple):
    """A finished BNN run: its training config, kept weights, episode split and dataset."""

    cfg: BNNTrainConfig
    model: BottleneckNetwork
    split: dict[str, Any]
    dataset: ShardDataset


def open_run(run: Path) -> BNNRun:
    """The run in folder ``run``, or ``SystemExit`` with a one-line reason if it is not one."""
    if not (run / "split.json").exists():
        raise SystemExit(f"{run}: not a BNN run folder (no split.json)")
    saved = saved_configs(run)
    if not isinstance(saved, dict) or "train" not in saved:
        raise SystemExit(f"{run}: no training config (not a BNN run folder)")
    split = read_json(run / "split.json")
    return BNNRun(validate(BNNTrainConfig, saved["train"]), load_trained_bottleneck(run), split,
                  ShardDataset(split["dataset"]))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--batches", type=int, default=30, help="batches scored per side (default 30)")
    args = ap.parse_args()
    if args.batches < 1:
        raise SystemExit(f"--batches must be at least 1, got {args.batches}")
    cfg, model, split, ds = open_run(args.run)
    device = torch.device("cpu")
    torch.use_deterministic_algorithms(cfg.deterministic)
    print(f"{args.run}: up to {args.batches} batches of {cfg.batch_size} samples per side")
    print(f"{'episodes':<10}{'samples':>9}{'recall':>9}{'precision':>11}")
    for side, key in (("training", "train_episodes"), ("held-out", "val_episodes")):
        ids = np.asarray(split[key], dtype=np.int64)
        batches = list(itertools.islice(ds.batches(cfg.batch_size, ids, seed=cfg.seed, epoch=0, mixed=False),
                                        args.batches))
        m = evaluate_bnn(model, batches, device, mmd_samples=2, dtype=resolve_precision(cfg.precision, device)).metrics
        n = sum(int(b.noisy.shape[0]) for b in batches)
        print(f"{side:<10}{n:>9}{m['val_vehicle_recall']:>9.3f}{m['val_vehicle_precision']:>11.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
