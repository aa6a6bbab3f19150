"""Fixtures: one tiny dataset collected once per session, copied by tests that modify it."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from latentdrive.config import validate
from latentdrive.data.collect import CollectConfig, collect


def tiny_config(**changes: object) -> CollectConfig:
    """Two fast scenarios, short episodes, a 2-frame 16×32 grid: a dataset in about a second."""
    base: dict[str, object] = {
        "scenarios": ["merge", "highway"],
        "episodes": 6,
        "shard_size": 40,
        "env": {"observation": {"height": 16, "width": 32, "frames": 2}, "duration": 4},
    }
    base.update(changes)
    return validate(CollectConfig, base)


@pytest.fixture(scope="session")
def collected(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Directory of the tiny dataset (do not modify; use ``dataset_copy``)."""
    root = tmp_path_factory.mktemp("collected") / "ds"
    collect(tiny_config(), root, progress=False)
    return root


@pytest.fixture
def dataset_copy(collected: Path, tmp_path: Path) -> Path:
    """A private copy of the tiny dataset that a test may damage."""
    dst = tmp_path / "ds"
    shutil.copytree(collected, dst)
    return dst
