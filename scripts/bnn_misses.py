"""Which vehicles does a BNN miss? Held-out recall and precision by scenario, channel and
how many vehicles a frame holds, beside the noisy input's recall.

Scores the run's kept weights (``best.safetensors``) on the first ``--batches`` mixed
batches (every scenario in each) of its held-out episodes (``split.json``), with the
object-level rules of :func:`latentdrive.bnn.vehicles.vehicle_counts` applied one frame at
a time to the HV and AV channels of the HV+AV pair. Each (sample, channel) is binned by its
vehicles per frame (the blobs of its frames divided by the stack's frames, rounded down, ``3``
meaning three or more). The noisy column scores the denoiser's own input the same way:
what the sensor shows of those vehicles. A network whose misses gather in sparse scenes or
one scenario draws the vehicles it has seen often, not the vehicles it is shown. Usage::

    python scripts/bnn_misses.py BNN_RUN [--batches 24]
"""

from __future__ import annotations

import argparse
import itertools
import runpy
from pathlib import Path

import numpy as np
import torch

from latentdrive.bnn.vehicles import VehicleCounts, vehicle_counts
from latentdrive.runtime import autocast, resolve_precision

# The run-folder checks and loading shared with scripts/bnn_gap.py.
_open_run = runpy.run_path(str(Path(__file__).resolve().parent / "bnn_gap.py"), run_name="bnn_gap")["open_run"]

CHANNELS = ("HV", "AV")
#: Vehicles per frame, the last bin open-ended.
MOST = 3


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--batches", type=int, default=24, help="held-out batches of 64 scored (default 24)")
    args = ap.parse_args()
    if args.batches < 1:
        raise SystemExit(f"--batches must be at least 1, got {args.batches}")
    cfg, model, split, ds = _open_run(args.run)
    model.eval()
    device = torch.device("cpu")
    dtype = resolve_precision(cfg.precision, device)
    names = ds.scenario_names
    ids = np.asarray(split["val_episodes"], dtype=np.int64)
    # (scenario, channel, bin) -> (model's counts, noisy input's counts, samples)
    cells: dict[tuple[int, int, int], tuple[VehicleCounts, VehicleCounts, int]] = {}
    zero = VehicleCounts(0, 0, 0, 0)
    with torch.no_grad():
        for b in itertools.islice(ds.batches(64, ids, seed=cfg.seed, epoch=0, mixed=True), args.batches):
            with autocast(dtype, device):
                recon, _ = model(b.noisy)
            rec = recon.float()[:, 0]
            target = model.pairs(b.clean)[:, 0]
            noisy = model.pairs(b.noisy.float())[:, 0]
            for i in range(rec.shape[0]):
                for ch in range(len(CHANNELS)):
                    c = vehicle_counts(rec[i, ch], target[i, ch])
                    cn = vehicle_counts(noisy[i, ch], target[i, ch])
                    key = (int(b.scenario[i]), ch, min(c.vehicles // target.shape[2], MOST))
                    old_c, old_n, n = cells.get(key, (zero, zero, 0))
                    cells[key] = (old_c.plus(c), old_n.plus(cn), n + 1)
    print(f"{args.run}: held-out, first {args.batches} mixed batches of 64")
    print(f"{'scenario':<14}{'ch':<4}{'veh/frame':>10}{'samples':>9}{'vehicles':>10}{'recall':>8}"
          f"{'precision':>11}{'noisy recall':>14}")
    for (s, ch, k), (c, cn, n) in sorted(cells.items()):
        name = names[s]
        bin_ = f"{k}+" if k == MOST else str(k)
        print(f"{name:<14}{CHANNELS[ch]:<4}{bin_:>10}{n:>9}{c.vehicles:>10}{c.recall:>8.3f}"
              f"{c.precision:>11.3f}{cn.recall:>14.3f}")
    for ch in range(len(CHANNELS)):
        for k in range(MOST + 1):
            c = VehicleCounts.total(v[0] for key, v in cells.items() if key[1] == ch and key[2] == k)
            cn = VehicleCounts.total(v[1] for key, v in cells.items() if key[1] == ch and key[2] == k)
            n = sum(v[2] for key, v in cells.items() if key[1] == ch and key[2] == k)
            bin_ = f"{k}+" if k == MOST else str(k)
            print(f"{'all':<14}{CHANNELS[ch]:<4}{bin_:>10}{n:>9}{c.vehicles:>10}{c.recall:>8.3f}"
                  f"{c.precision:>11.3f}{cn.recall:>14.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
