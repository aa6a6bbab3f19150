"""The kinds of step a study is made of: each a function ``(config, inputs, folder) -> summary``.

A step reads only its inputs' folders and writes only its own; its config holds JSON
values (no paths), so the same step can run in another process or on another machine
that sees the same study folder. Every function here is module-level, so that worker
processes receive it by reference.

Files each kind writes into its folder:

- ``dataset``: ``data/`` (a collected dataset);
- ``bnn``: ``run/`` (a BNN run);
- ``bnn-report``: ``report.json``, ``report.md``, ``figures/`` (the BNN study);
- ``policy``: ``run/`` (a policy run, with its learning curve in ``run/eval.csv``);
- ``evaluate``: ``outcomes.json`` (every episode of a policy or reference policy);
- ``probes``: ``probes.json``.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from latentdrive.bnn.train import BNNTrainConfig
from latentdrive.config import validate
from latentdrive.data.collect import CollectConfig, collect
from latentdrive.data.dataset import ShardDataset
from latentdrive.evaluate.planner import PlannerConfig
from latentdrive.evaluate.probes import ProbeConfig, run_probes
from latentdrive.evaluate.report import policy_report
from latentdrive.experiments.bnn import BNNStudyConfig, report_bnn_runs, train_on_dataset
from latentdrive.experiments.executor import StepKind
from latentdrive.experiments.graph import RESUMED
from latentdrive.experiments.policy import EvaluationSet, policy_makers
from latentdrive.fileio import atomic_write_text
from latentdrive.outcome import outcomes_to_json
from latentdrive.rl.config import PolicyTrainConfig
from latentdrive.rl.learner import REPLAY_PATTERN
from latentdrive.rl.policy import CHECKPOINT
from latentdrive.rl.train import train_policy

__all__ = ["OUTCOMES", "PROBES", "RUN", "STEP_KINDS"]

RUN = "run"
OUTCOMES = "outcomes.json"
PROBES = "probes.json"


def _quiet(_: str) -> None:
    pass


def run_dataset(config: Mapping[str, Any], inputs: Mapping[str, Path], folder: Path) -> dict[str, Any]:
    summary = collect(validate(CollectConfig, config["collect"]), folder / "data", progress=False)
    return {"samples": len(ShardDataset(folder / "data")), "collected_s": round(float(summary.seconds), 1),
            RESUMED: float(summary.resumed_s)}


def run_bnn(config: Mapping[str, Any], inputs: Mapping[str, Path], folder: Path) -> dict[str, Any]:
    metrics = train_on_dataset(inputs["dataset"] / "data", folder / RUN, validate(BNNTrainConfig, config["train"]),
                               int(config["latent_dim"]), channels=tuple(config["channels"]),
                               val_fraction=float(config["val_fraction"]), resume=True, progress=False,
                               model=config.get("model"))
    resumed = metrics.pop("resumed_s", 0.0)
    return {**{k: float(v) for k, v in metrics.items()}, RESUMED: float(resumed)}


def _one_thread() -> None:
    """Steps that evaluate networks use one thread: float sums then do not depend on the
    machine's (or the Ray worker's) thread count, and the study's numbers are the same
    whatever runs them."""
    torch.set_num_threads(1)


def run_bnn_report(config: Mapping[str, Any], inputs: Mapping[str, Path], folder: Path) -> dict[str, Any]:
    _one_thread()
    cfg = validate(BNNStudyConfig, config["study"])
    runs = {name: (inputs[f"run:{name}"] / RUN, int(d), float(lam)) for name, (d, lam) in config["runs"].items()}
    report = report_bnn_runs(cfg, inputs["dataset"] / "data", runs, folder, say=_quiet)
    return {name: {"vehicle_recall": r.get("vehicle_recall"), "val_recon": r.get("val_recon")}
            for name, r in report["runs"].items()}


def run_policy(config: Mapping[str, Any], inputs: Mapping[str, Path], folder: Path) -> dict[str, Any]:
    train = dict(config["train"])
    if "bnn" in inputs:
        train["bnn"] = str(inputs["bnn"] / RUN)
    if "init" in inputs:
        train["init_from"] = str(inputs["init"] / RUN)
    cfg = validate(PolicyTrainConfig, train)
    run = folder / RUN
    result = train_policy(cfg, run, resume=(run / CHECKPOINT).exists(), progress=False, say=_quiet)
    # The replay exists to resume an interrupted run; a finished study step is never resumed
    # (a larger budget is another step), and a raw policy's replay holds gigabytes.
    for f in run.iterdir():
        if REPLAY_PATTERN.fullmatch(f.name):
            f.unlink()
    return {"transitions": int(result.get("transitions", 0)), RESUMED: float(result.get("resumed_s", 0.0))}


def run_evaluate(config: Mapping[str, Any], inputs: Mapping[str, Path], folder: Path) -> dict[str, Any]:
    ev = config["eval"]
    planner = validate(PlannerConfig, ev["planner"]) if ev.get("planner") is not None else None
    eval_set = EvaluationSet(ev["scenarios"], int(ev["episodes"]), int(ev["envs"]), ev["backend"], int(ev["seed_offset"]),
                             observation=ev.get("observation") or {}, reward=ev.get("reward") or {}, planner=planner)
    _one_thread()
    if "policy" in inputs:
        run = str(inputs["policy"] / RUN)
        makers = policy_makers({run: run}, [], eval_set, torch.device("cpu"))
    else:
        makers = policy_makers({}, [config["reference"]], eval_set, torch.device("cpu"))
    (make,) = makers.values()
    outcomes = eval_set.run(make)
    atomic_write_text(folder / OUTCOMES, json.dumps(outcomes_to_json(outcomes), allow_nan=False) + "\n")
    rep = policy_report(outcomes)
    return {"episodes": len(outcomes), "failure_rate": rep.mixed.failure_rate.rate, "crash_rate": rep.mixed.crash_rate.rate}


def run_probes_step(config: Mapping[str, Any], inputs: Mapping[str, Path], folder: Path) -> dict[str, Any]:
    _one_thread()
    cfg = validate(ProbeConfig, config["probe"])
    result = run_probes(cfg, config["kinds"], inputs["bnn"] / RUN if "bnn" in inputs else None)
    atomic_write_text(folder / PROBES, json.dumps(result, indent=1, allow_nan=False) + "\n")
    return {"samples": result["samples"]}


STEP_KINDS: dict[str, StepKind] = {
    "dataset": StepKind(run_dataset, resumable=True),
    "bnn": StepKind(run_bnn, resumable=True, gpu=True),
    "bnn-report": StepKind(run_bnn_report),
    "policy": StepKind(run_policy, resumable=True, gpu=True),
    "evaluate": StepKind(run_evaluate),
    "probes": StepKind(run_probes_step),
}
