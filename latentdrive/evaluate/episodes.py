"""Per-episode outcomes in an ``evaluate --json`` file, and paired tests between two files.

``latentdrive evaluate ... --json FILE`` stores, for every policy it played, which episodes
it failed and which it crashed, each episode named by its scenario, reset seed, environment
slot and index in that slot (:func:`episode_columns`). ``latentdrive compare A.json B.json``
then pairs a policy of one file with a policy of another on the same episodes (McNemar's
exact test and the paired difference, :func:`latentdrive.evaluate.report.compare`) without
playing them again (:func:`pair`). Two files pair only if they scored the same evaluation
set (scenarios, episodes per scenario, environments, backend, reset seed) on the same
scenario specs (:func:`specs_digest`); otherwise a one-line error names what differs. Each
policy played the episodes through its own map, as with ``evaluate --compare``.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from latentdrive.config import ConfigError
from latentdrive.evaluate.report import EpisodeResult, compare
from latentdrive.evaluate.stats import PairedTest
from latentdrive.fileio import read_json
from latentdrive.outcome import EpisodeOutcome
from latentdrive.scenarios import ScenarioSpec

__all__ = ["StoredEvaluation", "episode_columns", "pair", "read_evaluation", "specs_digest"]

#: The fields of :meth:`EvaluationSet.as_dict` that name the episodes played; the planner's
#: settings only describe the ``plan`` reference.
EPISODE_FIELDS = ("scenarios", "episodes_per_scenario", "envs", "backend", "reset_seed", "seed_offset")
_COLUMNS = ("scenario", "seed", "env", "episode", "failed", "crashed")


def episode_columns(outcomes: Sequence[EpisodeOutcome]) -> dict[str, list[Any]]:
    """One policy's outcomes as JSON columns: ``scenario``, ``seed``, ``env``, ``episode``
    (which episode) and ``failed``, ``crashed`` (0/1), one entry per episode."""
    return {
        "scenario": [o.scenario for o in outcomes],
        "seed": [int(o.seed) for o in outcomes],
        "env": [int(o.env_index) for o in outcomes],
        "episode": [int(o.episode_index) for o in outcomes],
        "failed": [int(o.failed) for o in outcomes],
        "crashed": [int(o.crashed) for o in outcomes],
    }


def specs_digest(specs: Mapping[str, ScenarioSpec]) -> str:
    """SHA-256 of the scenario specs played, by name: two evaluations with the same seeds
    play the same episodes only on the same specs."""
    doc = {name: spec.model_dump(mode="json") for name, spec in sorted(specs.items())}
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()


@dataclass(frozen=True)
class StoredEvaluation:
    """What :func:`pair` needs of one ``evaluate --json`` file."""

    path: str
    #: The evaluation set's :data:`EPISODE_FIELDS`.
    evaluation: dict[str, Any]
    specs: str
    #: The file's first policy (its run, else its first reference).
    head: str
    episodes: dict[str, list[EpisodeResult]]


def _int(x: object) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


def _results(path: str, name: str, cols: object) -> list[EpisodeResult]:
    bad = f"{path}: the per-episode outcomes of {name!r} are malformed"
    if not isinstance(cols, dict) or set(cols) != set(_COLUMNS) or not all(isinstance(cols[c], list) for c in _COLUMNS):
        raise ConfigError(f"{bad} (columns {', '.join(_COLUMNS)} expected)")
    n = len(cols["scenario"])
    if any(len(cols[c]) != n for c in _COLUMNS):
        raise ConfigError(f"{bad} (columns of different lengths)")
    if not all(isinstance(s, str) for s in cols["scenario"]) or \
            not all(_int(v) for c in ("seed", "env", "episode") for v in cols[c]) or \
            not all(v in (0, 1) and _int(v) for c in ("failed", "crashed") for v in cols[c]):
        raise ConfigError(f"{bad} (a scenario that is not a name, or an entry that is not an integer or 0/1)")
    return [EpisodeResult(s, seed, env, ep, bool(f), bool(c))
            for s, seed, env, ep, f, c in zip(*(cols[k] for k in _COLUMNS), strict=True)]


def read_evaluation(path: str | Path) -> StoredEvaluation:
    """Read one ``evaluate --json`` file's evaluation set and per-episode outcomes;
    :class:`ConfigError` naming the file if it is not such a file or holds none."""
    where = str(path)
    doc = read_json(path, what="evaluation", error=ConfigError)
    evaluation = doc.get("config", {}).get("evaluation") if isinstance(doc, dict) and isinstance(doc.get("config"), dict) else None
    if not isinstance(evaluation, dict) or any(k not in evaluation for k in EPISODE_FIELDS):
        raise ConfigError(f"{where}: not a `latentdrive evaluate --json` result (no evaluation set)")
    block = doc.get("episodes")
    if block is None:
        raise ConfigError(f"{where}: holds no per-episode outcomes (written before `evaluate --json` stored them); "
                          "evaluate again with --json")
    if not isinstance(block, dict) or not isinstance(block.get("specs"), str) or not isinstance(block.get("policies"), dict) \
            or not block["policies"]:
        raise ConfigError(f"{where}: the per-episode outcomes are malformed (specs and policies expected)")
    head = doc.get("policy")
    if not isinstance(head, str) or head not in block["policies"]:
        raise ConfigError(f"{where}: its policy {head!r} has no per-episode outcomes")
    episodes = {str(name): _results(where, str(name), cols) for name, cols in block["policies"].items()}
    return StoredEvaluation(where, {k: evaluation[k] for k in EPISODE_FIELDS}, block["specs"], head, episodes)


def _policy(ev: StoredEvaluation, name: str | None) -> str:
    name = name or ev.head
    if name not in ev.episodes:
        raise ConfigError(f"{ev.path}: no per-episode outcomes of policy {name!r} (it holds {', '.join(ev.episodes)})")
    return name


def pair(a: StoredEvaluation, b: StoredEvaluation, policy_a: str | None = None,
         policy_b: str | None = None) -> tuple[str, str, dict[str, dict[str, PairedTest]]]:
    """Policy ``policy_a`` of ``a`` (default: its head policy) against ``policy_b`` of ``b``
    on the same episodes: their names and :func:`compare`'s tests per scenario and mixed.
    :class:`ConfigError` if the files scored other episodes or other specs."""
    na, nb = _policy(a, policy_a), _policy(b, policy_b)
    differ = [k for k in EPISODE_FIELDS if a.evaluation[k] != b.evaluation[k]]
    if differ:
        k = differ[0]
        raise ConfigError(f"{a.path} and {b.path} scored different evaluation sets ({k}: "
                          f"{a.evaluation[k]!r} against {b.evaluation[k]!r})")
    if a.specs != b.specs:
        raise ConfigError(f"{a.path} and {b.path} played different scenario specs under the same names")
    try:
        return na, nb, compare(a.episodes[na], b.episodes[nb])
    except ValueError as exc:
        raise ConfigError(f"{a.path} ({na}) and {b.path} ({nb}): {exc}") from None
