"""Which code produced a result: the git commit of the checkout latentdrive runs from."""

from __future__ import annotations

import functools
import hashlib
import os
import subprocess
from pathlib import Path

__all__ = ["loaded_revision", "source_revision"]

#: What decides a result: the package and its requirements; docs and tests do not.
_CODE = ("latentdrive", "pyproject.toml")


def source_revision(root: Path | None = None) -> str | None:
    """The commit (12 hex digits) of the git checkout this package is imported from (or of
    ``root``), with ``+changes.<8 hex digits>`` when the package's files (tracked or new)
    or ``pyproject.toml`` differ from it, the digits a hash of what those files now hold
    (two runs with the same digits ran the same code); None outside a checkout (an
    installed wheel) or where git cannot say.

    Never raises: a result is not lost to a question about its provenance.
    """
    root = Path(__file__).resolve().parent.parent if root is None else root
    if not (root / ".git").exists():  # a folder, or a file in a worktree
        return None
    try:
        head = _git(root, "rev-parse", "HEAD").strip().decode("ascii")
        changed = _git(root, "status", "--porcelain", "-z", "--untracked-files=all", "--", *_CODE)
    except (OSError, subprocess.SubprocessError, ValueError):
        return None
    return head[:12] + (f"+changes.{_changes_digest(root, changed)}" if changed.strip(b"\0") else "")


def _changes_digest(root: Path, status: bytes) -> str:
    """A hash of what every path ``git status -z`` lists holds in the working tree: the
    commit plus these determine the code. Only the files' names and contents count, not
    the index or the user's diff settings, so one tree has one name on every machine."""
    fields = status.split(b"\0")
    paths: set[bytes] = set()
    i = 0
    while i < len(fields):
        entry = fields[i]
        i += 1
        if len(entry) < 4:
            continue
        paths.add(entry[3:])
        if entry[:1] in (b"R", b"C"):  # a rename or copy in the index: its origin follows
            paths.add(fields[i])
            i += 1
    h = hashlib.sha256()
    for name in sorted(paths):
        h.update(name + b"\0" + _state(root / os.fsdecode(name)) + b"\0")
    return h.hexdigest()[:8]


def _state(path: Path) -> bytes:
    """What ``path`` holds: a file's bytes, a link's target, or what it is otherwise."""
    try:
        if path.is_symlink():
            return b"link:" + os.fsencode(os.readlink(path))
        if path.is_dir():
            return b"folder"
        if not path.exists():
            return b"deleted"
        return b"file:" + hashlib.sha256(path.read_bytes()).digest()
    except OSError:
        return b"unreadable"


def _git(root: Path, *args: str) -> bytes:
    """git's output in the checkout ``root``, whatever repository a caller's environment points
    git at (GIT_* dropped), without optional locks so that a user's own git command is never
    refused meanwhile."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("GIT_")}
    return subprocess.run(["git", "--no-optional-locks", "-C", str(root), *args], capture_output=True, timeout=5,
                          check=True, env=env).stdout


@functools.cache
def loaded_revision() -> str | None:
    """:func:`source_revision` as of this process's first call. Called where the code that
    produces results is imported, it names that code even if the checkout changes later
    while the process runs (a long study's workers keep the code they loaded)."""
    return source_revision()
