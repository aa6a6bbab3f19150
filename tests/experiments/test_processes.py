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


_ORPHAN_PARENT = """
import multiprocessing as mp, os, sys, time
from latentdrive.experiments.processes import Processes

def job(path):
    with open(path + ".tmp", "w") as f:
        f.write(str(os.getpid()))
    os.replace(path + ".tmp", path)
    time.sleep(120)

if __name__ == "__main__":
    Processes(mp.get_context(sys.argv[2])).start("sleeper", (job, (sys.argv[1],), {}))
    time.sleep(120)
"""


def _gone(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] == "Z"  # a zombie has stopped running
    except FileNotFoundError:
        return True


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="the parent-death signal is Linux's")
@pytest.mark.parametrize("method", ["spawn", "forkserver"])
def test_a_job_dies_with_a_parent_killed_outright(tmp_path, method) -> None:
    """Regression: a parent killed by SIGKILL cannot stop its jobs; they used to run on,
    orphaned. The kernel's parent-death signal now ends them."""
    import signal
    import subprocess
    import sys

    script, pid_file = tmp_path / "parent.py", tmp_path / "child.pid"
    script.write_text(_ORPHAN_PARENT)
    parent = subprocess.Popen([sys.executable, str(script), str(pid_file), method], cwd=tmp_path)
    try:
        deadline = time.monotonic() + 120
        while not pid_file.exists():
            assert parent.poll() is None and time.monotonic() < deadline, "the job never started"
            time.sleep(0.1)
        child = int(pid_file.read_text())
        assert not _gone(child)
        parent.send_signal(signal.SIGKILL)
        parent.wait()
        deadline = time.monotonic() + 30
        while not _gone(child) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert _gone(child)
    finally:
        parent.kill()
        if pid_file.exists() and not _gone(int(pid_file.read_text())):
            os.kill(int(pid_file.read_text()), signal.SIGKILL)


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
