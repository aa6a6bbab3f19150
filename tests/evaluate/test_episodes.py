"""Per-episode outcomes stored by `evaluate --json`, and pairing two stored files."""

from __future__ import annotations

import json
import re

import pytest

from latentdrive.config import ConfigError
from latentdrive.evaluate.episodes import outcome_block, pair, read_evaluation, specs_digest
from latentdrive.evaluate.report import compare
from latentdrive.outcome import outcomes_from_json, outcomes_to_json
from latentdrive.scenarios import get_spec

from .test_report import outcome

EVALUATION = {"scenarios": ["merge", "exit"], "episodes_per_scenario": 6, "envs": 2, "backend": "fast",
              "reset_seed": 2**30, "seed_offset": 0}


def _policy_a():
    return [outcome("success", "merge", s) for s in range(6)] + [outcome("crash", "exit", s) for s in range(6)]


def _policy_b():
    return [outcome("timeout", "merge", s) for s in range(6)] + [outcome("crash", "exit", s) for s in range(3)] + \
        [outcome("success", "exit", s) for s in range(3, 6)]


SPECS = {"merge": get_spec("merge"), "exit": get_spec("exit")}


def _file(path, policies, *, evaluation=None, specs=None, head=None):
    block = outcome_block(policies, SPECS)
    if specs is not None:
        block["specs"] = specs
    doc = {"policy": head or next(iter(policies)), "config": {"evaluation": evaluation or EVALUATION}, "outcomes": block}
    path.write_text(json.dumps(doc))
    return path


def _tests_as_dicts(tests):
    return {s: {k: t.as_dict() for k, t in by.items()} for s, by in tests.items()}


def test_the_block_holds_every_episode_as_the_study_stores_it() -> None:
    a = [outcome("crash", "merge", 7, env_index=1, episode_index=2), outcome("timeout", "exit", 9)]
    block = outcome_block({"a": a}, SPECS)
    assert block == {"specs": specs_digest(SPECS), "policies": {"a": outcomes_to_json(a)}}
    back = outcomes_from_json(json.loads(json.dumps(block))["policies"]["a"])
    assert [(o.scenario, o.seed, o.env_index, o.episode_index, o.failed, o.crashed, o.cause) for o in back] == \
        [("merge", 7, 1, 2, True, True, "HV ahead"), ("exit", 9, 0, 0, True, False, "time-out")]


def test_pairing_stored_files_gives_the_tests_of_pairing_the_outcomes(tmp_path) -> None:
    fa = read_evaluation(_file(tmp_path / "a.json", {"dqn": _policy_a()}))
    fb = read_evaluation(_file(tmp_path / "b.json", {"brake": _policy_b(), "other": _policy_a()}))
    na, nb, tests = pair(fa, fb)
    assert (na, nb) == ("dqn", "brake")  # each file's head policy by default
    assert _tests_as_dicts(tests) == _tests_as_dicts(compare(_policy_a(), _policy_b()))
    merge = tests["merge"]["failed"]
    assert (merge.a_only, merge.b_only, merge.p_value) == (0, 6, pytest.approx(0.03125))
    exit_crash = tests["exit"]["crashed"]
    assert (exit_crash.a_only, exit_crash.b_only) == (3, 0)
    # Another policy of a file, chosen by name: a policy against itself has no discordant pair.
    _, _, same = pair(fa, fb, policy_b="other")
    assert same["mixed"]["failed"].p_value == 1.0 and same["mixed"]["failed"].a_only == 0
    # The order of the scenarios does not change the episodes.
    fc = read_evaluation(_file(tmp_path / "c.json", {"brake": _policy_b()},
                               evaluation={**EVALUATION, "scenarios": ["exit", "merge"]}))
    assert _tests_as_dicts(pair(fa, fc)[2]) == _tests_as_dicts(tests)


def test_one_policy_of_one_file_against_itself_is_refused(tmp_path) -> None:
    fa = read_evaluation(_file(tmp_path / "a.json", {"dqn": _policy_a(), "rule": _policy_b()}))
    with pytest.raises(ConfigError, match="'dqn' against itself"):
        pair(fa, fa)
    assert pair(fa, fa, policy_b="rule")[:2] == ("dqn", "rule")


def test_the_spec_digest_names_the_specs_not_their_order() -> None:
    merge, exitspec = get_spec("merge"), get_spec("exit")
    assert specs_digest({"merge": merge, "exit": exitspec}) == specs_digest({"exit": exitspec, "merge": merge})
    assert specs_digest({"merge": merge}) != specs_digest({"merge": merge.model_copy(update={"n_hv": merge.n_hv + 1})})


@pytest.mark.parametrize(("change", "needle"), [
    ({"evaluation": {**EVALUATION, "episodes_per_scenario": 4}}, "different evaluation sets (episodes_per_scenario: 6 against 4)"),
    ({"evaluation": {**EVALUATION, "reset_seed": 2**30 + 1}}, "different evaluation sets (reset_seed"),
    ({"evaluation": {**EVALUATION, "backend": "highway"}}, "different evaluation sets (backend: 'fast' against 'highway')"),
    ({"specs": "another"}, "different scenario specs"),
])
def test_files_of_other_episodes_or_specs_are_refused(tmp_path, change, needle) -> None:
    fa = read_evaluation(_file(tmp_path / "a.json", {"dqn": _policy_a()}))
    fb = read_evaluation(_file(tmp_path / "b.json", {"brake": _policy_b()}, **change))
    with pytest.raises(ConfigError, match=r"scored|played") as err:
        pair(fa, fb)
    assert needle in str(err.value) and "\n" not in str(err.value)


def test_other_episodes_under_the_same_evaluation_set_are_refused(tmp_path) -> None:
    fa = read_evaluation(_file(tmp_path / "a.json", {"dqn": _policy_a()}))
    fb = read_evaluation(_file(tmp_path / "b.json", {"brake": [*_policy_b()[:-1], outcome("success", "exit", 99)]}))
    with pytest.raises(ConfigError, match="not the same evaluation episodes"):
        pair(fa, fb)


def test_an_unknown_policy_is_refused_with_the_ones_there(tmp_path) -> None:
    fa = read_evaluation(_file(tmp_path / "a.json", {"dqn": _policy_a(), "rule": _policy_b()}))
    with pytest.raises(ConfigError, match=r"no per-episode outcomes of policy 'plan' \(it holds dqn, rule\)"):
        pair(fa, fa, policy_b="plan")


@pytest.mark.parametrize(("edit", "needle"), [
    (lambda d: d.pop("outcomes"), "holds no per-episode outcomes"),
    (lambda d: d["config"].pop("evaluation"), "not a `latentdrive evaluate --json` result"),
    (lambda d: d["config"]["evaluation"].pop("reset_seed"), "lacks reset_seed"),
    (lambda d: d["outcomes"].pop("specs"), "malformed (specs and policies expected)"),
    (lambda d: d["outcomes"].update(policies={}), "malformed (specs and policies expected)"),
    (lambda d: d["outcomes"]["policies"]["dqn"][0].pop("seed"), "outcomes of 'dqn' are malformed"),
    (lambda d: d["outcomes"]["policies"]["dqn"][0].update(seed=-1), "outcomes of 'dqn' are malformed"),
    (lambda d: d["outcomes"]["policies"]["dqn"][0].update(agent_crashed=[True]), "outcomes of 'dqn' are malformed"),
    (lambda d: d["outcomes"]["policies"].update(dqn="x"), "outcomes of 'dqn' are malformed"),
    (lambda d: d.update(policy="absent"), "has no per-episode outcomes"),
])
def test_a_damaged_file_is_named_in_one_line(tmp_path, edit, needle) -> None:
    path = _file(tmp_path / "a.json", {"dqn": _policy_a()})
    doc = json.loads(path.read_text())
    edit(doc)
    path.write_text(json.dumps(doc))
    with pytest.raises(ConfigError, match=re.escape(str(path))) as err:
        read_evaluation(path)
    assert needle in str(err.value) and "\n" not in str(err.value)


@pytest.mark.parametrize("text", ["", "{", "[1, 2]", "null"])
def test_a_file_that_is_not_json_or_not_an_object_is_named(tmp_path, text) -> None:
    path = tmp_path / "x.json"
    path.write_text(text)
    with pytest.raises(ConfigError, match=r"x\.json"):
        read_evaluation(path)
