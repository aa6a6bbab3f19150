"""``scripts/bnn_misses.py``: held-out recall by scenario, channel and vehicles per frame."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

from latentdrive.cli import main
from latentdrive.config import validate
from latentdrive.data.collect import CollectConfig, collect
from latentdrive.data.dataset import ShardDataset
from latentdrive.fileio import read_json

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "bnn_misses.py"
TINY = {
    "scenarios": ["merge", "highway"], "episodes": 4, "shard_size": 40,
    "env": {"observation": {"height": 16, "width": 32, "frames": 2}, "duration": 3},
}


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    w = tmp_path_factory.mktemp("misses")
    collect(validate(CollectConfig, TINY), w / "ds", progress=False)
    assert main(["train-bnn", str(w / "ds"), str(w / "run"), "--latent-dim", "4", "--channels", "4",
                 "--epochs", "1", "--val-fraction", "0.5", "-q", "--set", "pretrain_epochs=1",
                 "--set", "epoch_steps=2", "--set", "batch_size=8"]) == 0
    return w / "run"


def _rows(out: str) -> list[list[str]]:
    return [line.split() for line in out.splitlines()[2:]]


def test_counts_every_held_out_vehicle(run: Path) -> None:
    out = subprocess.run([sys.executable, str(SCRIPT), str(run), "--batches", "1000"],
                         capture_output=True, text=True, check=True).stdout
    rows = _rows(out)
    totals = {ch: sum(int(r[4]) for r in rows if r[0] == "all" and r[1] == ch) for ch in ("HV", "AV")}
    by_scenario = {ch: sum(int(r[4]) for r in rows if r[0] != "all" and r[1] == ch) for ch in ("HV", "AV")}
    assert totals == by_scenario
    # Counted independently: 8-connected blobs of every held-out sample's clean HV and AV frames.
    split = read_json(run / "split.json")
    ds = ShardDataset(split["dataset"])
    expected = {"HV": 0, "AV": 0}
    for b in ds.batches(64, np.asarray(split["val_episodes"]), mixed=False):
        clean = b.clean.numpy()
        for ch, name in ((0, "HV"), (1, "AV")):
            for frame in clean[:, ch].reshape(-1, *clean.shape[-2:]):
                expected[name] += ndimage.label(frame > 0, structure=np.ones((3, 3)))[1]
    assert expected["HV"] > 0
    assert totals == expected
    for r in rows:
        if r[5] != "nan":
            assert 0.0 <= float(r[5]) <= 1.0 and 0.0 <= float(r[7]) <= 1.0


def test_refuses_a_folder_that_is_not_a_bnn_run(tmp_path: Path) -> None:
    res = subprocess.run([sys.executable, str(SCRIPT), str(tmp_path)], capture_output=True, text=True)
    assert res.returncode != 0
    assert "not a BNN run folder" in res.stderr
