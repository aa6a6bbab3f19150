"""Processes latentdrive starts end with the process that started them (``latentdrive.lifetime``)."""

from __future__ import annotations

import os
import time

import pytest

_ORPHAN_PARENT = """
import multiprocessing as mp, os, sys, time
from latentdrive.data.collect import worker_pool
from latentdrive.experiments.processes import Processes

def job(path):
    with open(path + ".tmp", "w") as f:
        f.write(str(os.getpid()))
    os.replace(path + ".tmp", path)
    time.sleep(120)

if __name__ == "__main__":
    if sys.argv[2] == "collect":
        worker_pool(1).submit(job, sys.argv[1])
    else:
        Processes(mp.get_context(sys.argv[2])).start("sleeper", (job, (sys.argv[1],), {}))
    time.sleep(120)
"""


def _gone(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] == "Z"  # a zombie has stopped running
    except FileNotFoundError:
        return True


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="reads process states from /proc")
@pytest.mark.parametrize("method", ["spawn", "forkserver", "collect"])
def test_a_job_dies_with_a_parent_killed_outright(tmp_path, method) -> None:
    """Regression: a parent killed by SIGKILL cannot stop its jobs (the study's steps under
    the forkserver, the BNN study's runs under spawn, data collection's pool workers); they
    used to run on, orphaned. Each now watches its parent and ends with it."""
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
