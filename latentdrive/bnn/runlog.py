"""What a run logs while it trains: CSV logs with their TensorBoard scalars (BNN and policy
runs alike), and a BNN run's metrics.csv and running loss means."""

from __future__ import annotations

import csv
import io
import numbers
import resource
import sys
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import IO, Any

import numpy as np

from latentdrive.bnn.evaluate import VAL_KEYS
from latentdrive.config import ConfigError
from latentdrive.fileio import atomic_write_text, read_log, seconds_logged

__all__ = ["METRICS_NAME", "METRIC_COLUMNS", "Meter", "RunLog", "logged_seconds", "metrics_log", "peak_rss_mb",
           "read_metrics", "write_metrics"]

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


def logged_seconds(rows: Sequence[Mapping[str, str]], step: int, where: Path) -> float:
    """Seconds the epochs logged up to ``step`` took (what a run resumed there had already
    cost; a log from before times were kept counts none); a time that is not a number of
    seconds is one line naming ``where``."""
    return sum(seconds_logged(r.get("elapsed_s") or "", f"{where} at step {r.get('step')}", ConfigError)
               for r in rows if r.get("kind") == "epoch" and float(r.get("step") or 0) <= step)


def read_metrics(run_dir: Path) -> list[dict[str, str]]:
    """The rows of a run's metrics.csv, checked (none when it is missing).

    A resumed run reads them before it writes anything, so that a damaged log is one
    line naming it and the run folder is left as it was.
    """
    try:
        return read_log(run_dir / METRICS_NAME, columns=METRIC_COLUMNS, key="step", what="training log")
    except FileNotFoundError:
        return []


class RunLog:
    """A run's CSV logs plus their TensorBoard scalars: the one writer of BNN and policy runs.

    ``logs`` maps each file name in ``run_dir`` to its columns; ``step_key`` is the column
    that orders rows and is TensorBoard's step. A resumed run gives ``resume_at``, its
    checkpoint's step, and ``rows``, each log as :func:`~latentdrive.fileio.read_log` read
    it: the rows up to that step are kept, the later ones dropped (those steps are about to
    be redone). Otherwise every log starts empty.
    """

    def __init__(self, run_dir: Path, logs: Mapping[str, Sequence[str]], step_key: str, resume_at: int | None,
                 rows: Mapping[str, list[dict[str, str]]] | None = None) -> None:
        self.step_key = step_key
        self._files: dict[str, tuple[IO[str], csv.DictWriter[str]]] = {}
        for name, columns in logs.items():
            path = run_dir / name
            kept = [r for r in (rows or {}).get(name, []) if resume_at is not None and int(r[step_key]) <= resume_at]
            buf = io.StringIO()
            w = csv.DictWriter(buf, fieldnames=columns, extrasaction="ignore", lineterminator="\n")
            w.writeheader()
            w.writerows(kept)
            atomic_write_text(path, buf.getvalue())
            fh = path.open("a", newline="")
            self._files[name] = (fh, csv.DictWriter(fh, fieldnames=columns, extrasaction="ignore", lineterminator="\n"))
        from torch.utils.tensorboard import SummaryWriter

        # purge_step hides TensorBoard events logged after the checkpoint (or, on a fresh
        # start, by an earlier attempt that never reached one).
        self.tb = SummaryWriter(str(run_dir / "tb"), purge_step=resume_at or 0)

    def write(self, name: str, row: Mapping[str, Any], prefix: str, scalars: Iterable[str] | None = None) -> None:
        """Append ``row`` to log ``name`` (None as an empty cell) and its numeric ``scalars``
        (default: every numeric value but the step) to TensorBoard under ``prefix/``."""
        fh, w = self._files[name]
        w.writerow({k: ("" if v is None else v) for k, v in row.items()})
        fh.flush()
        step = int(row[self.step_key])
        for key in row if scalars is None else scalars:
            v = row.get(key)
            if key != self.step_key and isinstance(v, numbers.Real) and not isinstance(v, bool) and v == v:  # skip NaN
                self.tb.add_scalar(f"{prefix}/{key}", float(v), step)

    def close(self) -> None:
        for fh, _ in self._files.values():
            fh.close()
        self.tb.close()


def metrics_log(run_dir: Path, resume_step: int | None, rows: list[dict[str, str]] | None = None) -> RunLog:
    """A BNN run's metrics.csv (``rows`` as :func:`read_metrics` read them), stepped by ``step``."""
    return RunLog(run_dir, {METRICS_NAME: METRIC_COLUMNS}, "step", resume_step, {METRICS_NAME: rows or []})


def write_metrics(log: RunLog, row: dict[str, Any]) -> None:
    """One row of a BNN run's metrics.csv: a training step's (``kind`` step) or an epoch's."""
    log.write(METRICS_NAME, row, "train" if row["kind"] == "step" else "epoch",
              ("loss", "recon", "reg", *VAL_KEYS, "samples_per_s"))
