"""``latentdrive bench --train --processes N``: how N training runs share one machine.

A study runs several policies at once, one per worker, and on a machine with one GPU
they share both its cores and that GPU. Measured alone, a run says nothing about
that. Here the same measurement as :func:`latentdrive.rl.bench.bench_training` runs
in ``N`` processes at once. Each timed loop (one per mode and precision) starts in
every process together (a barrier) and stops in every process when the first one has
done its agent-transitions, so each process is timed over the same window, under the
load of all the others. Each mode and precision gets the agent-transitions/s of each
process (min, median, max, and their sum, the machine's throughput) and the median's
ratio to the same measurement alone, run first in this process.

Processes are spawned (not forked), so each starts as a study worker does: its own
imports, threads and CUDA context.
"""

from __future__ import annotations

import multiprocessing as mp
import queue
import statistics
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from latentdrive.errors import LatentDriveError
from latentdrive.rl.bench import TrainBenchRow, bench_config, bench_training

__all__ = ["SharedRow", "bench_training_shared", "format_shared"]


@dataclass(frozen=True)
class SharedRow:
    """One mode and precision measured in ``len(per_process)`` processes at once."""

    mode: str
    device: str
    precision: str
    #: Agent-transitions/s of each process, in process order.
    per_process: tuple[float, ...]
    #: The same measurement in one process alone.
    alone: float

    @property
    def median(self) -> float:
        return statistics.median(self.per_process)

    @property
    def total(self) -> float:
        return sum(self.per_process)

    def as_dict(self) -> dict[str, Any]:
        return {"mode": self.mode, "device": self.device, "precision": self.precision, "processes": len(self.per_process),
                "per_process": list(self.per_process), "alone": self.alone, "median": self.median, "total": self.total}


class _Window:
    """The shared timed windows of one process (:class:`latentdrive.rl.bench.Together`):
    one barrier for every start, one event per window that the first process to finish
    its loop sets. Windows are counted, so a process never reads an earlier window's event."""

    def __init__(self, barrier: Any, ends: list[Any]) -> None:
        self.barrier, self.ends, self.window = barrier, ends, -1

    def start(self) -> None:
        self.window += 1
        self.barrier.wait()

    def over(self) -> bool:
        return bool(self.ends[self.window].is_set())

    def end(self) -> None:
        self.ends[self.window].set()


def _child(index: int, barrier: Any, ends: list[Any], results: Any, args: tuple[Any, ...],
           kwargs: dict[str, Any]) -> None:
    try:
        rows = bench_training(*args, **kwargs, together=_Window(barrier, ends))
        results.put((index, [r.as_dict() for r in rows], None))
    except BaseException as exc:  # reported to the parent, which names the process
        barrier.abort()  # the others stop waiting for this one
        results.put((index, None, f"{type(exc).__name__}: {exc}"))


def _collect(procs: list[Any], results: Any) -> list[list[dict[str, Any]]]:
    """Every process's rows, in process order; a one-line error naming the first process
    that failed (its own error, not the broken barrier the others then see) or that ended
    without reporting (killed, or a result that could not be sent)."""
    got: dict[int, list[dict[str, Any]]] = {}
    errors: dict[int, str] = {}
    while len(got) + len(errors) < len(procs):
        try:
            index, rows, error = results.get(timeout=1.0)
        except queue.Empty:
            silent = [i for i, p in enumerate(procs) if p.exitcode is not None and i not in got and i not in errors]
            if silent:
                # Give a result sent just before the exit a moment to arrive.
                try:
                    index, rows, error = results.get(timeout=2.0)
                except queue.Empty:
                    i = silent[0]
                    raise LatentDriveError(f"bench --processes: process {i} exited with code "
                                           f"{procs[i].exitcode} before reporting") from None
            else:
                continue
        if error is None:
            got[index] = rows
        else:
            errors[index] = error
    if errors:
        real = {i: e for i, e in errors.items() if not e.startswith("BrokenBarrierError")} or errors
        first = min(real)
        raise LatentDriveError(f"bench --processes: process {first}: {real[first]}")
    return [got[i] for i in range(len(procs))]


def bench_training_shared(processes: int, modes: Sequence[str], scenarios: Sequence[str], *, transitions: int = 2000,
                          updates: int = 50, envs: int = 16, bnn: str | None = None,
                          overrides: dict[str, Any] | None = None,
                          progress: Callable[[str], None] | None = None) -> tuple[list[TrainBenchRow], list[SharedRow]]:
    """The measurement alone (rows as :func:`bench_training` gives them), then in
    ``processes`` processes at once: one :class:`SharedRow` per mode and precision."""
    if processes < 2:
        raise ValueError(f"processes must be at least 2, got {processes}")
    for mode in modes:  # a bad mode or override fails here, not in N processes
        bench_config(mode, scenarios, envs, bnn, overrides)
    kwargs: dict[str, Any] = {"transitions": transitions, "updates": updates, "envs": envs, "bnn": bnn,
                              "overrides": overrides}
    if progress:
        progress("alone:")
    alone = bench_training(modes, scenarios, **kwargs, progress=progress)
    if progress:
        progress(f"{processes} processes at once ...")
    ctx = mp.get_context("spawn")
    barrier, results = ctx.Barrier(processes), ctx.Queue()
    ends = [ctx.Event() for _ in alone]  # one timed window per row of the measurement
    procs = [ctx.Process(target=_child, args=(i, barrier, ends, results, (list(modes), list(scenarios)), kwargs),
                         daemon=True) for i in range(processes)]
    try:
        for p in procs:
            p.start()
        per = _collect(procs, results)
    finally:
        for p in procs:
            if p.pid is not None:
                p.join(timeout=5.0)
                if p.is_alive():
                    p.terminate()
    rows = []
    for k, base in enumerate(alone):
        theirs = [rows_of[k] for rows_of in per]
        # Every process runs the same sequence of modes and precisions as the lone run.
        assert all((r["mode"], r["precision"]) == (base.mode, base.precision) for r in theirs)
        rows.append(SharedRow(mode=base.mode, device=base.device, precision=base.precision,
                              per_process=tuple(float(r["transitions_per_s"]) for r in theirs),
                              alone=base.transitions_per_s))
    return alone, rows


def format_shared(rows: list[SharedRow]) -> str:
    n = len(rows[0].per_process) if rows else 0
    lines = [f"{n} processes at once, each the measurement above, their timed loops started together and "
             "stopped when the first was done; agent-transitions/s per process",
             f"{'mode':<28}{'device':>7}{'prec':>6}{'min':>8}{'median':>8}{'max':>8}{'sum':>9}{'alone':>8}{'median/alone':>14}"]
    for r in rows:
        lines.append(f"{r.mode:<28}{r.device:>7}{r.precision:>6}{min(r.per_process):>8.0f}{r.median:>8.0f}"
                     f"{max(r.per_process):>8.0f}{r.total:>9.0f}{r.alone:>8.0f}{r.median / r.alone:>13.2f}x")
    lines.append("sum: the machine's agent-transitions/s with all of them running; median/alone: what a run "
                 "keeps of its own speed when that many share the machine")
    return "\n".join(lines)
