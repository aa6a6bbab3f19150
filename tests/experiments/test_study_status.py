"""``latentdrive status``: a study folder's progress, read without changing it."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

from latentdrive.cli import main
from latentdrive.experiments.graph import DONE
from latentdrive.experiments.reproduce import measure_study
from latentdrive.experiments.study_status import format_status, study_status
from latentdrive.runlock import dir_lock


def _snapshot(root: Path) -> dict[str, bytes | None]:
    return {str(p.relative_to(root)): (None if p.is_dir() else p.read_bytes()) for p in sorted(root.rglob("*"))}


@pytest.fixture
def study(tiny_study: Path, tmp_path: Path) -> Path:
    out = tmp_path / "study"
    shutil.copytree(tiny_study, out)
    return out


def test_a_finished_study_has_nothing_left(study: Path) -> None:
    st = study_status(study)
    assert st.finished == st.steps > 0 and not st.begun and st.left_h == 0 and st.wall_left_h == 0
    assert st.workers == 2  # the logged run's
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


def test_a_class_no_finished_step_measured_counts_at_the_rough_guess(study: Path) -> None:
    m = measure_study(study)
    (probe,) = [n for n in m.graph.order if m.graph.steps[n].kind == "probes"]
    (m.graph.folder(study, probe) / DONE).unlink()
    st = study_status(study)
    assert not st.classes["probes"].measured
    assert st.classes["probes"].left_h == pytest.approx(m.graph.steps[probe].cost / 3600)
    assert "* not measured by a finished step yet: the graph's rough guess (probes)" in format_status(st)


def test_a_run_holding_the_folder_is_named(study: Path) -> None:
    with dir_lock(study, "reproduce"):
        assert study_status(study).in_use == f"reproduce (pid {os.getpid()})"
    assert study_status(study).in_use is None


def test_the_command_prints_the_status_and_refuses_a_folder_that_is_no_study(study: Path, tmp_path: Path,
                                                                              capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["status", str(study)]) == 0
    out = capsys.readouterr().out
    assert "running now: nothing" in out and "left: 0.00 step-hours" in out
    assert main(["status", str(tmp_path / "nothing")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not a study folder (no study.json)" in err[0]
    assert main(["status", str(study), "--workers", "0"]) == 2
    assert "--workers must be at least 1" in capsys.readouterr().err
