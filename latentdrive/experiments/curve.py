"""Learning curves: held-out failure rate against agent-transitions and against wall-clock minutes.

A policy run logs a held-out evaluation every ``eval_every`` segments (``eval.csv``) and
its elapsed training time at each segment's end (``metrics.csv``). :func:`read_curve`
joins the two; :func:`write_curves` draws runs grouped by label (one line per training
seed, their mean over the evaluations all seeds reached) beside reference policies
scored on the very episodes the runs' evaluations play (:func:`reference_rates`).

Reading a curve: each point is one evaluation of ``eval_episodes`` episodes per scenario
(at 40 per scenario on the five-scenario mix, 200 episodes: a 95% interval of about ±7
points on a rate near one half), so seeds and neighbouring points differ by chance as much
as by learning; several training seeds tell a trend from noise. The minutes are the
training time logged when the point's segment ended: the earlier evaluations are in it,
that point's own evaluation and the run's set-up are not, and a resumed run's sessions
add up. They show what a setting costs on the machine the run was trained on; compare two
settings on them only when both ran on the same machine under the same load.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from numpy.typing import NDArray

from latentdrive.config import ConfigError, validate
from latentdrive.evaluate.planner import PlannerConfig
from latentdrive.evaluate.policies import SIMULATOR_POLICIES, reference_policy
from latentdrive.evaluate.report import MIXED, policy_report
from latentdrive.evaluate.stats import RateCI
from latentdrive.rl.config import PolicyTrainConfig
from latentdrive.rl.policy import read_run_config
from latentdrive.rl.runfolder import EVALS, METRICS, read_logs
from latentdrive.rl.train import periodic_evaluation
from latentdrive.viz import save_png

__all__ = ["Curve", "common_evaluation", "curve_table", "default_label", "group_curves", "read_curve", "reference_rates",
           "write_curves"]


class Curve(NamedTuple):
    """One run's periodic evaluations, in order."""

    label: str
    run: Path
    config: PolicyTrainConfig
    transitions: NDArray[np.int64]  #: ``(K,)`` agent-transitions at each evaluation
    minutes: NDArray[np.float64]  #: ``(K,)`` wall-clock training minutes then (evaluations included)
    failure: NDArray[np.float64]  #: ``(K,)`` failure rate on the evaluation's episodes
    episodes: int  #: episodes per evaluation


def default_label(cfg: PolicyTrainConfig) -> str:
    """``raw``, ``latent``, …; ``raw, imitating plan`` for a DAgger run."""
    return f"{cfg.mode}, imitating {cfg.imitation.expert}" if cfg.learner == "dagger" else cfg.mode


def read_curve(run: str | Path, label: str | None = None, scenario: str = MIXED) -> Curve:
    """A run's learning curve on ``scenario`` (a training scenario's name, or ``mixed``)."""
    root = Path(run)
    cfg = validate(PolicyTrainConfig, read_run_config(root)["train"])
    logs = read_logs(root)
    rows = [r for r in logs[EVALS] if r.get("scenario") == scenario]
    if not rows:
        known = sorted({r.get("scenario", "") for r in logs[EVALS]})
        if known:
            raise ConfigError(f"{root}: no evaluation of {scenario!r} in {EVALS} (it has {', '.join(known)})")
        raise ConfigError(f"{root}: no periodic evaluations in {EVALS} (train with --set eval_every=1)")
    elapsed = {int(r["transitions"]): _number(root / METRICS, r, "elapsed_s") for r in logs[METRICS]}
    transitions = np.array([int(r["transitions"]) for r in rows], dtype=np.int64)
    missing = [t for t in transitions.tolist() if t not in elapsed]
    if missing:
        raise ConfigError(f"{root}: {METRICS} has no row at {missing[0]} agent-transitions, where {EVALS} has one")
    episodes = {int(_number(root / EVALS, r, "episodes")) for r in rows}
    if len(episodes) > 1:
        raise ConfigError(f"{root / EVALS}: its evaluations of {scenario} differ in episodes ({sorted(episodes)})")
    return Curve(label or default_label(cfg), root, cfg, transitions,
                 np.array([elapsed[t] / 60.0 for t in transitions.tolist()]),
                 np.array([_number(root / EVALS, r, "failure_rate") for r in rows]), episodes.pop())


def _number(path: Path, row: dict[str, str], column: str) -> float:
    """``row[column]`` as a number; a missing or malformed value is an error naming the file."""
    try:
        return float(row[column])
    except (KeyError, TypeError, ValueError):
        raise ConfigError(f"{path}: no number in column {column!r} at {row.get('transitions')} "
                          "agent-transitions (a damaged log)") from None


#: Settings in which the seeds of one label may differ.
_PER_SEED = ("seed", "steps", "device", "threads", "init_from")


def group_curves(curves: Sequence[Curve]) -> dict[str, list[Curve]]:
    """Curves by label, in the order the labels first appear; the runs of one label must be
    seeds of one setting (their configs equal but for the seed, the budget and where they ran)."""
    groups: dict[str, list[Curve]] = {}
    for c in curves:
        group = groups.setdefault(c.label, [])
        if group:
            mine, first = c.config.model_dump(mode="json"), group[0].config.model_dump(mode="json")
            differ = sorted(k for k in mine if k not in _PER_SEED and mine[k] != first[k])
            if differ:
                raise ConfigError(f"{c.run} and {group[0].run} share the label {c.label!r} but differ in "
                                  f"{', '.join(differ)}: a label groups the seeds of one setting; give each "
                                  "setting its own (LABEL=RUN)")
            if c.run in (g.run for g in group):
                raise ConfigError(f"{c.run} is given twice under the label {c.label!r}")
        group.append(c)
    return groups


def _evaluation_set(cfg: PolicyTrainConfig) -> dict[str, Any]:
    """What decides the episodes of a run's periodic evaluations (see :func:`periodic_evaluation`)."""
    data = cfg.model_dump(mode="json")
    keys = ("scenarios", "eval_episodes", "eval_seeds", "backend", "observation", "reward")
    return {"specs": [data["specs"].get(n) for n in cfg.scenarios], **{k: data[k] for k in keys}}


def common_evaluation(curves: Sequence[Curve]) -> PolicyTrainConfig:
    """The config whose evaluation episodes every curve shares; an error names a run that differs."""
    first = curves[0]
    for c in curves[1:]:
        if _evaluation_set(c.config) != _evaluation_set(first.config):
            raise ConfigError(f"{c.run} and {first.run} were evaluated on different episodes (scenarios, specs, "
                              "eval_episodes, eval_seeds, backend, observation or reward differ): references "
                              "cannot be scored for both; draw them separately")
    return first.config


def reference_rates(cfg: PolicyTrainConfig, names: Sequence[str], scenario: str = MIXED,
                    planner: PlannerConfig | None = None) -> dict[str, RateCI]:
    """Failure rates of reference policies on the episodes of ``cfg``'s periodic evaluations."""
    out: dict[str, RateCI] = {}
    for name in dict.fromkeys(names):
        if name in SIMULATOR_POLICIES and cfg.backend != "fast":
            raise ConfigError(f"reference {name!r} needs the fast backend; the runs were evaluated on {cfg.backend!r}")
        report = policy_report(periodic_evaluation(cfg, reference_policy(name, planner=planner, reward=cfg.reward)))
        summary = report.mixed if scenario == MIXED else report.scenarios[scenario]
        out[name] = summary.failure_rate
    return out


def _mean(group: Sequence[Curve]) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Mean transitions, minutes and failure over the seeds, at the evaluations all of them reached."""
    k = min(len(c.failure) for c in group)
    return (np.mean([c.transitions[:k] for c in group], axis=0), np.mean([c.minutes[:k] for c in group], axis=0),
            np.mean([c.failure[:k] for c in group], axis=0))


def curve_table(groups: Mapping[str, Sequence[Curve]], references: dict[str, RateCI]) -> str:
    """The numbers the figure draws, one line per label (of :func:`group_curves`) and evaluation."""
    w = max(len(name) for name in ["label", *groups, *references]) + 2
    lines = [f"{'label':<{w}}{'seeds':>6}{'eval':>6}{'agent-transitions':>19}{'minutes':>9}{'failure %':>11}  per seed"]
    for label, group in groups.items():
        tr, mins, fail = _mean(group)
        for i in range(len(fail)):
            seeds = " ".join(f"{100 * c.failure[i]:.1f}" for c in group)
            lines.append(f"{label:<{w}}{len(group):>6}{i + 1:>6}{tr[i]:>19,.0f}{mins[i]:>9.1f}{100 * fail[i]:>11.1f}  {seeds}")
    for name, r in references.items():
        lines.append(f"{name:<{w}}{'':>6}{'':>6}{'':>19}{'':>9}{100 * r.rate:>11.1f}  "
                     f"[{100 * r.lo:.1f}, {100 * r.hi:.1f}] (95% Wilson, {r.n} episodes)")
    return "\n".join(lines)


def write_curves(path: str | Path, groups: Mapping[str, Sequence[Curve]], references: dict[str, RateCI],
                 title: str = "") -> Path:
    """Failure rate against agent-transitions (left) and wall-clock minutes (right): thin lines
    per seed, a thick line for their mean, dashed lines with their 95% band for references."""
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), sharey=True)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, (label, group) in enumerate(groups.items()):
        colour = colours[i % len(colours)]
        tr, mins, fail = _mean(group)
        for ax, xs, mean_x in ((axes[0], [c.transitions for c in group], tr), (axes[1], [c.minutes for c in group], mins)):
            for c, x in zip(group, xs, strict=True):
                ax.plot(x, 100 * c.failure, color=colour, lw=0.8, alpha=0.45)
            ax.plot(mean_x, 100 * fail, color=colour, lw=2.2, marker="o", ms=4,
                    label=f"{label} (mean of {len(group)} seed{'s' if len(group) > 1 else ''})")
    for j, (name, r) in enumerate(references.items()):
        colour = colours[(len(groups) + j) % len(colours)]
        for ax in axes:
            ax.axhline(100 * r.rate, color=colour, ls="--", lw=1.4, label=f"{name} {100 * r.rate:.1f}%")
            if not math.isnan(r.lo):
                ax.axhspan(100 * r.lo, 100 * r.hi, color=colour, alpha=0.08)
    axes[0].set_xlabel("agent-transitions")
    axes[1].set_xlabel("wall-clock training minutes (earlier evaluations included)")
    curves = [c for group in groups.values() for c in group]
    episodes = sorted({c.episodes for c in curves})
    per_point = f"{episodes[0]} episodes per point" if len(episodes) == 1 else "episodes per point vary"
    axes[0].set_ylabel(f"held-out failure rate, % ({per_point})")
    for ax in axes:
        ax.set_xlim(left=0)
        ax.set_ylim(0, 100)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8, loc="best")
    if title:
        fig.suptitle(title)
    return save_png(fig, path)
