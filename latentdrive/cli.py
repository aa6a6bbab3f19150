"""The ``latentdrive`` command line: one console script, one sub-command per job.

Errors caused by input (unknown scenario, bad config value, corrupt file) print one line
``latentdrive: error: ...`` and exit with status 2; nothing already written is removed.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from typing import NoReturn

from latentdrive.config import (
    ConfigError,
    LatentDriveError,
    nonnegative_int,
    parse_override_args,
    positive_int,
)
from latentdrive.data.cli import add_collect_parser
from latentdrive.errors import Terminated
from latentdrive.experiments.policy_cli import add_policy_parsers
from latentdrive.experiments.reproduce_cli import add_reproduce_parsers
from latentdrive.experiments.tune_cli import add_tune_parser
from latentdrive.fileio import atomic_write_text, output_problem

__all__ = ["main"]


def _cmd_scenarios(args: argparse.Namespace) -> int:
    from latentdrive.scenarios import SCENARIOS, get_spec
    from latentdrive.sim.reach import mission_routes

    names = args.specs or list(SCENARIOS)
    specs = [get_spec(n) for n in names]  # unknown names fail before any output
    # A spec file's name can be longer than the presets'; the column fits the longest.
    nw = max(13, *(len(s.name) + 1 for s in specs))
    print(f"{'scenario':<{nw}}{'layout':<13}{'AVs':>4}{'HVs':>5}{'duration s':>11}{'sim/policy Hz':>14}  "
          f"{'AV target speeds m/s':<22}{'farthest mission':>17}  mission")
    for s in specs:
        name = s.name
        goal = f"reach {'own destination' if s.av_spawn[0].destinations else '/'.join(s.goal.nodes)}"
        goal += f" (+{s.goal.longitudinal:g} m)"
        speeds = ", ".join(f"{v:g}" for v in s.av_target_speeds)
        far = max(mission_routes(s), key=lambda r: r.distance)
        reach = f"{far.distance:.0f} m, {far.share(s.duration):.0%}"
        print(f"{name:<{nw}}{s.layout:<13}{s.n_av:>4}{s.n_hv:>5}{s.duration:>11g}"
              f"{f'{s.simulation_frequency}/{s.policy_frequency}':>14}  {speeds:<22}{reach:>17}  {goal}")
    print("farthest mission: the longest route from a spawn region to mission completion, and the share "
          "of the duration it takes at the top target speed")
    if args.verbose:
        for s in specs:
            print(f"\n# {s.name}\n" + json.dumps(s.model_dump(mode="json"), indent=1))
    return 0


def _cmd_show(args: argparse.Namespace) -> int:
    import numpy as np

    from latentdrive.env import make_env
    from latentdrive.viz import save_show_figure

    _check_output("--out", args.out)
    overrides = parse_override_args(args.overrides)
    env = make_env(args.scenario, **overrides)
    if not 0 <= args.agent < env.spec_.n_av:
        raise LatentDriveError(f"--agent {args.agent} is out of range: the scenario has {env.spec_.n_av} AVs")
    rng = np.random.default_rng(args.seed)
    obs, info = env.reset(seed=args.seed)
    scenes, observations = [info["scene"]], [obs]
    for _ in range(args.steps - 1):
        action = np.ones(env.spec_.n_av, dtype=np.int64) if args.policy == "idle" else rng.integers(0, 5, env.spec_.n_av)
        obs, _, terminated, truncated, info = env.step(action)
        scenes.append(info["scene"])
        observations.append(obs)
        if terminated or truncated:
            break
    out = save_show_figure(args.out, scenes, observations, env.config.observation,
                           title=f"{env.spec_.name}: agent {args.agent}, seed {args.seed}, {args.policy} policy",
                           agent=args.agent)
    print(f"wrote {out} ({len(scenes)} steps)")
    return 0


def _say(line: str) -> None:
    """Progress goes to stderr, results to stdout."""
    print(line, file=sys.stderr)


def _check_output(flag: str, path: str) -> None:
    """Refuse an output file that cannot be written before the work, not after it."""
    problem = output_problem(path) if path else None
    if problem:
        raise LatentDriveError(f"{flag} {path}: cannot write a file there ({problem})")


def _write_json(path: str, rows: object) -> None:
    atomic_write_text(path, json.dumps(rows, indent=1) + "\n")


def _cmd_bench(args: argparse.Namespace) -> int:
    from latentdrive.config import ObservationConfig, validate
    from latentdrive.scenarios import SCENARIOS, get_spec

    names = args.scenarios.split(",") if args.scenarios else list(SCENARIOS)
    for name in names:
        get_spec(name)  # unknown names fail before any work
    if args.steps < 1:
        raise LatentDriveError("--steps must be at least 1")
    if sum(map(bool, (args.train, args.plan, args.bottleneck))) > 1:
        raise LatentDriveError("--train, --plan and --bottleneck measure different things: give one")
    if args.processes > 1 and not args.train:
        raise LatentDriveError("--processes measures training runs sharing the machine: it needs --train")
    if args.batch_size < 1:
        raise LatentDriveError(f"--batch-size must be at least 1, got {args.batch_size}")
    _check_output("--json", args.json)
    if args.bottleneck:
        from latentdrive.bnn.bench import (
            bench_bottleneck,
            bench_precisions,
            format_bottleneck_bench,
        )
        from latentdrive.models.bottleneck import BottleneckConfig
        from latentdrive.runtime import resolve_device

        fields = parse_override_args(args.overrides)
        threads = int(fields.pop("threads", 1))
        precision = str(fields.pop("precision", "auto"))
        try:
            precisions = bench_precisions(precision, resolve_device("auto"))
        except ValueError as exc:
            raise LatentDriveError(str(exc)) from None
        model_cfg = validate(BottleneckConfig, fields, prefix="model.")
        if precision == "auto" and "bf16" not in precisions:
            _say("bf16 not measured: precision auto is fp32 here (CUDA, no AMX-BF16, or its kernels unsound), "
                 "where bf16 is slower or no faster "
                 "(--set precision=bf16 measures it anyway)")
        _say(f"benchmarking BNN training in {' and '.join(precisions)} ({args.steps} steps of {args.batch_size}) ...")
        brows = bench_bottleneck(model_cfg, batch_size=args.batch_size, steps=args.steps, threads=threads,
                                 precisions=precisions)
        print(format_bottleneck_bench(brows, model_cfg, threads))
        if args.json:
            _write_json(args.json, [r.as_dict() for r in brows])
        return 0
    if args.train:
        from latentdrive.rl.bench import bench_training, format_train_bench

        overrides = parse_override_args(args.overrides)
        modes = args.modes.split(",") if args.modes else ["raw", "latent", "end-to-end"]
        _say(f"benchmarking training in {len(modes)} mode(s) on {', '.join(names)} ...")
        if args.processes > 1:
            from latentdrive.rl.bench_shared import bench_training_shared, format_shared

            if args.repeat > 1:
                raise LatentDriveError("--processes and --repeat: give one (each process runs the measurement once)")
            trows, shared = bench_training_shared(args.processes, modes, names, transitions=args.steps,
                                                  envs=args.batch_size, bnn=args.bnn or None, overrides=overrides,
                                                  progress=_say)
        else:
            trows = bench_training(modes, names, transitions=args.steps, envs=args.batch_size, bnn=args.bnn or None,
                                   overrides=overrides, progress=_say, repeat=args.repeat)
            shared = []
        print(format_train_bench(trows, args.batch_size, int(overrides.get("threads", 1))))
        if shared:
            print(format_shared(shared))
        if args.json:
            alone = [r.as_dict() for r in trows]
            _write_json(args.json, {"alone": alone, "at_once": [r.as_dict() for r in shared]} if shared else alone)
        return 0
    if args.plan:
        from latentdrive.evaluate.plan_bench import bench_planner, format_plan_bench
        from latentdrive.evaluate.planner import planner_config_from_args

        pcfg = planner_config_from_args(args.overrides)
        _say(f"benchmarking the planner on {', '.join(names)} ...")
        prows = bench_planner(names, envs=args.batch_size, decisions=args.steps, cfg=pcfg, progress=_say)
        print(format_plan_bench(prows, pcfg))
        if args.json:
            _write_json(args.json, [r.as_dict() for r in prows])
        return 0
    cfg = validate(ObservationConfig, parse_override_args(args.overrides), prefix="observation.")
    _say(f"benchmarking {len(names)} scenario(s) on the {args.backend} backend ...")
    if args.backend == "fast":
        from latentdrive.bench import bench_fast
        from latentdrive.sim.validate import format_throughput

        rows = bench_fast(names, batch_size=args.batch_size, steps=args.steps, seed=args.seed, obs_cfg=cfg,
                          repeat=args.repeat, progress=_say)
        print(f"fast batch of {args.batch_size} vs highway-env, one core, each pair in one run; "
              f"maps no: the simulation alone; maps yes: the environments, a {cfg.height}x{cfg.width} "
              "VelocityMap stack for every acting AV every step, resets included")
        print(format_throughput(rows))
        dicts = [r.as_dict() for r in rows]
    else:
        from latentdrive.bench import format_table, run_bench

        hrows = run_bench(names, steps=args.steps, seed=args.seed, obs_cfg=cfg, progress=_say)
        print(format_table(hrows, cfg))
        dicts = [r.as_dict() for r in hrows]
    if args.json:
        _write_json(args.json, dicts)
    return 0


def _cmd_validate_backend(args: argparse.Namespace) -> int:
    from latentdrive.scenarios import SCENARIOS, get_spec
    from latentdrive.sim.validate import fidelity_table, format_fidelity

    names = args.scenarios.split(",") if args.scenarios else list(SCENARIOS)
    for name in names:
        get_spec(name)
    unknown = [p for p in args.policies.split(",") if p not in ("random", "idle")]
    if unknown:
        raise LatentDriveError(f"--policies: unknown {', '.join(map(repr, unknown))} (known: random, idle)")
    if args.episodes < 2:
        raise LatentDriveError("--episodes must be at least 2")
    _check_output("--json", args.json)
    rows = fidelity_table(names, episodes=args.episodes, policies=tuple(args.policies.split(",")), seed=args.seed,
                          progress=_say)
    print(f"{args.episodes} seeded episodes per scenario and policy on both backends, same seeds and actions; "
          "± is the half-width of the 95% interval")
    print(format_fidelity(rows))
    if args.json:
        _write_json(args.json, [r.as_dict() for r in rows])
    bad = [r for r in rows if not r.ok]
    if bad:
        print(f"latentdrive: {len(bad)} statistic(s) outside tolerance", file=sys.stderr)
        return 1
    return 0


def _cmd_train_bnn(args: argparse.Namespace) -> int:
    from latentdrive.bnn.train import BNNTrainConfig
    from latentdrive.config import validate
    from latentdrive.experiments.bnn import train_on_dataset

    overrides = parse_override_args(args.overrides)
    model = {k.removeprefix("model."): v for k, v in overrides.items() if k.startswith("model.")}
    overrides = {k.removeprefix("train."): v for k, v in overrides.items() if not k.startswith("model.")}
    own = {"latent_dim": "--latent-dim", "channels": "--channels", "input_shape": "the dataset's sample shape"}
    clash = sorted(set(model) & set(own))
    if clash:
        raise ConfigError(f"model.{clash[0]} is set by {own[clash[0]]}, not --set")
    # --val-fraction is checked by train_on_dataset, before anything is written.
    base: dict[str, object] = {"lambda_distance": args.lam, "seed": args.seed}
    if args.foreground_weight is not None:
        base["foreground_weight"] = args.foreground_weight
    if args.epochs is not None:
        if args.epochs < 1:
            raise ConfigError(f"--epochs must be at least 1, got {args.epochs}")
        if "mixed_epochs" in overrides:
            raise ConfigError("give --epochs or --set mixed_epochs=..., not both")
        base["pretrain_epochs"] = min(args.epochs, 10)
    cfg = validate(BNNTrainConfig, {**base, **overrides}, prefix="train.")
    if args.epochs is not None:
        # --epochs is the total; pretraining keeps its own (overridable) length within it.
        if cfg.pretrain_epochs > args.epochs:
            raise ConfigError(f"--epochs {args.epochs} is shorter than pretrain_epochs={cfg.pretrain_epochs}")
        cfg = cfg.replace(mixed_epochs=args.epochs - cfg.pretrain_epochs)
    metrics = train_on_dataset(args.dataset, args.run_dir, cfg, args.latent_dim, channels=tuple(args.channels),
                               val_fraction=args.val_fraction, resume=args.resume, progress=not args.quiet,
                               model=model)
    print(f"done: held-out loss {metrics.get('val_loss', float('nan')):.6f} "
          f"(vehicle cells {metrics.get('val_vehicle_l2', float('nan')):.4f}, "
          f"vehicle recall {metrics.get('val_vehicle_recall', float('nan')):.2f}, "
          f"precision {metrics.get('val_vehicle_precision', float('nan')):.2f}), "
          f"{metrics.get('samples_per_s', float('nan')):.0f} samples/s, peak RSS {metrics.get('peak_rss_mb', float('nan')):.0f} MB")
    return 0


def _cmd_bnn_study(args: argparse.Namespace) -> int:
    from latentdrive.experiments.bnn import load_study_config, run_bnn_study

    cfg = load_study_config(args.preset, parse_override_args(args.overrides))
    t0 = time.perf_counter()
    report = run_bnn_study(cfg, args.out, progress=not args.quiet, workers=args.workers)
    from latentdrive.experiments.bnn_report import format_report

    print(format_report(report))
    print(f"report: {args.out}/report.md, figures: {args.out}/figures/")
    print(f"wall time of this command: {(time.perf_counter() - t0) / 60:.1f} min "
          f"(steps finished by an earlier, interrupted run are not counted)")
    return 0


def _cmd_figures(args: argparse.Namespace) -> int:
    from latentdrive.experiments.bnn import figures_from_study

    for path in figures_from_study(args.dir):
        print(f"wrote {path}")
    return 0


def _add_set(parser: argparse.ArgumentParser, help: str) -> None:
    parser.add_argument("-s", "--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE", help=help)


class _Parser(argparse.ArgumentParser):
    """Usage errors on one line, like every other error (sub-command parsers inherit it)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"latentdrive: error: {LatentDriveError(message)} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="latentdrive", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("scenarios", help="list the scenarios and their settings")
    s.add_argument("specs", nargs="*", help="scenario names or spec .yaml files (default: the five presets)")
    s.add_argument("-v", "--verbose", action="store_true", help="print every spec in full")
    s.set_defaults(func=_cmd_scenarios)

    s = sub.add_parser("show", help="draw a scenario beside an agent's four VelocityMap channels")
    s.add_argument("scenario", help="scenario name or spec .yaml")
    s.add_argument("--out", required=True, help="PNG file to write")
    s.add_argument("--steps", type=positive_int, default=4, help="policy steps to show (default 4)")
    s.add_argument("--seed", type=nonnegative_int, default=0)
    s.add_argument("--policy", choices=["random", "idle"], default="random")
    s.add_argument("--agent", type=int, default=0, help="which AV's view to show")
    _add_set(s, "config override, repeatable (--set n_av=3 --set observation.frames=2)")
    s.set_defaults(func=_cmd_show)

    s = sub.add_parser("bench", help="throughput: highway-env vs our observation (default) or vs the fast backend")
    s.add_argument("--backend", choices=["highway", "fast"], default="highway",
                   help="highway: sim steps/s and VelocityMap vs OccupancyGrid cost; fast: fast vs highway-env steps/s")
    s.add_argument("--scenarios", default="", help="comma-separated names (default: all five)")
    s.add_argument("--steps", type=int, default=50, help="policy steps per scenario and backend (default 50)")
    s.add_argument("--batch-size", type=int, default=64, help="environments per fast batch (default 64)")
    s.add_argument("--seed", type=nonnegative_int, default=0)
    s.add_argument("--json", default="", help="also write the rows to this JSON file")
    s.add_argument("--train", action="store_true",
                   help="benchmark the training loop instead: updates/s, agent-transitions/s and where the time goes, per mode "
                        "(--steps: agent-transitions measured; --batch-size: envs; --set: train-policy overrides)")
    s.add_argument("--plan", action="store_true",
                   help="benchmark the lookahead planner instead: ms per decision vs one simulated step "
                        "(--steps: decisions; --batch-size: envs; --set planner.KEY=VALUE)")
    s.add_argument("--bottleneck", action="store_true",
                   help="benchmark BNN training instead: samples/s of the network's step and of the training loop, "
                        "in fp32 and bf16 (--steps: optimizer steps timed; --batch-size: samples per step; "
                        "--set: BNN architecture fields, threads=N and precision=auto|fp32|bf16; auto measures bf16 "
                        "only where it is native)")
    s.add_argument("--modes", default="", help="with --train: comma-separated modes (default raw,latent,end-to-end)")
    s.add_argument("--bnn", default="", help="with --train: a BNN run for mode latent (default: an untrained encoder, same cost)")
    s.add_argument("--repeat", type=positive_int, default=1,
                   help="with --train or --backend fast: run each measurement this many times and report the "
                   "median run and the range (a shared machine's speed varies from run to run)")
    s.add_argument("--processes", type=positive_int, default=1,
                   help="with --train: also run the measurement in this many processes at once, as that many "
                   "study workers would share this machine (and its GPU), and report each one's agent-transitions/s "
                   "against the measurement alone")
    _add_set(s, "observation override, repeatable (--set height=64 --set resolution=1.0); with --train, train-policy overrides")
    s.set_defaults(func=_cmd_bench)

    s = sub.add_parser("validate-backend", help="fidelity of the fast backend to highway-env: episode statistics of both")
    s.add_argument("--scenarios", default="", help="comma-separated names (default: all five)")
    s.add_argument("--episodes", type=int, default=200, help="seeded episodes per scenario and policy (default 200)")
    s.add_argument("--policies", default="random,idle", help="comma-separated: random, idle (default both)")
    s.add_argument("--seed", type=nonnegative_int, default=0)
    s.add_argument("--json", default="", help="also write the rows to this JSON file")
    s.set_defaults(func=_cmd_validate_backend)

    add_collect_parser(sub)

    s = sub.add_parser("train-bnn", help="train the bottleneck network on a collected dataset")
    s.add_argument("dataset", help="dataset directory made by `latentdrive collect`")
    s.add_argument("run_dir", help="where checkpoints, metrics.csv, tb/ and config.json go")
    s.add_argument("--latent-dim", type=int, default=64, help="latent size d per channel pair (default 64)")
    s.add_argument("--lambda", dest="lam", type=float, default=0.0, help="weight of the scenario-distance regularizer (default 0)")
    s.add_argument("--epochs", type=int, default=None, help="total epochs, pretraining included (10 of them, or --set pretrain_epochs=N); "
                   "default: the config's 10 + 90")
    s.add_argument("--foreground-weight", type=float, default=None,
                   help="loss weight of vehicle cells (default: the config's 20; the paper's plain L2 is "
                   "--foreground-weight 1 --set loss=l2 --set road_weight=1 --set av_weight=1)")
    s.add_argument("--channels", type=int, nargs="+", default=[16, 32], help="encoder channel widths (default 16 32)")
    s.add_argument("--val-fraction", type=float, default=0.15, help="share of episodes held out for validation, in (0, 1) (default 0.15)")
    s.add_argument("--seed", type=nonnegative_int, default=0)
    s.add_argument("--resume", action="store_true", help="continue the run in RUN_DIR")
    s.add_argument("-q", "--quiet", action="store_true")
    _add_set(s, "training override, repeatable (--set batch_size=32 --set lr=3e-4); "
                "model.KEY=VALUE sets an architecture field (--set model.latent_activation=tanh)")
    s.set_defaults(func=_cmd_train_bnn)

    s = sub.add_parser("bnn-study", help="dataset, BNNs of latent size 16/32/64 and λ>0, evaluation, figures")
    s.add_argument("out", help="study directory (rerun the same command to resume)")
    s.add_argument("--preset", default="small", help="tiny, small (default), paper, or a .yaml file")
    s.add_argument("--workers", type=positive_int, default=1,
                   help="BNNs trained at once, each in its own process (default 1)")
    s.add_argument("-q", "--quiet", action="store_true")
    _add_set(s, "study override, repeatable (--set collect.episodes=20 --set train.mixed_epochs=4)")
    s.set_defaults(func=_cmd_bnn_study)

    add_policy_parsers(sub)
    add_reproduce_parsers(sub)
    add_tune_parser(sub)

    s = sub.add_parser("figures", help="redraw the figures of a finished study")
    s.add_argument("kind", choices=["bnn"], help="which study")
    s.add_argument("dir", help="the study directory")
    s.set_defaults(func=_cmd_figures)
    return p


def _raise_terminated(signum: int, frame: object) -> None:
    raise Terminated()


@contextmanager
def _terminate_as_interrupt() -> Iterator[None]:
    """SIGTERM raises :class:`Terminated` for the command's duration (main thread only).

    Without it a terminate ends the process where it stands: the child processes of
    ``reproduce`` and ``tune`` would run on, orphaned, writing into the run folder.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


def main(argv: Sequence[str] | None = None) -> int:
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exc:  # --help, or a usage error already printed on one line
        return exc.code if isinstance(exc.code, int) else 2
    try:
        with _terminate_as_interrupt():
            return int(args.func(args))
    except LatentDriveError as exc:
        print(f"latentdrive: error: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # the reader went away (`latentdrive status OUT | head`): stop quietly
        try:  # stdout's unflushed rest would fail again as the interpreter exits
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        except (OSError, ValueError):  # no file descriptor behind it (captured)
            pass
        return 141  # as a shell reports a command ended by SIGPIPE
    except OSError as exc:  # a path in the way (a file where a folder goes), a full disk, no permission
        where = f": {exc.filename}" if exc.filename else ""
        print(f"latentdrive: error: {LatentDriveError(f'{exc.strerror or exc}{where}')}", file=sys.stderr)
        return 2
    except Terminated:
        print("latentdrive: terminated", file=sys.stderr)
        return 143
    except KeyboardInterrupt:
        print("latentdrive: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
