"""One writer per output directory.

``collect`` and ``train-bnn`` resume whatever they find in their output directory; two
processes doing that at once would each redo the other's work and overwrite its files.
:func:`dir_lock` holds an advisory ``flock`` on ``DIR/.latentdrive.lock`` for the duration
of a run. The operating system drops it when the process ends however it ends, so a
killed run never leaves a stale lock behind. Where ``fcntl`` is missing (Windows) runs
are not locked.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

from latentdrive.config import LatentDriveError

try:
    import fcntl
except ImportError:  # pragma: no cover - not on POSIX
    fcntl = None  # type: ignore[assignment]

__all__ = ["LOCK_NAME", "DirectoryInUse", "dir_lock"]

#: The lock file's name; dataset and run directories ignore it.
LOCK_NAME = ".latentdrive.lock"


class DirectoryInUse(LatentDriveError):
    """Another process holds the directory's lock."""


@contextlib.contextmanager
def dir_lock(directory: str | Path, what: str) -> Iterator[None]:
    """Hold ``directory``'s lock (creating the directory) while the block runs.

    ``what`` names the kind of run for the error message (``"collect"``, ``"train-bnn"``).
    Raises :class:`DirectoryInUse`, naming the directory and the holder's pid, when
    another process holds it.
    """
    d = Path(directory)
    if d.exists() and not d.is_dir():
        raise LatentDriveError(f"{d}: exists and is not a directory")
    d.mkdir(parents=True, exist_ok=True)
    if fcntl is None:  # pragma: no cover
        yield
        return
    with (d / LOCK_NAME).open("a+") as f:
        try:
            fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            f.seek(0)
            holder = f.read().strip() or "unknown pid"
            raise DirectoryInUse(
                f"{d}: in use by another {what} run ({holder}); wait for it to finish or use "
                "another directory"
            ) from None
        f.seek(0)
        f.truncate()
        f.write(f"pid {os.getpid()}\n")
        f.flush()
        try:
            yield
        finally:
            fcntl.flock(f.fileno(), fcntl.LOCK_UN)
