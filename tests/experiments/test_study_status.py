"""``latentdrive status``: a study folder's progress, read without changing it."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest

from latentdrive.cli import main
from latentdrive.config import ConfigError
from latentdrive.experiments.graph import DONE
from latentdrive.experiments.reproduce import measure_study
from latentdrive.experiments.study_runs import RUNS
from latentdrive.experiments.study_status import format_status, study_status
from latentdrive.runlock import dir_lock


def _snapshot(root: Path) -> dict[str, bytes | None]:
    return {str(p.relative_to(root)): (None if p.is_dir() else p.read_bytes()) for p in sorted(root.rglob("*"))}


@pytest.fixture
def study(tiny_study: Path, tmp_path: Path) -> Path:
    out = tmp_path / "study"
    shutil.copytree(tiny_study, out)
    # One logged run of 2 workers (other tests rerun the shared study and log runs of their own).
    (out / RUNS).write_text(json.dumps([{
        "command": "latentdrive reproduce OUT --preset tiny --workers 2", "workers": 2,
        "started": "2030-01-01T00:00:00+00:00", "finished_before": 0, "steps": 49, "active_s": 80.0,
        "wall_s": 80.0, "ended": "finished"}]))
    return out


def test_a_finished_study_has_nothing_left(study: Path) -> None:
    st = study_status(study)
    assert st.finished == st.steps > 0 and not st.begun and st.left_h == 0 and st.wall_left_h == 0
    assert st.workers == 2 and st.workers_from == "the last logged run's"
    assert st.in_use is None
    assert st.recorded_h == pytest.approx(sum(r.cost_s for r in measure_study(study).records.values()) / 3600)


def test_unfinished_steps_are_counted_at_the_studys_own_rates(study: Path) -> None:
    m = measure_study(study)
    names = [n for n in m.graph.order if n.startswith("policy/latent/")]
    begun, gone = names[0], names[1]
    (m.graph.folder(study, begun) / DONE).unlink()  # as if cut off: its folder stays
    shutil.rmtree(m.graph.folder(study, gone))
    before = _snapshot(study)
    st = study_status(study, workers=1)
    assert _snapshot(study) == before  # nothing written
    assert st.finished == st.steps - 2 and st.begun == (begun,)
    (cls,) = {c for c, s in st.classes.items() if s.finished < s.steps}
    left = st.classes[cls]
    assert left.measured and left.steps - left.finished == 2
    # The class's rate comes from its steps that are still finished.
    rate = measure_study(study).rates[cls]
    assert left.left_h == pytest.approx(2 * rate * m.graph.steps[begun].config["train"]["steps"] / 3600)
    # On one worker the two run one after the other (the second reads nothing of the first).
    assert st.wall_left_h == pytest.approx(st.left_h)
    assert study_status(study, workers=2).wall_left_h == pytest.approx(st.left_h / 2)
    printed = format_status(st)
    assert f"begun: {begun}" in printed
    assert f"{st.steps - 2} finished, 1 begun and not finished, 1 not begun" in printed
    # A step waits for its unfinished inputs: the begun policy's evaluation comes after it.
    (evaluation,) = [n for n in m.graph.order if m.graph.steps[n].inputs.get("policy") == begun]
    (m.graph.folder(study, evaluation) / DONE).unlink()
    st2 = study_status(study, workers=2)
    ev_h = st2.left_h - st.left_h
    assert ev_h > 0 and st2.wall_left_h == pytest.approx(st.left_h / 2 + ev_h)
    with pytest.raises(ConfigError, match="--workers must be at least 1, got 0"):
        study_status(study, workers=0)


def test_a_class_no_finished_step_measured_counts_at_the_rough_guess(study: Path) -> None:
    m = measure_study(study)
    (probe,) = [n for n in m.graph.order if m.graph.steps[n].kind == "probes"]
    (m.graph.folder(study, probe) / DONE).unlink()
    st = study_status(study)
    assert not st.classes["probes"].measured
    assert st.classes["probes"].left_h == pytest.approx(m.graph.steps[probe].cost / 3600)
    printed = format_status(st)
    assert f"* {st.guessed_h:.2f} h of it the graph's rough guess, for classes no finished step has measured yet: " \
           "probes" in printed
    assert f"left: about {st.left_h:.2f} step-hours*" in printed


def test_a_run_holding_the_folder_is_named_and_not_called_cut_off(study: Path) -> None:
    runs = json.loads((study / RUNS).read_text())
    working = {**runs[0], "started": "2030-01-01T00:00:00+00:00", "ended": None, "wall_s": None}
    del working["ended"]
    (study / RUNS).write_text(json.dumps([*runs, working]))
    with dir_lock(study, "reproduce"):
        st = study_status(study)
        assert st.in_use == f"reproduce (pid {os.getpid()})"
        assert st.runs is not None and "still at work" in st.runs and "cut off" not in st.runs
    st = study_status(study)
    assert st.in_use is None and st.runs is not None and "1 cut off" in st.runs
    (study / RUNS).write_text("[1, 2")
    st = study_status(study)
    assert st.workers == 1 and st.workers_from == f"{study / RUNS} is damaged; give --workers"


def test_the_command_prints_the_status_and_refuses_a_folder_that_is_no_study(study: Path, tmp_path: Path,
                                                                              capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["status", str(study)]) == 0
    out = capsys.readouterr().out
    assert "running now: nothing" in out and "left: about 0.00 step-hours, 0.00 h on 2 worker(s)" in out
    assert main(["status", str(tmp_path / "nothing")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not a study folder (no study.json)" in err[0]
    assert main(["status", str(study), "--workers", "0"]) == 2
    assert "--workers must be at least 1" in capsys.readouterr().err
