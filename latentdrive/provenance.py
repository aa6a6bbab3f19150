"""Which code produced a result: the git commit of the checkout latentdrive runs from."""

from __future__ import annotations

import subprocess
from pathlib import Path

__all__ = ["source_revision"]


def source_revision() -> str | None:
    """The commit (12 hex digits) of the git checkout this package is imported from, with
    ``+changes`` when its tracked files differ from that commit; None outside a checkout (an
    installed wheel) or where git cannot say.

    Asked afresh at each call: a long study may outlive a commit of the tree it runs from.
    """
    root = Path(__file__).resolve().parent.parent
    if not (root / ".git").exists():  # a folder, or a file in a worktree
        return None
    try:
        def git(*args: str) -> str:
            return subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, timeout=30,
                                  check=True).stdout.strip()

        head = git("rev-parse", "HEAD")
        changed = git("status", "--porcelain", "--untracked-files=no")
    except (OSError, subprocess.SubprocessError):
        return None
    return head[:12] + ("+changes" if changed else "")
