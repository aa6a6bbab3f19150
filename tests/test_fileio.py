"""latentdrive.fileio: the one atomic write, bounded reads, and names confined to their folder;
and, over the whole package, that nothing writes or unpickles around them."""

from __future__ import annotations

import ast
import functools
import os
import re
import stat
from pathlib import Path

import pytest
from helpers import examples
from hypothesis import given, settings
from hypothesis import strategies as st

from latentdrive import fileio
from latentdrive.fileio import (
    FileFormatError,
    atomic_write_bytes,
    atomic_write_text,
    confined,
    is_temp_file,
    read_bytes,
    read_json,
    read_log,
    read_text,
)

PACKAGE = Path(fileio.__file__).parent


def _one_line_naming(exc: pytest.ExceptionInfo[BaseException], path: object) -> None:
    msg = str(exc.value)
    assert msg.startswith(str(path)) and "\n" not in msg, msg


# ---------------------------------------------------------------------------------------
# Writing


def test_atomic_write_syncs_the_file_and_then_its_folder(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    synced: list[str] = []
    real_fsync = os.fsync

    def recording_fsync(fd: int) -> None:
        synced.append("folder" if stat.S_ISDIR(os.fstat(fd).st_mode) else "file")
        real_fsync(fd)

    monkeypatch.setattr(fileio.os, "fsync", recording_fsync)
    out = atomic_write_text(tmp_path / "new" / "a.json", "{}\n")
    assert out.read_text() == "{}\n"
    assert synced == ["file", "folder"]
    assert oct(out.stat().st_mode & 0o777) == oct(0o666 & ~_umask())


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = atomic_write_bytes(tmp_path / "a.bin", b"old")

    def full_disk(src: str, dst: str) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(fileio.os, "replace", full_disk)
    with pytest.raises(OSError, match="disk full"):
        atomic_write_bytes(path, b"new")
    assert path.read_bytes() == b"old"
    assert os.listdir(tmp_path) == ["a.bin"]


def test_temporary_names_are_recognised(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    seen: list[Path] = []
    real_replace = os.replace

    def spy(src: str, dst: str) -> None:
        seen.append(Path(src))
        real_replace(src, dst)

    monkeypatch.setattr(fileio.os, "replace", spy)
    atomic_write_bytes(tmp_path / "s.npz", b"x")
    assert len(seen) == 1 and is_temp_file(seen[0]) and seen[0].parent == tmp_path
    assert not is_temp_file(tmp_path / "s.npz")


# ---------------------------------------------------------------------------------------
# Reading


def test_reads_are_bounded_and_errors_are_one_line(tmp_path: Path) -> None:
    big = tmp_path / "big.json"
    big.write_bytes(b" " * 101)
    with pytest.raises(FileFormatError, match="larger than 100 bytes") as exc:
        read_bytes(big, limit=100)
    _one_line_naming(exc, big)
    assert read_bytes(big, limit=101) == b" " * 101
    # A device that never ends is cut off at the bound, not read forever.
    with pytest.raises(FileFormatError, match="larger than"):
        read_bytes("/dev/zero", limit=1000)
    with pytest.raises(FileFormatError, match="is a folder") as exc:
        read_text(tmp_path, limit=100, what="config file")
    _one_line_naming(exc, tmp_path)
    with pytest.raises(FileNotFoundError):
        read_bytes(tmp_path / "missing", limit=100)


@pytest.mark.parametrize(("content", "needle"), [
    (bytes(range(256)), "not UTF-8"),
    (b'{"a": ', "not valid JSON"),
    (b"[" * 10_000, "JSON"),
    (b"1" * 5000, "not usable JSON"),
])
def test_unusable_json_is_one_line(tmp_path: Path, content: bytes, needle: str) -> None:
    path = tmp_path / "x.json"
    path.write_bytes(content)
    with pytest.raises(FileFormatError, match=needle) as exc:
        read_json(path)
    _one_line_naming(exc, path)


def test_callers_choose_the_error_type(tmp_path: Path) -> None:
    class Mine(Exception):
        pass

    path = tmp_path / "x.json"
    path.write_bytes(b"\xff")
    with pytest.raises(Mine):
        read_json(path, error=Mine)


COLUMNS = ("step", "loss", "lr")


def test_a_log_reads_as_rows_with_a_count_under_its_key(tmp_path: Path) -> None:
    path = tmp_path / "metrics.csv"
    path.write_bytes(b"step,loss,lr\r\n1,0.5,0.1\r\n\r\n2,nan,\r\n")
    assert read_log(path, columns=COLUMNS, key="step") == [
        {"step": "1", "loss": "0.5", "lr": "0.1"}, {"step": "2", "loss": "nan", "lr": ""}]
    # An older version's log, without the newer columns, in another order.
    path.write_text("loss,step\n0.5,1\n")
    assert read_log(path, columns=COLUMNS, key="step") == [{"loss": "0.5", "step": "1"}]
    # A last row cut off while a killed run wrote it is left out; an empty log has no rows.
    path.write_text("step,loss,lr\n1,0.5,0.1\n2,0.")
    assert read_log(path, columns=COLUMNS, key="step") == [{"step": "1", "loss": "0.5", "lr": "0.1"}]
    path.write_text("")
    assert read_log(path, columns=COLUMNS, key="step") == []
    with pytest.raises(FileNotFoundError):
        read_log(tmp_path / "missing.csv", columns=COLUMNS, key="step")


@pytest.mark.parametrize(("content", "needle"), [
    (bytes(range(256)) * 4, "not UTF-8"),
    (b"step,loss\n1," + b"9" * 200_000 + b"\n", "not CSV (line 2: field larger than field limit"),
    (b"a,b,c\n1,2,3\n", "not a metrics log (its columns are 'a,b,c'"),
    (b"loss,lr\n1,2\n", "not a metrics log"),
    (b"step,step\n1,2\n", "not a metrics log"),
    (b"\n\n", "not a metrics log"),
    (b"kind,step\nstep,abc\n", "line 2 of the metrics log has step 'abc', not a count"),
    (b"step,loss\n-1,2\n", "has step '-1', not a count"),
    (b"step,loss\n1\n2,3\n", "line 2 of the metrics log has 1 fields, its header 2"),
    (b"step,loss\n1,2,3\n", "has 3 fields"),
])
def test_a_damaged_log_is_one_line(tmp_path: Path, content: bytes, needle: str) -> None:
    path = tmp_path / "metrics.csv"
    path.write_bytes(content)
    with pytest.raises(FileFormatError, match=re.escape(needle)) as exc:
        read_log(path, columns=(*COLUMNS, "kind"), key="step", what="metrics log")
    _one_line_naming(exc, path)


def test_a_log_is_read_within_its_bound(tmp_path: Path) -> None:
    path = tmp_path / "metrics.csv"
    with path.open("wb") as f:  # sparse: nothing of it is read
        f.truncate(fileio.MAX_LOG_BYTES + 1)
    with pytest.raises(FileFormatError, match="larger than 256 MiB") as exc:
        read_log(path, columns=COLUMNS, key="step")
    _one_line_naming(exc, path)


# ---------------------------------------------------------------------------------------
# Names read out of files


@pytest.mark.parametrize("name", ["/etc/passwd", "../x", "a/../../x", "a/..", "", ".", "..", "x\x00y",
                                  "a\\..\\x", "line\nbreak", 3, None, ["a"]])
def test_names_outside_the_folder_are_refused(tmp_path: Path, name: object) -> None:
    source = tmp_path / "manifest.json"
    with pytest.raises(FileFormatError, match="not a path inside its folder") as exc:
        confined(tmp_path, name, source=source)
    _one_line_naming(exc, source)


def test_names_inside_the_folder_are_followed(tmp_path: Path) -> None:
    assert confined(tmp_path, "s.npz", source=tmp_path / "m") == tmp_path / "s.npz"
    assert confined(tmp_path, "sub/s.npz", source=tmp_path / "m") == tmp_path / "sub" / "s.npz"


def test_a_symlink_out_of_the_folder_is_refused(tmp_path: Path) -> None:
    root = tmp_path / "ds"
    root.mkdir()
    (tmp_path / "secret").write_text("x")
    (root / "s.npz").symlink_to(tmp_path / "secret")
    (root / "loop").symlink_to(root / "loop")
    for name in ("s.npz", "loop"):
        with pytest.raises(FileFormatError):
            confined(root, name, source=root / "manifest.json")


@settings(max_examples=examples(200), deadline=None)
@given(name=st.text(max_size=30) | st.sampled_from(["..", "/", "./../x", "a/./b", "//x"]))
def test_a_followed_name_always_stays_inside(tmp_path_factory: pytest.TempPathFactory, name: str) -> None:
    root = tmp_path_factory.getbasetemp() / "confined-root"
    root.mkdir(exist_ok=True)
    try:
        path = confined(root, name, source=root / "m.json")
    except FileFormatError as exc:
        assert "\n" not in str(exc)
        return
    assert path.resolve().is_relative_to(root.resolve()) and path.resolve() != root.resolve()


# ---------------------------------------------------------------------------------------
# The package as a whole


@functools.cache
def _calls(path: Path) -> list[tuple[str, ast.Call]]:
    """Every call in a source file, as the dotted name it is made through."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Call):
            parts = []
            f: ast.expr = node.func
            while isinstance(f, ast.Attribute):
                parts.append(f.attr)
                f = f.value
            if isinstance(f, ast.Name):
                parts.append(f.id)
            out.append((".".join(reversed(parts)), node))
    return out


SOURCES = sorted(PACKAGE.rglob("*.py"))


def test_the_scan_sees_the_package() -> None:
    names = {name for p in SOURCES for name, _ in _calls(p)}
    assert "atomic_write_bytes" in names and "np.load" in names and "os.replace" in names


def test_nothing_is_unpickled() -> None:
    """No torch.load, no pickle, and numpy loads with allow_pickle=False only."""
    found = []
    for path in SOURCES:
        text = path.read_text()
        if "import pickle" in text or "from pickle" in text or "import dill" in text:
            found.append(f"{path.name}: imports pickle")
        for name, call in _calls(path):
            if name.endswith("torch.load") or name.startswith("pickle.") or name.endswith("joblib.load"):
                found.append(f"{path.name}:{call.lineno}: {name}")
            if name in ("np.load", "numpy.load"):
                kw = {k.arg: k.value for k in call.keywords}
                flag = kw.get("allow_pickle")
                if not (isinstance(flag, ast.Constant) and flag.value is False):
                    found.append(f"{path.name}:{call.lineno}: np.load without allow_pickle=False")
    assert not found


def test_every_file_is_written_through_the_one_atomic_write() -> None:
    """Renames, temporary files and direct writes live in latentdrive.fileio only."""
    found = []
    for path in SOURCES:
        if path.name == "fileio.py" and path.parent == PACKAGE:
            continue
        for name, call in _calls(path):
            last = name.rsplit(".", 1)[-1]
            if name in ("os.replace", "os.rename", "tempfile.mkstemp", "tempfile.NamedTemporaryFile") \
                    or last in ("write_text", "write_bytes", "savefig"):
                # savefig to an in-memory buffer is fine; to a path it is not.
                if last == "savefig" and call.args and isinstance(call.args[0], ast.Name) and call.args[0].id == "buf":
                    continue
                found.append(f"{path.relative_to(PACKAGE)}:{call.lineno}: {name}")
    assert not found


def test_the_peak_memory_mark_resets_between_jobs() -> None:
    from latentdrive.fileio import peak_rss_mb, reset_peak_rss

    reset_peak_rss()
    block = bytearray(200 << 20)  # 200 MB, touched so it is resident
    block[:: 4096] = b"x" * len(block[:: 4096])
    high = peak_rss_mb()
    del block
    reset_peak_rss()
    assert high - peak_rss_mb() > 150
