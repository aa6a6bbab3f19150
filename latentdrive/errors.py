"""The one exception type the command line prints without a traceback.

It lives in a module of its own, below every other, so that the lowest modules (file
input and output) can raise it without importing the configuration machinery.
"""

from __future__ import annotations

__all__ = ["LatentDriveError", "Terminated", "first_line", "printable"]


def printable(text: str) -> str:
    """``text`` with line breaks and other control characters escaped, so that names read
    from a file (a key such as ``"\\n"``) cannot split a message over several lines."""
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


def first_line(exc: BaseException) -> str:
    """The first non-empty line of an exception's message (or its type's name), for quoting
    a library's multi-line error inside one of ours."""
    lines = str(exc).strip().splitlines()
    return lines[0] if lines else type(exc).__name__


class LatentDriveError(Exception):
    """An error caused by the user's input, with a one-line message that names the problem.

    The CLI prints these without a traceback and exits non-zero. The message is kept to one
    line whatever it quotes: control characters are escaped on construction.
    """

    def __init__(self, *args: object) -> None:
        if len(args) == 1 and isinstance(args[0], str):
            args = (printable(args[0]),)
        super().__init__(*args)


class Terminated(KeyboardInterrupt):
    """SIGTERM (a batch scheduler's stop, ``kill PID``), raised in the main thread by the
    command line's handler.

    A subclass of KeyboardInterrupt so that every clean-up an interrupt runs (child
    processes stopped, nothing half-written) runs on a terminate too; the CLI exits 143.
    """
