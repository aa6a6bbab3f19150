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
    assert rev is not None and re.fullmatch(r"[0-9a-f]{12}(\+changes)?", rev)
    assert rev == head[:12] + ("+changes" if changed else "")


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
