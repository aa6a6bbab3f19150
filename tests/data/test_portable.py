"""A dataset is self-contained: it resumes from the scenario specs its manifest stored,
from any working directory, without the spec file it was collected from."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import yaml

from latentdrive.cli import main
from latentdrive.data.collect import dataset_specs
from latentdrive.data.shards import MANIFEST, DatasetError
from latentdrive.scenarios import get_spec

ARGS = ["--episodes", "4", "--shard-size", "40", "--set", "observation.height=16", "--set", "observation.width=32",
        "--set", "observation.frames=2", "--set", "duration=4", "-q"]


def _shards(root: Path) -> dict[str, str]:
    return {n: e["content_sha256"] for n, e in json.loads((root / MANIFEST).read_text())["shards"].items()}


def test_a_dataset_of_a_spec_file_resumes_wherever_it_lies(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    made, moved, elsewhere = (tmp_path / d for d in ("made", "moved", "elsewhere"))
    for d in (made, moved, elsewhere):
        d.mkdir()
    spec = get_spec("merge").model_dump(mode="json") | {"name": "merge2", "n_hv": 3}
    (made / "merge2.yaml").write_text(yaml.safe_dump(spec))
    monkeypatch.chdir(made)
    assert main(["collect", "ds", "--scenarios", "merge2.yaml,highway", *ARGS]) == 0
    whole = _shards(made / "ds")
    assert dataset_specs(made / "ds")["merge2.yaml"].n_hv == 3

    # Moved, one shard lost, the spec file changed: resumed from a third directory, first
    # with the same command, then with OUT_DIR alone, it ends with the same content.
    shutil.move(made / "ds", moved / "ds")
    (made / "merge2.yaml").write_text(yaml.safe_dump(spec | {"n_hv": 1}))
    monkeypatch.chdir(elsewhere)
    ds = moved / "ds"
    first = sorted(ds.glob("*.npz"))[0]
    first.unlink()
    assert main(["collect", str(ds), "--scenarios", "merge2.yaml,highway", *ARGS]) == 0
    assert _shards(ds) == whole
    (made / "merge2.yaml").unlink()
    first.unlink()
    assert main(["collect", str(ds), "-q"]) == 0
    assert _shards(ds) == whole and first.is_file()

    # A BNN trains on the moved dataset from here; the BNN run, moved in turn, resumes from
    # a fourth directory, and a policy takes it as its encoder.
    bnn = ["--latent-dim", "4", "--channels", "4", "--set", "pretrain_epochs=0", "--set", "batch_size=16", "-q"]
    assert main(["train-bnn", str(ds), str(elsewhere / "bnn"), "--epochs", "1", *bnn]) == 0
    shutil.move(elsewhere / "bnn", moved / "bnn")
    monkeypatch.chdir(made)
    assert main(["train-bnn", str(ds), str(moved / "bnn"), "--epochs", "2", "--resume", *bnn]) == 0
    assert main(["train-policy", "p", "--mode", "latent", "--bnn", str(moved / "bnn"), "--scenarios", "merge",
                 "--steps", "40", "--envs", "2", "--set", "observation.height=16", "--set", "observation.width=32",
                 "--set", "observation.frames=2", "--set", "segment=40", "--set", "eval_episodes=2",
                 "--set", "dqn.learning_starts=20", "--set", "vfan.hidden=16", "--set", "vfan.channels=[4,4,4]",
                 "-q"]) == 0


def test_a_manifest_whose_scenarios_and_specs_do_not_pair_up_is_one_line(collected: Path, tmp_path: Path) -> None:
    ds = tmp_path / "ds"
    shutil.copytree(collected, ds)
    m = json.loads((ds / MANIFEST).read_text())
    m["env_configs"] = m["env_configs"][:1]
    (ds / MANIFEST).write_text(json.dumps(m))
    with pytest.raises(DatasetError, match="do not pair up"):
        dataset_specs(ds)
