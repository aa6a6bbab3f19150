"""A policy run is self-contained: it stores the specs of its scenarios and evaluates and
resumes from them wherever its folder lies, without the spec file it was configured with."""

import json
import shutil
from pathlib import Path

import pytest
import yaml

from latentdrive.cli import main
from latentdrive.scenarios import get_spec

from .test_policy_cli import TINY_SETS


def _spec_file(path: Path, **changes: object) -> Path:
    """A user's own scenario: the roundabout preset under another name, with ``changes``."""
    spec = get_spec("roundabout").model_dump(mode="json")
    spec.update(name="roundabout3", **changes)
    path.write_text(yaml.safe_dump(spec))
    return path


def _evaluate(run: Path, out: Path, *more: str) -> dict:
    assert main(["evaluate", str(run), "--policy", "none", "--episodes", "3", "--envs", "3", "-q",
                 "--json", str(out), *more]) == 0
    return json.loads(out.read_text())


def _numbers(doc: dict) -> list:
    """The evaluation's per-policy results, whatever path names the run."""
    return list(doc["policies"].values())


@pytest.fixture
def dirs(tmp_path: Path) -> dict[str, Path]:
    d = {k: tmp_path / k for k in ("trained", "moved", "elsewhere", "alone")}
    for p in d.values():
        p.mkdir()
    return d


def test_a_run_trained_on_a_spec_file_evaluates_and_resumes_wherever_it_lies(dirs, monkeypatch, capsys):
    monkeypatch.chdir(dirs["trained"])
    _spec_file(Path("roundabout3.yaml"), duration=8)
    assert main(["train-policy", "rb3", "--mode", "raw", "--scenarios", "roundabout3.yaml", "--steps", "100",
                 *TINY_SETS, "-q"]) == 0
    here = _evaluate(Path("rb3"), dirs["trained"] / "e.json")
    stored = json.loads(Path("rb3/config.json").read_text())["train"]["specs"]
    assert list(stored) == ["roundabout3.yaml"] and stored["roundabout3.yaml"]["duration"] == 8

    # Moved, and used from a third working directory where no roundabout3.yaml exists.
    shutil.move(dirs["trained"] / "rb3", dirs["moved"] / "rb3")
    monkeypatch.chdir(dirs["elsewhere"])
    run = dirs["moved"] / "rb3"
    assert _numbers(_evaluate(run, dirs["elsewhere"] / "e.json")) == _numbers(here)

    # The spec file changes (or disappears): the run still evaluates on the spec it trained on.
    _spec_file(dirs["trained"] / "roundabout3.yaml", duration=3)
    assert _numbers(_evaluate(run, dirs["elsewhere"] / "e2.json")) == _numbers(here)
    (dirs["trained"] / "roundabout3.yaml").unlink()

    # A copy of the folder alone resumes, and --scenarios can still name others.
    alone = dirs["alone"] / "rb3"
    shutil.copytree(run, alone)
    assert main(["train-policy", str(alone), "--resume", "--steps", "150", "-q"]) == 0
    assert json.loads((alone / "config.json").read_text())["train"]["specs"] == stored
    other = _evaluate(alone, dirs["elsewhere"] / "e3.json", "--scenarios", "roundabout3.yaml,merge")
    assert set(other["scenarios"]) == {"roundabout3", "merge"}
    assert other["config"]["evaluation"]["scenarios"] == ["roundabout3.yaml", "merge"]
    capsys.readouterr()


def test_a_spec_file_named_on_evaluation_is_read_when_the_run_does_not_store_that_name(dirs, monkeypatch, capsys):
    monkeypatch.chdir(dirs["elsewhere"])
    assert main(["train-policy", "m", "--mode", "raw", "--scenarios", "merge", "--steps", "60", *TINY_SETS, "-q"]) == 0
    capsys.readouterr()
    assert main(["evaluate", "m", "--policy", "none", "--episodes", "1", "--scenarios", "missing.yaml", "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "missing.yaml: no such config file" in err[0], err


def test_a_policy_config_refuses_a_spec_for_a_scenario_it_does_not_train_on():
    from latentdrive.config import ConfigError, validate
    from latentdrive.rl.config import PolicyTrainConfig

    spec = get_spec("exit").model_dump(mode="json")
    with pytest.raises(ConfigError, match="'exit' is not one of scenarios"):
        validate(PolicyTrainConfig, {"mode": "raw", "scenarios": ["merge"], "specs": {"exit": spec}})
    # A stored spec stands for its name even where no preset or file of that name exists.
    cfg = validate(PolicyTrainConfig, {"mode": "raw", "scenarios": ["gone.yaml"], "specs": {"gone.yaml": spec}})
    assert cfg.scenario_specs()[0].name == "exit"


def test_a_latent_run_moved_without_its_bnn_folder_evaluates_and_resumes(dirs, monkeypatch, capsys):
    import torch

    from .test_policy_cli import _bnn_run

    torch.manual_seed(0)
    bnn = _bnn_run(dirs["trained"] / "bnn", (2, 16, 32))
    monkeypatch.chdir(dirs["trained"])
    assert main(["train-policy", "lat", "--mode", "latent", "--bnn", "bnn", "--scenarios", "merge", "--steps", "60",
                 *TINY_SETS, "-q"]) == 0
    here = _evaluate(Path("lat"), dirs["trained"] / "e.json")
    shutil.move(dirs["trained"] / "lat", dirs["moved"] / "lat")
    shutil.rmtree(bnn)
    monkeypatch.chdir(dirs["elsewhere"])
    run = dirs["moved"] / "lat"
    assert _numbers(_evaluate(run, dirs["elsewhere"] / "e.json")) == _numbers(here)
    before = {k: v for k, v in json.loads((run / "config.json").read_text()).items() if k != "train"}
    assert main(["train-policy", str(run), "--resume", "--steps", "90", "-q"]) == 0
    after = json.loads((run / "config.json").read_text())
    assert after["encoder"] == before["encoder"] and after["scenario_hashes"] == before["scenario_hashes"]
    # Another BNN named on resumption is still checked: a missing one is a one-line error.
    capsys.readouterr()
    assert main(["train-policy", str(run), "--resume", "--bnn", "nowhere", "--steps", "120", "-q"]) == 2
    assert "nowhere" in capsys.readouterr().err
