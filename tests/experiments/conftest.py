from pathlib import Path

import pytest

from latentdrive.cli import main


@pytest.fixture(scope="session")
def tiny_study(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The tiny study, run once per test session with two local workers."""
    out = tmp_path_factory.mktemp("study") / "out"
    assert main(["reproduce", str(out), "--preset", "tiny", "--workers", "2", "-q"]) == 0
    return out
