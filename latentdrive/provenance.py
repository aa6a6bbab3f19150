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
    or ``pyproject.toml`` differ from it, the digits a hash of those differences (two runs
    with the same ones ran the same code); None outside a checkout (an installed wheel) or
    where git cannot say.

    Never raises: a result is not lost to a question about its provenance.
    """
    root = Path(__file__).resolve().parent.parent if root is None else root
    if not (root / ".git").exists():  # a folder, or a file in a worktree
        return None
    try:
        head = _git(root, "rev-parse", "HEAD").decode("ascii")
        changed = _git(root, "status", "--porcelain", "-z", "--untracked-files=all", "--", *_CODE)
        digest = _changes_digest(root, changed) if changed else ""
    except (OSError, subprocess.SubprocessError, ValueError):
        return None
    return head[:12] + (f"+changes.{digest}" if changed else "")


def _changes_digest(root: Path, status: bytes) -> str:
    """A hash of how the code differs from its commit: the diff of tracked files, and the
    names and bytes of new ones."""
    h = hashlib.sha256(_git(root, "diff", "HEAD", "--binary", "--", *_CODE))
    for entry in sorted(status.split(b"\0")):
        if entry.startswith(b"?? "):
            name = entry[3:]
            h.update(b"\0" + name + b"\0" + (root / os.fsdecode(name)).read_bytes())
    return h.hexdigest()[:8]


def _git(root: Path, *args: str) -> bytes:
    """git's output in the checkout ``root``, whatever repository a caller's environment points
    git at (GIT_* dropped), without optional locks so that a user's own git command is never
    refused meanwhile."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("GIT_")}
    return subprocess.run(["git", "--no-optional-locks", "-C", str(root), *args], capture_output=True, timeout=5,
                          check=True, env=env).stdout.strip()


@functools.cache
def loaded_revision() -> str | None:
    """:func:`source_revision` as of this process's first call. Called where the code that
    produces results is imported, it names that code even if the checkout changes later
    while the process runs (a long study's workers keep the code they loaded)."""
    return source_revision()
