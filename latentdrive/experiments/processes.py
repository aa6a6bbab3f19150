"""Jobs each in a fresh process, a few at a time: the study's steps and the BNN study's runs.

A process per job, not a pool: a job whose process dies (killed, out of memory) fails
alone, where a broken pool would take every running job down with it. :class:`Processes`
starts jobs and collects their results or their errors' first lines; the study's executor
schedules steps on it, and :func:`run_processes` runs independent resumable jobs (BNN
runs), stopping them all at the first failure or an interrupt, since they continue from
their last checkpoints when run again.
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
from collections.abc import Callable, Mapping, Sequence
from multiprocessing.connection import wait as mp_wait
from typing import Any

from latentdrive.errors import LatentDriveError, first_line
from latentdrive.lifetime import die_with_parent

__all__ = ["Job", "ProcessDied", "Processes", "run_processes"]

#: ``(function, args, kwargs)``: a module-level function (sent to the child by reference).
Job = tuple[Callable[..., Any], tuple[Any, ...], Mapping[str, Any]]


class ProcessDied(LatentDriveError):
    """A job's process ended without sending a result (killed, out of memory, ``os._exit``)."""


def _error(exc: BaseException) -> tuple[bool, str]:
    return False, first_line(exc) if isinstance(exc, LatentDriveError) else f"{type(exc).__name__}: {first_line(exc)}"


def _child(conn: Any, job: Job) -> None:
    die_with_parent()
    fn, args, kwargs = job
    try:
        msg: tuple[bool, Any] = (True, fn(*args, **kwargs))
    except BaseException as exc:  # reported by the parent with the job's name
        msg = _error(exc)
    gone = (BrokenPipeError, ConnectionResetError)  # the parent stopped listening: no one to tell
    try:
        conn.send(msg)
    except gone:
        pass
    except Exception as exc:  # a result that cannot be sent (unpicklable): pickling fails
        with contextlib.suppress(*gone):  # before a byte is written, so the pipe is still clean
            conn.send(_error(exc))
    finally:
        conn.close()


class _Running:
    """A job's process and the pipe its result comes back on."""

    def __init__(self, process: Any, conn: Any) -> None:
        self.process, self.conn = process, conn


class Processes:
    """Jobs, each in its own process of the multiprocessing context ``ctx`` (spawn by
    default: a forked child would inherit torch's thread pools and locks)."""

    def __init__(self, ctx: Any = None) -> None:
        self.ctx = ctx if ctx is not None else mp.get_context("spawn")
        self.live: set[_Running] = set()

    def start(self, name: str, job: Job) -> _Running:
        """Start ``job`` in a new process named after ``name``; returns its handle."""
        recv, send = self.ctx.Pipe(duplex=False)
        p = self.ctx.Process(target=_child, args=(send, job), name=f"latentdrive {name}")
        try:
            p.start()
        except BaseException:  # e.g. a job that cannot be sent to the child: no pipe left open
            recv.close()
            raise
        finally:
            send.close()
        h = _Running(p, recv)
        self.live.add(h)
        return h

    def wait(self, handles: Sequence[_Running]) -> list[_Running]:
        """Block until at least one of ``handles`` has finished; return the finished ones."""
        # A result arriving, or a process ending without one, wakes the caller; waiting on
        # the pipe too means a child never blocks on a full pipe while the caller waits.
        ready = set(mp_wait([x for h in handles for x in (h.conn, h.process.sentinel)]))
        return [h for h in handles if h.conn in ready or h.process.sentinel in ready]

    def result(self, h: _Running) -> Any:
        """The finished job's return value.

        Raises:
            LatentDriveError: the job's error (its first line, with the exception's type
                unless it was a LatentDriveError).
            ProcessDied: ``its process died (…) before finishing``, when the process
                ended without a result.
        """
        try:
            msg = h.conn.recv() if h.conn.poll() else None
        except EOFError:  # the pipe closed with nothing in it: the process died
            msg = None
        finally:
            h.process.join()
            h.conn.close()
            self.live.discard(h)
        if msg is None:
            code = h.process.exitcode
            how = f"killed by signal {-code}" if code is not None and code < 0 else f"exit code {code}"
            raise ProcessDied(f"its process died ({how}) before finishing")
        ok, value = msg
        if not ok:
            raise LatentDriveError(value)
        return value

    def stop(self) -> None:
        """Terminate every job still running and wait for their processes to end."""
        for h in list(self.live):
            h.process.terminate()
        for h in list(self.live):
            h.process.join()
            h.conn.close()
        self.live.clear()


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
    pool = Processes()
    todo = list(jobs.items())
    running: dict[_Running, str] = {}
    results: dict[str, Any] = {}
    try:
        while todo or running:
            while todo and len(running) < workers:
                name, job = todo.pop(0)
                running[pool.start(name, job)] = name
            for h in pool.wait(list(running)):
                name = running.pop(h)
                try:
                    results[name] = pool.result(h)
                except ProcessDied as exc:
                    raise LatentDriveError(f"{name}: {exc}; run the same command again to resume") from None
                except LatentDriveError as exc:
                    raise LatentDriveError(f"{name}: {exc}") from None
                if on_done is not None:
                    on_done(name, results[name])
    finally:
        pool.stop()
    return results
