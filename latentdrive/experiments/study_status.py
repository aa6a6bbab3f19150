"""Where a study folder stands: ``latentdrive status OUT``.

A study that runs for hours, or over several sittings, is read from its folder alone:
which steps have finished, which were begun and have not (running now, or cut off and
waiting for a rerun to resume them), the step time its records hold, and the time left,
estimated from the study's own finished steps. A step class none of them has measured yet
counts at the graph's rough guess (:attr:`~latentdrive.experiments.graph.Step.cost`) and
is marked so. Reading the status changes nothing in the folder.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

from latentdrive.config import ConfigError
from latentdrive.experiments.estimate import makespan, step_times
from latentdrive.experiments.graph import Graph
from latentdrive.experiments.reproduce import measure_study
from latentdrive.experiments.study_runs import RUNS, read_runs, runs_summary
from latentdrive.runlock import UNKNOWN, holder

__all__ = ["ClassStatus", "StudyStatus", "format_status", "study_status"]


@dataclass(frozen=True)
class ClassStatus:
    """The steps of one step class (as ``estimate`` names them)."""

    steps: int
    finished: int
    #: Hours the finished steps' records hold (their wall time and any resumed time).
    recorded_h: float
    #: Hours the unfinished ones should take, begun ones counted whole.
    left_h: float
    #: Whether ``left_h`` comes from this study's own finished steps of the class (else the
    #: graph's rough guess).
    measured: bool


@dataclass(frozen=True)
class StudyStatus:
    """A study folder's progress; :func:`format_status` prints it."""

    out: Path
    preset: str
    steps: int
    finished: int
    #: Steps with a folder and no record: running now, or cut off.
    begun: tuple[str, ...]
    classes: dict[str, ClassStatus]
    workers: int
    #: Where ``workers`` came from (given, the last logged run's, or a default of 1).
    workers_from: str
    #: Wall hours the unfinished steps should take on ``workers``, about: a list schedule
    #: of their times, longest chain first.
    wall_left_h: float
    #: The lock holder's line while a run holds the folder, None when none does, or
    #: :data:`~latentdrive.runlock.UNKNOWN`.
    in_use: str | None
    #: One line on the runs its log holds (None when there is nothing to say).
    runs: str | None

    @property
    def recorded_h(self) -> float:
        """Hours the finished steps' records hold."""
        return sum(c.recorded_h for c in self.classes.values())

    @property
    def left_h(self) -> float:
        """Step-hours the unfinished steps should take."""
        return sum(c.left_h for c in self.classes.values())

    @property
    def guessed_h(self) -> float:
        """Of :attr:`left_h`, the hours of classes no finished step has measured yet."""
        return sum(c.left_h for c in self.classes.values() if not c.measured)


def study_status(out: str | Path, workers: int | None = None) -> StudyStatus:
    """Read the status of the study in ``out``; ``workers`` the wall time is estimated for
    (default: the last logged run's, else 1)."""
    out = Path(out)
    if workers is not None and workers < 1:
        raise ConfigError(f"--workers must be at least 1, got {workers}")
    m = measure_study(out)
    graph, records = m.graph, m.records
    runs = read_runs(out)
    workers_from = "given"
    if workers is None:
        logged = runs[-1].get("workers") if runs else None
        if isinstance(logged, int) and logged > 0:
            workers, workers_from = logged, "the last logged run's"
        else:
            workers = 1
            workers_from = (f"{out / RUNS} is damaged" if runs is None else "no run logged one") + "; give --workers"
    sized = step_times(graph, m.rates, m.epoch_samples(m.config))
    pending = [n for n in graph.order if n not in records]
    # A step of a class no finished step has measured counts at the graph's rough guess.
    times = {n: t if (t := sized[n][1]) is not None else graph.steps[n].cost for n in pending}
    classes = {}
    for cls in sorted({c for c, _ in sized.values()}):
        names = [n for n, (c, _) in sized.items() if c == cls]
        done = [n for n in names if n in records]
        classes[cls] = ClassStatus(len(names), len(done), sum(records[n].cost_s for n in done) / 3600,
                                   sum(times[n] for n in names if n in times) / 3600, cls in m.rates)
    # The finished steps are done: the rest is scheduled on its own, from now.
    rest = Graph(dataclasses.replace(graph.steps[n], inputs={r: d for r, d in graph.steps[n].inputs.items()
                                                               if d in times}) for n in pending)
    begun = tuple(n for n in pending if graph.folder(out, n).is_dir())
    in_use = holder(out)
    return StudyStatus(out, m.preset, len(graph.order), len(records), begun, classes, workers, workers_from,
                       makespan(rest, times, workers) / 3600, in_use,
                       runs_summary(runs, running=in_use is not None and in_use != UNKNOWN))


def format_status(st: StudyStatus) -> str:
    """The lines ``latentdrive status`` prints."""
    lines = [f"{st.out}: {st.preset or 'custom'} study, {st.steps} steps: {st.finished} finished, "
             f"{len(st.begun)} begun and not finished, {st.steps - st.finished - len(st.begun)} not begun",
             "running now: " + (st.in_use or "nothing (no run holds the folder)")]
    guessed = [cls for cls, c in st.classes.items() if c.steps > c.finished and not c.measured]
    mark = "*" if guessed else ""
    w = max(len("step class"), *(len(c) for c in st.classes))
    lines.append(f"{'step class':<{w}}  {'finished':>9}  {'recorded h':>10}  {'left h':>8}")
    for cls, c in st.classes.items():
        left = "" if c.steps == c.finished else f"{c.left_h:.2f}{'' if c.measured else '*'}"
        lines.append(f"{cls:<{w}}  {f'{c.finished}/{c.steps}':>9}  {c.recorded_h:>10.2f}  {left:>8}")
    lines.append(f"{'all':<{w}}  {f'{st.finished}/{st.steps}':>9}  {st.recorded_h:>10.2f}  "
                 f"{f'{st.left_h:.2f}{mark}':>8}")
    lines.append(f"left: about {st.left_h:.2f} step-hours{mark}, {st.wall_left_h:.2f} h on {st.workers} worker(s) "
                 f"({st.workers_from}), at this study's own step times; steps begun count whole")
    if guessed:
        lines.append(f"* {st.guessed_h:.2f} h of it the graph's rough guess, for classes no finished step has "
                     "measured yet: " + ", ".join(guessed))
    for name in st.begun:
        lines.append(f"begun: {name}")
    if st.runs:
        lines.append(st.runs.removeprefix("- "))
    return "\n".join(lines)
