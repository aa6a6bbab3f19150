"""Independent jobs in their own processes: results, a failing job, a dying process."""

from __future__ import annotations

import os
import time

import pytest

from latentdrive.config import ConfigError
from latentdrive.errors import LatentDriveError
from latentdrive.experiments.processes import run_processes


def _fail(message: str) -> None:
    raise ConfigError(message)


def test_every_job_runs_and_reports_its_result() -> None:
    done: list[str] = []
    out = run_processes({"a": (pow, (2, 3), {}), "b": (pow, (3, 2), {}), "c": (int, ("11",), {"base": 2})}, 2,
                        on_done=lambda name, _: done.append(name))
    assert out == {"a": 8, "b": 9, "c": 3}
    assert sorted(done) == ["a", "b", "c"]


def test_a_failing_job_stops_the_others_at_once_with_a_one_line_error() -> None:
    t0 = time.perf_counter()
    with pytest.raises(LatentDriveError, match=r"^bad: d = 3 is not allowed$"):
        run_processes({"slow": (time.sleep, (120,), {}), "bad": (_fail, ("d = 3 is not allowed",), {}),
                       "never": (time.sleep, (120,), {})}, 2)
    # Not after the two-minute job: it was terminated, and the third never started.
    assert time.perf_counter() - t0 < 60


def test_a_process_that_dies_is_named_with_its_exit_code() -> None:
    with pytest.raises(LatentDriveError, match=r"^gone: its process died \(exit code 3\) before finishing"):
        run_processes({"gone": (os._exit, (3,), {})}, 1)


def test_workers_must_be_positive() -> None:
    with pytest.raises(LatentDriveError, match="workers must be at least 1"):
        run_processes({}, 0)
