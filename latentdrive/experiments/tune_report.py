"""What a search leaves in OUT: ``tune.md``, ``best.yaml`` and optuna's plots (``figures/``)."""

from __future__ import annotations

import warnings
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml

from latentdrive.config import merge_overrides, validate
from latentdrive.errors import first_line
from latentdrive.experiments.tune import Search, counted_trials
from latentdrive.fileio import atomic_write_text
from latentdrive.rl.config import PolicyTrainConfig

if TYPE_CHECKING:
    import optuna

__all__ = ["BEST", "FIGURES", "REPORT", "best_config", "importances", "write_report"]

REPORT = "tune.md"
BEST = "best.yaml"
FIGURES = "figures"
#: Fewest completed trials the importances are computed from (fANOVA fits a forest to them).
MIN_IMPORTANCE_TRIALS = 3


def best_config(search: Search, trial: optuna.trial.FrozenTrial) -> dict[str, Any]:
    """The train-policy config of ``trial``: the base with its settings, without the seed (give
    ``--seed``) and with the default periodic evaluation (a tuned run is scored on evaluation
    episodes afterwards, not validation ones)."""
    cfg = validate(PolicyTrainConfig, merge_overrides(search.base.model_dump(), dict(trial.params)))
    data = cfg.model_dump(mode="json")
    for key in ("seed", "eval_seeds"):
        data.pop(key)
    return data


def importances(study: optuna.Study) -> tuple[dict[str, float], str]:
    """The parameter importances (fANOVA) and a note; empty with the reason when there are
    too few completed trials or they do not vary."""
    import optuna

    done = [t for t in study.get_trials(deepcopy=False) if t.state == optuna.trial.TrialState.COMPLETE]
    if len(done) < MIN_IMPORTANCE_TRIALS:
        return {}, f"needs at least {MIN_IMPORTANCE_TRIALS} completed trials (have {len(done)})"
    if len({t.value for t in done}) < 2:
        return {}, "every completed trial scored the same; nothing to attribute"
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return dict(optuna.importance.get_param_importances(study)), ""
    except (RuntimeError, ValueError, ZeroDivisionError) as exc:
        return {}, f"not computed ({first_line(exc)})"


def _plots(study: optuna.Study, folder: Path, with_importance: bool) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import optuna.visualization.matplotlib as ovm

    from latentdrive.viz import save_png

    makers: dict[str, Callable[[optuna.Study], Any]] = {"history": ovm.plot_optimization_history, "intermediate": ovm.plot_intermediate_values,
              "slice": ovm.plot_slice, "parallel": ovm.plot_parallel_coordinate}
    if with_importance:
        makers["importance"] = ovm.plot_param_importances
    written = []
    for name, make in makers.items():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                ax = make(study)
            except (RuntimeError, ValueError) as exc:  # a plot that needs more trials
                plt.close("all")
                warnings.warn(f"{name} plot not drawn: {first_line(exc)}", stacklevel=2)
                continue
            first = ax.flat[0] if hasattr(ax, "flat") else ax
            # The parallel-coordinate plot's colour bar trips tight_layout's warning, harmlessly.
            written.append(save_png(first.figure, folder / f"{name}.png"))
    return written


def _fmt(value: Any) -> str:
    return f"{value:.3g}" if isinstance(value, float) else str(value)


def write_report(search: Search, study: optuna.Study, command: str) -> list[Path]:
    """Write ``tune.md``, ``best.yaml`` (when a trial completed) and the plots; returns them."""
    import optuna

    out = search.out
    trials = study.get_trials(deepcopy=False)
    keys = list(search.space.space)
    base = search.base
    lines = [
        "# Hyperparameter search", "",
        f"Written by `{command}`.", "",
        f"Objective: the mean, over training seeds 0..{search.seeds - 1}, of the mixed failure rate "
        f"(crashed or mission not completed) on {base.eval_episodes} validation episodes per scenario "
        f"({', '.join(base.scenarios)}) after {base.steps} agent-transitions in {base.mode} mode. Validation "
        "episodes come from a seed range of their own (`latentdrive.seeds.VALIDATION_RESET_SEEDS`), disjoint "
        "from training and from every evaluation set: these numbers are not test numbers.", "",
        f"Trials: {counted_trials(trials)} of {search.trials}; sampler TPE (seed {search.sampler_seed}); "
        f"pruner {'median' if search.prune else 'none'}.", "",
        "## Trials", "",
        "| trial | state | failure rate | per seed | " + " | ".join(f"`{k}`" for k in keys) + " | minutes |",
        "|" + "---|" * (5 + len(keys)),
    ]
    for t in trials:
        seeds = ", ".join(f"{r:.3f}" for r in t.user_attrs.get("seed_failure_rates", []))
        value = f"{t.value:.3f}" if t.value is not None else ""
        state = t.state.name.lower()
        if "error" in t.user_attrs:
            state += f" ({t.user_attrs['error']})"
        elif t.system_attrs.get("failed_trial") is not None:
            state += f" (retry of {t.system_attrs['failed_trial']})"
        params = " | ".join(_fmt(t.params[k]) if k in t.params else "" for k in keys)
        lines.append(f"| {t.number} | {state} | {value} | {seeds} | {params} | {t.user_attrs.get('minutes', '')} |")
    done = [t for t in trials if t.state == optuna.trial.TrialState.COMPLETE]
    written: list[Path] = []
    lines += ["", "## Best settings", ""]
    if done:
        best = min(done, key=lambda t: float(t.value))  # type: ignore[arg-type]
        path = out / BEST
        cfg = best_config(search, best)
        header = (f"# Best of a search (`{command}`): trial {best.number}, mean validation failure rate "
                  f"{best.value:.3f}.\n# Train with: latentdrive train-policy RUN --config {BEST} --seed N\n")
        written.append(atomic_write_text(path, header + yaml.safe_dump(cfg, sort_keys=False)))
        lines += [f"Trial {best.number}: mean validation failure rate {best.value:.3f}. "
                  f"`{BEST}` holds its full train-policy config (`latentdrive train-policy RUN --config {out / BEST}`).", "",
                  "```yaml", yaml.safe_dump(dict(best.params), sort_keys=False).rstrip(), "```"]
    else:
        lines.append("No trial has completed yet; there is no best.yaml.")
    imp, note = importances(study)
    lines += ["", "## Parameter importances", ""]
    if imp:
        lines += ["fANOVA over the completed trials (shares of the objective's variance, summing to 1):", "",
                  "| setting | importance |", "|---|---|"]
        lines += [f"| `{k}` | {v:.3f} |" for k, v in imp.items()]
    else:
        lines.append(f"Not computed: {note}.")
    figures = _plots(study, out / FIGURES, bool(imp)) if done else []
    if figures:
        lines += ["", "## Figures", ""] + [f"![{p.stem}]({FIGURES}/{p.name})" for p in figures]
    written += figures
    written.insert(0, atomic_write_text(out / REPORT, "\n".join(lines) + "\n"))
    return written
