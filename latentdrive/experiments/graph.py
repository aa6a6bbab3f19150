"""A study as a graph of steps, each keyed by the hash of what defines it.

A :class:`Step` names its kind (which function runs it), its resolved config (JSON values
only) and its inputs (other steps it reads, by role). Its key hashes the kind, the config
and the keys of its inputs, so changing anything upstream changes every key downstream,
and nothing else. A step writes only into its own folder, ``OUT/steps/<name>-<key>``;
it is finished when that folder holds ``done.json`` with its key (written last,
atomically). Re-running a study skips finished steps; a changed step gets a new folder
and leaves the old one alone.

Nothing here runs a step: the executors (:mod:`latentdrive.experiments.executor`) do.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from latentdrive.config import ConfigError
from latentdrive.fileio import MAX_JSON_BYTES, FileFormatError, atomic_write_text, read_json

__all__ = ["DONE", "LATER_SETTINGS", "RESUMED", "Graph", "Step", "StepRecord", "keyed_config"]

DONE = "done.json"
#: The summary key in which a resumable step reports the seconds that earlier, interrupted
#: attempts spent on the work it resumed from; the record keeps it beside ``wall_s``.
RESUMED = "resumed_s"
STEPS_DIR = "steps"
_SAFE = re.compile(r"[^A-Za-z0-9_.=-]+")

#: Settings added after studies had been run, each with the value that leaves what a step
#: does unchanged. A step's key leaves such a setting out while it holds that value, so
#: adding a setting keeps finished studies' keys, and their results (a test pins keys).
#: A path matches the end of a setting's path in the step's config.
LATER_SETTINGS: Mapping[tuple[str, ...], Any] = {
    ("train", "val_samples"): 0,
    ("train", "dice_weight"): 0.0,
    ("model",): {},
    ("reward", "failure"): 0.0,
    ("observation", "route"): 0.0,
    ("study", "score_samples"): 0,
    ("dqn", "adam_eps"): 1e-8,
    ("dqn", "augment_shift"): 0,
    ("dqn", "explore_rule"): 0.0,
    ("dqn", "aux_scale"): 0.0,
    ("dqn", "aux_neighbours"): 12,
    ("dqn", "aux_joint"): False,
    ("dqn", "aux_pretrain"): 0,
    ("keep",): "last",
    ("planner", "human_routes"): "known",
    ("vfan", "reader"): "conv",
    ("vfan", "attention_width"): 64,
    ("vfan", "attention_heads"): 4,
    ("vfan", "attention_context"): 0,
    ("vfan", "attention_stem"): "conv",
    ("vfan", "objects_k"): 16,
    ("vfan", "objects_frames"): 1,
    ("vfan", "objects_layers"): 0,
}


def keyed_config(config: Mapping[str, Any], path: tuple[str, ...] = ()) -> dict[str, Any]:
    """``config`` as its step's key sees it: without :data:`LATER_SETTINGS` at their values."""
    out: dict[str, Any] = {}
    for k, v in config.items():
        here = (*path, k)
        if any(here[-len(p):] == p and type(v) is type(d) and v == d for p, d in LATER_SETTINGS.items()):
            continue
        out[k] = keyed_config(v, here) if isinstance(v, Mapping) else v
    return out


@dataclass(frozen=True)
class Step:
    """One unit of work of a study.

    Attributes:
        name: unique in the study, e.g. ``policy/latent/mixed/s0``.
        kind: the step function that runs it (see :mod:`latentdrive.experiments.steps`).
        config: its resolved settings, JSON values only; part of the key.
        inputs: role → name of a step whose folder it reads; the inputs' keys are part
            of the key, their paths are not (a study can move).
        cost: a rough estimate of its run time in seconds, for the progress display's
            ETA and for starting long steps first; not part of the key.
    """

    name: str
    kind: str
    config: Mapping[str, Any]
    inputs: Mapping[str, str] = field(default_factory=dict)
    cost: float = 1.0


@dataclass(frozen=True)
class StepRecord:
    """What ``done.json`` holds: the step's key, its summary and what it cost."""

    name: str
    kind: str
    key: str
    summary: dict[str, Any]
    wall_s: float
    peak_rss_mb: float
    #: The commit the step ran from (:func:`latentdrive.provenance.source_revision`); None
    #: when unknown, and in records written before it was kept.
    source: str | None = None
    #: Seconds that earlier, interrupted attempts spent on the work this one resumed from
    #: (``wall_s`` is the finishing attempt's alone); 0 for a step run in one go.
    resumed_s: float = 0.0

    @property
    def cost_s(self) -> float:
        """What the step cost, interrupted attempts included (less work they redid)."""
        return self.wall_s + self.resumed_s

    def as_dict(self) -> dict[str, Any]:
        return {"name": self.name, "kind": self.kind, "key": self.key, "wall_s": self.wall_s,
                "resumed_s": self.resumed_s, "peak_rss_mb": self.peak_rss_mb, "source": self.source,
                "summary": self.summary}


class Graph:
    """Steps and their dependencies, checked: unique names, known inputs, no cycles."""

    def __init__(self, steps: Iterable[Step]) -> None:
        self.steps: dict[str, Step] = {}
        for s in steps:
            if s.name in self.steps:
                raise ConfigError(f"study graph: two steps are named {s.name!r}")
            self.steps[s.name] = s
        for s in self.steps.values():
            for role, dep in s.inputs.items():
                if dep not in self.steps:
                    raise ConfigError(f"study graph: step {s.name!r} reads {role} from unknown step {dep!r}")
        self.order = self._topological()
        self.keys: dict[str, str] = {}
        for name in self.order:
            self.keys[name] = self._key(self.steps[name])

    def _topological(self) -> list[str]:
        order: list[str] = []
        state: dict[str, int] = {}  # 1: being visited, 2: placed
        for root in self.steps:
            stack = [(root, iter(self.steps[root].inputs.values()))]
            if state.get(root):
                continue
            state[root] = 1
            while stack:
                name, deps = stack[-1]
                dep = next(deps, None)
                if dep is None:
                    stack.pop()
                    state[name] = 2
                    order.append(name)
                elif state.get(dep) == 1:
                    raise ConfigError(f"study graph: steps {name!r} and {dep!r} depend on each other")
                elif not state.get(dep):
                    state[dep] = 1
                    stack.append((dep, iter(self.steps[dep].inputs.values())))
        return order

    def _key(self, step: Step) -> str:
        blob = json.dumps({"kind": step.kind, "config": keyed_config(step.config),
                           "inputs": {role: self.keys[dep] for role, dep in step.inputs.items()}},
                          sort_keys=True, separators=(",", ":"), allow_nan=False)
        return hashlib.sha256(blob.encode()).hexdigest()[:12]

    def folder(self, out: Path, name: str) -> Path:
        """The one folder step ``name`` writes: ``OUT/steps/<name>-<key>``."""
        return out / STEPS_DIR / f"{_SAFE.sub('-', name)}-{self.keys[name]}"

    def inputs(self, out: Path, name: str) -> dict[str, Path]:
        return {role: self.folder(out, dep) for role, dep in self.steps[name].inputs.items()}

    def record(self, out: Path, name: str) -> StepRecord | None:
        """The step's record when it has finished with its current key, else None.

        Raises:
            ConfigError: ``done.json`` exists but is not a record of this step.
        """
        path = self.folder(out, name) / DONE
        if not path.is_file():
            return None
        try:
            data = read_json(path, limit=MAX_JSON_BYTES, what="step record", error=FileFormatError)
            rec = StepRecord(name=data["name"], kind=data["kind"], key=data["key"], summary=dict(data["summary"]),
                             wall_s=float(data["wall_s"]), peak_rss_mb=float(data["peak_rss_mb"]),
                             source=None if data.get("source") is None else str(data["source"]),
                             resumed_s=float(data.get(RESUMED, 0.0)))
        except (KeyError, TypeError, ValueError) as exc:
            raise ConfigError(f"{path}: not a step record ({type(exc).__name__}: {exc})") from None
        if not all(math.isfinite(v) and v >= 0 for v in (rec.wall_s, rec.peak_rss_mb, rec.resumed_s)):
            raise ConfigError(f"{path}: not a step record (wall_s {rec.wall_s}, resumed_s {rec.resumed_s}, "
                              f"peak_rss_mb {rec.peak_rss_mb})")
        if rec.key != self.keys[name] or rec.name != name:
            raise ConfigError(f"{path}: records step {rec.name!r} with key {rec.key}, not {name!r} with key {self.keys[name]}")
        return rec

    def pending(self, out: Path) -> list[str]:
        """Unfinished steps, in dependency order."""
        return [n for n in self.order if self.record(out, n) is None]

    def write_record(self, out: Path, rec: StepRecord) -> None:
        atomic_write_text(self.folder(out, rec.name) / DONE, json.dumps(rec.as_dict(), indent=1, allow_nan=False) + "\n")
