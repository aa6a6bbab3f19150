"""The runs log of a study folder: written as a run goes, so a run cut off still shows its work."""

from __future__ import annotations

from pathlib import Path

from latentdrive.experiments.study_runs import RUNS, StudyRuns, read_runs, runs_summary


def test_each_run_is_logged_as_it_goes_and_a_later_run_is_added(tmp_path: Path) -> None:
    notes: list[str] = []
    first = StudyRuns(tmp_path, "latentdrive reproduce X", 2, 0, notes.append)
    (entry,) = read_runs(tmp_path) or []
    assert entry["command"] == "latentdrive reproduce X" and entry["steps"] == 0 and entry["wall_s"] is None
    first.step_done(object())
    first.step_done(object())
    (entry,) = read_runs(tmp_path) or []
    assert entry["steps"] == 2 and entry["wall_s"] is None  # as a run cut off here would leave it
    second = StudyRuns(tmp_path, "again", 1, 2, notes.append)
    wall = second.end()
    runs = read_runs(tmp_path) or []
    assert [r["command"] for r in runs] == ["latentdrive reproduce X", "again"]
    assert runs[0]["wall_s"] is None and runs[1]["wall_s"] == wall and runs[1]["finished_before"] == 2
    assert not notes


def test_a_damaged_log_is_left_alone_and_the_run_goes_unlogged(tmp_path: Path) -> None:
    for damaged in (b"[{", b'{"not": "a list"}', b"[1, 2]"):
        (tmp_path / RUNS).write_bytes(damaged)
        notes: list[str] = []
        run = StudyRuns(tmp_path, "cmd", 1, 0, notes.append)
        run.step_done(object())
        run.end()
        assert (tmp_path / RUNS).read_bytes() == damaged
        assert read_runs(tmp_path) is None
        assert len(notes) == 1 and "damaged" in notes[0] and "\n" not in notes[0]


def test_the_summary_adds_up_the_runs_and_counts_those_cut_off() -> None:
    ended = {"started": "2026-01-01T10:00:00+00:00", "active_s": 100.0, "wall_s": 100.0}
    cut = {"started": "2026-01-01T09:00:00+00:00", "active_s": 3500.0, "wall_s": None}
    assert runs_summary(None) is None and runs_summary([]) is None
    assert runs_summary([ended]) is None  # the last-run line says it all
    line = runs_summary([cut, ended])
    assert line is not None and line.startswith("- Runs of this folder: 2, from 2026-01-01T09:00:00+00:00")
    assert "3600 s (1.00 h) of wall time in all, 1 of them cut off" in line
    only_cut = runs_summary([cut])
    assert only_cut is not None and "1 of them cut off" in only_cut
