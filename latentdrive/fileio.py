"""Reading and writing the files latentdrive keeps: atomically, bounded, and confined.

Every artifact (datasets, checkpoints, run configs, reports, figures) is written with
:func:`atomic_write_bytes`, so that a reader, or a run resumed after a crash, sees the old
file or the complete new one and never half of one.

Every file read back as JSON, YAML or text goes through :func:`read_bytes` and its
wrappers: it may come from anywhere (a hand-edited config, a damaged disk, a directory
someone else made), so its size is bounded before it is parsed, and every way it can be
unusable becomes one line that names the file. A file that names another file (a dataset
manifest naming its shards, a checkpoint naming its replay, a report naming its runs) is
only followed inside its own folder: see :func:`confined`.

This module sits below every other one in the package and imports none of them but
:mod:`latentdrive.errors`.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import math
import os
import re
import stat
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path, PurePosixPath
from typing import Any

from latentdrive.errors import LatentDriveError

__all__ = [
    "MAX_CONFIG_BYTES",
    "MAX_JSON_BYTES",
    "MAX_LOG_BYTES",
    "FileFormatError",
    "atomic_write_bytes",
    "atomic_write_text",
    "confined",
    "is_temp_file",
    "output_problem",
    "peak_rss_mb",
    "read_bytes",
    "read_json",
    "read_log",
    "read_text",
    "reset_peak_rss",
    "seconds_logged",
    "seconds_recorded",
    "shown",
]

#: Largest YAML config, preset or scenario spec read (1 MiB): real ones are a few KiB.
MAX_CONFIG_BYTES = 1 << 20
#: Largest JSON document read (64 MiB): a manifest of a paper-sized dataset is a few MiB.
MAX_JSON_BYTES = 64 << 20
#: Largest CSV training log read (metrics.csv, eval.csv: a row every few optimizer steps or
#: every segment; a long run's is a few MiB).
MAX_LOG_BYTES = 256 << 20

TMP_SUFFIX = ".tmp"

#: What a reader raises: an exception type taking the one-line message.
ErrorType = Callable[[str], Exception]


class FileFormatError(LatentDriveError, ValueError):
    """A file cannot be read as what it should be; the one-line message starts with its path."""


# ---------------------------------------------------------------------------------------
# Writing


def _umask() -> int:
    # The umask can only be read by setting it; set it straight back.
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _fsync_folder(folder: Path) -> None:
    """Persist a rename in ``folder``; not every platform allows fsync on a directory."""
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` through a temporary file in the same folder and a rename.

    Readers see the old file or the complete new one. The data is fsynced before the
    rename and the folder after it, so a crash can leave neither a renamed but empty file
    nor a write that silently never happened. The folder is created when missing; the
    file gets the permissions a plain ``open()`` would give it. Returns ``path``.
    """
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=p.parent, prefix=f".{p.name}.", suffix=TMP_SUFFIX)
    try:
        # mkstemp creates the file private (0600); replacing a file must not change who
        # may read it.
        with contextlib.suppress(OSError):
            os.chmod(tmp, 0o666 & ~_umask())
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, p)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    _fsync_folder(p.parent)
    return p


def atomic_write_text(path: str | Path, text: str) -> Path:
    """:func:`atomic_write_bytes` of ``text`` as UTF-8."""
    return atomic_write_bytes(path, text.encode("utf-8"))


def is_temp_file(path: Path) -> bool:
    """Whether ``path`` is a temporary file that an interrupted :func:`atomic_write_bytes` left."""
    return path.name.startswith(".") and path.name.endswith(TMP_SUFFIX)


def output_problem(path: str | Path) -> str | None:
    """Why a file cannot be written at ``path`` (None when it looks writable).

    Commands check the files they will write before a long computation, not after it.
    """
    p = Path(path)
    if p.is_dir():
        return "is a folder"
    for parent in p.parents:
        if parent.exists():
            return None if parent.is_dir() else f"{parent} is not a folder"
    return None


# ---------------------------------------------------------------------------------------
# Reading


def _size(n: int) -> str:
    return f"{n / (1 << 20):g} MiB" if n >= 1 << 20 else f"{n} bytes"


def read_bytes(path: str | Path, *, limit: int, what: str = "file",
               error: ErrorType = FileFormatError) -> bytes:
    """The bytes of ``path``, at most ``limit`` of them.

    A missing file raises ``FileNotFoundError`` unchanged, so that the caller can say what
    creates it. Anything else that keeps the file from being read (a folder, no
    permission, more than ``limit`` bytes, including from a device that never ends)
    raises ``error`` with a one-line message that starts with the path and says ``what``
    was expected.
    """
    p = Path(path)
    too_large = f"{p}: {what} is larger than {_size(limit)}, the most read from such a file"
    try:
        with open(p, "rb") as f:
            st = os.fstat(f.fileno())
            oversize = stat.S_ISREG(st.st_mode) and st.st_size > limit
            data = b"" if oversize else f.read(limit + 1)
    except FileNotFoundError:
        raise
    except IsADirectoryError:
        raise error(f"{p}: is a folder, not a {what}") from None
    except OSError as exc:
        raise error(f"{p}: cannot read {what} ({exc.strerror or type(exc).__name__})") from None
    if oversize or len(data) > limit:
        raise error(too_large)
    return data


def read_text(path: str | Path, *, limit: int, what: str = "file",
              error: ErrorType = FileFormatError) -> str:
    """:func:`read_bytes` decoded as UTF-8; a binary file is an ``error``, not a traceback."""
    data = read_bytes(path, limit=limit, what=what, error=error)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        raise error(f"{path}: {what} is not UTF-8 text (a binary file?)") from None


def read_json(path: str | Path, *, limit: int = MAX_JSON_BYTES, what: str = "JSON file",
              error: ErrorType = FileFormatError) -> Any:
    """The JSON document in ``path``; any unreadable or malformed file is one ``error`` line."""
    text = read_text(path, limit=limit, what=what, error=error)
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise error(f"{path}: {what} is not valid JSON ({exc.msg} at line {exc.lineno})") from None
    except (ValueError, RecursionError) as exc:  # e.g. nesting or integers beyond the parser's limits
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise error(f"{path}: {what} is not usable JSON ({reason})") from None


_COUNT = re.compile(r"[0-9]{1,18}")


def seconds_logged(text: str, where: str, error: ErrorType = FileFormatError) -> float:
    """A duration a CSV log recorded (``elapsed_s``), in seconds: finite and at least 0; an
    empty field (a log from before times were kept) is 0; anything else is one ``error``
    line naming ``where``."""
    if not text:
        return 0.0
    try:
        seconds = float(text)
    except ValueError:
        seconds = math.nan
    return _seconds(seconds, text, where, error, "elapsed_s")


def seconds_recorded(value: object, where: str, error: ErrorType = FileFormatError, *, name: str) -> float:
    """A duration a JSON file recorded under ``name``: a number of seconds, finite and at
    least 0; anything else (a string, ``true``, an integer beyond float's range) is one
    ``error`` line naming ``where``."""
    seconds = math.nan
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        try:
            seconds = float(value)
        except OverflowError:
            seconds = math.inf
    return _seconds(seconds, value, where, error, name)


def _seconds(seconds: float, recorded: object, where: str, error: ErrorType, name: str) -> float:
    if not (math.isfinite(seconds) and seconds >= 0):
        raise error(f"{where}: {name} {shown(recorded)} is not a number of seconds")
    return seconds


def shown(value: object, width: int = 40) -> str:
    """``repr(value)`` cut to ``width`` characters: what an error line quotes of a value a
    file held (a huge integer or string would otherwise fill the line)."""
    text = repr(value)
    return text if len(text) <= width else text[:width - 3] + "..."


def read_log(path: str | Path, *, columns: Sequence[str], key: str, limit: int = MAX_LOG_BYTES,
             what: str = "training log", error: ErrorType = FileFormatError) -> list[dict[str, str]]:
    """The rows of a CSV log that a run appends to (``metrics.csv``), checked.

    The header must name some of ``columns`` (a log written by an older version may lack
    the newer ones), ``key`` among them, each once; every row must have one field per
    column and a count (an integer >= 0) under ``key``. A last line without its line
    break is a row whose writing was cut off (a killed run): it is left out. An empty file
    has no rows. Anything else, a binary file or one larger than ``limit`` included, is
    one ``error`` line that names the file; a missing file raises ``FileNotFoundError``.
    """
    text = read_text(path, limit=limit, what=what, error=error)
    if not text:
        return []
    complete = text.endswith(("\n", "\r"))
    reader = csv.reader(io.StringIO(text, newline=""))
    try:
        lines = [(reader.line_num, row) for row in reader if row]
    except csv.Error as exc:
        raise error(f"{path}: {what} is not CSV (line {reader.line_num}: {exc})") from None
    header, rows = (lines[0][1], lines[1:]) if lines else ([], [])
    unknown = [c for c in header if c not in columns]
    if unknown or key not in header or len(set(header)) != len(header):
        shown = ",".join(header)
        shown = shown if len(shown) <= 80 else shown[:77] + "..."
        raise error(f"{path}: not a {what} (its columns are {shown!r}; expected {key} and others of "
                    f"{', '.join(columns)})")
    if rows and not complete:
        rows.pop()  # cut off while it was written
    k = header.index(key)
    out = []
    for line, row in rows:
        if len(row) != len(header):
            raise error(f"{path}: line {line} of the {what} has {len(row)} fields, its header {len(header)}")
        if not _COUNT.fullmatch(row[k]):
            shown = row[k] if len(row[k]) <= 20 else row[k][:17] + "..."
            raise error(f"{path}: line {line} of the {what} has {key} {shown!r}, not a count")
        out.append(dict(zip(header, row, strict=True)))
    return out


def confined(root: str | Path, name: object, *, source: str | Path,
             error: ErrorType = FileFormatError) -> Path:
    """``root / name`` for a ``name`` read out of the file ``source`` that lives in ``root``.

    A file may only name files inside its own folder: ``name`` must be a non-empty,
    printable relative path without ``..`` or backslashes, and must not lead out of
    ``root`` through a symbolic link either. Anything else (``/etc/passwd``, ``../x``, a number) raises ``error``
    naming ``source`` and the bad name, so a damaged or hostile file cannot make
    latentdrive open, hash or overwrite a file elsewhere.
    """
    base = Path(root)
    # Printable only: no NUL, and no line break that would split an error message naming it.
    if isinstance(name, str) and name.isprintable() and "\\" not in name:
        rel = PurePosixPath(name)
        if rel.parts and not rel.is_absolute() and ".." not in rel.parts:
            full = base / rel
            try:
                inside = full.resolve().is_relative_to(base.resolve())
            except (OSError, RuntimeError):  # a symlink loop
                inside = False
            if inside:
                return full
    shown = repr(name)
    if len(shown) > 80:
        shown = shown[:77] + "..."
    raise error(f"{source}: names {shown}, which is not a path inside its folder {base}")


def reset_peak_rss() -> None:
    """Reset this process's peak resident memory (Linux: ``/proc/self/clear_refs`` 5), so
    that a process reused for several jobs reports each job's own peak. Elsewhere a no-op."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        pass


def peak_rss_mb() -> float:
    """Peak resident memory since :func:`reset_peak_rss`, in MB (``VmHWM``); where /proc is
    missing, the process's lifetime peak."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    import resource
    import sys

    scale = 1024 if sys.platform != "darwin" else 1024 * 1024  # ru_maxrss: KB on Linux, bytes on macOS
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / scale
