"""RunLog: the one CSV + TensorBoard writer of BNN and policy runs."""

from pathlib import Path

from latentdrive.bnn.runlog import RunLog
from latentdrive.fileio import read_log


def test_a_resumed_log_keeps_the_rows_up_to_its_checkpoint_and_appends(tmp_path: Path) -> None:
    cols = ("step", "loss", "note")
    log = RunLog(tmp_path, {"a.csv": cols, "b.csv": ("step", "x")}, "step", None)
    for step in (1, 2, 3):
        log.write("a.csv", {"step": step, "loss": 0.5 * step, "note": None}, "train")
    log.write("b.csv", {"step": 3, "x": float("nan")}, "eval")
    log.close()
    rows = read_log(tmp_path / "a.csv", columns=cols, key="step", what="log")
    assert [r["step"] for r in rows] == ["1", "2", "3"] and rows[0]["note"] == ""
    # Resumed at step 2: step 3 is about to be redone, so its row goes; b.csv keeps none.
    log = RunLog(tmp_path, {"a.csv": cols, "b.csv": ("step", "x")}, "step", 2,
                 {"a.csv": rows, "b.csv": read_log(tmp_path / "b.csv", columns=("step", "x"), key="step", what="log")})
    log.write("a.csv", {"step": 3, "loss": 9.0, "note": "again"}, "train")
    log.close()
    rows = read_log(tmp_path / "a.csv", columns=cols, key="step", what="log")
    assert [(r["step"], r["loss"]) for r in rows] == [("1", "0.5"), ("2", "1.0"), ("3", "9.0")]
    assert read_log(tmp_path / "b.csv", columns=("step", "x"), key="step", what="log") == []
    # A fresh start (no resume step) drops whatever rows it is given.
    RunLog(tmp_path, {"a.csv": cols}, "step", None, {"a.csv": rows}).close()
    assert read_log(tmp_path / "a.csv", columns=cols, key="step", what="log") == []


def test_the_seconds_logged_before_a_step_add_up_its_epochs_and_refuse_what_is_not_time(tmp_path: Path) -> None:
    import pytest

    from latentdrive.bnn.runlog import logged_seconds
    from latentdrive.config import ConfigError

    rows = [{"kind": "epoch", "step": "4", "elapsed_s": "1.5"}, {"kind": "window", "step": "6", "elapsed_s": ""},
            {"kind": "epoch", "step": "8", "elapsed_s": "2.5"}, {"kind": "epoch", "step": "12", "elapsed_s": "9"}]
    assert logged_seconds(rows, 8, tmp_path) == 4.0 and logged_seconds(rows, 3, tmp_path) == 0.0
    # A log written before times were kept has none to add.
    assert logged_seconds([{"kind": "epoch", "step": "8"}, {**rows[2], "elapsed_s": ""}], 8, tmp_path) == 0.0
    for bad in ("nan", "-1", "soon"):
        with pytest.raises(ConfigError, match=r"at step 8: elapsed_s .* is not a number of seconds"):
            logged_seconds([{**rows[2], "elapsed_s": bad}], 8, tmp_path)
