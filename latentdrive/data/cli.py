"""``latentdrive collect``: the command that collects bottleneck-network datasets."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from latentdrive.config import load_yaml, merge_overrides, nonnegative_int, parse_override_args

__all__ = ["add_collect_parser"]


def _cmd_collect(args: argparse.Namespace) -> int:
    from latentdrive.config import validate
    from latentdrive.data.collect import CollectConfig, collect, dataset_specs
    from latentdrive.data.shards import read_manifest

    # The scenario specs a dataset already in OUT_DIR stored stand for their names, so it
    # resumes wherever it lies, without the spec files it was collected from.
    stored = dataset_specs(args.out_dir)
    flags = {
        "episodes": args.episodes, "workers": args.workers, "seed": args.seed,
        "behaviour": args.behaviour, "rule_fraction": args.rule_fraction,
        "shard_size": args.shard_size, "sample_every": args.sample_every,
    }
    given = args.config or args.scenarios or args.overrides or any(v is not None for v in flags.values())
    data: dict[str, Any] = load_yaml(args.config) if args.config else {}
    if stored and not given:  # OUT_DIR alone: continue the dataset there with its own settings
        data = {k: v for k, v in read_manifest(Path(args.out_dir))["config"].items() if k != "workers"}
    data.update({k: v for k, v in flags.items() if v is not None})
    if args.scenarios:
        data["scenarios"] = [s.strip() for s in args.scenarios.split(",") if s.strip()]
    if args.overrides:
        data["env"] = merge_overrides(data.get("env") or {}, parse_override_args(args.overrides))
    cfg = validate(CollectConfig, data, context={"specs": stored})
    summary = collect(cfg, args.out_dir, progress=not args.quiet)
    print(f"{summary.root}: {summary.samples_total} samples in {summary.shards_total} shards "
          f"({summary.shards_written} collected now, {summary.shards_skipped} already there; "
          f"{summary.samples_per_s:.0f} samples/s)")
    return 0


def add_collect_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Register ``collect`` on the ``latentdrive`` sub-command parsers; returns its parser."""
    s: argparse.ArgumentParser = subparsers.add_parser(
        "collect", help="collect (noisy, clean) VelocityMap datasets for the bottleneck network",
        description="Roll out episodes with a behaviour policy and write sharded (noisy, clean) "
        "observation pairs to OUT_DIR. Rerunning the same command resumes an interrupted run "
        "(`collect OUT_DIR` alone does too, with the settings and scenario specs the dataset "
        "stored, from any directory); a different config in the same directory is refused.")
    s.add_argument("out_dir", metavar="OUT_DIR", help="dataset directory (created if needed)")
    s.add_argument("--config", default="", help="YAML file of collect settings; flags override it")
    s.add_argument("--scenarios", default="", help="comma-separated names (default: all five)")
    s.add_argument("--episodes", type=int, default=None, help="episodes per scenario (default 200)")
    s.add_argument("--workers", type=int, default=None, help="worker processes (default 1)")
    s.add_argument("--seed", type=nonnegative_int, default=None, help="root seed (default 0)")
    s.add_argument("--behaviour", choices=["mixed", "random", "rule"], default=None,
                   help="behaviour policy (default mixed)")
    s.add_argument("--rule-fraction", type=float, default=None,
                   help="share of rule-driven episodes under 'mixed' (default 0.5)")
    s.add_argument("--shard-size", type=int, default=None, help="target samples per shard (default 512)")
    s.add_argument("--sample-every", type=int, default=None, help="record every k-th policy step (default 1)")
    s.add_argument("-s", "--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="env override for every scenario, repeatable "
                   "(--set observation.frames=2 --set duration=10)")
    s.add_argument("-q", "--quiet", action="store_true", help="no per-shard progress lines")
    s.set_defaults(func=_cmd_collect)
    return s
