"""The runs log of a study folder: written as a run goes, so a run cut off still shows its work."""

from __future__ import annotations

from pathlib import Path

import pytest

from latentdrive.experiments.study_runs import RUNS, StudyRuns, read_runs, runs_summary


def test_each_run_is_logged_as_it_goes_and_a_later_run_is_added(tmp_path: Path) -> None:
    notes: list[str] = []
    first = StudyRuns(tmp_path, "latentdrive reproduce X", 2, 0, notes.append)
    assert read_runs(tmp_path) == []  # nothing until a step finishes
    first.step_done(object())
    first.step_done(object())
    (entry,) = read_runs(tmp_path) or []
    assert entry["command"] == "latentdrive reproduce X" and entry["steps"] == 2
    assert entry["wall_s"] is None and "ended" not in entry  # as a run cut off here would leave it
    second = StudyRuns(tmp_path, "again", 1, 2, notes.append)
    second.step_done(object())
    wall = second.end()
    runs = read_runs(tmp_path) or []
    assert [r["command"] for r in runs] == ["latentdrive reproduce X", "again"]
    assert runs[1]["wall_s"] == wall and runs[1]["ended"] == "finished" and runs[1]["finished_before"] == 2
    # A run that finishes no step (a rerun that only rebuilds the report, a refused one) leaves no entry.
    before = (tmp_path / RUNS).read_bytes()
    StudyRuns(tmp_path, "nothing to do", 1, 3, notes.append).end()
    StudyRuns(tmp_path, "refused", 1, 3, notes.append).end("failed")
    assert (tmp_path / RUNS).read_bytes() == before
    assert not notes


@pytest.mark.parametrize("damaged", [b"[{", b'{"not": "a list"}', b"[1, 2]",
                                     b'[{"command": "c", "started": "t", "steps": 1, "active_s": "x", "wall_s": null}]',
                                     b'[{"command": "c", "started": "t", "steps": 1, "active_s": 1, "wall_s": -1}]',
                                     b'[{"command": 3, "started": "t", "steps": 1, "active_s": 1, "wall_s": 1}]',
                                     b'[{"command": "c", "started": "t", "steps": 1, "active_s": 1, "wall_s": 1, '
                                     b'"ended": "exploded"}]'])
def test_a_damaged_log_is_left_alone_and_the_run_goes_unlogged(tmp_path: Path, damaged: bytes) -> None:
    (tmp_path / RUNS).write_bytes(damaged)
    notes: list[str] = []
    run = StudyRuns(tmp_path, "cmd", 1, 0, notes.append)
    run.step_done(object())
    run.end()
    assert (tmp_path / RUNS).read_bytes() == damaged
    assert read_runs(tmp_path) is None and runs_summary(read_runs(tmp_path)) is None
    assert len(notes) == 1 and "damaged" in notes[0] and "\n" not in notes[0]


def test_a_log_that_cannot_be_written_loses_only_the_log(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import latentdrive.experiments.study_runs as study_runs

    def disk_full(path: Path, text: str) -> Path:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(study_runs, "atomic_write_text", disk_full)
    notes: list[str] = []
    run = StudyRuns(tmp_path, "cmd", 1, 0, notes.append)
    run.step_done(object())
    run.step_done(object())
    assert run.end() >= 0
    assert len(notes) == 1 and "could not be written" in notes[0] and "No space left" in notes[0]
    # A folder where the log should be reads as a damaged log, not a crash.
    (tmp_path / RUNS).mkdir()
    assert read_runs(tmp_path) is None


def test_the_summary_adds_up_the_runs_and_counts_those_not_run_to_their_end() -> None:
    ended = {"started": "2026-01-01T10:00:00+00:00", "steps": 2, "active_s": 100.0, "wall_s": 100.0,
             "ended": "finished"}
    cut = {"started": "2026-01-01T09:00:00+00:00", "steps": 5, "active_s": 3400.0, "wall_s": None}
    failed = {**ended, "active_s": 100.0, "ended": "failed"}
    assert runs_summary(None) is None and runs_summary([]) is None
    assert runs_summary([ended]) is None  # the last-run line says it all
    line = runs_summary([cut, failed, ended])
    assert line is not None and line.startswith("- Runs of this folder: 3, from 2026-01-01T09:00:00+00:00")
    assert "3600 s (1.00 h) of wall time in all, 2 of them not to their end (1 cut off, 1 stopped by" in line
    only_cut = runs_summary([cut])
    assert only_cut is not None and "1 of them not to their end (1 cut off, 0 stopped" in only_cut
