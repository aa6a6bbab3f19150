"""Run independent jobs, each in a fresh process, a few at a time.

For resumable jobs that write their own results (BNN runs of the study): a job that fails
stops the others at once (they continue from their last checkpoint when run again), an
interrupt stops them all, and a process that dies gives a one-line error, not a broken
pool. Processes are spawned: a forked child would inherit torch's thread pools and locks.
"""

from __future__ import annotations

import multiprocessing as mp
from collections.abc import Callable, Mapping
from multiprocessing.connection import wait as mp_wait
from typing import Any

from latentdrive.errors import LatentDriveError, first_line

__all__ = ["Job", "run_processes"]

#: ``(function, args, kwargs)``: a module-level function (sent to the child by reference).
Job = tuple[Callable[..., Any], tuple[Any, ...], Mapping[str, Any]]


def _child(conn: Any, job: Job) -> None:
    fn, args, kwargs = job
    try:
        conn.send((True, fn(*args, **kwargs)))
    except BaseException as exc:  # reported by the parent with the job's name
        conn.send((False, first_line(exc) if isinstance(exc, LatentDriveError) else
                   f"{type(exc).__name__}: {first_line(exc)}"))
    finally:
        conn.close()


def run_processes(jobs: Mapping[str, Job], workers: int,
                  on_done: Callable[[str, Any], None] | None = None) -> dict[str, Any]:
    """Run ``jobs`` (name → job), at most ``workers`` at once, in the order given; returns
    name → result. ``on_done(name, result)`` is called as each one finishes.

    Raises:
        LatentDriveError: ``"<name>: <the job's error>"`` for the first job that fails or
            whose process dies; the jobs still running are terminated first.
    """
    if workers < 1:
        raise LatentDriveError(f"workers must be at least 1, got {workers}")
    ctx = mp.get_context("spawn")
    todo = list(jobs.items())
    live: dict[Any, tuple[str, Any, Any]] = {}  # sentinel → (name, process, connection)
    results: dict[str, Any] = {}
    try:
        while todo or live:
            while todo and len(live) < workers:
                name, job = todo.pop(0)
                recv, send = ctx.Pipe(duplex=False)
                p = ctx.Process(target=_child, args=(send, job), name=f"latentdrive {name}")
                p.start()
                send.close()
                live[p.sentinel] = (name, p, recv)
            # Waiting on the pipes too means a child never blocks on a full pipe.
            ready = set(mp_wait([x for _, p, c in live.values() for x in (c, p.sentinel)]))
            for sentinel, (name, p, conn) in list(live.items()):
                if conn not in ready and sentinel not in ready:
                    continue
                try:
                    msg = conn.recv() if conn.poll() else None
                except EOFError:  # closed with nothing in it: the process died
                    msg = None
                p.join()
                conn.close()
                del live[sentinel]
                if msg is None:
                    code = p.exitcode
                    how = f"killed by signal {-code}" if code is not None and code < 0 else f"exit code {code}"
                    raise LatentDriveError(f"{name}: its process died ({how}) before finishing; "
                                           f"run the same command again to resume")
                ok, value = msg
                if not ok:
                    raise LatentDriveError(f"{name}: {value}")
                results[name] = value
                if on_done is not None:
                    on_done(name, value)
    finally:
        for _, p, _ in live.values():
            p.terminate()
        for _, p, conn in live.values():
            p.join()
            conn.close()
    return results
