"""The one exception type the command line prints without a traceback.

It lives in a module of its own, below every other, so that the lowest modules (file
input and output) can raise it without importing the configuration machinery.
"""

from __future__ import annotations

__all__ = ["LatentDriveError"]


class LatentDriveError(Exception):
    """An error caused by the user's input, with a one-line message that names the problem.

    The CLI prints these without a traceback and exits non-zero.
    """
