"""Per-episode outcomes in an ``evaluate --json`` file, and paired tests between two files.

``latentdrive evaluate ... --json FILE`` stores, under ``"outcomes"``, which episodes each
policy it played failed and crashed (:func:`outcome_block`): the episodes once per scenario,
each named ``"SEED/ENV/EPISODE"`` (its reset seed, environment slot and index in that slot),
sorted, and for each policy a string of 0s and 1s per scenario aligned with them.
``latentdrive compare A.json B.json`` then pairs a policy of one file with a policy of
another on the same episodes (McNemar's exact test and the paired difference,
:func:`latentdrive.evaluate.report.compare`) without playing them again (:func:`pair`).

Two files pair only if they scored the same evaluation set (the scenarios, in any order,
episodes per scenario, environments, backend, reset seed) on the same scenario specs
(:func:`specs_digest`), and hold the same episodes; otherwise a one-line error names what
differs. Each policy played the episodes through its own map, as with ``evaluate
--compare``. What no check can see: files written by versions of the simulator that play
the same seeds differently.
"""

from __future__ import annotations

import hashlib
import json
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from latentdrive.config import ConfigError
from latentdrive.evaluate.report import EpisodeResult, compare
from latentdrive.evaluate.seeds import evaluation_set
from latentdrive.evaluate.stats import PairedTest
from latentdrive.fileio import read_json
from latentdrive.outcome import EpisodeOutcome
from latentdrive.scenarios import ScenarioSpec

__all__ = ["EPISODE_FIELDS", "StoredEvaluation", "outcome_block", "pair", "read_evaluation", "specs_digest"]

#: The fields of an evaluation set (``EvaluationSet.as_dict``) that name the episodes played;
#: the planner's settings describe only the ``plan`` reference.
EPISODE_FIELDS = ("scenarios", "episodes_per_scenario", "envs", "backend", "reset_seed", "seed_offset")
_KEY = re.compile(r"(0|[1-9][0-9]{0,18})/(0|[1-9][0-9]{0,5})/(0|[1-9][0-9]{0,9})")
_FLAGS = re.compile(r"[01]*")


def _key(o: EpisodeOutcome) -> tuple[int, int, int]:
    return int(o.seed), int(o.env_index), int(o.episode_index)


def outcome_block(outcomes: Mapping[str, Sequence[EpisodeOutcome]], specs: Mapping[str, ScenarioSpec]) -> dict[str, Any]:
    """The ``"outcomes"`` block of ``evaluate --json`` for every policy's outcomes (all on
    the same episodes, as :func:`~latentdrive.experiments.policy.evaluate_many` plays them):
    ``{"specs": DIGEST, "episodes": {SCENARIO: ["SEED/ENV/EPISODE", ...]}, "failed":
    {POLICY: {SCENARIO: "0110..."}}, "crashed": {...}}``."""
    keys: dict[str, list[tuple[int, int, int]]] = {}
    failed: dict[str, dict[str, str]] = {}
    crashed: dict[str, dict[str, str]] = {}
    for name, outs in outcomes.items():
        by: dict[str, dict[tuple[int, int, int], EpisodeOutcome]] = {}
        for o in outs:
            by.setdefault(o.scenario, {})[_key(o)] = o
        for scenario, episodes in by.items():
            order = keys.setdefault(scenario, sorted(episodes))
            if sorted(episodes) != order:
                raise RuntimeError(f"{name} played other {scenario} episodes than the first policy")
            failed.setdefault(name, {})[scenario] = "".join("1" if episodes[k].failed else "0" for k in order)
            crashed.setdefault(name, {})[scenario] = "".join("1" if episodes[k].crashed else "0" for k in order)
    return {"specs": specs_digest(specs), "episodes": {s: [f"{a}/{b}/{c}" for a, b, c in ks] for s, ks in keys.items()},
            "failed": failed, "crashed": crashed}


def specs_digest(specs: Mapping[str, ScenarioSpec]) -> str:
    """SHA-256 of the scenario specs played, by name: two evaluations with the same seeds
    play the same episodes only on the same specs."""
    doc = {name: spec.model_dump(mode="json") for name, spec in sorted(specs.items())}
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()


@dataclass(frozen=True)
class StoredEvaluation:
    """What :func:`pair` needs of one ``evaluate --json`` file."""

    path: str
    #: The whole evaluation set the file records (:data:`EPISODE_FIELDS` and more).
    evaluation: dict[str, Any]
    specs: str
    #: The file's first policy (its run, else its first reference).
    head: str
    episodes: dict[str, list[EpisodeResult]]


def _policies(where: str, block: dict[str, Any], keys: dict[str, list[tuple[int, int, int]]]) -> dict[str, list[EpisodeResult]]:
    failed, crashed = block.get("failed"), block.get("crashed")
    if not isinstance(failed, dict) or not isinstance(crashed, dict) or not failed or set(failed) != set(crashed):
        raise ConfigError(f"{where}: the per-episode outcomes are malformed (failed and crashed of the same policies expected)")
    out: dict[str, list[EpisodeResult]] = {}
    for name in failed:
        f, c = failed[name], crashed[name]
        ok = isinstance(f, dict) and isinstance(c, dict) and set(f) == set(c) == set(keys) and all(
            isinstance(f[s], str) and isinstance(c[s], str) and _FLAGS.fullmatch(f[s]) and _FLAGS.fullmatch(c[s])
            and len(f[s]) == len(c[s]) == len(keys[s]) for s in keys)
        if not ok:
            raise ConfigError(f"{where}: the per-episode outcomes of {name!r} are malformed (a string of 0s and 1s "
                              "per scenario, one per episode, expected)")
        out[name] = [EpisodeResult(s, seed, env, ep, f[s][i] == "1", c[s][i] == "1")
                     for s in keys for i, (seed, env, ep) in enumerate(keys[s])]
    return out


def read_evaluation(path: str | Path) -> StoredEvaluation:
    """Read one ``evaluate --json`` file's evaluation set and per-episode outcomes;
    :class:`ConfigError` naming the file if it is not such a file or holds none."""
    where = str(path)
    doc = read_json(path, what="evaluation", error=ConfigError)
    evaluation = evaluation_set(doc, path)
    missing = [k for k in EPISODE_FIELDS if k not in evaluation]
    if missing:
        raise ConfigError(f"{where}: not a `latentdrive evaluate --json` result (its evaluation set lacks {missing[0]})")
    block = doc.get("outcomes")
    if block is None:
        raise ConfigError(f"{where}: holds no per-episode outcomes (written before `evaluate --json` stored them); "
                          "evaluate again with --json")
    episodes = block.get("episodes") if isinstance(block, dict) else None
    if not isinstance(block, dict) or not isinstance(block.get("specs"), str) or not isinstance(episodes, dict) \
            or set(episodes) != set(evaluation["scenarios"]):
        raise ConfigError(f"{where}: the per-episode outcomes are malformed (specs and the episodes of every "
                          "scenario expected)")
    keys: dict[str, list[tuple[int, int, int]]] = {}
    for s, names in episodes.items():
        matches = [_KEY.fullmatch(n) if isinstance(n, str) else None for n in names] if isinstance(names, list) else [None]
        if not all(matches) or len(set(names)) != len(names):
            raise ConfigError(f"{where}: the per-episode outcomes name the {s} episodes wrongly "
                              "(distinct SEED/ENV/EPISODE expected)")
        keys[s] = [(int(m.group(1)), int(m.group(2)), int(m.group(3))) for m in matches if m]
    head = doc.get("policy")
    policies = _policies(where, block, keys)
    if not isinstance(head, str) or head not in policies:
        raise ConfigError(f"{where}: its policy {head!r} has no per-episode outcomes")
    return StoredEvaluation(where, evaluation, block["specs"], head, policies)


def _policy(ev: StoredEvaluation, name: str | None) -> str:
    name = name or ev.head
    if name not in ev.episodes:
        raise ConfigError(f"{ev.path}: no per-episode outcomes of policy {name!r} (it holds {', '.join(ev.episodes)})")
    return name


def _episode_fields(ev: StoredEvaluation) -> dict[str, Any]:
    # The order of --scenarios does not change the episodes: each scenario's start from
    # the same reset seed whatever its place.
    return {**{k: ev.evaluation[k] for k in EPISODE_FIELDS}, "scenarios": sorted(ev.evaluation["scenarios"])}


def pair(a: StoredEvaluation, b: StoredEvaluation, policy_a: str | None = None,
         policy_b: str | None = None) -> tuple[str, str, dict[str, dict[str, PairedTest]]]:
    """Policy ``policy_a`` of ``a`` (default: its head policy) against ``policy_b`` of ``b``
    on the same episodes: their names and :func:`compare`'s tests per scenario and mixed.
    :class:`ConfigError` if the files scored other episodes or other specs, or if both sides
    are one policy of one file."""
    na, nb = _policy(a, policy_a), _policy(b, policy_b)
    if na == nb and Path(a.path).resolve() == Path(b.path).resolve():
        raise ConfigError(f"{a.path}: policy {na!r} against itself; name another with --a or --b")
    fa, fb = _episode_fields(a), _episode_fields(b)
    differ = [k for k in EPISODE_FIELDS if fa[k] != fb[k]]
    if differ:
        k = differ[0]
        raise ConfigError(f"{a.path} and {b.path} scored different evaluation sets ({k}: {fa[k]!r} against {fb[k]!r})")
    if a.specs != b.specs:
        raise ConfigError(f"{a.path} and {b.path} played different scenario specs under the same names")
    try:
        return na, nb, compare(a.episodes[na], b.episodes[nb])
    except ValueError as exc:
        raise ConfigError(f"{a.path} ({na}) and {b.path} ({nb}): {exc}") from None
