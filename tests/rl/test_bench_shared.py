"""`latentdrive bench --train --processes N`: the measurement in N processes at once."""

import json
import queue
import subprocess
import sys
from types import SimpleNamespace
from typing import Any

import pytest

from latentdrive.config import ConfigError
from latentdrive.errors import LatentDriveError
from latentdrive.rl import bench_shared as shared
from latentdrive.rl.bench import bench_training
from latentdrive.rl.bench_shared import SharedRow, _collect, bench_training_shared, format_shared

from .test_bench import SMALL


def test_each_process_is_measured_and_set_against_the_measurement_alone():
    alone, shared = bench_training_shared(2, ["raw"], ["merge"], transitions=24, updates=2, envs=2, overrides=SMALL)
    (base,), (row,) = alone, shared
    assert (row.mode, row.precision, row.device) == (base.mode, base.precision, base.device)
    assert len(row.per_process) == 2 and all(r > 0 for r in row.per_process)
    assert row.alone == base.transitions_per_s and row.total == pytest.approx(sum(row.per_process))
    text = format_shared(shared)
    assert "2 processes at once" in text and f"{row.median / row.alone:.2f}x" in text


def test_the_median_and_sum_are_the_processes():
    row = SharedRow("raw", "cpu", "fp32", (100.0, 300.0, 200.0), alone=400.0)
    assert row.median == 200.0 and row.total == 600.0
    assert row.as_dict()["processes"] == 3 and "0.50x" in format_shared([row])


def test_a_bad_mode_fails_before_any_process_starts(monkeypatch):
    # The second mode is the bad one: the lone run would time the first before failing.
    def no_run(*args, **kwargs):
        raise AssertionError("measured before the modes were checked")

    monkeypatch.setattr(shared, "bench_training", no_run)
    with pytest.raises(ConfigError):
        bench_training_shared(2, ["raw", "no-such-mode"], ["merge"], transitions=24, envs=2, overrides=SMALL)
    with pytest.raises(ConfigError):
        bench_training_shared(2, ["raw"], ["merge"], transitions=24, envs=2, overrides={**SMALL, "dqn": {"gamma": 2.0}})
    with pytest.raises(ValueError, match="at least 2"):
        bench_training_shared(1, ["raw"], ["merge"])


def test_a_failure_inside_a_process_is_reported_with_its_cause_not_the_others_broken_barrier():
    results: queue.Queue = queue.Queue()
    results.put((1, None, "BrokenBarrierError: "))
    results.put((0, None, "ValueError: the replay is empty"))
    procs = [SimpleNamespace(exitcode=1), SimpleNamespace(exitcode=1)]
    with pytest.raises(LatentDriveError, match="process 0: ValueError: the replay is empty"):
        _collect(procs, results)


def test_a_process_killed_before_reporting_is_named():
    results: queue.Queue = queue.Queue()
    results.put((0, [{"mode": "raw"}], None))
    procs = [SimpleNamespace(exitcode=0), SimpleNamespace(exitcode=-9)]
    with pytest.raises(LatentDriveError, match="process 1 exited with code -9"):
        _collect(procs, results)


def test_a_process_that_exits_without_its_result_is_named_even_with_code_0():
    results: queue.Queue = queue.Queue()
    procs = [SimpleNamespace(exitcode=0)]
    with pytest.raises(LatentDriveError, match="process 0 exited with code 0 before reporting"):
        _collect(procs, results)


class _Counting:
    """A :class:`~latentdrive.rl.bench.Together` that another process ends after ``after`` checks."""

    def __init__(self, after: int) -> None:
        self.starts = self.ends = self.checks = 0
        self.after = after

    def start(self) -> None:
        self.starts += 1

    def over(self) -> bool:
        self.checks += 1
        return self.checks > self.after

    def end(self) -> None:
        self.ends += 1


def test_each_timed_loop_starts_together_and_stops_when_another_process_is_done():
    kwargs: dict[str, Any] = {"transitions": 400, "updates": 2, "envs": 2, "overrides": SMALL}
    free = _Counting(after=10**9)
    (full,) = bench_training(["raw"], ["merge"], **kwargs, together=free)
    assert (free.starts, free.ends) == (1, 1) and free.checks > 50  # it ran its 400 transitions
    stopped = _Counting(after=3)
    (early,) = bench_training(["raw"], ["merge"], **kwargs, together=stopped)
    # Three vector steps, then the fourth check finds the window over.
    assert (stopped.starts, stopped.ends) == (1, 1) and stopped.checks == 4
    assert early.env_steps_per_s > 0 and full.env_steps_per_s > 0


def test_every_process_reporting_gives_their_rows_in_process_order():
    results: queue.Queue = queue.Queue()
    results.put((1, [{"mode": "b"}], None))
    results.put((0, [{"mode": "a"}], None))
    assert _collect([SimpleNamespace(exitcode=0)] * 2, results) == [[{"mode": "a"}], [{"mode": "b"}]]


def test_the_cli_refuses_processes_without_train_and_with_repeat(tmp_path):
    def cli(*args):
        return subprocess.run([sys.executable, "-m", "latentdrive", "bench", *args], capture_output=True, text=True)

    out = cli("--processes", "2", "--scenarios", "merge")
    assert out.returncode != 0 and "--processes" in out.stderr and "--train" in out.stderr
    out = cli("--train", "--processes", "2", "--repeat", "2", "--scenarios", "merge")
    assert out.returncode != 0 and "--repeat" in out.stderr
    path = tmp_path / "rows.json"
    out = cli("--train", "--processes", "2", "--modes", "raw", "--scenarios", "merge", "--steps", "24",
              "--batch-size", "2", "--json", str(path), *[f"--set={k}" for k in (
                  "precision=fp32", "observation.height=16", "observation.width=32", "observation.frames=2",
                  "dqn.learning_starts=16", "dqn.batch_size=4", "dqn.buffer_size=200")])
    assert out.returncode == 0, out.stderr
    data = json.loads(path.read_text())
    assert len(data["alone"]) == 1 and data["at_once"][0]["processes"] == 2
    assert "2 processes at once" in out.stdout
