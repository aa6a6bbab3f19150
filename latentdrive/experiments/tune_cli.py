"""The ``tune`` sub-command."""

from __future__ import annotations

import argparse
import shlex
import sys
from typing import Any

from latentdrive.config import ConfigError, parse_override_args, positive_int

__all__ = ["add_tune_parser"]


def _command(args: argparse.Namespace, steps: int) -> str:
    """The command that reproduces this search (the report quotes it)."""
    words = ["latentdrive", "tune", args.out, "--space", args.space, "--trials", str(args.trials), "--steps", str(steps),
             "--seeds", str(args.seeds), "--sampler-seed", str(args.sampler_seed)]
    if args.no_prune:
        words.append("--no-prune")
    for item in args.overrides:
        words += ["--set", item]
    return " ".join(shlex.quote(w) for w in words)


def _cmd_tune(args: argparse.Namespace) -> int:
    from pathlib import Path

    from latentdrive.experiments.tune import STUDY_DB, Search, open_study, run_search
    from latentdrive.experiments.tune_report import write_report
    from latentdrive.experiments.tune_space import base_config, check_space, load_space

    space = load_space(args.space)
    base = base_config(space, args.steps, parse_override_args(args.overrides))
    check_space(space, base)
    search = Search(out=Path(args.out), space=space, base=base, seeds=args.seeds, trials=args.trials,
                    storage=args.storage or None, sampler_seed=args.sampler_seed, prune=not args.no_prune)
    command = _command(args, base.steps)
    if args.report_only:
        # A look at a search as it stands (running elsewhere, or stopped): no trial runs,
        # no lock is taken, and a folder without a search gets no study.db.
        if search.storage is None and not (search.out / STUDY_DB).is_file():
            raise ConfigError(f"{search.out / STUDY_DB}: no search here to report on")
        study = open_study(search, create=False)
    else:
        study = run_search(search, workers=args.workers, progress=not args.quiet,
                           say=lambda line: print(line, file=sys.stderr))
    for path in write_report(search, study, command):
        print(f"wrote {path}")
    return 0


def add_tune_parser(sub: Any) -> None:
    s = sub.add_parser("tune", help="hyperparameter search of train-policy settings (Optuna, TPE, pruned on validation episodes)",
                       description="Search train-policy settings: each trial trains --seeds policies and is scored by "
                       "their mean mixed failure rate on validation episodes (never evaluation ones). The study lives in "
                       "OUT/study.db (or --storage); rerun the command to resume a killed search. Writes OUT/tune.md, "
                       "OUT/best.yaml (for train-policy --config) and OUT/figures/.")
    s.add_argument("out", help="search folder: study.db, trials/<n>/seed-<k>/ runs, tune.md, best.yaml, figures/")
    s.add_argument("--space", default="raw", help="search space: a preset (raw, the default; raw-short, 25,000 agent-transitions per run) or a .yaml file")
    s.add_argument("--trials", type=positive_int, default=30, help="trials in the study when done (default 30)")
    s.add_argument("--steps", type=positive_int, default=None, help="agent-transitions per training run (default: the space's base)")
    s.add_argument("--seeds", type=positive_int, default=2, help="training seeds per trial, 0..N-1; the objective is their mean (default 2)")
    s.add_argument("--workers", type=positive_int, default=1, help="trials run at once, each in its own process (default 1)")
    s.add_argument("--storage", default="", metavar="URL",
                   help="a database URL that several machines share (e.g. postgresql://host/db) instead of OUT/study.db")
    s.add_argument("--sampler-seed", type=int, default=0, help="seed of the TPE sampler (default 0)")
    s.add_argument("--no-prune", action="store_true", help="run every trial to the end (no median pruning)")
    s.add_argument("--report-only", action="store_true",
                   help="write tune.md, best.yaml and figures from the trials so far and run none (the other "
                   "flags must name the same search)")
    s.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    s.add_argument("-s", "--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="base train-policy setting, repeatable (--set envs=8 --set eval_episodes=20)")
    s.set_defaults(func=_cmd_tune)
