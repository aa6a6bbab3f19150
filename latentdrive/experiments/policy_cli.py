"""``latentdrive train-policy``, ``latentdrive evaluate``, ``latentdrive aggregate``, ``latentdrive compare`` and
``latentdrive curve``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from latentdrive.config import (
    ConfigError,
    load_yaml,
    merge_overrides,
    nonnegative_int,
    parse_override_args,
)
from latentdrive.fileio import output_problem

__all__ = ["add_policy_parsers"]


def _say(line: str) -> None:
    print(line, file=sys.stderr)


def _split(text: str) -> list[str]:
    return [s.strip() for s in text.split(",") if s.strip()]


def _cmd_train_policy(args: argparse.Namespace) -> int:
    from latentdrive.config import validate
    from latentdrive.rl.config import PolicyTrainConfig
    from latentdrive.rl.policy import read_run_config
    from latentdrive.rl.train import train_policy

    base: dict[str, Any] = read_run_config(args.run)["train"] if args.resume else {}
    if args.config:
        # A config file (tune's best.yaml), under the flags and --set.
        base = merge_overrides(base, load_yaml(args.config))
    flags = {"mode": args.mode, "learner": args.learner, "bnn": args.bnn, "steps": args.steps, "seed": args.seed, "envs": args.envs,
             "backend": args.backend, "init_from": args.init_from}
    data = merge_overrides(base, {k: v for k, v in flags.items() if v is not None})
    if args.scenarios:
        data["scenarios"] = _split(args.scenarios)
        # A resumed run's stored specs stand for the names it keeps.
        data["specs"] = {k: v for k, v in (data.get("specs") or {}).items() if k in data["scenarios"]}
    data = merge_overrides(data, parse_override_args(args.overrides))
    try:
        cfg = validate(PolicyTrainConfig, data)
    except ConfigError as exc:
        if not args.config:
            raise
        raise ConfigError(f"{exc} (settings from {args.config}, the flags and --set)") from None
    result = train_policy(cfg, args.run, resume=args.resume, progress=not args.quiet, say=_say)
    ev = result.get("evaluation") or {}
    mixed = ev.get("mixed")
    line = f"done: {result['transitions']} agent-transitions, {result['updates']} updates, {result['episodes']} episodes"
    if mixed:
        line += (f"; held-out failure rate {mixed['failure_rate']['rate']:.3f}, crash rate "
                 f"{mixed['crash_rate']['rate']:.3f} over {mixed['episodes']} episodes")
    kept = result.get("kept")
    if kept:
        line += (f"; kept the weights of {kept['transitions']} agent-transitions (held-out failure rate "
                 f"{kept['failure_rate']:.3f})")
    print(line)
    return 0


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from latentdrive.config import validate
    from latentdrive.evaluate.planner import planner_config_from_args
    from latentdrive.evaluate.policies import (
        REFERENCE_POLICIES,
        SIMULATOR_POLICIES,
        check_references,
    )
    from latentdrive.evaluate.report import format_compare, format_table
    from latentdrive.evaluate.run import quotas
    from latentdrive.experiments.policy import (
        EvaluationSet,
        evaluate_many,
        policy_makers,
        save_policies_gif,
        save_policy_gif,
        write_json,
    )
    from latentdrive.rl.policy import (
        changed_scenarios,
        greedy_policy,
        load_policy_network,
        read_run_config,
    )
    from latentdrive.runtime import resolve_device
    from latentdrive.scenarios import SCENARIOS, ScenarioSpec
    from latentdrive.seeds import MAX_ENVS, eval_reset_seed

    # A run's name in the tables, the JSON and the GIF's panels: its LABEL, or its path.
    names: dict[str, str] = {}

    def name_run(arg: str) -> str:
        label, run = _labelled(arg)
        if label in REFERENCE_POLICIES:
            raise ConfigError(f"{arg}: {label!r} is a reference policy's name; label the run otherwise")
        same = [r for r in names if Path(r).resolve() == Path(run).resolve()]
        if same:  # the run compared with itself: one policy, one name
            if label not in (None, names[same[0]]):
                raise ConfigError(f"{arg}: the RUN itself, under another label")
            return names[same[0]]
        names[run] = label or run
        return names[run]

    if args.run:
        name_run(args.run)
    if args.policy is None:  # every reference the backend can run
        references = [p for p in REFERENCE_POLICIES if args.backend == "fast" or p not in SIMULATOR_POLICIES]
    else:
        references = [] if args.policy in ("", "none") else _split(args.policy)
    if args.compare:
        if not names:
            raise ConfigError("--compare needs a RUN to compare with")
        # A run directory wins over a reference policy of the same name.
        if args.compare in REFERENCE_POLICIES and not (Path(args.compare) / "config.json").exists():
            if args.compare not in references:
                references.append(args.compare)
            compared = args.compare
        else:
            compared = name_run(args.compare)
    runs = list(names)

    def shown(run: str) -> str:
        return run if names[run] == run else f"{names[run]} ({run})"
    configs = [read_run_config(r) for r in runs]  # fail before any work
    for run, c in zip(runs, configs, strict=True):
        moved = changed_scenarios(c)
        if moved:
            _say(f"warning: {run} was trained on {', '.join(moved)} as specified then; the spec has changed "
                 "since, and the evaluation uses today's")
    check_references(references)
    if not runs and not references:
        raise ConfigError("nothing to evaluate: give a RUN or --policy")
    if args.scenarios:
        scenarios = _split(args.scenarios)
    elif configs:
        scenarios = list(configs[0]["train"]["scenarios"])
    else:
        scenarios = list(SCENARIOS)
    if args.episodes < 1:
        raise ConfigError(f"--episodes must be at least 1, got {args.episodes}")
    if not 1 <= args.envs <= MAX_ENVS:
        raise ConfigError(f"--envs must be in [1, {MAX_ENVS}], got {args.envs}")
    eval_reset_seed(args.seed_offset)  # a one-line error for an offset out of range
    if args.gif_episode and not args.gif:
        raise ConfigError("--gif-episode needs --gif")
    first_slot = quotas(args.episodes, min(args.envs, args.episodes))[0]
    if not 0 <= args.gif_episode < first_slot:
        # Episodes past those draw ones the evaluation never played.
        raise ConfigError(f"--gif-episode must be in [0, {first_slot}): the evaluation's first environment plays "
                          f"{first_slot} of its episodes (--episodes {args.episodes}, --envs {args.envs}), "
                          f"got {args.gif_episode}")
    if len(set(names.values())) < len(names):
        raise ConfigError(f"the RUN and --compare go by one name, {names[runs[-1]]!r}: label them apart")
    clash = sorted(set(names.values()) & set(references))
    if clash:
        raise ConfigError(f"{clash[0]!r} names both a run and a reference policy; give the run as ./{clash[0]} "
                          "or another LABEL")
    for flag, out in (("--json", args.json), ("--gif", args.gif)):
        problem = output_problem(out) if out else None
        if problem:
            raise ConfigError(f"{flag} {out}: cannot write a file there ({problem})")
    if len(set(scenarios)) != len(scenarios):
        raise ConfigError(f"--scenarios repeats a name: {', '.join(scenarios)}")
    observations = [c["train"]["observation"] for c in configs]
    rewards = [c["train"].get("reward") for c in configs]
    # A name the first run trained on stands for the spec it stored (it needs no spec file
    # and no preset of today); --scenarios may name others, resolved as usual.
    stored = {k: validate(ScenarioSpec, v) for k, v in configs[0]["train"]["specs"].items()} if configs else {}
    for run, c in zip(runs[1:], configs[1:], strict=True):
        other = [n for n in scenarios if n in stored and n in c["train"]["specs"]
                 and c["train"]["specs"][n] != stored[n].model_dump(mode="json")]
        if other:
            _say(f"warning: {shown(run)} was trained on another spec of {', '.join(other)} than {shown(runs[0])}; "
                 f"both are evaluated on {names[runs[0]]}'s")
    eval_set = EvaluationSet(scenarios, args.episodes, args.envs, args.backend, args.seed_offset,
                             observation=observations[0] if observations else None,
                             reward=rewards[0] if rewards and all(r == rewards[0] for r in rewards) else None,
                             planner=planner_config_from_args(args.overrides) if "plan" in references else None,
                             specs=stored,
                             observations={names[r]: o for r, o in zip(runs, observations, strict=True)
                                           if o != observations[0]})
    if eval_set.observations:
        _say(f"note: the runs observe different maps ({', '.join(shown(r) for r in runs if names[r] in eval_set.observations)} "
             f"not as {shown(runs[0])}); each plays the same episodes through its own, and the references see "
             f"{names[runs[0]]}'s")
    if args.overrides and "plan" not in references:
        raise ConfigError("--set planner.* given, but the planner ('plan') is not evaluated")
    device = resolve_device(args.device)
    total = args.episodes * len(scenarios) * (len(runs) + len(references))
    makers = policy_makers({name: run for run, name in names.items()}, references, eval_set, device)
    with tqdm(total=total, unit="ep", disable=args.quiet, desc="evaluate", dynamic_ncols=True) as bar:
        reports, outcomes = evaluate_many(makers, eval_set, progress=bar.update)
    print(f"{args.episodes} evaluation episodes per scenario ({eval_set.envs} envs, reset seed "
          f"{eval_set.as_dict()['reset_seed']}, {args.backend} backend); failure = crashed or mission not "
          "completed in time. [95% Wilson intervals]")
    print(format_table(reports))
    if args.causes:
        from latentdrive.evaluate.report import format_causes

        print("how the episodes ended (% of episodes; for a crash, where the other vehicle was, not whose fault it was)")
        print(format_causes(outcomes))
    comparison = None
    if args.compare:
        from latentdrive.evaluate.report import compare, tests_json

        a, b = names[runs[0]], compared
        tests = compare(outcomes[a], outcomes[b])  # once: its intervals are bootstrapped
        comparison = tests_json(tests)
        print(f"paired on the same episodes: A = {a}, B = {b}")
        print(format_compare(tests, names=("A", "B")))
    if args.json:
        head = names[runs[0]] if runs else references[0]
        doc: dict[str, Any] = {
            **reports[head].as_dict(), "policy": head,
            "config": {"evaluation": eval_set.as_dict(),
                       "runs": {names[r]: c["train"] for r, c in zip(runs, configs, strict=True)}},
            "policies": {name: rep.as_dict() for name, rep in reports.items()},
        }
        if any(name != r for r, name in names.items()):
            doc["config"]["paths"] = {name: r for r, name in names.items()}
        if args.causes:
            from latentdrive.evaluate.report import cause_counts

            doc["causes"] = {name: cause_counts(o) for name, o in outcomes.items()}
        if comparison is not None:
            doc["compare"] = {"a": names[runs[0]], "b": compared, "tests": comparison}
        from latentdrive.evaluate.episodes import outcome_block

        # Per-episode outcomes let `latentdrive compare` pair this file with another later.
        doc["outcomes"] = outcome_block(outcomes, eval_set.specs)
        print(f"wrote {write_json(args.json, doc)}")
    if args.gif:
        # Side by side where the policies were chosen (not the default references beside a run).
        if len(makers) > 1 and (args.policy is not None or args.compare):
            path = save_policies_gif(args.gif, makers, scenarios[0], eval_set, args.gif_episode)
        elif runs:
            net, _ = load_policy_network(runs[0], device)
            path = save_policy_gif(args.gif, net, greedy_policy(net, device), scenarios[0], eval_set,
                                   f"{names[runs[0]]} ({net.mode}) on {scenarios[0]}", device, args.gif_episode)
        else:
            path = save_policy_gif(args.gif, None, makers[references[0]], scenarios[0], eval_set,
                                   f"{references[0]} on {scenarios[0]}", device, args.gif_episode)
        print(f"wrote {path}")
    return 0


def _cmd_compare(args: argparse.Namespace) -> int:
    from latentdrive.evaluate.episodes import pair, read_evaluation
    from latentdrive.evaluate.report import format_compare, tests_json
    from latentdrive.experiments.policy import write_json

    _check_output(args.json, [args.a_file, args.b_file])
    a, b = read_evaluation(args.a_file), read_evaluation(args.b_file)
    na, nb, tests = pair(a, b, args.a or None, args.b or None)
    print(f"paired on the same episodes: A = {na} ({a.path}), B = {nb} ({b.path})")
    print(format_compare(tests, names=("A", "B")))
    if args.json:
        doc = {"a": {"file": a.path, "policy": na, "evaluation": a.evaluation},
               "b": {"file": b.path, "policy": nb, "evaluation": b.evaluation},
               "tests": tests_json(tests)}
        print(f"wrote {write_json(args.json, doc)}")
    return 0


def _labelled(arg: str) -> tuple[str | None, str]:
    """``LABEL=RUN`` or ``RUN`` (a folder that exists is a run, even with '=' in its name)."""
    if Path(arg).is_dir() or "=" not in arg:
        return None, arg
    label, run = arg.split("=", 1)
    if not label:
        raise ConfigError(f"{arg}: an empty label before '='")
    if not run or not Path(run).is_dir():
        raise ConfigError(f"{arg}: neither a run folder nor LABEL=RUN with one (no folder {run!r}); a LABEL "
                          "names a run, reference policies go by their own names")
    return label, run


def _check_output(out: str, inputs: list[str]) -> None:
    """Refuse a ``--json`` output that cannot be written or would overwrite an input."""
    if not out:
        return
    if problem := output_problem(out):
        raise ConfigError(f"--json {out}: {problem}")
    if any(Path(out).resolve() == Path(f).resolve() for f in inputs):
        raise ConfigError(f"--json {out}: is one of the files read; write the result elsewhere")


def _cmd_aggregate(args: argparse.Namespace) -> int:
    from latentdrive.evaluate.seeds import aggregate_seeds, format_seeds, read_seed_eval
    from latentdrive.experiments.policy import write_json

    _check_output(args.json, args.files)
    agg = aggregate_seeds([read_seed_eval(f) for f in args.files])
    print(format_seeds(agg))
    if args.json:
        print(f"wrote {write_json(args.json, agg)}")
    return 0


def _cmd_curve(args: argparse.Namespace) -> int:
    from latentdrive.evaluate.planner import planner_config_from_args
    from latentdrive.evaluate.policies import check_references
    from latentdrive.experiments.curve import (
        common_evaluation,
        curve_table,
        group_curves,
        read_curve,
        reference_rates,
        write_curves,
    )

    problem = output_problem(args.out)
    if problem:
        raise ConfigError(f"{args.out}: cannot write a file there ({problem})")
    if not args.out.endswith(".png"):
        raise ConfigError(f"{args.out}: the figure is a PNG; name it *.png")
    references = [] if args.references in ("", "none") else list(dict.fromkeys(_split(args.references)))
    check_references(references)
    if args.overrides and "plan" not in references:
        raise ConfigError("--set planner.* given, but the planner ('plan') is not a reference")
    curves = [read_curve(run, label, args.scenario) for label, run in map(_labelled, args.runs)]
    groups = group_curves(curves)  # a label that mixes settings fails before any episode is played
    cfg = common_evaluation(curves) if references else curves[0].config
    if references:
        _say(f"scoring {', '.join(references)} on the runs' evaluation episodes ...")
    rates = reference_rates(cfg, references, args.scenario, planner_config_from_args(args.overrides))
    episodes = sorted({c.episodes for c in curves})
    per_eval = f"{episodes[0]} episodes per evaluation" if len(episodes) == 1 else "episodes per evaluation vary"
    print(f"held-out failure rate on {args.scenario} ({per_eval}); failure % is the mean over the label's "
          "seeds at the evaluations all of them reached; minutes: training time when the segment ended")
    print(curve_table(groups, rates))
    print(f"wrote {write_curves(args.out, groups, rates, args.title)}")
    return 0


def add_policy_parsers(sub: Any) -> None:
    """Add ``train-policy``, ``evaluate``, ``aggregate`` and ``curve`` to the CLI's sub-parsers."""
    s = sub.add_parser("train-policy", help="train a driving policy (multi-agent double DQN on a VFAN, or the imitation reference)",
                       description="Train a policy in RUN. Interrupt it at any time; --resume continues from the "
                       "last checkpoint and ends with the weights an uninterrupted run would have.")
    s.add_argument("run", help="run directory (config.json, checkpoint, metrics.csv, eval.csv, tb/)")
    s.add_argument("--mode", choices=["raw", "latent", "latent-random", "end-to-end"], default=None,
                   help="input representation (default latent)")
    s.add_argument("--learner", choices=["dqn", "dagger"], default=None,
                   help="dqn: double DQN on the reward (default); dagger: imitate the lookahead planner through the "
                   "same observation and network (the imitation reference; fast backend)")
    s.add_argument("--bnn", default=None, help="BNN run directory (train-bnn); required by --mode latent")
    s.add_argument("--scenarios", default="", help="comma-separated scenarios (default merge); a mixture plays each on its share of the envs")
    s.add_argument("--steps", type=int, default=None, help="budget in agent-transitions (default 50000)")
    s.add_argument("--seed", type=nonnegative_int, default=None, help="training seed (default 0)")
    s.add_argument("--envs", type=int, default=None, help="environments stepped together (default 16)")
    s.add_argument("--backend", choices=["fast", "highway"], default=None, help="simulator (default fast)")
    s.add_argument("--init-from", default=None, help="start from another policy run's weights (fine-tuning)")
    s.add_argument("--config", default="", metavar="FILE",
                   help="train-policy settings from a YAML file (as `tune` writes in best.yaml); flags and --set override it")
    s.add_argument("--resume", action="store_true", help="continue the run in RUN (a larger --steps extends it)")
    s.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    s.add_argument("-s", "--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="config override, repeatable (--set dqn.lr=1e-3 --set segment=5000 --set vfan.hidden=256)")
    s.set_defaults(func=_cmd_train_policy)

    s = sub.add_parser("evaluate", help="failure, crash and success rates of policies on held-out episodes",
                       description="Evaluate a trained run and the reference policies on the same held-out "
                       "episodes (seeds training never uses), per scenario and mixed, with 95% intervals.")
    s.add_argument("run", nargs="?", default="",
                   help="policy run directory (optional), as RUN or LABEL=RUN: the name its rows, JSON entries and "
                   "GIF panel show")
    s.add_argument("--policy", default=None,
                   help="reference policies to include, comma-separated, or 'none' (default: random, idle, stop, "
                   "rule and, on the fast backend, plan, the lookahead planner)")
    s.add_argument("--scenarios", default="", help="comma-separated (default: the run's training scenarios, or all five)")
    s.add_argument("--episodes", type=int, default=100, help="episodes per scenario (default 100)")
    s.add_argument("--envs", type=int, default=16, help="environments per scenario; part of the evaluation set's definition (default 16)")
    s.add_argument("--backend", choices=["fast", "highway"], default="fast")
    s.add_argument("--seed-offset", type=int, default=0, help="another fixed evaluation set, disjoint from the default (default 0; training's own evaluation uses 1)")
    s.add_argument("--json", default="", help="write the results to this JSON file")
    s.add_argument("--compare", default="",
                   help="a second run (RUN or LABEL=RUN), or a reference policy name: paired differences on the "
                   "same episodes and McNemar's exact test")
    s.add_argument("--gif", default="", help="draw one episode of the first scenario to this GIF: the scene beside "
                   "the map the RUN (or the first reference) sees, or, with policies named by --compare or --policy "
                   "beside it, the same episode under each, side by side")
    s.add_argument("--gif-episode", type=int, default=0, metavar="K",
                   help="which episode --gif draws: the K-th one the evaluation's first environment plays "
                   "(default 0, the first)")
    s.add_argument("--causes", action="store_true",
                   help="also print how the episodes ended: success, time-out, or a crash by where the other "
                   "vehicle was (HV ahead, behind, beside; the other AV; none: off the road)")
    s.add_argument("--device", default="auto")
    s.add_argument("-s", "--set", dest="overrides", action="append", default=[], metavar="planner.KEY=VALUE",
                   help="lookahead planner setting, repeatable (--set planner.depth=5 --set planner.rounds=1)")
    s.add_argument("-q", "--quiet", action="store_true")
    s.set_defaults(func=_cmd_evaluate)

    s = sub.add_parser("aggregate", help="one setting's training seeds: mean failure rates with intervals over seeds",
                       description="Read one `evaluate --json` result per training seed of one setting (each "
                       "scored on the same episodes) and print, per scenario and mixed, each seed's failure "
                       "rate, their mean with rliable's 95% stratified-bootstrap interval over seeds and, "
                       "where the files hold a --compare, each seed's paired difference and McNemar p.")
    s.add_argument("files", nargs="+", metavar="EVAL_JSON", help="`latentdrive evaluate ... --json FILE` results, one per seed")
    s.add_argument("--json", default="", help="also write the aggregate to this JSON file")
    s.set_defaults(func=_cmd_aggregate)

    s = sub.add_parser("compare", help="paired tests of two stored evaluations, without playing the episodes again",
                       description="Pair a policy of one `evaluate --json` result with a policy of another on the "
                       "same episodes: per scenario and mixed, both failure and crash rates, the paired difference "
                       "with its 95% interval and McNemar's exact p. The files must score the same evaluation set "
                       "on the same scenario specs.")
    s.add_argument("a_file", metavar="A.json", help="`latentdrive evaluate ... --json FILE` result holding policy A")
    s.add_argument("b_file", metavar="B.json", help="the result holding policy B (may be A.json again)")
    s.add_argument("--a", default="", metavar="POLICY", help="policy A in A.json (default: its run, else its first reference)")
    s.add_argument("--b", default="", metavar="POLICY", help="policy B in B.json (default: its run, else its first reference)")
    s.add_argument("--json", default="", help="also write the tests to this JSON file")
    s.set_defaults(func=_cmd_compare)

    s = sub.add_parser("curve", help="learning curves: held-out failure rate against agent-transitions and minutes",
                       description="Draw the periodic held-out evaluations of policy runs (their eval.csv; train "
                       "with --set eval_every=1) against agent-transitions and against wall-clock training "
                       "minutes, one line per run and the mean per label, with reference policies scored on "
                       "the same episodes. Prints the numbers it draws.")
    s.add_argument("out", help="the figure to write (PNG)")
    s.add_argument("runs", nargs="+", metavar="RUN",
                   help="policy run directories, each optionally LABEL=RUN; runs with one label are seeds "
                   "of one setting (default label: the run's input mode, or 'MODE, imitating EXPERT' for a "
                   "DAgger run)")
    s.add_argument("--references", default="rule",
                   help="reference policies scored on the runs' evaluation episodes, comma-separated, or 'none' "
                   "(default rule; plan, the lookahead planner, takes minutes)")
    s.add_argument("--scenario", default="mixed", help="a training scenario, or mixed (default)")
    s.add_argument("--title", default="", help="the figure's title")
    s.add_argument("-s", "--set", dest="overrides", action="append", default=[], metavar="planner.KEY=VALUE",
                   help="lookahead planner setting for the 'plan' reference, repeatable")
    s.set_defaults(func=_cmd_curve)
