"""Training seeds of one setting, each evaluated on its own, read as one result.

``latentdrive evaluate RUN --compare B --json FILE`` scores one trained policy; a setting is
judged over several training seeds. :func:`aggregate_seeds` reads one such file per seed
and gives, per scenario and mixed, each seed's failure rate, their mean with rliable's
stratified-bootstrap interval over seeds (:func:`latentdrive.evaluate.aggregate.seed_interval`;
the mixed ones resample seeds within each scenario), and each seed's paired difference to
its ``--compare`` with McNemar's exact p-value, the mean difference with its interval. The files must score the same evaluation
episodes; a file that is not an ``evaluate --json`` result, or scores other episodes, is
refused with its name.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from latentdrive.config import ConfigError
from latentdrive.evaluate.aggregate import seed_interval
from latentdrive.evaluate.policies import REFERENCE_POLICIES
from latentdrive.evaluate.report import render_table
from latentdrive.fileio import read_json

__all__ = ["SeedEval", "aggregate_seeds", "evaluation_set", "format_seeds", "read_seed_eval"]

MIXED = "mixed"


@dataclass(frozen=True)
class SeedEval:
    """One seed's ``evaluate --json`` result: failure rates per scenario and mixed."""

    path: str
    policy: str
    evaluation: dict[str, Any]
    failure: dict[str, float]
    #: The ``--compare`` policy or run (None without one) and its paired tests per scenario.
    compare: str | None
    tests: dict[str, dict[str, Any]]
    #: The folders of the policy and of the ``--compare`` run where they were given a label
    #: (``evaluate LABEL=RUN``: ``config.paths``); a name without one is its own.
    paths: dict[str, str] = field(default_factory=dict)

    def folder(self, name: str) -> str:
        """What policy ``name`` of this file is: the run folder it was read from, or the name
        itself (a reference, or a run given by its path)."""
        return self.paths.get(name, name)


def _at(doc: object, *keys: str) -> Any:
    """``doc[k0][k1]...``, or None where a level is missing or not an object."""
    for k in keys:
        if not isinstance(doc, dict):
            return None
        doc = doc.get(k)
    return doc


def _need(cond: bool, path: str | Path, what: str) -> None:
    if not cond:
        raise ConfigError(f"{path}: not a `latentdrive evaluate --json` result ({what})")


def _number(x: object) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def evaluation_set(doc: object, path: str | Path) -> dict[str, Any]:
    """The evaluation set of an ``evaluate --json`` document (``config.evaluation``, its
    scenarios a list of distinct names); :class:`ConfigError` naming ``path`` if it has none."""
    ev = _at(doc, "config", "evaluation")
    scenarios = _at(ev, "scenarios")
    _need(isinstance(scenarios, list) and bool(scenarios) and all(isinstance(s, str) for s in scenarios)
          and len(set(scenarios)) == len(scenarios) and MIXED not in scenarios, path, "no evaluation set")
    assert isinstance(ev, dict)
    return ev


def read_seed_eval(path: str | Path) -> SeedEval:
    """Read one ``evaluate --json`` file; :class:`ConfigError` naming it if it is not one."""
    doc = read_json(path, what="evaluation")
    ev = evaluation_set(doc, path)
    scenarios = ev["scenarios"]
    names = [*scenarios, MIXED]
    failure: dict[str, float] = {}
    for name in names:
        rate = _at(doc, MIXED, "failure_rate", "rate") if name == MIXED else \
            _at(doc, "scenarios", name, "failure_rate", "rate")
        _need(_number(rate) and 0.0 <= rate <= 1.0, path, f"no failure rate for {name}")
        failure[name] = float(rate)
    compare, tests = None, {}
    if _at(doc, "compare") is not None:
        compare = str(_at(doc, "compare", "b"))
        for name in names:
            t = _at(doc, "compare", "tests", name, "failed")
            _need(all(_number(_at(t, k)) for k in ("rate_b", "difference", "p_value")), path,
                  f"no paired test for {name}")
            tests[name] = t
    paths = _at(doc, "config", "paths") or {}
    _need(isinstance(paths, dict) and all(isinstance(v, str) for v in paths.values()), path,
          "config.paths is not a mapping of labels to run folders")
    return SeedEval(str(path), str(_at(doc, "policy")), ev, failure, compare, tests, dict(paths))


def aggregate_seeds(evals: Sequence[SeedEval], *, reps: int = 2000) -> dict[str, Any]:
    """Mean failure rates over ``evals`` (one per training seed) with intervals over seeds.

    Returns ``{"evaluation", "policies", "compare", "compare_runs", "paired", "rows"}``
    (``compare``: the distinct B names, sorted; ``compare_runs``: each seed's B, in the order
    given; ``paired``: each seed's B is a run of its own rather than one shared reference); ``rows[scenario]`` holds
    ``rates`` (per seed), ``mean``/``lo``/``hi`` (rliable, over seeds) and, with a comparison,
    ``compare_rates``, ``differences`` and ``p_values`` per seed and the mean difference
    with its interval. Raises :class:`ConfigError` when the files score different episodes
    or some compare and others do not.
    """
    if not evals:
        raise ConfigError("no evaluation files given")
    head = evals[0]
    seen: dict[str, str] = {}
    for e in evals:
        for key in (str(Path(e.path).resolve()), f"policy {Path(e.folder(e.policy)).resolve()}"):
            if key in seen:
                raise ConfigError(f"{e.path}: the same {'policy' if key.startswith('policy ') else 'file'} as "
                                  f"{seen[key]}; give each training seed once")
            seen[key] = e.path
    compares = {e.compare for e in evals if e.compare is not None}
    # Identity by folder: seeds whose runs share a label ("latent") are still each its own run.
    compared = {e.folder(e.compare) for e in evals if e.compare is not None}
    if len(compared) > 1 and compared & set(REFERENCE_POLICIES):
        # Each seed against its own run (raw seed k against latent seed k) is a pairing;
        # seeds against different reference drivers are not one comparison.
        raise ConfigError(f"the files compare against different policies ({', '.join(sorted(map(str, compares)))}); "
                          "compare every seed with the same reference")
    for e in evals[1:]:
        if e.evaluation != head.evaluation:
            raise ConfigError(f"{e.path}: scores other episodes than {head.path} (evaluation set "
                              f"{e.evaluation} against {head.evaluation}); evaluate every seed alike")
        if (e.compare is None) != (head.compare is None):
            raise ConfigError(f"{e.path}: {'has no' if e.compare is None else 'has a'} --compare, "
                              f"unlike {head.path}")
    names = [*head.evaluation["scenarios"], MIXED]
    rows: dict[str, dict[str, Any]] = {}
    for name in names:
        rates = [e.failure[name] for e in evals]
        if name == MIXED:
            # Stratified by scenario: seeds are resampled within each, as rliable does per task.
            scores: Any = [[e.failure[s] for s in head.evaluation["scenarios"]] for e in evals]
        else:
            scores = rates
        row: dict[str, Any] = {"rates": rates, **seed_interval(scores, reps=reps)}
        if head.compare is not None:
            diffs = [float(e.tests[name]["difference"]) for e in evals]
            d = seed_interval([[float(e.tests[s]["difference"]) for s in head.evaluation["scenarios"]]
                               for e in evals] if name == MIXED else diffs, reps=reps)
            row.update(compare_rates=[float(e.tests[name]["rate_b"]) for e in evals], differences=diffs,
                       p_values=[float(e.tests[name]["p_value"]) for e in evals],
                       difference={"mean": d["mean"], "lo": d["lo"], "hi": d["hi"]})
        rows[name] = row
    return {"evaluation": head.evaluation, "policies": [e.policy for e in evals], "compare": sorted(compares),
            "compare_runs": [e.compare for e in evals], "paired": len(compared) > 1, "rows": rows}


def _pct(x: float, sign: str = "") -> str:
    return f"{100 * x:{sign}.1f}"


def _interval(mean: float, lo: float | None, hi: float | None, sign: str = "") -> str:
    if lo is None or hi is None:
        return _pct(mean, sign)
    return f"{_pct(mean, sign)} [{_pct(lo, sign)}, {_pct(hi, sign)}]"


def format_seeds(agg: dict[str, Any]) -> str:
    """The table ``latentdrive aggregate`` prints: failure % per scenario, per seed and mean."""
    n = len(agg["policies"])
    ev = agg["evaluation"]
    lines = [f"{n} training seed(s), runs 1..{n}: {', '.join(agg['policies'])}",
             f"{ev.get('episodes_per_scenario')} evaluation episodes per scenario (reset seed {ev.get('reset_seed')}); "
             "failure %, the mean over seeds with rliable's 95% stratified-bootstrap interval over seeds"]
    has_cmp = bool(agg["compare"])
    head = ["scenario", *[f"run {i + 1}" for i in range(n)], "mean [95% CI]"]
    if has_cmp:
        # One reference for every seed, or each seed against its own run (named in run order).
        paired = agg["paired"]
        b_head = f"B, runs 1..{n} = {', '.join(agg['compare_runs'])}" if paired else f"B = {agg['compare'][0]}"
        head += [b_head, "A−B, mean [95% CI]", "p per seed (McNemar)"]
    rows = []
    for name, row in agg["rows"].items():
        cells = [name, *[_pct(r) for r in row["rates"]], _interval(row["mean"], row["lo"], row["hi"])]
        if has_cmp:
            b = row["compare_rates"] if paired else row["compare_rates"][:1]
            d = row["difference"]
            cells += [" / ".join(_pct(x) for x in b), _interval(d["mean"], d["lo"], d["hi"], "+"),
                      " ".join(f"{p:.2g}" for p in row["p_values"])]
        rows.append(cells)
    if n < 5:
        # Each resample draws from n values: with 3 seeds all three land on the lowest with
        # probability 1/27 > 2.5%, so a percentile interval is at most the seeds' range.
        lines.append(f"note: with {n} seed(s) a scenario's interval over seeds is at most the seeds' range and "
                     "covers less than 95%; read each seed's own test beside it")
    return "\n".join([*lines, render_table(head, rows, left=1)])
