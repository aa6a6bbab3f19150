"""Is a BNN's haze a calibration bias? Held-out vehicle recall and precision with the vehicle
logits shifted down before the sigmoid.

A vehicle-weighted cross-entropy (``train.foreground_weight`` w) biases the decoder towards
drawing cars: where a cell is a car or empty with equal odds, its optimum sits ln w higher
in logit than the odds. Subtracting a multiple of ln w from the logits of the HV+AV pair
(both channels) undoes that bias; if the haze were only that bias, precision would rise
with little loss of recall. Prints recall, precision and F1 for shifts of 0, ½, 1 and 1½
ln w on the run's own validation batches (rebuilt as training builds them; shift 0
reproduces the run's logged numbers for the same weights). Usage::

    python scripts/logit_shift.py BNN_RUN [--weights best|checkpoint]
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import torch

from latentdrive.bnn.checkpoint import load_checkpoint, read_checkpoint
from latentdrive.bnn.evaluate import add_counts, vehicle_counts_by_scenario
from latentdrive.bnn.train_config import BNNTrainConfig
from latentdrive.bnn.vehicles import VehicleCounts
from latentdrive.config import validate
from latentdrive.data.dataset import ShardDataset
from latentdrive.models.bottleneck import BottleneckConfig, BottleneckNetwork
from latentdrive.runtime import autocast, resolve_precision


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--weights", choices=["best", "checkpoint"], default="best",
                    help="best.safetensors (the weights the run keeps) or checkpoint.safetensors (the latest)")
    args = ap.parse_args()
    path = args.run / f"{args.weights}.safetensors"
    if not (args.run / "split.json").exists() or not path.exists():
        raise SystemExit(f"{args.run}: not a BNN run folder (needs split.json and {path.name})")
    _, state = read_checkpoint(path)
    if not isinstance(state.get("config"), dict) or "train" not in state["config"]:
        raise SystemExit(f"{path}: not a BNN checkpoint (no training config)")
    cfg = validate(BNNTrainConfig, state["config"]["train"])
    if cfg.loss != "bce" or cfg.foreground_weight <= 1 or cfg.foreground_weight_final is not None:
        raise SystemExit(f"{path}: the shift undoes a constant vehicle weight w > 1 under loss 'bce'; this run "
                         f"trained loss {cfg.loss!r}, weight {cfg.foreground_weight:g} to "
                         f"{cfg.foreground_weight_final}")
    model = BottleneckNetwork(validate(BottleneckConfig, state["config"]["model"]))
    info = load_checkpoint(path, model)
    model.eval().requires_grad_(False)
    device = torch.device("cpu")
    dtype = resolve_precision(cfg.precision, device)
    split = json.loads((args.run / "split.json").read_text())
    ds = ShardDataset(split["dataset"])
    _, val_ids = ds.split_by_episode(split["val_fraction"], cfg.seed)
    if val_ids.tolist() != split["val_episodes"]:
        raise SystemExit(f"{args.run}: the dataset's split differs from split.json")
    log_w = math.log(cfg.foreground_weight)
    shifts = [0.0, 0.5 * log_w, log_w, 1.5 * log_w]
    counts: dict[float, dict[int, VehicleCounts]] = {s: {} for s in shifts}
    torch.use_deterministic_algorithms(cfg.deterministic)
    with torch.no_grad():
        for b in ds.batches(cfg.batch_size, val_ids, seed=cfg.seed, epoch=0, mixed=False):
            with autocast(dtype, device):
                logits, _ = model.forward_logits(b.noisy)
            pair = logits.float()[:, 0]  # the HV+AV pair, (B, 2, T, H, W): both are vehicle channels
            target = model.pairs(b.clean)[:, 0]
            for s in shifts:
                counts[s] = add_counts(counts[s], vehicle_counts_by_scenario(torch.sigmoid(pair - s), target, b.scenario))
    print(f"{path}: epoch {info.epoch}, step {info.step}; {ds.num_samples(val_ids)} held-out samples; "
          f"vehicle weight w = {cfg.foreground_weight:g}")
    print(f"{'shift':>8}{'× ln w':>8}{'recall':>9}{'precision':>11}{'F1':>7}")
    for s in shifts:
        c = VehicleCounts.total(counts[s].values())
        f1 = 2 * c.recall * c.precision / (c.recall + c.precision) if c.recall + c.precision > 0 else float("nan")
        print(f"{s:>8.3f}{s / log_w:>8.1f}{c.recall:>9.3f}{c.precision:>11.3f}{f1:>7.3f}")
    logged = info.extra.get("metrics", {})
    if logged:
        print(f"logged for these weights: recall {logged.get('val_vehicle_recall', float('nan')):.3f}, "
              f"precision {logged.get('val_vehicle_precision', float('nan')):.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
