"""The ``reproduce`` and ``report`` sub-commands."""

from __future__ import annotations

import argparse
from typing import Any

from latentdrive.config import parse_override_args

__all__ = ["add_reproduce_parsers"]


def _cmd_reproduce(args: argparse.Namespace) -> int:
    from latentdrive.experiments.reproduce import run_study
    from latentdrive.experiments.study import load_reproduce_config

    overrides = parse_override_args(args.overrides)
    if args.seeds is not None:
        overrides["seeds"] = args.seeds
    cfg = load_reproduce_config(args.preset, overrides)
    run_study(cfg, args.out, workers=args.workers, preset=args.preset, progress=not args.quiet)
    print(f"report: {args.out}/report.md")
    return 0


def _cmd_report(args: argparse.Namespace) -> int:
    from latentdrive.experiments.reproduce import rebuild_report

    rebuild_report(args.out)
    print(f"report: {args.out}/report.md")
    return 0


def add_reproduce_parsers(sub: Any) -> None:
    s = sub.add_parser("reproduce", help="the paper's study in one command: data, BNNs, policies, evaluations, report")
    s.add_argument("out", help="study folder (rerun the same command to resume; finished steps are skipped)")
    s.add_argument("--preset", default="quick", help="tiny (a minute), quick (default, about 30 min on 2 cores), "
                   "paper, or a .yaml file")
    s.add_argument("--seeds", type=int, default=None, help="training seeds per policy (default: the preset's)")
    s.add_argument("--workers", type=int, default=1, help="steps run at once, each in its own process (default 1); "
                   "results do not depend on it")
    s.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    s.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="study override, repeatable (--set policy.steps=20000 --set evaluate.episodes=100)")
    s.set_defaults(func=_cmd_reproduce)

    s = sub.add_parser("report", help="rebuild a study's results.json, report.md and figures from its finished steps")
    s.add_argument("out", help="the study folder")
    s.set_defaults(func=_cmd_report)
