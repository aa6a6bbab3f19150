"""The log of a study folder's runs: when each started, what it ran and how long it lasted.

A study too long for one sitting runs several times into the same folder, each run
resuming where the last stopped. A run cut off never reaches its end, so its entry is
written as each of its steps finishes: a run that was cut off still shows how long it
worked, up to its last finished step. A run that finishes no step leaves no entry (a rerun
that only rebuilds the report, or one refused before it started). The report adds the
runs up; the log never decides what runs, and a log that cannot be written only loses
the log.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from latentdrive.fileio import MAX_JSON_BYTES, FileFormatError, atomic_write_text, read_json

__all__ = ["ENDS", "RUNS", "StudyRuns", "read_runs", "runs_summary"]

RUNS = "runs.json"
#: How a run ended, as logged; a run cut off (killed, the machine gone) logs none.
ENDS = ("finished", "failed", "interrupted")


def _number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v >= 0


def _entry_ok(r: Any) -> bool:
    return (isinstance(r, dict) and isinstance(r.get("command"), (str, type(None)))
            and isinstance(r.get("started"), str) and isinstance(r.get("steps"), int) and _number(r.get("active_s"))
            and (r.get("wall_s") is None or _number(r["wall_s"])) and r.get("ended", "finished") in ENDS)


def read_runs(out: Path) -> list[dict[str, Any]] | None:
    """The runs logged in study folder ``out``: empty when none was, None when the log is damaged."""
    try:
        data = read_json(out / RUNS, limit=MAX_JSON_BYTES, what="runs log")
    except FileNotFoundError:
        return []
    except (FileFormatError, OSError):  # OSError: not a file (a folder by that name, say)
        return None
    if not isinstance(data, list) or not all(_entry_ok(r) for r in data):
        return None
    return data


class StudyRuns:
    """This run's entry in ``OUT/runs.json``, written once it has finished a step and kept
    up to date as it goes.

    A damaged log is left as it is (nothing already written changes) and this run goes
    unlogged, with a note through ``say``; so does a run whose log cannot be written.
    """

    def __init__(self, out: Path, command: str | None, workers: int | str, finished_before: int,
                 say: Callable[[str], None]) -> None:
        self.out, self.say = out, say
        runs = read_runs(out)
        if runs is None:
            say(f"note: {out / RUNS} is damaged; it is left as it is and this run is not logged in it")
        self.runs = runs
        self.t0 = time.perf_counter()
        self.entry: dict[str, Any] = {
            "command": command, "workers": workers,
            "started": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "finished_before": finished_before, "steps": 0, "active_s": 0.0, "wall_s": None}

    def step_done(self, *_: Any) -> None:
        """One of this run's steps finished (a callback of the executors)."""
        self.entry["steps"] += 1
        self.entry["active_s"] = round(time.perf_counter() - self.t0, 1)
        self._write()

    def end(self, how: str = "finished") -> float:
        """This run ended (one of :data:`ENDS`); returns its wall time in seconds."""
        wall = round(time.perf_counter() - self.t0, 1)
        self.entry.update(active_s=wall, wall_s=wall, ended=how)
        if self.entry["steps"]:
            self._write()
        return wall

    def _write(self) -> None:
        if self.runs is None:
            return
        if not self.runs or self.runs[-1] is not self.entry:
            self.runs.append(self.entry)
        try:
            atomic_write_text(self.out / RUNS, json.dumps(self.runs, indent=1, allow_nan=False) + "\n")
        except OSError as exc:
            self.say(f"note: {self.out / RUNS} could not be written ({exc}); this run goes on unlogged")
            self.runs = None


def runs_summary(runs: list[dict[str, Any]] | None, running: bool = False) -> str | None:
    """One report line on every run of a study folder, or None when there is nothing to say
    (no log, or one run that ran to its end: the report's last-run line says it all).
    ``running``: the last run is still at work (it has logged no end yet, and is not cut off)."""
    if not runs:
        return None
    done = runs[:-1] if running else runs
    short = [r for r in done if r.get("ended") != "finished"]
    if len(runs) == 1 and not short:
        return None
    active = sum(float(r["active_s"]) for r in runs)
    line = (f"- Runs of this folder: {len(runs)}, from {runs[0]['started']} to the last's start at "
            f"{runs[-1]['started']}; they worked {active:.0f} s ({active / 3600:.2f} h) of wall time in all")
    if short:
        cut = sum(1 for r in short if r.get("ended") is None)
        line += (f", {len(short)} of them not to their end ({cut} cut off, {len(short) - cut} stopped by an error "
                 "or an interrupt; a run cut off counts to its last finished step)")
    if running:
        line += "; the last is still at work (counted to its last finished step)"
    return line + "."
