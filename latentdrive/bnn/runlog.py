"""What a BNN run logs while it trains: metrics.csv, TensorBoard scalars, running loss means."""

from __future__ import annotations

import csv
import io
import resource
import sys
from pathlib import Path
from typing import Any

import numpy as np

from latentdrive.bnn.evaluate import VAL_KEYS
from latentdrive.fileio import atomic_write_text, read_log

__all__ = ["METRICS_NAME", "METRIC_COLUMNS", "Meter", "MetricsLog", "peak_rss_mb", "read_metrics"]

METRICS_NAME = "metrics.csv"
METRIC_COLUMNS = (
    "kind", "phase", "epoch", "step", "loss", "recon", "reg", "lr",
    *VAL_KEYS, "samples_per_s", "peak_rss_mb", "peak_cuda_mb", "elapsed_s",
)


def peak_rss_mb() -> float:
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    # Linux reports KiB, macOS bytes.
    return rss / (1024 * 1024) if sys.platform == "darwin" else rss / 1024


class Meter:
    """Running sums of the (total, recon, reg) losses over batches, with samples and seconds."""

    def __init__(self) -> None:
        self.sums = np.zeros(3)
        self.batches = 0
        self.samples = 0
        self.seconds = 0.0

    def add(self, values: np.ndarray, samples: int, seconds: float) -> None:
        self.sums += values
        self.batches += 1
        self.samples += samples
        self.seconds += seconds

    def means(self) -> tuple[float, float, float]:
        m = self.sums / max(self.batches, 1)
        return float(m[0]), float(m[1]), float(m[2])

    def rate(self) -> float:
        """Samples per second."""
        return self.samples / max(self.seconds, 1e-9)


def read_metrics(run_dir: Path) -> list[dict[str, str]]:
    """The rows of a run's metrics.csv, checked (none when it is missing).

    A resumed run reads them before it writes anything, so that a damaged log is one
    line naming it and the run folder is left as it was.
    """
    try:
        return read_log(run_dir / METRICS_NAME, columns=METRIC_COLUMNS, key="step", what="training log")
    except FileNotFoundError:
        return []


class MetricsLog:
    """metrics.csv plus TensorBoard scalars.

    A resumed run gives ``resume_step``, its checkpoint's step, and ``rows``, its log as
    :func:`read_metrics` read it: the rows up to that step are kept, the later ones
    dropped (those steps are about to be redone). Otherwise the log starts empty.
    """

    def __init__(self, run_dir: Path, resume_step: int | None, rows: list[dict[str, str]] | None = None) -> None:
        self.path = run_dir / METRICS_NAME
        kept = [r for r in rows or [] if resume_step is not None and int(r["step"]) <= resume_step]
        buf = io.StringIO()
        w = csv.DictWriter(buf, fieldnames=METRIC_COLUMNS, extrasaction="ignore")
        w.writeheader()
        w.writerows(kept)
        atomic_write_text(self.path, buf.getvalue())
        self._file = self.path.open("a", newline="")
        self._csv = csv.DictWriter(self._file, fieldnames=METRIC_COLUMNS)
        from torch.utils.tensorboard import SummaryWriter

        # purge_step hides TensorBoard events logged after the checkpoint (or, on a fresh
        # start, by an earlier attempt that never reached one).
        self.tb = SummaryWriter(str(run_dir / "tb"), purge_step=resume_step or 0)

    def write(self, row: dict[str, Any]) -> None:
        self._csv.writerow({k: ("" if v is None else v) for k, v in row.items()})
        self._file.flush()
        prefix = "train" if row["kind"] == "step" else "epoch"
        for key in ("loss", "recon", "reg", *VAL_KEYS, "samples_per_s"):
            v = row.get(key)
            if v is not None and v == v:  # skip NaN
                self.tb.add_scalar(f"{prefix}/{key}", float(v), int(row["step"]))

    def close(self) -> None:
        self._file.close()
        self.tb.close()
