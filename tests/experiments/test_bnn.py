import json
import shutil
from typing import Any

import numpy as np
import pytest
from helpers import held_by_another_process

from latentdrive.cli import main
from latentdrive.config import ConfigError, LatentDriveError
from latentdrive.data.dataset import ShardDataset
from latentdrive.experiments.bnn import (
    load_study_config,
    report_bnn_runs,
    run_bnn_study,
    run_name,
    study_runs,
)
from latentdrive.experiments.bnn_report import format_report
from latentdrive.experiments.bnn_scores import raw_features


@pytest.fixture(scope="module")
def tiny_study(tmp_path_factory):
    out = tmp_path_factory.mktemp("study")
    cfg = load_study_config("tiny")
    report = run_bnn_study(cfg, out, progress=False, say=lambda s: None)
    return out, cfg, report


def test_tiny_study_writes_report_and_figures(tiny_study):
    out, _cfg, report = tiny_study
    assert set(report["runs"]) == {"d4", "d8", "d8-lam0.01"}
    for name, run in report["runs"].items():
        assert (out / "runs" / name / "checkpoint.safetensors").exists()
        m = np.array(run["latent_distance"])
        assert m.shape == (3, 3) and np.allclose(m, m.T) and np.allclose(np.diag(m), 0)
        assert run["val_recon"] > 0
    assert json.loads((out / "report.json").read_text()) == report
    text = (out / "report.md").read_text()
    assert "held-out L2" in text and "| noisy input (reference) |" in text
    ref = report["noisy_input_vehicles"]
    assert ref["vehicles"] > 0 and 0.0 < ref["vehicle_recall"] <= 1.0
    assert set(ref["by_scenario"]) <= {"roundabout", "intersection", "merge"} and ref["by_scenario"]
    for run in report["runs"].values():
        assert run["vehicle_recall"] is None or 0.0 <= run["vehicle_recall"] <= 1.0
        assert set(run["vehicle_recall_by_scenario"]) == set(ref["by_scenario"])
    assert "## Held-out vehicles recovered, per scenario" in text
    # Where drawn cells lie: shares that grow with the distance; the noisy input's are high
    # (it draws cars where they are, jittered by under a cell), chance's low.
    reach = text.split("## Where the drawn vehicle cells lie")[1]
    assert "| noisy input (reference) | " in reach and "| every cell (chance) | " in reach
    chance = report["every_cell_within"]
    for within in [ref["drawn_cells_within"], chance, *(r["drawn_cells_within"] for r in report["runs"].values())]:
        shares = [within[k] for k in ("1", "2", "3", "5", "8")]
        assert shares[0] is None or (shares == sorted(shares) and 0.0 <= shares[0] and shares[-1] <= 1.0)
    assert ref["drawn_cells_within"]["1"] is not None and chance["1"] is not None
    assert ref["drawn_cells_within"]["1"] > 0.9 > 0.5 > chance["1"] > 0.0
    for fig in ("bnn_loss", "bnn_reconstruction", "bnn_latents", "bnn_distance"):
        assert (out / "figures" / f"{fig}.png").read_bytes()[:4] == b"\x89PNG"


def test_rerun_resumes_without_retraining(tiny_study):
    out, cfg, report = tiny_study
    ckpt = out / "runs" / "d4" / "checkpoint.safetensors"
    before = ckpt.stat().st_mtime_ns
    again = run_bnn_study(cfg, out, progress=False, say=lambda s: None)
    assert ckpt.stat().st_mtime_ns == before
    assert again["runs"]["d4"]["val_recon"] == pytest.approx(report["runs"]["d4"]["val_recon"])


def test_score_samples_caps_the_held_out_samples_scored(tiny_study, tmp_path):
    out, cfg, full = tiny_study
    held = ShardDataset(out / "dataset").num_samples(json.loads((out / "runs" / "d4" / "split.json").read_text())["val_episodes"])
    runs = {n: (out / "runs" / n, d, lam) for n, d, lam in study_runs(cfg)}

    def report(cap: int) -> dict[str, Any]:
        return report_bnn_runs(cfg.replace(score_samples=cap), out / "dataset", runs, tmp_path / str(cap), say=lambda s: None)

    assert full["scored_samples"] is None and "scored on every held-out sample" in (out / "report.md").read_text()
    capped = report(held // 3)
    assert capped["scored_samples"] == held // 3
    assert f"scored on the first {held // 3} held-out samples of mixed batches" in (tmp_path / str(held // 3) / "report.md").read_text()
    assert 0 < capped["noisy_input_vehicles"]["vehicles"] < full["noisy_input_vehicles"]["vehicles"]
    # Mixed batches: every scenario is in the capped score.
    assert set(capped["noisy_input_vehicles"]["by_scenario"]) == set(full["noisy_input_vehicles"]["by_scenario"])
    # A cap at or above the held-out count scores every sample: the same vehicles, in another order.
    whole = report(held)
    assert whole["scored_samples"] is None
    assert whole["noisy_input_vehicles"] == full["noisy_input_vehicles"]
    for name, r in whole["runs"].items():
        assert r["vehicle_recall"] == full["runs"][name]["vehicle_recall"]
        assert r["val_recon"] == pytest.approx(full["runs"][name]["val_recon"], rel=1e-5)


def test_held_out_episodes_are_not_trained_on(tiny_study):
    out, _, _ = tiny_study
    split = json.loads((out / "runs" / "d4" / "split.json").read_text())
    assert split["val_episodes"] and not set(split["val_episodes"]) & set(split["train_episodes"])


def test_run_names_and_presets():
    assert run_name(64) == "d64" and run_name(64, 0.01) == "d64-lam0.01"
    assert load_study_config("small").latent_dims == [16, 32, 64]
    with pytest.raises(ConfigError, match="unknown preset 'huge'"):
        load_study_config("huge")
    with pytest.raises(ConfigError, match="lambdas"):
        load_study_config("tiny", {"lambdas": [0.0]})


def test_raw_features_pool():
    x = np.arange(2 * 4 * 1 * 4 * 4, dtype=np.float32).reshape(2, 4, 1, 4, 4)
    f = raw_features(x, 2)
    assert f.shape == (2, 4 * 1 * 2 * 2)
    assert f[0, 0] == pytest.approx(np.mean([0, 1, 4, 5]))


def test_format_report_lists_every_run():
    run: dict[str, Any] = {"latent_dim": 4, "lambda": 0.0, "val_recon": 0.5, "val_vehicle_l2": 0.25,
                           "vehicle_recall": 0.875, "vehicle_precision": 0.5, "latent_scenarios": ["a", "b"],
                           "latent_distance": [[0, 0.5], [0.5, 0]], "mean_between_scenario_distance": 0.5}
    report = {"dataset_samples": 10, "held_out_samples": 4, "raw_scenarios": ["a", "b"],
              "raw_distance": [[0, 1], [1, 0]], "raw_mean_between_scenario_distance": 1.0, "runs": {"d4": run}}
    text = format_report(report)
    assert "| d4 | 4 | 0 | 0.500000 | 0.2500 | 87.5% | 50.0% | 0.5000 |" in text
    # A report written before the drawn cells' distances were measured has no such table.
    assert "Where the drawn vehicle cells lie" not in text
    run["drawn_cells_within"] = {"1": 0.5, "2": 0.75, "3": 0.8, "5": 0.9, "8": 1.0}
    assert "| d4 | 50.0% | 75.0% | 80.0% | 90.0% | 100.0% |" in format_report(report)


def test_train_bnn_cli_on_the_study_dataset(tiny_study, tmp_path, capsys):
    out, _, _ = tiny_study
    args = ["train-bnn", str(out / "dataset"), str(tmp_path / "run"), "--latent-dim", "4", "--epochs", "1",
            "--channels", "4", "8", "-q", "--set", "batch_size=16"]
    assert main(args) == 0
    assert "held-out loss" in capsys.readouterr().out
    # The run records how its maps were drawn, for the policies that will read its code.
    drawn = ShardDataset(out / "dataset").manifest["env_configs"][0]["observation"]
    assert json.loads((tmp_path / "run" / "config.json").read_text())["observation"] == drawn
    # A second start without --resume refuses to overwrite; with it, it continues.
    assert main(args) == 2
    assert main([*args, "--resume"]) == 0


def test_train_bnn_epochs_is_the_total_whatever_the_pretraining(tiny_study, tmp_path):
    # Regression: --epochs 3 with pretrain_epochs=1 used to run 1 + (3 - 10 → 0) epochs.
    out, _, _ = tiny_study
    run = tmp_path / "run"
    args = ["train-bnn", str(out / "dataset"), str(run), "--latent-dim", "4", "--epochs", "3",
            "--channels", "4", "-q", "--set", "batch_size=16", "--set", "pretrain_epochs=1"]
    assert main(args) == 0
    train = json.loads((run / "config.json").read_text())["train"]
    assert (train["pretrain_epochs"], train["mixed_epochs"]) == (1, 2)


def test_epoch_steps_caps_each_epoch(tiny_study, tmp_path, capsys):
    out, _, _ = tiny_study
    run = tmp_path / "run"
    args = ["train-bnn", str(out / "dataset"), str(run), "--latent-dim", "4", "--epochs", "3",
            "--channels", "4", "--set", "batch_size=4", "--set", "pretrain_epochs=1",
            "--set", "epoch_steps=2", "--set", "val_every=1"]
    assert main(args) == 0
    text = capsys.readouterr().out
    epochs = [line for line in (run / "metrics.csv").read_text().splitlines() if line.startswith("epoch,")]
    # Uncapped, an epoch of this dataset would be longer than two batches of 4.
    split = json.loads((run / "split.json").read_text())
    assert ShardDataset(out / "dataset").num_samples(np.asarray(split["train_episodes"])) > 2 * 4
    # Two steps per epoch, three epochs: the epoch rows' step column reads 2, 4, 6.
    assert [int(line.split(",")[3]) for line in epochs] == [2, 4, 6]
    # Each epoch line shows the held-out objective beside the plain error.
    assert text.count("(objective ") == 3


def test_train_bnn_model_overrides_reach_the_architecture(tiny_study, tmp_path, capsys):
    out, _, _ = tiny_study
    run = tmp_path / "run"
    args = ["train-bnn", str(out / "dataset"), str(run), "--latent-dim", "4", "--epochs", "1", "--channels", "4",
            "-q", "--set", "batch_size=16", "--set", "model.latent_activation=tanh", "--set", "model.spatial_kernel=5"]
    assert main(args) == 0
    model = json.loads((run / "config.json").read_text())["model"]
    assert (model["latent_activation"], model["spatial_kernel"]) == ("tanh", 5)
    bad = ["train-bnn", str(out / "dataset"), str(tmp_path / "bad"), "-q", "--set", "model.spatial_kernel=4"]
    assert main(bad) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "model.spatial_kernel" in err[0]


@pytest.mark.parametrize("extra", [
    ["--set", "pretrain_epochs=5"], ["--set", "mixed_epochs=2"], ["--epochs", "0"],
    ["--set", "pretrain_epochs=-1"],
])
def test_train_bnn_epochs_conflicts_are_refused(tiny_study, tmp_path, capsys, extra):
    out, _, _ = tiny_study
    args = ["train-bnn", str(out / "dataset"), str(tmp_path / "run"), "--epochs", "3", "-q", *extra]
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "epochs" in err[0]
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("key", ["latent_dim=8", "channels=[4]", "input_shape=[1,8,8]"])
def test_train_bnn_model_fields_with_their_own_option_are_refused(tiny_study, tmp_path, capsys, key):
    out, _, _ = tiny_study
    assert main(["train-bnn", str(out / "dataset"), str(tmp_path / "run"), "-q", "--set", f"model.{key}"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"model.{key.split('=')[0]}" in err[0]


def test_train_bnn_into_a_run_directory_in_use_writes_nothing(tiny_study, tmp_path, capsys):
    out, _, _ = tiny_study
    run = tmp_path / "run"
    with held_by_another_process(run, "train-bnn"):
        assert main(["train-bnn", str(out / "dataset"), str(run), "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(run) in err[0] and "in use" in err[0]
    assert [p.name for p in run.iterdir()] == [".latentdrive.lock"]


def test_train_bnn_cli_rejects_a_missing_dataset(tmp_path, capsys):
    assert main(["train-bnn", str(tmp_path / "nothing"), str(tmp_path / "run"), "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nothing" in err[0]


def test_figures_command_redraws_and_rejects_non_study(tiny_study, tmp_path, capsys):
    out, _, _ = tiny_study
    fig = out / "figures" / "bnn_distance.png"
    fig.unlink()
    assert main(["figures", "bnn", str(out)]) == 0
    assert fig.exists()
    assert main(["figures", "bnn", str(tmp_path)]) == 2
    assert "not a finished study directory" in capsys.readouterr().err


def _files(root):
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_a_trained_run_is_not_resumed_on_another_split(tiny_study, tmp_path, capsys):
    out, _, _ = tiny_study
    run = tmp_path / "run"
    args = ["train-bnn", str(out / "dataset"), str(run), "--latent-dim", "4", "--epochs", "1",
            "--channels", "4", "-q", "--set", "batch_size=16"]
    assert main(args) == 0
    before = _files(run)
    # Held-out episodes would move into training: refused, and the run is left as it was.
    assert main([*args, "--resume", "--val-fraction", "0.5"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "another episode split" in err[0]
    assert _files(run) == before


@pytest.mark.parametrize(("change", "needle"), [
    ({"val_fraction": 0.5}, "another episode split"),
    ({"train": {"lr": 0.5}}, "other training settings"),
    ({"collect": {"seed": 7}}, "holds a dataset of config"),
    ({"model": {"head_hidden": 0}}, r"another model config \(head_hidden \(256 → 0\)\)"),
])
def test_a_study_rerun_that_would_be_refused_writes_nothing(tiny_study, change, needle):
    out, cfg, _ = tiny_study
    before = _files(out)
    with pytest.raises(LatentDriveError, match=needle):
        run_bnn_study(cfg.replace(**change), out, progress=False, say=lambda s: None)
    assert _files(out) == before


def test_a_study_of_a_spec_file_reads_its_config_from_the_dataset_s_stored_specs(tiny_study, tmp_path):
    # As if collected from a spec file that is gone: the study's config names the file,
    # and the dataset's manifest stored its spec under that name.
    import shutil

    from latentdrive.experiments.bnn import STUDY_CONFIG, read_study_config

    out, _, _ = tiny_study
    copy = tmp_path / "study"
    shutil.copytree(out, copy)
    first = json.loads((copy / STUDY_CONFIG).read_text())["collect"]["scenarios"][0]
    for path, key in ((copy / STUDY_CONFIG, "collect"), (copy / "dataset" / "manifest.json", "config")):
        data = json.loads(path.read_text())
        data[key]["scenarios"] = ["gone.yaml" if s == first else s for s in data[key]["scenarios"]]
        path.write_text(json.dumps(data))
    assert read_study_config(copy).collect.scenarios[0] == "gone.yaml"
    shutil.rmtree(copy / "dataset")
    with pytest.raises(ConfigError, match=r"gone\.yaml: no such config file"):
        read_study_config(copy)


def test_runs_trained_in_parallel_match_runs_trained_one_after_another(tiny_study, tmp_path):
    out, _, _ = tiny_study
    # The paper's structure (the study's model section) in both, to check that it reaches the runs too.
    cfg = load_study_config("tiny", {"train": {"num_threads": 1}, "model": {"head_hidden": 0, "latent_norm": False}})
    reports: dict[int, dict] = {}
    said: list[str] = []
    for workers in (1, 2):
        folder = tmp_path / f"w{workers}"
        shutil.copytree(out / "dataset", folder / "dataset")
        reports[workers] = run_bnn_study(cfg, folder, progress=False, say=said.append, workers=workers)
    assert reports[1]["runs"] == reports[2]["runs"]
    for workers in (1, 2):
        model = json.loads((tmp_path / f"w{workers}" / "runs" / "d8" / "config.json").read_text())["model"]
        assert (model["head_hidden"], model["latent_norm"]) == (0, False)
    assert "[2/4] training 3 BNNs, 2 at a time (1 thread(s) each) -> " + str(tmp_path / "w2" / "runs") in said
    assert sum(line.startswith("[2/4] d4 done (") for line in said) == 1
    with pytest.raises(ConfigError, match="workers must be at least 1"):
        run_bnn_study(cfg, tmp_path / "w0", progress=False, workers=0)

