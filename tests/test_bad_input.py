"""Bad input, through the command line: one line on stderr, a non-zero exit, no traceback,
and every file already there left exactly as it was.

One workspace per module holds every kind of bad file (a binary config, a folder where a
file should be, a hostile dataset manifest, a foreign checkpoint, an empty report...);
each case runs ``latentdrive.cli.main`` in-process on it and compares the workspace's
bytes before and after. Cases refused only after real work (simulating, training) do
not belong here: each case must fail within seconds.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

import pytest
import torch
from safetensors.torch import save_file

from latentdrive.bnn.checkpoint import save_checkpoint
from latentdrive.bnn.train import BNNTrainConfig
from latentdrive.cli import main
from latentdrive.config import validate
from latentdrive.data.collect import CollectConfig, collect
from latentdrive.experiments.bnn import BNNStudyConfig
from latentdrive.models.bottleneck import BottleneckConfig, BottleneckNetwork

TINY = {
    "scenarios": ["merge", "highway"], "episodes": 4, "shard_size": 40,
    "env": {"observation": {"height": 16, "width": 32, "frames": 2}, "duration": 3},
}


def _manifest_edit(edit: Callable[[dict], None]) -> Callable[[Path], None]:
    def apply(ds: Path) -> None:
        m = json.loads((ds / "manifest.json").read_text())
        edit(m)
        (ds / "manifest.json").write_text(json.dumps(m))

    return apply


def _unit0(key: str, value: object) -> Callable[[dict], None]:
    def edit(m: dict) -> None:
        old = m["units"][0]["name"]
        if value is None:
            del m["units"][0][key]
        else:
            m["units"][0][key] = value
            if key == "name":
                m["shards"][value] = m["shards"].pop(old)

    return edit


#: Damaged copies of the tiny dataset: folder name → damage.
DATASETS: dict[str, Callable[[Path], object]] = {
    "ds_no_first_episode": _manifest_edit(_unit0("first_episode", None)),
    "ds_passwd": _manifest_edit(_unit0("name", "/etc/passwd")),
    "ds_dotdot": _manifest_edit(_unit0("name", "../outside.npz")),
    "ds_float_episode": _manifest_edit(_unit0("first_episode", 1.5)),
    "ds_huge_episode": _manifest_edit(_unit0("first_episode", 10**30)),
    "ds_units_not_list": _manifest_edit(lambda m: m.update(units={"a": 1})),
    "ds_huge_shard_time": _manifest_edit(lambda m: next(iter(m["shards"].values())).update(wall_s=10**400)),
    "ds_truncated_manifest": lambda ds: (ds / "manifest.json").write_bytes((ds / "manifest.json").read_bytes()[:100]),
    "ds_binary_manifest": lambda ds: (ds / "manifest.json").write_bytes(bytes(range(256))),
}


@pytest.fixture(scope="module")
def ws(tmp_path_factory: pytest.TempPathFactory) -> Path:
    w = tmp_path_factory.mktemp("bad-input")
    collect(validate(CollectConfig, TINY), w / "ds", progress=False)
    # One episode per scenario: none to hold out.
    collect(validate(CollectConfig, {**TINY, "episodes": 1}), w / "ds_one_episode", progress=False)
    for name, damage in DATASETS.items():
        shutil.copytree(w / "ds", w / name)
        damage(w / name)
    (w / "outside.npz").write_bytes(b"not for a dataset to read")

    (w / "bin.yaml").write_bytes(bytes(range(256)) * 4)
    (w / "folder.yaml").mkdir()
    (w / "big.yaml").write_text("a: 1\n" + "#" * (2 << 20) + "\n")
    (w / "deep.yaml").write_text("a: " + "[" * 5_000 + "\n")
    (w / "list.yaml").write_text("- 1\n- 2\n")
    (w / "unknown_key.yaml").write_text("colour: red\n")
    (w / "a_file").write_text("I am a file\n")

    # Studies: a config of its own beside a report that is not one, and a folder holding
    # another config's dataset.
    cfg = json.dumps(validate(BNNStudyConfig, {}).model_dump(mode="json"))
    reports = {"empty": "{}", "truncated": '{"dataset_samples": 3, "runs": {', "list": "[1, 2]",
               "escaping_run": json.dumps({
                   "dataset_samples": 1, "held_out_samples": 1, "raw_scenarios": ["a"], "raw_distance": [[0.0]],
                   "raw_mean_between_scenario_distance": None,
                   "runs": {"../../x": {"latent_dim": 4, "lambda": 0, "val_recon": 0.1,
                                        "mean_between_scenario_distance": None,
                                        "latent_scenarios": ["a"], "latent_distance": [[0.0]]}}}),
               "ragged_matrix": json.dumps({
                   "dataset_samples": 1, "held_out_samples": 1, "raw_scenarios": ["a", "b"],
                   "raw_distance": [[0.0, 1.0], [1.0]], "raw_mean_between_scenario_distance": None,
                   "runs": {"d4": {"latent_dim": 4, "lambda": 0, "val_recon": 0.1,
                                   "mean_between_scenario_distance": None,
                                   "latent_scenarios": ["a"], "latent_distance": [[0.0]]}}}),
               "reach_not_a_share": json.dumps({
                   "dataset_samples": 1, "held_out_samples": 1, "raw_scenarios": ["a"], "raw_distance": [[0.0]],
                   "raw_mean_between_scenario_distance": None,
                   "runs": {"d4": {"latent_dim": 4, "lambda": 0, "val_recon": 0.1,
                                   "mean_between_scenario_distance": None, "drawn_cells_within": {"1": "most"},
                                   "latent_scenarios": ["a"], "latent_distance": [[0.0]]}}})}
    for name, text in reports.items():
        (w / f"study_{name}").mkdir()
        (w / f"study_{name}" / "study_config.json").write_text(cfg)
        (w / f"study_{name}" / "report.json").write_text(text)
    (w / "study_binary_config").mkdir()
    (w / "study_binary_config" / "study_config.json").write_bytes(bytes(range(256)))
    (w / "study_binary_config" / "report.json").write_text("{}")
    shutil.copytree(w / "ds", w / "study_other" / "dataset")
    (w / "study_other" / "study_config.json").write_text(cfg)

    # Checkpoints that are not ours, or not checkpoints.
    (w / "bnn_foreign").mkdir()
    save_file({"w": torch.zeros(3)}, str(w / "bnn_foreign" / "checkpoint.safetensors"))
    for name, data in {"run_garbage": b"\x00" * 100, "run_huge_header": (10**12).to_bytes(8, "little") + b"{}"}.items():
        (w / name).mkdir()
        (w / name / "checkpoint.safetensors").write_bytes(data)
        (w / name / "split.json").write_text('{"train_episodes": [], "val_episodes": []}\n')
    # A BNN run that train-bnn's defaults resume, whose training log is damaged.
    model_cfg = BottleneckConfig(input_shape=(2, 16, 32), latent_dim=64, channels=(16, 32))
    train_cfg = validate(BNNTrainConfig, {"lambda_distance": 0.0, "seed": 0})
    net = BottleneckNetwork(model_cfg)
    save_checkpoint(w / "bnn_bad_log" / "checkpoint.safetensors", net, torch.optim.AdamW(net.parameters()),
                    step=0, epoch=1, config={"train": train_cfg.model_dump(mode="json"),
                                             "model": model_cfg.model_dump(mode="json")})
    (w / "bnn_bad_log" / "metrics.csv").write_text("kind,step\nstep,abc\n")
    pol = {"kind": "policy", "train": {"mode": "raw", "scenarios": ["merge"]}, "encoder": None}
    (w / "pol_foreign").mkdir()
    (w / "pol_foreign" / "config.json").write_text(json.dumps(pol))
    save_file({"w": torch.zeros(3)}, str(w / "pol_foreign" / "checkpoint.safetensors"))
    (w / "pol_binary").mkdir()
    (w / "pol_binary" / "config.json").write_bytes(bytes(range(256)))
    (w / "pol_bad_train").mkdir()
    (w / "pol_bad_train" / "config.json").write_text(json.dumps({**pol, "train": "raw"}))
    (w / "pol_bad_field").mkdir()
    (w / "pol_bad_field" / "config.json").write_text(json.dumps({**pol, "train": {"mode": "raw", "envs": -1}}))
    return w


def snapshot(root: Path) -> dict[str, bytes | None]:
    """Every file's bytes (None for a folder), by path relative to ``root``."""
    return {str(p.relative_to(root)): (None if p.is_dir() else p.read_bytes()) for p in sorted(root.rglob("*"))}


# (case id, argv with {w} for the workspace, text the error line must hold)
CASES = [
    # Datasets whose manifest is damaged or names files outside the dataset.
    ("unit-without-first-episode", "train-bnn {w}/ds_no_first_episode {w}/new_run", "first_episode"),
    ("unit-named-etc-passwd", "train-bnn {w}/ds_passwd {w}/new_run", "'/etc/passwd'"),
    ("unit-named-dotdot", "train-bnn {w}/ds_dotdot {w}/new_run", "'../outside.npz'"),
    ("unit-float-episode", "train-bnn {w}/ds_float_episode {w}/new_run", "first_episode"),
    ("units-not-a-list", "train-bnn {w}/ds_units_not_list {w}/new_run", "units must be a list"),
    ("truncated-manifest", "train-bnn {w}/ds_truncated_manifest {w}/new_run", "not valid JSON"),
    ("binary-manifest", "train-bnn {w}/ds_binary_manifest {w}/new_run", "not UTF-8"),
    ("dataset-is-a-file", "train-bnn {w}/a_file {w}/new_run", "manifest"),
    ("unit-huge-episode", "train-bnn {w}/ds_huge_episode {w}/new_run", "first_episode must be an integer >= 0 and < 2**62"),
    ("shard-time-beyond-float", "train-bnn {w}/ds_huge_shard_time {w}/new_run", f"wall_s {str(10**400)[:37]}... is not a number of seconds"),
    ("val-fraction-out-of-range", "train-bnn {w}/ds {w}/new_run --val-fraction 1.5", "--val-fraction"),
    ("val-fraction-zero", "train-bnn {w}/ds {w}/new_run --val-fraction 0", "--val-fraction) must be in (0, 1)"),
    ("nothing-to-hold-out", "train-bnn {w}/ds_one_episode {w}/new_run", "no validation episodes at val_fraction 0.15"),
    # Runs that hold an unusable checkpoint: refused before split.json is rewritten.
    ("resume-garbage-checkpoint", "train-bnn {w}/ds {w}/run_garbage --resume", "not a safetensors file"),
    ("resume-huge-header", "train-bnn {w}/ds {w}/run_huge_header --resume", "bad header length"),
    ("existing-run-without-resume", "train-bnn {w}/ds {w}/run_garbage", "exists: resume it"),
    ("resume-damaged-log", "train-bnn {w}/ds {w}/bnn_bad_log --resume", "step 'abc', not a count"),
    # Collect: config files that are folders, binary, too big, too deep, not a mapping.
    ("config-is-a-folder", "collect {w}/new_ds --config {w}/folder.yaml", "is a folder"),
    ("config-is-binary", "collect {w}/new_ds --config {w}/bin.yaml", "not UTF-8"),
    ("config-too-big", "collect {w}/new_ds --config {w}/big.yaml", "larger than 1 MiB"),
    ("config-too-deep", "collect {w}/new_ds --config {w}/deep.yaml", "malformed YAML"),
    ("config-not-a-mapping", "collect {w}/new_ds --config {w}/list.yaml", "mapping"),
    ("config-unknown-key", "collect {w}/new_ds --config {w}/unknown_key.yaml", "colour: unknown key"),
    ("config-missing", "collect {w}/new_ds --config {w}/nowhere.yaml", "no such config file"),
    ("collect-another-config", "collect {w}/ds --scenarios merge,highway --episodes 3 -q", "holds a dataset of config"),
    ("collect-into-a-file", "collect {w}/a_file -q", "not a directory"),
    # Scenario specs.
    ("show-binary-spec", "show {w}/bin.yaml --out {w}/x.png", "not UTF-8"),
    ("show-folder-spec", "show {w}/folder.yaml --out {w}/x.png", "is a folder"),
    ("show-unknown-scenario", "show lake --out {w}/x.png", "unknown scenario 'lake'"),
    ("show-out-is-a-folder", "show merge --out {w}/folder.yaml", "--out"),
    # Bench: sizes checked before any work.
    ("bench-fast-batch-zero", "bench --backend fast --batch-size 0 --scenarios merge --steps 1", "--batch-size"),
    ("bench-batch-negative", "bench --batch-size -3 --scenarios merge --steps 1", "--batch-size"),
    ("bench-steps-zero", "bench --steps 0 --scenarios merge", "--steps"),
    ("bench-json-is-a-folder", "bench --scenarios merge --steps 1 --json {w}/folder.yaml", "--json"),
    # Studies: reports that are not reports, a config that is not one, another dataset.
    ("figures-empty-report", "figures bnn {w}/study_empty", "not a BNN study report"),
    ("figures-truncated-report", "figures bnn {w}/study_truncated", "not valid JSON"),
    ("figures-report-is-a-list", "figures bnn {w}/study_list", "not a BNN study report"),
    ("figures-run-escapes", "figures bnn {w}/study_escaping_run", "'../../x'"),
    ("figures-ragged-matrix", "figures bnn {w}/study_ragged_matrix", "raw_distance"),
    ("figures-reach-not-a-share", "figures bnn {w}/study_reach_not_a_share", "drawn_cells_within"),
    ("figures-binary-config", "figures bnn {w}/study_binary_config", "not UTF-8"),
    ("figures-not-a-study", "figures bnn {w}/ds", "not a finished study"),
    ("study-into-another-dataset", "bnn-study {w}/study_other --preset tiny -q", "holds a dataset of config"),
    ("study-into-a-file", "bnn-study {w}/a_file --preset tiny -q", "not a folder"),
    ("study-binary-preset", "bnn-study {w}/new_study --preset {w}/bin.yaml -q", "not UTF-8"),
    ("study-unknown-preset", "bnn-study {w}/new_study --preset huge -q", "unknown preset"),
    # Policies: foreign checkpoints, configs that are not configs, unknown scenarios.
    ("policy-foreign-bnn", "train-policy {w}/new_pol --mode latent --bnn {w}/bnn_foreign -q", "not a latentdrive checkpoint"),
    ("evaluate-foreign-checkpoint", "evaluate {w}/pol_foreign --policy none --episodes 1 -q", "not a latentdrive checkpoint"),
    ("evaluate-binary-config", "evaluate {w}/pol_binary --policy none -q", "not UTF-8"),
    ("evaluate-train-not-a-mapping", "evaluate {w}/pol_bad_train --policy none -q", "not a policy run's config"),
    ("evaluate-invalid-train-field", "evaluate {w}/pol_bad_field --policy none -q", "envs"),
    ("evaluate-unknown-scenario", "evaluate --policy idle --scenarios lake -q", "unknown scenario 'lake'"),
    ("resume-a-non-run", "train-policy {w}/ds --resume -q", "not a policy run"),
    ("train-policy-unknown-scenario", "train-policy {w}/new_pol --mode raw --scenarios lake -q", "lake"),
    # Usage errors: one line too, naming the option.
    ("negative-seed", "show merge --out {w}/x.png --seed -1", "--seed: must be 0 or more, got -1"),
    ("negative-bench-seed", "bench --seed -1 --scenarios merge --steps 1", "--seed"),
    ("show-no-steps", "show merge --out {w}/x.png --steps 0", "--steps: must be at least 1"),
    ("unknown-option", "bench --bogus", "unrecognized arguments: --bogus"),
    ("unknown-choice", "bench --backend lake", "invalid choice: 'lake'"),
    ("seed-not-a-number", "train-policy {w}/new_pol --seed x", "expected an integer, got 'x'"),
    ("validate-unknown-policy", "validate-backend --policies bogus --scenarios merge", "unknown 'bogus'"),
    ("gpu-fraction-above-one", "reproduce {w}/new_study --gpu-fraction 2", "--gpu-fraction: must be in (0, 1]"),
    ("bench-repeat-zero", "bench --train --repeat 0", "--repeat: must be at least 1"),
    ("lambda-nan", "train-bnn {w}/ds {w}/new_run --lambda nan", "finite number"),
    ("ray-host-unknown", "reproduce {w}/new_study --preset tiny --ray no-such-host.invalid:6379", "cannot resolve host"),
]


@pytest.mark.parametrize(("argv", "needle"), [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_bad_input_is_one_line_and_changes_nothing(ws: Path, argv: str, needle: str,
                                                    capsys: pytest.CaptureFixture[str],
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(ws)
    before = snapshot(ws)
    rc = main(argv.format(w=ws).split())  # an uncaught exception fails the test: that is a traceback
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert rc == 2, err
    assert len(lines) == 1 and lines[0].startswith("latentdrive: error: "), err
    assert needle in lines[0], lines[0]
    after = snapshot(ws)
    assert after == before, sorted(set(after.items()) ^ set(before.items()))[:3]

