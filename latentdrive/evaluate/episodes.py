"""Per-episode outcomes in an ``evaluate --json`` file, and paired tests between two files.

``latentdrive evaluate ... --json FILE`` stores, under ``"outcomes"``, every episode each
policy it played, as the study's step folders store them
(:func:`latentdrive.outcome.outcomes_to_json`: scenario, reset seed, environment slot and
index in it, steps, per-AV crashes, arrivals and returns, speed, cause), beside a digest of
the scenario specs played (:func:`outcome_block`). ``latentdrive compare A.json B.json``
then pairs a policy of one file with a policy of another on the same episodes (McNemar's
exact test and the paired difference, :func:`latentdrive.evaluate.report.compare`) without
playing them again (:func:`pair`).

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
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from latentdrive.config import ConfigError
from latentdrive.evaluate.report import compare
from latentdrive.evaluate.seeds import evaluation_set
from latentdrive.evaluate.stats import PairedTest
from latentdrive.fileio import read_json
from latentdrive.outcome import EpisodeOutcome, outcomes_from_json, outcomes_to_json
from latentdrive.scenarios import ScenarioSpec

__all__ = ["EPISODE_FIELDS", "StoredEvaluation", "outcome_block", "pair", "read_evaluation", "specs_digest"]

#: The fields of an evaluation set (``EvaluationSet.as_dict``) that name the episodes played;
#: the planner's settings describe only the ``plan`` reference.
EPISODE_FIELDS = ("scenarios", "episodes_per_scenario", "envs", "backend", "reset_seed", "seed_offset")


def outcome_block(outcomes: Mapping[str, Sequence[EpisodeOutcome]], specs: Mapping[str, ScenarioSpec]) -> dict[str, Any]:
    """The ``"outcomes"`` block of ``evaluate --json``: ``{"specs": DIGEST, "policies":
    {POLICY: [episode, ...]}}``, each episode as :func:`~latentdrive.outcome.outcomes_to_json`
    writes it."""
    return {"specs": specs_digest(specs), "policies": {name: outcomes_to_json(list(o)) for name, o in outcomes.items()}}


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
    episodes: dict[str, list[EpisodeOutcome]]


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
    policies = block.get("policies") if isinstance(block, dict) else None
    if not isinstance(block, dict) or not isinstance(block.get("specs"), str) or not isinstance(policies, dict) \
            or not policies:
        raise ConfigError(f"{where}: the per-episode outcomes are malformed (specs and policies expected)")
    episodes: dict[str, list[EpisodeOutcome]] = {}
    for name, items in policies.items():
        try:
            episodes[name] = outcomes_from_json(items)
        except ValueError as exc:
            raise ConfigError(f"{where}: the per-episode outcomes of {name!r} are malformed ({exc})") from None
    head = doc.get("policy")
    if not isinstance(head, str) or head not in episodes:
        raise ConfigError(f"{where}: its policy {head!r} has no per-episode outcomes")
    return StoredEvaluation(where, evaluation, block["specs"], head, episodes)


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
