"""One writer per output directory.

``collect`` and ``train-bnn`` resume whatever they find in their output directory; two
processes doing that at once would each redo the other's work and overwrite its files.
:func:`dir_lock` holds an advisory ``flock`` on ``DIR/.latentdrive.lock`` for the duration
of a run. The operating system drops it when the process ends however it ends, so a
killed run never leaves a stale lock behind. The lock is re-entrant within a process
(a study that trains into a directory it already holds does not block itself). Where
``fcntl`` is missing (Windows) or the filesystem refuses ``flock``, runs go unlocked.
"""

from __future__ import annotations

import contextlib
import errno
import os
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from latentdrive.config import LatentDriveError

try:
    import fcntl
except ImportError:  # pragma: no cover - not on POSIX
    fcntl = None  # type: ignore[assignment]

__all__ = ["LOCK_NAME", "UNKNOWN", "DirectoryInUse", "Turn", "dir_lock", "holder"]

#: flock's errors where the filesystem cannot lock at all: run unlocked rather than fail.
_UNLOCKABLE = (errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL)

#: The lock file's name; dataset and run directories ignore it.
LOCK_NAME = ".latentdrive.lock"

# Directories this process holds, with their nesting depth. Process-wide on purpose: flock
# conflicts between two opens of one file even within a process.
_held: dict[Path, int] = {}
_held_guard = threading.Lock()


class DirectoryInUse(LatentDriveError):
    """Another process holds the directory's lock."""


@contextlib.contextmanager
def dir_lock(directory: str | Path, what: str) -> Iterator[None]:
    """Hold ``directory``'s lock (creating the directory) while the block runs.

    ``what`` names the kind of run (``"collect"``, ``"train-bnn"``); it is recorded in the
    lock file with the pid, for the error another process gets. Raises
    :class:`DirectoryInUse`, naming the directory and the holder, when another process
    holds it.
    """
    d = Path(directory)
    if d.exists() and not d.is_dir():
        raise LatentDriveError(f"{d}: exists and is not a directory")
    d.mkdir(parents=True, exist_ok=True)
    key = d.resolve()
    with _held_guard:
        if key in _held:
            _held[key] += 1
            reentered = True
        else:
            reentered = False
    if reentered:
        try:
            yield
        finally:
            with _held_guard:
                _held[key] -= 1
        return
    if fcntl is None:  # pragma: no cover
        yield
        return
    with (d / LOCK_NAME).open("a+") as f:
        try:
            _lock_exclusive(f.fileno())
        except BlockingIOError:
            f.seek(0)
            who = f.read().strip() or "another run"
            raise DirectoryInUse(
                f"{d}: in use by {who}; wait for it to finish or use another directory"
            ) from None
        except OSError as exc:
            if exc.errno not in _UNLOCKABLE:
                raise
            print(f"latentdrive: {d}: cannot lock ({exc.strerror}); running unlocked", file=sys.stderr)
            yield
            return
        f.seek(0)
        f.truncate()
        f.write(f"{what} (pid {os.getpid()})\n")
        f.flush()
        with _held_guard:
            _held[key] = 1
        try:
            yield
        finally:
            with _held_guard:
                del _held[key]
            fcntl.flock(f.fileno(), fcntl.LOCK_UN)


#: How long :func:`dir_lock` tries before calling a directory in use (seconds): a
#: :func:`holder` probe holds a shared lock for an instant, which must not refuse a run.
_PATIENCE_S = 0.5


def _lock_exclusive(fd: int) -> None:
    """Take ``fd``'s exclusive lock, trying for :data:`_PATIENCE_S`; BlockingIOError when
    it stays held."""
    deadline = time.monotonic() + _PATIENCE_S
    while True:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return
        except BlockingIOError:
            if time.monotonic() >= deadline:
                raise
            time.sleep(0.02)


#: :func:`holder`'s answer where it cannot tell (no locks here, an unreadable lock file).
UNKNOWN = "unknown (the lock cannot be read here)"


def holder(directory: str | Path) -> str | None:
    """Who holds ``directory``'s lock: the line its holder wrote (e.g. ``reproduce (pid
    123)``), None when no process does (or the directory was never locked), or
    :data:`UNKNOWN`. Nothing is written; the probe holds a shared lock for an instant,
    which :func:`dir_lock` waits out."""
    path = Path(directory) / LOCK_NAME
    if fcntl is None:  # pragma: no cover - not on POSIX
        return UNKNOWN
    if not path.exists():
        return None
    try:
        f = path.open()
    except OSError:  # unreadable, or not a file
        return UNKNOWN
    with f:
        try:
            fcntl.flock(f.fileno(), fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            return f.read().strip() or "another run"
        except OSError:
            return UNKNOWN
        fcntl.flock(f.fileno(), fcntl.LOCK_UN)
    return None


class Turn:
    """A blocking, exclusive ``flock`` on ``path`` that the processes of one machine take in
    turn: :meth:`acquire` waits for it, :meth:`release` (or leaving the ``with`` block, or
    the process ending) passes it on. Unlike :func:`dir_lock` it is released wherever the
    holder decides, not at the end of a block. Unlocked where ``flock`` is missing or refused.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._file: Any = None

    def acquire(self) -> None:
        if fcntl is None or self._file is not None:  # pragma: no cover - not on POSIX
            return
        f = self.path.open("a")
        try:
            fcntl.flock(f.fileno(), fcntl.LOCK_EX)
        except OSError as exc:
            f.close()
            if exc.errno not in _UNLOCKABLE:
                raise
            print(f"latentdrive: {self.path}: cannot lock ({exc.strerror}); taking turns unlocked", file=sys.stderr)
            return
        except BaseException:  # interrupted while waiting
            f.close()
            raise
        self._file = f

    def release(self) -> None:
        f, self._file = self._file, None
        if f is not None:
            fcntl.flock(f.fileno(), fcntl.LOCK_UN)
            f.close()

    def __enter__(self) -> Turn:
        self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()
