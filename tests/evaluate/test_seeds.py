"""``latentdrive aggregate``: training seeds' ``evaluate --json`` results read as one."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from latentdrive.cli import main
from latentdrive.config import ConfigError
from latentdrive.evaluate.seeds import aggregate_seeds, read_seed_eval

SCEN = ["merge", "highway"]


def _doc(rates: dict[str, float], rule: dict[str, float] | None = None, reset_seed: int = 1073741824,
         policy: str = "runs/s0") -> dict:
    """The parts of an ``evaluate --json`` result that ``aggregate`` reads."""
    def block(r: float) -> dict:
        return {"episodes": 200, "failure_rate": {"k": round(200 * r), "n": 200, "rate": r, "lo": 0.0, "hi": 1.0}}

    mixed = sum(rates[s] for s in SCEN) / len(SCEN)
    doc = {"scenarios": {s: block(rates[s]) for s in SCEN}, "mixed": block(mixed), "policy": policy,
           "config": {"evaluation": {"scenarios": SCEN, "episodes_per_scenario": 200, "envs": 16,
                                     "backend": "fast", "reset_seed": reset_seed, "seed_offset": 0}}}
    if rule is not None:
        rule_mixed = sum(rule[s] for s in SCEN) / len(SCEN)
        doc["compare"] = {"a": policy, "b": "rule", "tests": {
            s: {"failed": {"rate_b": b, "difference": a - b, "p_value": 0.01 * (i + 1)}}
            for i, (s, a, b) in enumerate([*((s, rates[s], rule[s]) for s in SCEN), ("mixed", mixed, rule_mixed)])}}
    return doc


RULE = {"merge": 1.0, "highway": 0.25}
SEEDS = [{"merge": 0.6, "highway": 0.3}, {"merge": 0.5, "highway": 0.4}, {"merge": 0.7, "highway": 0.2}]


def _files(tmp_path: Path, docs: list[dict]) -> list[Path]:
    paths = []
    for i, d in enumerate(docs):
        p = tmp_path / f"s{i}.json"
        p.write_text(json.dumps(d))
        paths.append(p)
    return paths


def test_rates_means_and_paired_tests_per_seed(tmp_path) -> None:
    files = _files(tmp_path, [_doc(r, RULE, policy=f"runs/s{i}") for i, r in enumerate(SEEDS)])
    agg = aggregate_seeds([read_seed_eval(f) for f in files])
    merge, mixed = agg["rows"]["merge"], agg["rows"]["mixed"]
    assert merge["rates"] == [0.6, 0.5, 0.7]
    assert merge["mean"] == pytest.approx(0.6)
    assert 0.5 <= merge["lo"] <= 0.6 <= merge["hi"] <= 0.7
    assert merge["differences"] == pytest.approx([-0.4, -0.5, -0.3])
    assert merge["difference"]["mean"] == pytest.approx(-0.4)
    assert merge["compare_rates"] == [1.0, 1.0, 1.0]
    assert mixed["rates"] == pytest.approx([0.45, 0.45, 0.45])
    assert mixed["p_values"] == pytest.approx([0.03, 0.03, 0.03])
    assert agg["policies"] == ["runs/s0", "runs/s1", "runs/s2"] and agg["compare"] == ["rule"]


def test_the_command_prints_the_table_and_writes_json(tmp_path, capsys) -> None:
    files = _files(tmp_path, [_doc(r, RULE, policy=f"runs/s{i}") for i, r in enumerate(SEEDS)])
    assert main(["aggregate", *map(str, files), "--json", str(tmp_path / "out.json")]) == 0
    out = capsys.readouterr().out
    row = next(line for line in out.splitlines() if line.startswith("merge"))
    assert row.split()[:5] == ["merge", "60.0", "50.0", "70.0", "60.0"]
    assert "100.0" in row and "-40.0" in row
    assert json.loads((tmp_path / "out.json").read_text())["rows"]["highway"]["rates"] == [0.3, 0.4, 0.2]


def test_seeds_scored_on_other_episodes_are_refused(tmp_path, capsys) -> None:
    files = _files(tmp_path, [_doc(SEEDS[0], RULE), _doc(SEEDS[1], RULE, reset_seed=7, policy="runs/s1")])
    assert main(["aggregate", *map(str, files)]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "s1.json: scores other episodes" in err[0]


def test_a_mix_of_compared_and_uncompared_seeds_is_refused(tmp_path) -> None:
    files = _files(tmp_path, [_doc(SEEDS[0], RULE), _doc(SEEDS[1], policy="runs/s1")])
    with pytest.raises(ConfigError, match=r"s1\.json: has no --compare"):
        aggregate_seeds([read_seed_eval(f) for f in files])


def test_a_seed_given_twice_is_refused(tmp_path) -> None:
    a, b = _files(tmp_path, [_doc(SEEDS[0], RULE, policy="runs/s0"), _doc(SEEDS[1], RULE, policy="runs/s0")])
    with pytest.raises(ConfigError, match="the same file"):
        aggregate_seeds([read_seed_eval(a), read_seed_eval(a)])
    with pytest.raises(ConfigError, match="the same policy"):
        aggregate_seeds([read_seed_eval(a), read_seed_eval(b)])


def test_seeds_against_different_reference_drivers_are_refused(tmp_path) -> None:
    files = _files(tmp_path, [_doc(SEEDS[0], RULE, policy="runs/s0"), _doc(SEEDS[1], RULE, policy="runs/s1")])
    doc = json.loads(files[1].read_text())
    doc["compare"]["b"] = "plan"
    files[1].write_text(json.dumps(doc))
    with pytest.raises(ConfigError, match="different policies"):
        aggregate_seeds([read_seed_eval(f) for f in files])
    doc["compare"]["b"] = "runs/raw-s1"  # each seed against its own run is a pairing
    files[1].write_text(json.dumps(doc))
    first = json.loads(files[0].read_text())
    first["compare"]["b"] = "runs/raw-s0"
    files[0].write_text(json.dumps(first))
    assert aggregate_seeds([read_seed_eval(f) for f in files])["compare"] == ["runs/raw-s0", "runs/raw-s1"]


def test_the_mixed_difference_is_resampled_within_scenarios(tmp_path) -> None:
    """Its interval is built like the mixed failure rate's, from the scenarios' differences."""
    files = _files(tmp_path, [_doc(r, RULE, policy=f"runs/s{i}") for i, r in enumerate(SEEDS)])
    mixed = aggregate_seeds([read_seed_eval(f) for f in files])["rows"]["mixed"]
    # Merge's differences (-0.4, -0.5, -0.3) and highway's (0.05, 0.15, -0.05) recombine
    # across seeds: the interval reaches past the per-seed mixed differences (all -0.175).
    assert mixed["differences"] == pytest.approx([-0.175] * 3)
    assert mixed["difference"]["lo"] < -0.175 < mixed["difference"]["hi"]


@pytest.mark.parametrize("text", ["[1, 2]", "{}", '{"config": {"evaluation": {"scenarios": [1, 2]}}}',
                                  '{"config": {"evaluation": {"scenarios": [["a"]]}}}',
                                  '{"config": {"evaluation": {"scenarios": ["mixed"]}}}', '{"config": [1]}', '{"config": {"evaluation": {"scenarios": []}}}', '{"config": {"evaluation": {"scenarios": ["merge"]}}}', "not json"])
def test_a_file_that_is_not_an_evaluation_is_named(tmp_path, capsys, text) -> None:
    bad = tmp_path / "bad.json"
    bad.write_text(text)
    assert main(["aggregate", str(bad)]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("latentdrive: error:") and "bad.json" in err[0]


def test_seeds_against_their_own_runs_print_each_b_in_run_order(tmp_path, capsys) -> None:
    """Regression: the B column showed the distinct B rates sorted, losing which seed each was."""
    docs = [_doc(r, {"merge": 0.9 - 0.1 * i, "highway": 0.3}, policy=f"runs/lat-s{i}") for i, r in enumerate(SEEDS)]
    for i, d in enumerate(docs):
        d["compare"]["b"] = f"/abs/runs/rand-s{i}" if i else f"runs/rand-s{i}"
    files = _files(tmp_path, docs)
    assert main(["aggregate", *map(str, files)]) == 0
    out = capsys.readouterr().out
    assert "B, runs 1..3 = runs/rand-s0, /abs/runs/rand-s1, /abs/runs/rand-s2" in out
    row = next(line for line in out.splitlines() if line.startswith("merge"))
    assert "90.0 / 80.0 / 70.0" in row
    highway = next(line for line in out.splitlines() if line.startswith("highway"))
    assert "30.0 / 30.0 / 30.0" in highway


def test_seeds_evaluated_under_one_label_are_told_apart_by_their_folders(tmp_path, capsys) -> None:
    """`evaluate raw=runs/raw-sK --compare latent=runs/lat-sK` names every seed alike: the
    folders in `config.paths` say which run each is."""
    docs = [_doc(r, {"merge": 0.9 - 0.1 * i, "highway": 0.3}, policy="raw") for i, r in enumerate(SEEDS)]
    for i, d in enumerate(docs):
        d["compare"]["b"] = "latent"
        d["config"]["paths"] = {"raw": f"runs/raw-s{i}", "latent": f"runs/lat-s{i}"}
    files = _files(tmp_path, docs)
    agg = aggregate_seeds([read_seed_eval(f) for f in files])
    assert agg["paired"] and agg["rows"]["merge"]["compare_rates"] == pytest.approx([0.9, 0.8, 0.7])
    assert main(["aggregate", *map(str, files)]) == 0
    merge = next(line for line in capsys.readouterr().out.splitlines() if line.startswith("merge"))
    assert "90.0 / 80.0 / 70.0" in merge  # each seed's own B, not the first seed's alone
    # One folder under two labels is still one seed given twice.
    docs[1]["policy"], docs[1]["config"]["paths"] = "other", {"other": "runs/raw-s0", "latent": "runs/lat-s1"}
    files = _files(tmp_path, docs)
    with pytest.raises(ConfigError, match="the same policy"):
        aggregate_seeds([read_seed_eval(f) for f in files])
    docs[1]["config"]["paths"] = ["runs/raw-s1"]
    files = _files(tmp_path, docs)
    with pytest.raises(ConfigError, match=r"s1\.json: .*config\.paths is not a mapping"):
        read_seed_eval(files[1])
