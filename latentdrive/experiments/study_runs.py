"""The log of a study folder's runs: when each started, what it ran and how long it lasted.

A study too long for one sitting runs several times into the same folder, each run
resuming where the last stopped. A run cut off never reaches its end, so the log is
written when a run starts and again each time one of its steps finishes: a run that was
cut off still shows how long it worked, up to its last finished step. The report adds
the runs up; the log never decides what runs.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from latentdrive.fileio import MAX_JSON_BYTES, FileFormatError, atomic_write_text, read_json

__all__ = ["RUNS", "StudyRuns", "read_runs", "runs_summary"]

RUNS = "runs.json"


def read_runs(out: Path) -> list[dict[str, Any]] | None:
    """The runs logged in study folder ``out``: empty when none was, None when the log is damaged."""
    try:
        data = read_json(out / RUNS, limit=MAX_JSON_BYTES, what="runs log")
    except FileNotFoundError:
        return []
    except FileFormatError:
        return None
    if not isinstance(data, list) or not all(isinstance(r, dict) for r in data):
        return None
    return data


class StudyRuns:
    """This run's entry in ``OUT/runs.json``, kept up to date as it goes.

    A damaged log is left as it is (nothing already written changes) and this run goes
    unlogged, with a note through ``say``.
    """

    def __init__(self, out: Path, command: str | None, workers: int | str, finished_before: int,
                 say: Callable[[str], None]) -> None:
        self.out = out
        runs = read_runs(out)
        if runs is None:
            say(f"note: {out / RUNS} is damaged; it is left as it is and this run is not logged in it")
        self.runs = runs
        self.t0 = time.perf_counter()
        self.entry: dict[str, Any] = {
            "command": command, "workers": workers,
            "started": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "finished_before": finished_before, "steps": 0, "active_s": 0.0, "wall_s": None}
        if self.runs is not None:
            self.runs.append(self.entry)
            self._write()

    def step_done(self, *_: Any) -> None:
        """One of this run's steps finished (a callback of the executors)."""
        self.entry["steps"] += 1
        self.entry["active_s"] = round(time.perf_counter() - self.t0, 1)
        self._write()

    def end(self) -> float:
        """This run ran to its end; returns its wall time in seconds."""
        wall = round(time.perf_counter() - self.t0, 1)
        self.entry["active_s"] = self.entry["wall_s"] = wall
        self._write()
        return wall

    def _write(self) -> None:
        if self.runs is not None:
            atomic_write_text(self.out / RUNS, json.dumps(self.runs, indent=1, allow_nan=False) + "\n")


def runs_summary(runs: list[dict[str, Any]] | None) -> str | None:
    """One report line on every run of a study folder, or None when there is nothing to say
    (no log, or one run that ran to its end: the report's last-run line says it all)."""
    if not runs:
        return None
    cut = [r for r in runs if r.get("wall_s") is None]
    if len(runs) == 1 and not cut:
        return None
    active = sum(float(r.get("active_s") or 0.0) for r in runs)
    line = (f"- Runs of this folder: {len(runs)}, from {runs[0].get('started', '–')} to the last's start at "
            f"{runs[-1].get('started', '–')}; they worked {active:.0f} s ({active / 3600:.2f} h) of wall time in all")
    if cut:
        line += (f", {len(cut)} of them cut off (counted to their last finished step: the work they did after it, "
                 "kept by a resumable step or lost, is not)")
    return line + "."
