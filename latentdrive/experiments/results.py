"""The study's numbers, from its finished steps: what ``results.json`` holds.

Rates of one policy on one test set carry Wilson intervals over episodes; rates of a
policy *kind* (say, latent policies trained on the mix) average its training seeds and
carry rliable's bootstrap interval over seeds. Bottleneck and baseline meet identical
episodes, so they are compared with McNemar's exact test on the paired episodes (pooled
over seeds: seed ``k`` of one against seed ``k`` of the other), and seed by seed.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from scipy.stats import spearmanr

from latentdrive.config import ConfigError
from latentdrive.evaluate.aggregate import seed_interval
from latentdrive.evaluate.probes import read_probe_results
from latentdrive.evaluate.stats import json_values, paired_test, rate_ci
from latentdrive.experiments.bnn_report import read_report
from latentdrive.experiments.graph import Graph, StepRecord
from latentdrive.experiments.steps import OUTCOMES, PROBES, RUN
from latentdrive.experiments.study import (
    ABLATIONS,
    IMITATION,
    REPS,
    ReproduceConfig,
    policy_name,
    reference_name,
)
from latentdrive.fileio import read_json, read_log
from latentdrive.outcome import EpisodeOutcome, outcomes_from_json
from latentdrive.rl.runfolder import EVAL_COLUMNS, EVALS

__all__ = ["MIXED", "gather_results"]

MIXED = "mixed"
Episodes = list[EpisodeOutcome]
#: References each mix policy seed is tested against, alone (the rule driver is the bar a
#: learned policy must clear; the random policy, the least it must do).
PER_SEED_REFERENCES = ("random", "rule")


def _load(path: Path, eval_cfg: Mapping[str, Any]) -> Episodes:
    """A finished evaluation step's outcomes: every episode its config asked for."""
    try:
        data = read_json(path, limit=1 << 30, what="evaluation outcomes", error=ConfigError)
    except FileNotFoundError:
        raise ConfigError(f"{path}: missing, though its step is recorded as finished; delete "
                          f"{path.parent} and run the study again") from None
    try:
        eps = outcomes_from_json(data)
    except ValueError as exc:
        raise ConfigError(f"{path}: {exc}") from None
    for scen in eval_cfg["scenarios"]:
        n = sum(o.scenario == scen for o in eps)
        if n != eval_cfg["episodes"]:
            raise ConfigError(f"{path}: {n} episodes of {scen}, not the {eval_cfg['episodes']} its step ran")
    return eps


def _subset(eps: Episodes, test: str) -> Episodes:
    """The episodes of one test scenario, or all of them for the mixed test set, in a fixed
    order (scenario, slot, episode), so that two policies' lists pair up."""
    chosen = eps if test == MIXED else [o for o in eps if o.scenario == test]
    return sorted(chosen, key=lambda o: (o.scenario, o.env_index, o.episode_index))


def _flags(eps: Episodes, what: str) -> np.ndarray:
    return np.array([o.failed if what == "failure" else o.crashed for o in eps], dtype=bool)


def _rates(eps: Episodes) -> dict[str, Any]:
    out: dict[str, Any] = {"episodes": len(eps)}
    for what in ("failure", "crash"):
        flags = _flags(eps, what)
        r = rate_ci(int(flags.sum()), len(flags))
        out[what] = {"rate": r.rate, "lo": r.lo, "hi": r.hi}
    return out


class _Study:
    """Outcomes of every evaluation step, indexed for the tables."""

    def __init__(self, cfg: ReproduceConfig, graph: Graph, out: Path) -> None:
        self.cfg, self.graph, self.out = cfg, graph, out
        self.tests = [*cfg.scenarios, MIXED]
        self.eps: dict[str, Episodes] = {}
        for name in graph.order:
            if graph.steps[name].kind == "evaluate":
                self.eps[name] = _load(graph.folder(out, name) / OUTCOMES, graph.steps[name].config["eval"])

    def seeds(self, rep: str, train: str, prefix: str = "evaluate/") -> list[Episodes]:
        names = [prefix + policy_name(rep, train, k) for k in range(self.cfg.seeds)]
        return [self.eps[n] for n in names if n in self.eps]

    def kind(self, rep: str, train: str, tests: Sequence[str] | None = None) -> dict[str, Any]:
        """A policy kind's failure and crash rates per test set, over its seeds."""
        runs = self.seeds(rep, train)
        out: dict[str, Any] = {}
        for test in tests or self.tests:
            per_seed = [_subset(e, test) for e in runs]
            entry: dict[str, Any] = {"episodes_per_seed": len(per_seed[0]) if per_seed else 0}
            for what in ("failure", "crash"):
                flags = [_flags(e, what) for e in per_seed]
                pooled = np.concatenate(flags) if flags else np.zeros(0, dtype=bool)
                w = rate_ci(int(pooled.sum()), len(pooled))
                # The Wilson interval over the pooled episodes describes these trained
                # policies; the interval over seeds, the training method.
                entry[what] = {**seed_interval([float(f.mean()) for f in flags]),
                               "per_seed": [float(f.mean()) for f in flags],
                               "episodes": {"rate": w.rate, "lo": w.lo, "hi": w.hi, "n": w.n}}
            out[test] = entry
        return out

    def paired(self, a: str, b: str, train: str, test: str) -> dict[str, Any]:
        """``a`` against ``b`` (representations trained on ``train``) on identical episodes of ``test``."""
        xa, xb = self.seeds(a, train), self.seeds(b, train)
        n = min(len(xa), len(xb))
        out: dict[str, Any] = {}
        for what in ("failure", "crash"):
            fa = np.concatenate([_flags(_subset(xa[k], test), what) for k in range(n)])
            fb = np.concatenate([_flags(_subset(xb[k], test), what) for k in range(n)])
            out[what] = paired_test(fa, fb).as_dict()
        return out

    def paired_per_seed(self, a: str, b: str, train: str, test: str = MIXED) -> list[dict[str, Any]]:
        """Seed ``k`` of ``a`` against seed ``k`` of ``b`` on identical episodes (failure), each seed alone."""
        xa, xb = self.seeds(a, train), self.seeds(b, train)
        return [paired_test(_flags(_subset(xa[k], test), "failure"), _flags(_subset(xb[k], test), "failure")).as_dict()
                for k in range(min(len(xa), len(xb)))]

    def against_reference(self, rep: str, train: str, ref: str, test: str = MIXED) -> list[dict[str, Any]]:
        """Each seed of a policy kind against a reference on the same episodes (failure)."""
        ref_eps = _subset(self.eps[reference_name(ref)], test)
        return [paired_test(_flags(_subset(e, test), "failure"), _flags(ref_eps, "failure")).as_dict()
                for e in self.seeds(rep, train)]


def _curve(run: Path, test: str) -> list[list[float]]:
    """``[[transitions, failure_rate], ...]`` of a policy run's periodic evaluations."""
    path = run / EVALS
    try:
        rows = read_log(path, columns=EVAL_COLUMNS, key="transitions", what="evaluation log", error=ConfigError)
    except FileNotFoundError:
        return []
    try:
        return [[float(r["transitions"]), float(r["failure_rate"])] for r in rows if r.get("scenario") == test]
    except (KeyError, TypeError, ValueError) as exc:
        raise ConfigError(f"{path}: not an evaluation log ({type(exc).__name__}: {exc})") from None


def _distance_to_rest(names: Sequence[str], m: Sequence[Sequence[float]], left_out: str) -> float:
    """Mean scenario distance from the left-out scenario to the scenarios trained on."""
    i = list(names).index(left_out)
    return float(np.mean([m[i][j] for j in range(len(names)) if j != i]))


def gather_results(cfg: ReproduceConfig, graph: Graph, out: Path, records: Mapping[str, StepRecord]) -> dict[str, Any]:
    """Every number the report shows, from the finished steps of ``graph`` in ``out``."""
    st = _Study(cfg, graph, out)
    scen = list(cfg.scenarios)
    exp = cfg.experiments
    res: dict[str, Any] = {"scenarios": scen, "seeds": cfg.seeds, "tests": st.tests,
                           "evaluation": {"episodes_per_scenario": cfg.evaluate.episodes, "envs": cfg.evaluate.envs,
                                          "seed_offset": cfg.evaluate.seed_offset}}
    res["references"] = {ref: {t: _rates(_subset(st.eps[reference_name(ref)], t)) for t in st.tests}
                         for ref in cfg.evaluate.references}

    # Bottleneck vs baseline: each scenario's oracle, and the mix policy on the mixed test set.
    head = []
    for train, test in [*((s, s) for s in scen), (MIXED, MIXED)]:
        row: dict[str, Any] = {"train": train, "test": test}
        for rep in REPS:
            row[rep] = st.kind(rep, train, [test])[test]
        row["paired"] = st.paired("latent", "raw", train, test)
        head.append(row)
    res["headline"] = head

    # Train × test matrices.
    trains = [*scen, MIXED]
    by_train = {(rep, train): st.kind(rep, train) for rep in REPS for train in trains}
    for key, what in (("matrix", "failure"), ("matrix_crash", "crash")):
        res[key] = {rep: {train: {t: v[what]["mean"] for t, v in by_train[rep, train].items()} for train in trains}
                    for rep in REPS}

    # Domain adaptation: the mix policy against each scenario's oracle.
    res["domain_adaptation"] = {rep: {s: {"mixed": st.kind(rep, MIXED, [s])[s]["failure"],
                                          "oracle": st.kind(rep, s, [s])[s]["failure"]} for s in scen} for rep in REPS}

    # Each seed on its own: whether every training seed, not just their mean, beats a reference.
    res["per_seed"] = {"latent_vs_raw": st.paired_per_seed("latent", "raw", MIXED),
                       **{f"vs_{ref}": {rep: st.against_reference(rep, MIXED, ref) for rep in REPS}
                          for ref in PER_SEED_REFERENCES if ref in cfg.evaluate.references}}

    if exp.transfer_target:
        t = exp.transfer_target
        res["transfer"] = {"target": t, **{rep: {
            "finetuned": st.kind(rep, f"{t}-finetuned", [t])[t]["failure"],
            "scratch": st.kind(rep, t, [t])[t]["failure"],
            "zero_shot": st.kind(rep, f"without-{t}", [t])[t]["failure"],
            "curves": {"finetuned": [_curve(graph.folder(out, policy_name(rep, f"{t}-finetuned", k)) / RUN, t)
                                     for k in range(cfg.seeds)],
                       "scratch": [_curve(graph.folder(out, policy_name(rep, t, k)) / RUN, t)
                                   for k in range(cfg.seeds)]},
        } for rep in REPS}}

    try:
        bnn = read_report(graph.folder(out, "bnn/report"))
    except FileNotFoundError:
        raise ConfigError(f"{graph.folder(out, 'bnn/report')}: the BNN study's report.json is missing") from None
    res["bnn"] = {"report": bnn, "policy_run": f"d{cfg.policy_bnn}",
                  "figures": str((graph.folder(out, "bnn/report") / "figures").relative_to(out))}

    if exp.leave_one_out:
        loo: dict[str, Any] = {}
        latent = bnn["runs"].get(f"d{cfg.policy_bnn}", {})
        spaces = {"raw": (bnn.get("raw_scenarios"), bnn.get("raw_distance")),
                  "latent": (latent.get("latent_scenarios"), latent.get("latent_distance"))}
        for rep in REPS:
            rows = {s: {"zero_shot": st.kind(rep, f"without-{s}", [s])[s]["failure"],
                        "oracle": st.kind(rep, s, [s])[s]["failure"]} for s in scen}
            for space, (names, m) in spaces.items():
                if names and m and all(s in names for s in scen):
                    for s in scen:
                        rows[s][f"distance_{space}"] = _distance_to_rest(names, m, s)
            corr = {}
            for space in spaces:
                xs = [rows[s].get(f"distance_{space}") for s in scen]
                if None not in xs and len(scen) >= 3:
                    rho, p = spearmanr(xs, [rows[s]["zero_shot"]["mean"] for s in scen])
                    corr[space] = {"spearman": None if np.isnan(rho) else float(rho), "p": None if np.isnan(p) else float(p),
                                   "points": len(scen)}
            loo[rep] = {"scenarios": rows, "distance_vs_zero_shot": corr}
        res["leave_one_out"] = loo

    if exp.ablations:
        variants = [*REPS, *ABLATIONS]
        res["ablations"] = {v: st.kind(v, MIXED, [MIXED])[MIXED] for v in variants}

    if exp.imitation:
        # Paired with raw on the same episodes: the gap between what Q-learning reached and
        # what copying the planner reached, from the same map and budget.
        res["imitation"] = {"policy": st.kind(IMITATION, MIXED),
                            "vs_raw": st.paired("raw", IMITATION, MIXED, MIXED)["failure"]}

    if exp.probe_episodes:
        res["probes"] = read_probe_results(graph.folder(out, "probes") / PROBES)

    if cfg.evaluate.cross_backend_episodes:
        cross: dict[str, Any] = {}
        for rep in REPS:
            fast = st.seeds(rep, MIXED, prefix="cross/fast/")
            slow = st.seeds(rep, MIXED, prefix="cross/highway/")
            per = []
            for f, h in zip(fast, slow, strict=True):
                per.append({"fast": _rates(_subset(f, MIXED)), "highway": _rates(_subset(h, MIXED)),
                            "paired": paired_test(_flags(_subset(f, MIXED), "failure"),
                                                  _flags(_subset(h, MIXED), "failure")).as_dict()})
            cross[rep] = per
        res["cross_backend"] = cross

    res["steps"] = {n: {"kind": r.kind, "wall_s": r.wall_s, "resumed_s": r.resumed_s, "peak_rss_mb": r.peak_rss_mb,
                        "source": r.source}
                    for n, r in records.items()}
    clean: dict[str, Any] = json_values(res)
    return clean
