"""Which commit produced a result."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

import latentdrive.provenance as provenance
from latentdrive.provenance import source_revision

ROOT = Path(provenance.__file__).resolve().parent.parent


@pytest.mark.skipif(not (ROOT / ".git").exists(), reason="latentdrive is not imported from a git checkout")
def test_a_checkout_names_its_commit_and_whether_tracked_files_changed() -> None:
    head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"], capture_output=True, text=True,
                          check=True).stdout.strip()
    # The package and its requirements decide results; docs and tests do not.
    changed = subprocess.run(["git", "-C", str(ROOT), "status", "--porcelain", "--", "latentdrive", "pyproject.toml"],
                             capture_output=True, text=True, check=True).stdout.strip()
    rev = source_revision()
    assert rev is not None and re.fullmatch(r"[0-9a-f]{12}(\+changes\.[0-9a-f]{8})?", rev)
    assert rev.startswith(head[:12]) and ("+changes" in rev) == bool(changed)


def test_the_changes_are_named_by_a_hash_of_what_they_are(tmp_path: Path) -> None:
    def git(*args: str) -> None:
        subprocess.run(["git", "-C", str(tmp_path), "-c", "user.name=t", "-c", "user.email=t@t", *args],
                       check=True, capture_output=True)

    git("init", "-q")
    code = tmp_path / "latentdrive" / "a.py"
    code.parent.mkdir()
    code.write_text("x = 1\n")
    git("add", ".")
    git("commit", "-qm", "one")
    clean = source_revision(tmp_path)
    assert clean is not None and re.fullmatch(r"[0-9a-f]{12}", clean)
    (tmp_path / "notes.md").write_text("docs do not decide results\n")
    assert source_revision(tmp_path) == clean
    seen = set()
    for edit in ("x = 2\n", "x = 3\n", "x = 2\n"):
        code.write_text(edit)
        rev = source_revision(tmp_path)
        assert rev is not None and rev.startswith(clean + "+changes.")
        seen.add(rev)
    assert len(seen) == 2  # the same change, the same name; another change, another
    code.write_text("x = 1\n")
    new = tmp_path / "latentdrive" / "b.py"
    new.write_text("y = 1\n")  # a new file of the package counts, by its bytes
    one = source_revision(tmp_path)
    new.write_text("y = 2\n")
    assert one != source_revision(tmp_path) and "+changes." in str(one)
    new.unlink()
    assert source_revision(tmp_path) == clean
    # The name is the tree's, not the index's: the same edit staged or not reads alike.
    code.write_text("x = 2\n")
    unstaged = source_revision(tmp_path)
    git("add", "latentdrive/a.py")
    assert source_revision(tmp_path) == unstaged
    git("reset", "-q")
    # A deleted file, a staged rename and odd names are changes too, each its own.
    code.write_text("x = 1\n")
    code.unlink()
    deleted = source_revision(tmp_path)
    git("checkout", "--", "latentdrive/a.py")
    git("mv", "latentdrive/a.py", "latentdrive/b c.py")
    renamed = source_revision(tmp_path)
    assert len({deleted, renamed, clean}) == 3 and "+changes." in str(deleted) and "+changes." in str(renamed)
    git("mv", "latentdrive/b c.py", "latentdrive/a.py")
    assert source_revision(tmp_path) == clean


def test_what_git_lists_but_cannot_be_read_still_names_the_commit(tmp_path: Path) -> None:
    def git(*args: str) -> None:
        subprocess.run(["git", "-C", str(tmp_path), "-c", "user.name=t", "-c", "user.email=t@t", *args],
                       check=True, capture_output=True)

    git("init", "-q")
    (tmp_path / "latentdrive").mkdir()
    (tmp_path / "latentdrive" / "a.py").write_text("x = 1\n")
    git("add", ".")
    git("commit", "-qm", "one")
    clean = source_revision(tmp_path)
    assert clean is not None
    (tmp_path / "latentdrive" / "gone.py").symlink_to(tmp_path / "nowhere")  # a broken link
    nested = tmp_path / "latentdrive" / "vendored"  # another repository inside: git lists the folder
    nested.mkdir()
    subprocess.run(["git", "-C", str(nested), "init", "-q"], check=True)
    rev = source_revision(tmp_path)
    assert rev is not None and re.fullmatch(re.escape(clean) + r"\+changes\.[0-9a-f]{8}", rev)


def test_without_git_the_commit_is_unknown(monkeypatch: pytest.MonkeyPatch) -> None:
    def no_git(*args: object, **kwargs: object) -> None:
        raise FileNotFoundError("git")

    monkeypatch.setattr(provenance.subprocess, "run", no_git)
    assert source_revision() is None


def test_the_revision_of_the_loaded_code_is_pinned_at_the_first_call(monkeypatch: pytest.MonkeyPatch) -> None:
    provenance.loaded_revision.cache_clear()
    monkeypatch.setattr(provenance, "source_revision", lambda: "aaaaaaaaaaaa")
    assert provenance.loaded_revision() == "aaaaaaaaaaaa"
    # The checkout moves on while the process runs the code it loaded: the first answer stays.
    monkeypatch.setattr(provenance, "source_revision", lambda: "bbbbbbbbbbbb")
    assert provenance.loaded_revision() == "aaaaaaaaaaaa"
    provenance.loaded_revision.cache_clear()
