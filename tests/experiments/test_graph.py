"""The study graph: keys that change exactly when a step's definition does, resumable
execution in worker processes, failures that cost only their descendants."""

from __future__ import annotations

import json
import os
import signal
import threading
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pytest

from latentdrive.config import ConfigError
from latentdrive.experiments.executor import StepFailed, StepKind, run_local
from latentdrive.experiments.graph import DONE, Graph, Step


def _write(config: Mapping[str, Any], inputs: Mapping[str, Path], folder: Path) -> dict[str, Any]:
    """A toy step: its value plus the sum of its inputs' values; counts its runs in a log."""
    total = config["value"] + sum(json.loads((p / "value.json").read_text()) for p in inputs.values())
    (folder / "value.json").write_text(json.dumps(total))
    with open(folder.parent.parent / "runs.log", "a") as log:
        log.write(f"{folder.name}\n")
    if config.get("fail"):
        raise ValueError("this step always fails\nsecond line")
    if config.get("die"):
        os.kill(os.getpid(), 9)  # as the kernel's out-of-memory killer would
    if config.get("wait_for"):
        (folder / "pid").write_text(str(os.getpid()))
        deadline = time.monotonic() + 60
        while not Path(config["wait_for"]).exists() and time.monotonic() < deadline:
            time.sleep(0.02)
    return {"value": total, "pid": os.getpid(), "nan": float("nan")}


KINDS = {"toy": StepKind(_write)}
# The worker processes' fork server starts once per test session, with the preload of
# whichever test starts it: the study's own, so that study tests run at full speed.
PRELOAD = ("latentdrive.experiments.steps",)


def _diamond(top: int = 1, fail_left: bool = False) -> Graph:
    return Graph([
        Step("top", "toy", {"value": top}),
        Step("left", "toy", {"value": 10, "fail": fail_left}, {"a": "top"}),
        Step("right", "toy", {"value": 100}, {"a": "top"}, cost=5),
        Step("bottom", "toy", {"value": 1000}, {"l": "left", "r": "right"}),
        Step("alone", "toy", {"value": 7}),
    ])


def _runs(out: Path) -> list[str]:
    return (out / "runs.log").read_text().split()


def test_keys_change_downstream_of_a_changed_step_only() -> None:
    a, b = _diamond(top=1), _diamond(top=2)
    assert {n for n in a.order if a.keys[n] != b.keys[n]} == {"top", "left", "right", "bottom"}
    assert _diamond().keys == _diamond().keys
    # The cost estimate is not part of the definition.
    c = Graph([Step("top", "toy", {"value": 1}, cost=99)])
    assert c.keys["top"] == a.keys["top"]


def test_the_graph_refuses_bad_shapes() -> None:
    with pytest.raises(ConfigError, match="two steps are named 'a'"):
        Graph([Step("a", "toy", {}), Step("a", "toy", {})])
    with pytest.raises(ConfigError, match="unknown step 'nope'"):
        Graph([Step("a", "toy", {}, {"x": "nope"})])
    with pytest.raises(ConfigError, match="depend on each other"):
        Graph([Step("a", "toy", {}, {"x": "b"}), Step("b", "toy", {}, {"x": "a"})])


def test_steps_run_once_in_dependency_order_and_resume_skips_them(tmp_path: Path) -> None:
    g = _diamond()
    recs = run_local(g, tmp_path, KINDS, workers=2, preload=PRELOAD, progress=False)
    assert recs["bottom"].summary["value"] == 1000 + (10 + 1) + (100 + 1)
    assert recs["bottom"].summary["nan"] is None  # summaries are always valid JSON
    order = _runs(tmp_path)
    assert sorted(order) == sorted(g.folder(tmp_path, n).name for n in g.order)
    assert order.index(g.folder(tmp_path, "bottom").name) > order.index(g.folder(tmp_path, "left").name)
    # Each step ran in a process of its own, none in this one.
    pids = {r.summary["pid"] for r in recs.values()}
    assert os.getpid() not in pids and len(pids) == len(recs)
    assert all(r.peak_rss_mb > 0 and r.wall_s >= 0 for r in recs.values())

    run_local(g, tmp_path, KINDS, workers=1, preload=PRELOAD, progress=False)
    assert len(_runs(tmp_path)) == len(order)  # nothing ran again

    g2 = _diamond(top=2)
    run_local(g2, tmp_path, KINDS, workers=1, preload=PRELOAD, progress=False)
    assert len(_runs(tmp_path)) == len(order) + 4  # the changed step and its descendants
    assert g.record(tmp_path, "top") is not None  # the old version is left alone


def test_a_failed_step_costs_only_its_descendants(tmp_path: Path) -> None:
    g = _diamond(fail_left=True)
    with pytest.raises(StepFailed) as info:
        run_local(g, tmp_path, KINDS, workers=2, preload=PRELOAD, progress=False)
    msg = str(info.value)
    assert "left: ValueError: this step always fails" in msg and "second line" not in msg
    assert "1 steps that need them" in msg
    assert g.record(tmp_path, "right") is not None and g.record(tmp_path, "alone") is not None
    assert g.record(tmp_path, "left") is None and g.record(tmp_path, "bottom") is None
    assert not (g.folder(tmp_path, "bottom")).exists()


def test_an_interrupted_step_runs_again_from_a_clean_folder(tmp_path: Path) -> None:
    g = _diamond()
    stale = g.folder(tmp_path, "top")
    stale.mkdir(parents=True)
    (stale / "half-written.tmp").write_text("x")  # what a killed attempt leaves: no done.json
    run_local(g, tmp_path, KINDS, workers=1, preload=PRELOAD, progress=False)
    assert not (stale / "half-written.tmp").exists() and (stale / DONE).exists()


def test_a_foreign_record_is_a_one_line_error(tmp_path: Path) -> None:
    g = _diamond()
    run_local(g, tmp_path, KINDS, workers=1, preload=PRELOAD, progress=False)
    path = g.folder(tmp_path, "alone") / DONE
    data = json.loads(path.read_text())
    path.write_text(json.dumps({**data, "key": "0" * 12}))
    with pytest.raises(ConfigError, match="records step 'alone' with key 000000000000"):
        g.record(tmp_path, "alone")
    path.write_text("[1, 2")
    with pytest.raises(ConfigError) as info:
        g.record(tmp_path, "alone")
    assert "\n" not in str(info.value) and str(path) in str(info.value)
    for bad in ("NaN", -1.0):  # Regression: a NaN time reached the report as a TypeError
        path.write_text(json.dumps({**data, "wall_s": bad}))
        with pytest.raises(ConfigError, match=r"not a step record \(wall_s"):
            g.record(tmp_path, "alone")
        path.write_text(json.dumps({**data, "resumed_s": bad}))
        with pytest.raises(ConfigError, match=r"not a step record \(wall_s .*resumed_s"):
            g.record(tmp_path, "alone")
    # A record written before resumed_s was kept reads as a step run in one go.
    path.write_text(json.dumps({k: v for k, v in data.items() if k != "resumed_s"}))
    rec = g.record(tmp_path, "alone")
    assert rec is not None and rec.resumed_s == 0 and rec.cost_s == rec.wall_s


def _resumed(config: Mapping[str, Any], inputs: Mapping[str, Path], folder: Path) -> dict[str, Any]:
    """A toy step that reports the seconds an earlier attempt spent."""
    return {"value": 1, "resumed_s": 12.5}


def test_a_resumed_steps_earlier_attempts_count_in_its_cost(tmp_path: Path) -> None:
    g = Graph([Step("s", "resumed", {})])
    run_local(g, tmp_path, {"resumed": StepKind(_resumed, resumable=True)}, workers=1, preload=PRELOAD, progress=False)
    rec = g.record(tmp_path, "s")
    assert rec is not None and rec.resumed_s == 12.5 and rec.summary == {"value": 1}
    assert rec.cost_s == pytest.approx(rec.wall_s + 12.5)


def test_a_worker_killed_mid_step_fails_its_step_only(tmp_path: Path) -> None:
    # Regression: with a process pool, one killed worker broke the pool, failed the steps
    # running beside it and ended the study with a traceback.
    g = Graph([Step("dies", "toy", {"value": 1, "die": True}), Step("slow", "toy", {"value": 2}),
               Step("after", "toy", {"value": 3}, {"a": "slow"}), Step("more", "toy", {"value": 4})])
    with pytest.raises(StepFailed) as info:
        run_local(g, tmp_path, KINDS, workers=2, preload=PRELOAD, progress=False)
    assert "dies: its process died (killed by signal 9)" in str(info.value)
    assert all(g.record(tmp_path, n) is not None for n in ("slow", "after", "more"))


def _gone(pid: int, within: float = 10.0) -> bool:
    deadline = time.monotonic() + within
    while time.monotonic() < deadline:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return True
        time.sleep(0.05)
    return False


def test_an_interrupt_stops_the_running_step_and_a_rerun_finishes_it(tmp_path: Path) -> None:
    go = tmp_path / "go"
    g = Graph([Step("long", "toy", {"value": 1, "wait_for": str(go)})])
    folder = g.folder(tmp_path, "long")

    seen: dict[str, float | bool] = {}

    def ctrl_c() -> None:
        start = time.monotonic()
        while not (folder / "pid").exists() and time.monotonic() < start + 60:
            time.sleep(0.02)
        seen.update(pid_file=(folder / "pid").exists(), after_s=time.monotonic() - start)
        # To the main thread itself: a process-directed SIGINT may land on this thread,
        # and then the main thread's wait on the step is not interrupted until it ends.
        signal.pthread_kill(threading.main_thread().ident or 0, signal.SIGINT)

    # Ctrl-C as at a terminal: a shell that starts the tests in the background (`cmd &`)
    # hands them SIGINT ignored, and Python then never raises KeyboardInterrupt.
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    threading.Thread(target=ctrl_c, daemon=True).start()
    started = time.monotonic()
    try:
        run_local(g, tmp_path, KINDS, workers=1, preload=PRELOAD, progress=False)
    except KeyboardInterrupt:
        pass
    else:
        pytest.fail(f"the study was not interrupted: it ran {time.monotonic() - started:.1f} s; "
                    f"the interrupt thread saw {seen}")
    finally:
        signal.signal(signal.SIGINT, before)
    # The step's process does not outlive the study, and the step is not recorded as done.
    assert _gone(int((folder / "pid").read_text()))
    assert g.record(tmp_path, "long") is None
    go.write_text("")
    run_local(g, tmp_path, KINDS, workers=1, preload=PRELOAD, progress=False)
    rec = g.record(tmp_path, "long")
    assert rec is not None and rec.summary["value"] == 1


def test_a_retried_task_whose_step_had_finished_keeps_its_results(tmp_path: Path) -> None:
    # A Ray worker can die after writing done.json and before reporting back; Ray then
    # runs the task again, which must not clear the finished folder and redo the work.
    from latentdrive.experiments.executor import StepRecords, execute_step

    g = _diamond()
    records = StepRecords(g, tmp_path)
    first = execute_step(KINDS["toy"], g.steps["top"], g.keys["top"], {}, g.folder(tmp_path, "top"), records)
    again = execute_step(KINDS["toy"], g.steps["top"], g.keys["top"], {}, g.folder(tmp_path, "top"), records)
    assert again == first and _runs(tmp_path) == [g.folder(tmp_path, "top").name]
