"""The study's step functions: what they hand the step record."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from latentdrive.data.shards import MANIFEST, SHARD_WALL
from latentdrive.experiments.executor import StepRecords, execute_step
from latentdrive.experiments.graph import DONE, RESUMED, Graph, Step
from latentdrive.experiments.steps import STEP_KINDS

COLLECT = {"scenarios": ["merge", "highway"], "episodes": 4, "shard_size": 40,
           "env": {"observation": {"height": 16, "width": 32, "frames": 2}, "duration": 3}}


def test_a_resumed_dataset_step_records_what_its_earlier_attempt_spent(tmp_path: Path) -> None:
    graph = Graph([Step(name="dataset", kind="dataset", config={"collect": COLLECT})])
    step, key, folder = graph.steps["dataset"], graph.keys["dataset"], graph.folder(tmp_path, "dataset")
    records = StepRecords(graph, tmp_path)
    whole = execute_step(STEP_KINDS["dataset"], step, key, {}, folder, records)
    assert whole.resumed_s == 0 and RESUMED not in whole.summary
    # As if the first attempt had been cut off after all but one shard: the kept shards'
    # recorded shares are what the second attempt resumed from (set large so that they show).
    (folder / DONE).unlink()
    manifest = json.loads((folder / "data" / MANIFEST).read_text())
    last = sorted(manifest["shards"])[-1]
    del manifest["shards"][last]
    for entry in manifest["shards"].values():
        entry[SHARD_WALL] = 100.0
    (folder / "data" / MANIFEST).write_text(json.dumps(manifest))
    (folder / "data" / last).unlink()
    resumed = execute_step(STEP_KINDS["dataset"], step, key, {}, folder, records)
    assert len(manifest["shards"]) > 0 and resumed.resumed_s == pytest.approx(100.0 * len(manifest["shards"]))
    assert resumed.cost_s == pytest.approx(resumed.wall_s + resumed.resumed_s)
    assert graph.record(tmp_path, "dataset") == resumed
