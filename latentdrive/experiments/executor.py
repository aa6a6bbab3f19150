"""Run a study graph's unfinished steps in local worker processes.

Each step runs in a fresh process (so its peak memory is its own, and a crash or a leak
stays with it), started from a fork server that has already imported the step functions.
Ready steps start in order of their longest remaining chain of estimated costs, so long
chains (data → BNN → latent policies) begin first and short steps fill the gaps.

A failed step is reported with its error's first line; the steps that do not depend on it
still run, so one bad step costs only its descendants. An interrupt cancels what has not
started; a step killed mid-way leaves no ``done.json`` and runs again (continuing where it
can) next time.
"""

from __future__ import annotations

import multiprocessing as mp
import shutil
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from tqdm.auto import tqdm

from latentdrive.errors import LatentDriveError, first_line
from latentdrive.evaluate.stats import json_values
from latentdrive.experiments.graph import RESUMED, Graph, Step, StepRecord
from latentdrive.experiments.processes import Processes
from latentdrive.fileio import peak_rss_mb, reset_peak_rss
from latentdrive.provenance import loaded_revision

__all__ = ["Runner", "StepFailed", "StepKind", "StepRecords", "check_kinds", "execute_step", "run_graph", "run_local"]

StepFn = Callable[[Mapping[str, Any], Mapping[str, Path], Path], dict[str, Any]]


@dataclass(frozen=True)
class StepKind:
    """How to run one kind of step.

    Attributes:
        run: ``run(config, inputs, folder) -> summary`` writes the step's files into
            ``folder`` and returns a small JSON summary. Must be a module-level function
            (it is sent to worker processes by reference).
        resumable: a folder left by an interrupted attempt is continued (``run`` resumes
            from what it finds); otherwise it is cleared first. A resumable ``run`` may
            report under :data:`~latentdrive.experiments.graph.RESUMED` the seconds its
            earlier attempts spent on what it resumed from (the record's ``resumed_s``).
        cpus: cores the step keeps busy (a request for cluster schedulers).
        gpu: the step can use a GPU when one is there.
    """

    run: StepFn
    resumable: bool = False
    cpus: int = 1
    gpu: bool = False

    def wants_gpu(self, step: Step) -> bool:
        """Whether a scheduler should reserve a GPU share for ``step``: its kind can use
        one and its config does not pin it to the CPU (``train.device: cpu``, as a study
        sets with ``--set policy.train.device=cpu`` where policies run faster on the
        cores than sharing a GPU)."""
        train = step.config.get("train")
        device = train.get("device", "auto") if isinstance(train, Mapping) else "auto"
        return self.gpu and device != "cpu"


class StepFailed(LatentDriveError):
    """Steps of a study failed; the message names each with its error."""


# The commit of the code this process loads: the step code is imported with this module
# (by a study's fork server at its start, or by a Ray worker), so pin it now rather than
# when a step ends, after the checkout may have moved on.
loaded_revision()


def execute_step(kind: StepKind, step: Step, key: str, inputs: Mapping[str, Path], folder: Path,
                 records: StepRecords) -> StepRecord:
    """Run one step into ``folder`` and record it; this is what a worker process does.

    A step already recorded with this key is not run again: a task retried after its
    worker died between writing ``done.json`` and reporting back keeps its results.
    """
    if (done := records.finished(step.name)) is not None:
        return done
    t0 = time.perf_counter()
    reset_peak_rss()
    if folder.exists() and not kind.resumable:
        shutil.rmtree(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for role, path in inputs.items():
        if not path.is_dir():
            raise LatentDriveError(f"step {step.name}: its input {role} is missing ({path})")
    summary = json_values(kind.run(step.config, inputs, folder))
    peak_mb = peak_rss_mb()
    resumed = float(summary.pop(RESUMED, 0.0))
    rec = StepRecord(name=step.name, kind=step.kind, key=key, summary=summary,
                     wall_s=round(time.perf_counter() - t0, 2), peak_rss_mb=round(peak_mb, 1),
                     source=loaded_revision(), resumed_s=round(resumed, 2))
    records.write(rec)
    return rec


def _ranks(graph: Graph, names: Sequence[str]) -> dict[str, float]:
    """Each step's cost plus the costliest chain of pending steps that waits on it."""
    pending = set(names)
    dependents: dict[str, list[str]] = {n: [] for n in names}
    for n in names:
        for dep in graph.steps[n].inputs.values():
            if dep in pending:
                dependents[dep].append(n)
    rank: dict[str, float] = {}
    for n in reversed([m for m in graph.order if m in pending]):
        rank[n] = graph.steps[n].cost + max((rank[d] for d in dependents[n]), default=0.0)
    return rank


class Runner(Protocol):
    """Where steps run: local worker processes, or Ray tasks (``ray_executor``)."""

    #: Steps kept in flight at once.
    slots: int

    def submit(self, kind: StepKind, step: Step, key: str, inputs: Mapping[str, Path], folder: Path,
               records: StepRecords) -> Any:
        """Start ``execute_step`` with these arguments; returns a handle."""

    def wait(self, handles: Sequence[Any]) -> list[Any]:
        """Block until at least one handle has finished; return the finished ones."""

    def result(self, handle: Any) -> StepRecord:
        """The record of a finished step, or its exception raised."""


class _Steps:
    """The :class:`Runner` of local worker processes: one fresh process per step
    (:class:`~latentdrive.experiments.processes.Processes`), so a step whose process dies
    fails alone."""

    def __init__(self, ctx: Any, slots: int) -> None:
        self.pool, self.slots = Processes(ctx), slots

    def submit(self, kind: StepKind, step: Step, key: str, inputs: Mapping[str, Path], folder: Path,
               records: StepRecords) -> Any:
        return self.pool.start(f"step {step.name}", (execute_step, (kind, step, key, inputs, folder, records), {}))

    def wait(self, handles: Sequence[Any]) -> list[Any]:
        return self.pool.wait(handles)

    def result(self, handle: Any) -> StepRecord:
        rec: StepRecord = self.pool.result(handle)
        return rec

    def stop(self) -> None:
        self.pool.stop()


def check_kinds(graph: Graph, kinds: Mapping[str, StepKind]) -> None:
    for s in graph.steps.values():
        if s.kind not in kinds:
            raise LatentDriveError(f"study graph: step {s.name!r} has unknown kind {s.kind!r}")


def run_local(graph: Graph, out: Path, kinds: Mapping[str, StepKind], workers: int = 1,
              preload: Sequence[str] = (), progress: bool = True,
              on_done: Callable[[StepRecord], None] | None = None) -> dict[str, StepRecord]:
    """Run every unfinished step of ``graph`` with ``workers`` processes; returns all records.

    Raises:
        StepFailed: after every runnable step has run, naming the steps that failed.
    """
    if workers < 1:
        raise LatentDriveError(f"--workers must be at least 1, got {workers}")
    check_kinds(graph, kinds)
    ctx = mp.get_context("forkserver")
    ctx.set_forkserver_preload(list(preload))
    runner = _Steps(ctx, workers)
    try:
        return run_graph(graph, out, kinds, runner, progress=progress, on_done=on_done)
    finally:
        runner.stop()  # after an interrupt: the running steps stop too, and run again next time


def run_graph(graph: Graph, out: Path, kinds: Mapping[str, StepKind], runner: Runner, progress: bool = True,
              on_done: Callable[[StepRecord], None] | None = None) -> dict[str, StepRecord]:
    """The one scheduling loop, whatever runs the steps: start ready steps longest chain
    first, up to ``runner.slots`` at once; record what finishes; report what fails."""
    records = {n: r for n in graph.order if (r := graph.record(out, n)) is not None}
    todo = [n for n in graph.order if n not in records]
    rank = _ranks(graph, todo)
    failed: dict[str, str] = {}
    blocked: set[str] = set()
    running: dict[Any, str] = {}
    # Float totals: rounding each step's cost would let the bar end short of (or past) 100%.
    bar = tqdm(total=sum(graph.steps[n].cost for n in todo), disable=not progress or not todo,
               unit="s", bar_format="{desc} {percentage:3.0f}%|{bar}| {elapsed}<{remaining} {postfix}",
               dynamic_ncols=True)
    done_count = len(records)

    def describe() -> None:
        bar.set_description_str(f"study: {done_count}/{len(graph.order)} steps")
        names = sorted(running.values())
        bar.set_postfix_str(("running " + ", ".join(names)) if names else "", refresh=True)

    try:
        while todo or running:
            ready = [n for n in todo if all(d in records for d in graph.steps[n].inputs.values())]
            for n in sorted(ready, key=lambda m: -rank[m])[: runner.slots - len(running)]:
                todo.remove(n)
                step = graph.steps[n]
                handle = runner.submit(kinds[step.kind], step, graph.keys[n], graph.inputs(out, n),
                                       graph.folder(out, n), StepRecords(graph, out))
                running[handle] = n
            describe()
            if not running:
                break  # what is left waits on failed steps
            for handle in runner.wait(list(running)):
                n = running.pop(handle)
                bar.update(min(graph.steps[n].cost, max(0.0, bar.total - bar.n)))  # float sums may overshoot
                try:
                    records[n] = runner.result(handle)
                    done_count += 1
                    if on_done is not None:
                        on_done(records[n])
                except Exception as exc:  # reported with the step's name; the others go on
                    failed[n] = first_line(exc)
                    bar.write(f"step {n} failed: {failed[n]}")
                    blocked.update(_descendants(graph, n))
                    # What can no longer run leaves the total, so the bar still ends full.
                    bar.total -= sum(graph.steps[m].cost for m in todo if m in blocked)
                    todo = [m for m in todo if m not in blocked]
    finally:
        bar.close()
    if failed:
        lost = f"; {len(blocked)} steps that need them did not run" if blocked else ""
        raise StepFailed(f"{len(failed)} step(s) failed: " + "; ".join(f"{n}: {e}" for n, e in failed.items()) + lost)
    return records


class StepRecords:
    """The steps' ``done.json`` files, read and written from a worker (picklable, unlike a closure)."""

    def __init__(self, graph: Graph, out: Path) -> None:
        self.graph, self.out = graph, out

    def write(self, rec: StepRecord) -> None:
        self.graph.write_record(self.out, rec)

    def finished(self, name: str) -> StepRecord | None:
        return self.graph.record(self.out, name)


def _descendants(graph: Graph, name: str) -> set[str]:
    found: set[str] = set()
    for n in graph.order:
        if any(d == name or d in found for d in graph.steps[n].inputs.values()):
            found.add(n)
    return found
