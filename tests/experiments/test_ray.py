"""The study's steps as Ray tasks: the same numbers as local workers, and a worker killed
mid-step is retried without losing what had finished."""

from __future__ import annotations

import json
import os
import shutil
import signal
import sys
import threading
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pytest
from helpers import study_numbers

from latentdrive.cli import main
from latentdrive.experiments.executor import StepKind
from latentdrive.experiments.graph import Graph, Step
from latentdrive.experiments.study import build_graph, load_reproduce_config

ray = pytest.importorskip("ray")


def test_the_tiny_study_through_ray_gives_the_numbers_of_local_workers(tiny_study: Path, tmp_path: Path) -> None:
    out = tmp_path / "ray"
    shutil.copytree(tiny_study, out)
    graph = build_graph(load_reproduce_config("tiny"))
    # One step of every kind runs again, on Ray this time.
    redo = ["dataset", "bnn/d4", "bnn/report", "policy/raw/merge/s0", "policy/latent/roundabout-finetuned/s0",
            "evaluate/policy/raw/merge/s0", "evaluate/ref/plan", "probes"]
    for name in redo:
        shutil.rmtree(graph.folder(out, name))
    assert main(["reproduce", str(out), "--preset", "tiny", "--ray", "local", "--workers", "2", "-q"]) == 0
    assert all(graph.record(out, n) is not None for n in redo)
    assert study_numbers(out) == study_numbers(tiny_study)
    # The run is logged step by step through Ray's executor as through local workers.
    last = json.loads((out / "runs.json").read_text())[-1]
    assert last["workers"] == "ray local" and last["steps"] == len(redo) and last["ended"] == "finished"


def _slow(config: Mapping[str, Any], inputs: Mapping[str, Path], folder: Path) -> dict[str, Any]:
    """Records its process id, then takes a while: long enough to be killed on the first try."""
    attempts = folder.parent / f"{config['name']}.pids"
    with open(attempts, "a") as f:
        f.write(f"{os.getpid()}\n")
    if len(attempts.read_text().split()) == 1 and config.get("slow"):
        time.sleep(60)
    (folder / "value.json").write_text(json.dumps(config["name"]))
    return {"attempts": len(attempts.read_text().split())}


def test_a_killed_ray_worker_is_retried_and_nothing_finished_is_lost(tmp_path: Path) -> None:
    from latentdrive.experiments.ray_executor import run_ray

    graph = Graph([Step("a", "slow", {"name": "a"}), Step("b", "slow", {"name": "b", "slow": True}, {"x": "a"})])
    kinds = {"slow": StepKind(_slow)}
    pids = tmp_path / "steps" / "b.pids"

    def kill_first_attempt() -> None:
        # Generous: on a loaded 2-core machine a local Ray cluster took over 120 s to start
        # the step. Without the file the test fails below, on the attempt count.
        deadline = time.monotonic() + 600
        while not pids.exists() and time.monotonic() < deadline:
            time.sleep(0.1)
        if pids.exists():
            os.kill(int(pids.read_text().split()[0]), signal.SIGKILL)

    killer = threading.Thread(target=kill_first_attempt)
    killer.start()
    # Ray's workers import this module to run its step function.
    tests = str(Path(__file__).resolve().parents[1])
    records = run_ray(graph, tmp_path, kinds, "local", retries=2, progress=False,
                      runtime_env={"env_vars": {"PYTHONPATH": os.pathsep.join([tests, *sys.path])}})
    killer.join()
    assert records["b"].summary["attempts"] == 2
    assert records["a"].summary["attempts"] == 1  # finished before the kill: not run again
