"""The ``reproduce``, ``estimate``, ``status`` and ``report`` sub-commands."""

from __future__ import annotations

import argparse
import shlex
from typing import Any

from latentdrive.config import LatentDriveError, parse_override_args, unit_fraction

__all__ = ["add_reproduce_parsers", "reproduce_command"]


def reproduce_command(args: argparse.Namespace) -> str:
    """The command as the report shows it: what a reader runs to get the same study
    (progress settings left out; the GPU share where it applies and is not the default)."""
    share = args.ray and args.gpu_fraction != 1.0
    return shlex.join(["latentdrive", "reproduce", str(args.out), "--preset", args.preset,
                       *(["--seeds", str(args.seeds)] if args.seeds is not None else []),
                       *[a for o in args.overrides for a in ("--set", o)], "--workers", str(args.workers),
                       *(["--ray", args.ray] if args.ray else []),
                       *(["--gpu-fraction", str(args.gpu_fraction)] if share else [])])


def _cmd_reproduce(args: argparse.Namespace) -> int:
    from latentdrive.experiments.reproduce import run_study
    from latentdrive.experiments.study import load_reproduce_config

    overrides = parse_override_args(args.overrides)
    if args.seeds is not None:
        overrides["seeds"] = args.seeds
    cfg = load_reproduce_config(args.preset, overrides)
    run_study(cfg, args.out, workers=args.workers, preset=args.preset, progress=not args.quiet, ray=args.ray,
              gpu_fraction=args.gpu_fraction, command=reproduce_command(args))
    print(f"report: {args.out}/report.md")
    return 0


def _cmd_report(args: argparse.Namespace) -> int:
    from latentdrive.experiments.reproduce import rebuild_report

    rebuild_report(args.out)
    print(f"report: {args.out}/report.md")
    return 0


def _cmd_estimate(args: argparse.Namespace) -> int:
    from latentdrive.experiments.reproduce import estimate_from
    from latentdrive.experiments.study import load_reproduce_config

    if any(w < 1 for w in args.workers):
        raise LatentDriveError("--workers must all be at least 1")
    cfg = load_reproduce_config(args.preset, parse_override_args(args.overrides))
    speedup = {}
    for item in args.speedup:
        # The factor follows the last '=': a class name may hold '=' (a BNN's model settings).
        name, sep, value = item.rpartition("=")
        try:
            speedup[name.strip()] = float(value)
        except ValueError:
            raise LatentDriveError(f"--speedup {item!r}: expected CLASS=FACTOR, e.g. bnn=20") from None
        if not sep:
            raise LatentDriveError(f"--speedup {item!r}: expected CLASS=FACTOR, e.g. bnn=20")
    estimates = estimate_from(args.measured, cfg, args.workers, speedup)
    first = estimates[0]
    faster = f", {', '.join(f'{k} {v:g}x faster' for k, v in speedup.items())}" if speedup else ""
    print(f"{args.preset}: {first.steps} steps, {first.step_hours:.1f} step-hours at the step times of "
          f"{args.measured}{faster}")
    width = max((len(c) for c in first.by_class), default=0) + 2
    for cls, hours in first.by_class.items():
        print(f"  {cls:<{width}}{hours:>9.2f} h")
    # Unmeasured steps count as 0, so the times are lower bounds then.
    least = "at least " if first.unmeasured else ""
    for e in estimates:
        print(f"wall time with {e.workers:>3} worker(s): {least}{e.wall_hours:.1f} h")
    if first.unmeasured:
        print("not measured there (counted as 0): " + ", ".join(first.unmeasured))
    return 0


def _cmd_status(args: argparse.Namespace) -> int:
    from latentdrive.experiments.study_status import format_status, study_status

    print(format_status(study_status(args.out, args.workers)))
    return 0


def add_reproduce_parsers(sub: Any) -> None:
    s = sub.add_parser("reproduce", help="the paper's study in one command: data, BNNs, policies, evaluations, report")
    s.add_argument("out", help="study folder (rerun the same command to resume; finished steps are skipped)")
    s.add_argument("--preset", default="quick", help="tiny (a minute), quick (default, about 17 min on 2 cores), "
                   "rates (quick's scale at the paper's costs per unit: measures what `estimate` scales), "
                   "standard (every experiment, 3 seeds, 100,000 agent-transitions per policy: hours on 2 cores, "
                   "see `estimate`), paper, or a .yaml file")
    s.add_argument("--seeds", type=int, default=None, help="training seeds per policy (default: the preset's)")
    s.add_argument("--workers", type=int, default=1, help="steps run at once, each in its own process (default 1; "
                   "with --ray local, the instance's CPUs); results do not depend on it")
    s.add_argument("--ray", metavar="ADDRESS", default=None,
                   help="run the steps as Ray tasks on the cluster at ADDRESS ('auto': the one this machine joined; "
                   "'local': a private instance); OUT must be on a filesystem every node sees")
    s.add_argument("--gpu-fraction", type=unit_fraction, default=1.0,
                   help="with --ray, the share of a GPU each training step asks for (default 1)")
    s.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    s.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="study override, repeatable (--set policy.steps=20000 --set evaluate.episodes=100)")
    s.set_defaults(func=_cmd_reproduce)

    s = sub.add_parser("estimate", help="a study's expected time from the step times a finished study measured")
    s.add_argument("measured", help="a study folder whose finished steps were timed (e.g. the quick study)")
    s.add_argument("--preset", default="paper", help="the study to estimate (default paper), or a .yaml file")
    s.add_argument("--workers", type=int, nargs="+", default=[1, 2, 16], help="worker counts to estimate (default 1 2 16)")
    s.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE", help="study override")
    s.add_argument("--speedup", action="append", default=[], metavar="CLASS=FACTOR",
                   help="the target runs this step class (bnn, policy:raw, ...; or a whole kind: policy) FACTOR times "
                   "faster than the measuring machine, e.g. the ratio of `bench --train` agent-transitions/s there "
                   "and here; repeatable (a kind's factor and one of its classes' multiply)")
    s.set_defaults(func=_cmd_estimate)

    s = sub.add_parser("status", help="where a study folder stands: steps finished and begun, hours recorded and left",
                       description="Read a study folder (while it runs, or between runs): its steps by class, finished "
                       "and begun, the hours their records hold, and the hours left at the study's own step times. "
                       "Changes nothing in the folder.")
    s.add_argument("out", help="the study folder")
    s.add_argument("--workers", type=int, default=None,
                   help="workers to estimate the wall time left for (default: the last logged run's, else 1)")
    s.set_defaults(func=_cmd_status)

    s = sub.add_parser("report", help="rebuild a study's results.json, report.md and figures from its finished steps")
    s.add_argument("out", help="the study folder")
    s.set_defaults(func=_cmd_report)
