"""Property: every loader of a file a user can hand latentdrive (YAML configs, study reports,
policy run configs) returns what it promises or raises its one-line error; the command
line refuses every non-positive size before any work."""

from __future__ import annotations

import json
import tempfile
from pathlib import Path
from typing import Any

import pytest
import yaml
from helpers import examples
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from latentdrive.cli import main
from latentdrive.config import ConfigError, load_yaml
from latentdrive.experiments.bnn_report import read_report
from latentdrive.rl.policy import read_run_config

JSON = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**64), 2**64) | st.floats() | st.text(max_size=10),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=10), inner, max_size=4),
    max_leaves=12,
)
QUICK = settings(max_examples=examples(80), deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


def _one_line(exc: BaseException, path: Path) -> None:
    msg = str(exc)
    assert "\n" not in msg and str(path) in msg, msg


@QUICK
@given(content=st.binary(max_size=300) | st.text(max_size=300).map(str.encode)
       | JSON.map(lambda v: yaml.safe_dump(v).encode()))
def test_load_yaml_returns_a_mapping_or_one_line(content: bytes) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "c.yaml"
        path.write_bytes(content)
        try:
            data = load_yaml(path)
        except ConfigError as exc:
            _one_line(exc, path)
            return
    assert isinstance(data, dict)


def _valid_report() -> dict[str, Any]:
    run = {"latent_dim": 8, "lambda": 0, "val_recon": 0.1, "mean_between_scenario_distance": 0.2,
           "latent_scenarios": ["a", "b"], "latent_distance": [[0.0, 0.2], [0.2, 0.0]], "vehicle_recall": 0.5}
    return {"dataset_samples": 10, "held_out_samples": 4, "raw_scenarios": ["a", "b"],
            "raw_distance": [[0.0, 0.3], [0.3, 0.0]], "raw_mean_between_scenario_distance": 0.3,
            "noisy_input_vehicles": {"vehicle_recall": 0.4, "vehicle_precision": 0.9, "by_scenario": {"a": 0.4}},
            "runs": {"d8": run}}


def _keys(obj: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    items = obj.items() if isinstance(obj, dict) else enumerate(obj) if isinstance(obj, list) else ()
    out = []
    for k, v in items:
        out += [(*prefix, k), *_keys(v, (*prefix, k))]
    return out


def _changed(doc: dict[str, Any], data: st.DataObject) -> Any:
    """``doc`` with one value replaced by arbitrary JSON, or removed, or entirely arbitrary JSON."""
    if data.draw(st.integers(0, 9), label="whole") == 0:
        return data.draw(JSON, label="document")
    path = data.draw(st.sampled_from(_keys(doc)), label="path")
    parent = doc
    for k in path[:-1]:
        parent = parent[k]
    if data.draw(st.booleans(), label="delete"):
        del parent[path[-1]]
    else:
        parent[path[-1]] = data.draw(JSON, label="value")
    return doc


def test_the_valid_report_reads(tmp_path: Path) -> None:
    (tmp_path / "report.json").write_text(json.dumps(_valid_report()))
    assert read_report(tmp_path)["runs"]["d8"]["lambda"] == 0


@QUICK
@given(data=st.data())
def test_read_report_returns_a_checked_report_or_one_line(data: st.DataObject) -> None:
    doc = _changed(_valid_report(), data)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        (out / "report.json").write_text(json.dumps(doc))
        try:
            report = read_report(out)
        except ConfigError as exc:
            _one_line(exc, out / "report.json")
            return
    # Whatever was accepted is what the figures and tables index without checking.
    for name, run in report["runs"].items():
        n = len(run["latent_scenarios"])
        assert len(run["latent_distance"]) == n and all(len(r) == n for r in run["latent_distance"])
        assert (out / "runs" / name).resolve().is_relative_to((out / "runs").resolve())
    assert any(r["lambda"] == 0 for r in report["runs"].values())


@QUICK
@given(data=st.data())
def test_read_run_config_returns_a_valid_train_section_or_one_line(data: st.DataObject) -> None:
    doc = _changed({"kind": "policy", "train": {"mode": "raw", "scenarios": ["merge"], "envs": 4},
                    "encoder": None}, data)
    with tempfile.TemporaryDirectory() as tmp:
        run = Path(tmp)
        (run / "config.json").write_text(json.dumps(doc))
        try:
            cfg = read_run_config(run)
        except ConfigError as exc:
            _one_line(exc, run)
            return
    assert {"scenarios", "observation", "reward"} <= set(cfg["train"])


# capsys is read (and so emptied) by every example.
@settings(max_examples=examples(25), deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(backend=st.sampled_from(["fast", "highway"]), batch=st.integers(-(10**6), 0) | st.just(1),
       steps=st.integers(-(10**6), 0) | st.just(1))
def test_bench_refuses_non_positive_sizes_before_any_work(capsys: pytest.CaptureFixture[str], backend: str,
                                                          batch: int, steps: int) -> None:
    if batch == 1 and steps == 1:
        return  # valid: would run the benchmark
    rc = main(["bench", "--backend", backend, "--batch-size", str(batch), "--steps", str(steps), "--scenarios", "merge"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and err[0].startswith("latentdrive: error: --")


def test_a_control_character_in_a_key_stays_on_one_line(tmp_path: Path) -> None:
    # Regression: a report whose `runs` held the key "\n" printed a two-line error.
    report = _valid_report()
    report["runs"] = {"\n": None}
    (tmp_path / "report.json").write_text(json.dumps(report))
    with pytest.raises(ConfigError) as info:
        read_report(tmp_path)
    _one_line(info.value, tmp_path / "report.json")
    assert "runs.\\n" in str(info.value)
