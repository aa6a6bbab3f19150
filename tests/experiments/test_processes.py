"""Jobs in their own processes: results, a failing job, a dying process, stopping."""

from __future__ import annotations

import os
import time

import pytest

from latentdrive.config import ConfigError
from latentdrive.errors import LatentDriveError
from latentdrive.experiments.processes import ProcessDied, Processes, run_processes


def _fail(message: str) -> None:
    raise ConfigError(message)


def test_every_job_runs_and_reports_its_result() -> None:
    done: list[str] = []
    out = run_processes({"a": (pow, (2, 3), {}), "b": (pow, (3, 2), {}), "c": (int, ("11",), {"base": 2})}, 2,
                        on_done=lambda name, _: done.append(name))
    assert out == {"a": 8, "b": 9, "c": 3}
    assert sorted(done) == ["a", "b", "c"]


def test_a_failing_job_stops_the_others_at_once_with_a_one_line_error() -> None:
    t0 = time.perf_counter()
    with pytest.raises(LatentDriveError, match=r"^bad: d = 3 is not allowed$"):
        run_processes({"slow": (time.sleep, (120,), {}), "bad": (_fail, ("d = 3 is not allowed",), {}),
                       "never": (time.sleep, (120,), {})}, 2)
    # Not after the two-minute job: it was terminated, and the third never started.
    assert time.perf_counter() - t0 < 60


def test_a_process_that_dies_is_named_with_its_exit_code() -> None:
    with pytest.raises(LatentDriveError, match=r"^gone: its process died \(exit code 3\) before finishing"):
        run_processes({"gone": (os._exit, (3,), {})}, 1)


def test_workers_must_be_positive() -> None:
    with pytest.raises(LatentDriveError, match="workers must be at least 1"):
        run_processes({}, 0)


def test_a_job_whose_error_mentions_a_dying_process_is_not_told_to_resume() -> None:
    with pytest.raises(LatentDriveError, match=r"^odd: its process died here$"):
        run_processes({"odd": (_fail, ("its process died here",), {})}, 1)


def test_processes_return_results_errors_and_deaths_and_stop_what_runs() -> None:
    pool = Processes()
    ok, bad, gone = (pool.start("ok", (pow, (2, 5), {})), pool.start("bad", (_fail, ("no",), {})),
                     pool.start("gone", (os._exit, (4,), {})))
    waiting = [ok, bad, gone]
    outcomes: dict[str, object] = {}
    while waiting:
        for h in pool.wait(waiting):
            waiting.remove(h)
            name = {id(ok): "ok", id(bad): "bad", id(gone): "gone"}[id(h)]
            try:
                outcomes[name] = pool.result(h)
            except ProcessDied as exc:
                outcomes[name] = f"died: {exc}"
            except LatentDriveError as exc:
                outcomes[name] = f"error: {exc}"
    assert outcomes == {"ok": 32, "bad": "error: no", "gone": "died: its process died (exit code 4) before finishing"}
    assert not pool.live
    # stop() terminates what still runs, at once.
    slow = pool.start("slow", (time.sleep, (120,), {}))
    t0 = time.perf_counter()
    pool.stop()
    assert not slow.process.is_alive() and not pool.live and time.perf_counter() - t0 < 30


def test_a_job_that_cannot_be_sent_leaves_nothing_running() -> None:
    pool = Processes()
    with pytest.raises(Exception):  # noqa: B017 - pickling a lambda fails with the pickler's own error
        pool.start("lambda", (lambda: 1, (), {}))
    assert not pool.live


def test_a_job_whose_parent_stopped_listening_ends_quietly() -> None:
    """Regression: a step finishing just as its study was terminated printed a
    BrokenPipeError traceback under the parent's one-line message."""
    import multiprocessing as mp

    from latentdrive.experiments.processes import _child

    for fn in (int, _fails):
        recv, send = mp.Pipe(duplex=False)
        recv.close()
        _child(send, (fn, (), {}))  # raises nothing
        assert send.closed


def _fails() -> None:
    raise LatentDriveError("no")


def _unpicklable() -> object:
    import threading

    return threading.Lock()


def test_a_result_that_cannot_be_sent_is_reported_as_the_jobs_error() -> None:
    """Regression: an unpicklable result printed a traceback in the child and was reported
    as a dead process ('run the same command again'), which rerunning cannot mend."""
    with pytest.raises(LatentDriveError, match="j: TypeError: cannot pickle"):
        run_processes({"j": (_unpicklable, (), {})}, workers=1)
