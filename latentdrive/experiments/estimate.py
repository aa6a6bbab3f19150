"""How long a study would take, from the step times another study measured.

Each step has a *size* in the unit its time grows with (agent-transitions for a policy,
training samples for a BNN, episodes for an evaluation), and a *class* within which that time
per unit is roughly constant (a policy's input mode, a BNN's batch size and architecture,
an evaluation's backend and policy). A class the measured study did not run is reported
as unmeasured rather than borrowed from another.
A finished study gives seconds per unit for each class; a planned study's steps times
their sizes give its step times, and a list schedule over ``workers`` (the executor's own
order: longest remaining chain first) gives its wall time.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from latentdrive.config import ConfigError
from latentdrive.experiments.graph import Graph, Step, StepRecord
from latentdrive.models.vfan import VFANConfig
from latentdrive.rl.config import PolicyTrainConfig
from latentdrive.rl.dqn import DQNConfig

__all__ = ["Estimate", "estimate_study", "makespan", "measured_rates", "scored_count", "step_size", "step_times"]


def step_size(step: Step, epoch_samples: float | None = None) -> tuple[str, float]:
    """``(class, size)`` of a step: what its run time is proportional to.

    A BNN step's size is the training samples it processes: its epochs times the samples of
    an epoch, which is ``epoch_steps`` batches when capped (whatever the dataset) and the
    training episodes' samples, ``epoch_samples``, otherwise (or when the cap exceeds them).
    The BNN report's is the held-out samples it scores, for each run and the noisy input.
    The step's config does not hold the dataset's size, so the caller gives it.
    """
    c = step.config
    if step.kind == "dataset":
        return "dataset", float(c["collect"]["episodes"] * len(c["collect"]["scenarios"]))
    if step.kind == "bnn":
        t = c["train"]
        cap = float(t["epoch_steps"] * t["batch_size"]) if t.get("epoch_steps") else math.inf
        per_epoch = min(cap, math.inf if epoch_samples is None else epoch_samples)
        if math.isinf(per_epoch):
            raise ConfigError(f"{step.name}: an uncapped BNN epoch's size needs its dataset's sample count")
        return _bnn_class(c), float(t["pretrain_epochs"] + t["mixed_epochs"]) * per_epoch
    if step.kind == "bnn-report":
        return "bnn-report", float((len(c["runs"]) + 1) * _scored_samples(step, epoch_samples))
    if step.kind == "policy":
        return _policy_class(c["train"]), float(c["train"]["steps"])
    if step.kind == "evaluate":
        ev = c["eval"]
        who = c.get("reference") or "policy"
        return f"evaluate:{ev['backend']}:{who}", float(ev["episodes"] * len(ev["scenarios"]))
    if step.kind == "probes":
        p = c["probe"]
        return "probes", float(p["episodes"] * len(p["scenarios"]))
    raise ConfigError(f"no size for step kind {step.kind!r}")


def _policy_class(train: Mapping[str, Any]) -> str:
    """``policy:<mode>``, then what changes the time per agent-transition several-fold where it
    differs from the defaults: the map reader (the objects reader learns several times as fast
    per update as the convolutional one), DAgger's planner labels, the updates per
    agent-transition, the batch and a precision set other than ``auto``. A study measured
    with other such settings leaves the class unmeasured rather than lending its times."""
    parts = [f"policy:{train['mode']}"]
    reader = (train.get("vfan") or {}).get("reader", VFANConfig.model_fields["reader"].default)
    if reader != VFANConfig.model_fields["reader"].default:
        parts.append(reader)
    learner = train.get("learner", PolicyTrainConfig.model_fields["learner"].default)
    if learner != PolicyTrainConfig.model_fields["learner"].default:
        parts.append(learner)
    dqn = train.get("dqn") or {}
    for key, short in (("updates_per_transition", "upt"), ("batch_size", "batch")):
        default = DQNConfig.model_fields[key].default
        if dqn.get(key, default) != default:
            parts.append(f"{short}{dqn[key]:g}")
    # bf16 autocast makes a train step 1.5-1.9 times as fast where the CPU has AMX-BF16.
    precision = train.get("precision", PolicyTrainConfig.model_fields["precision"].default)
    if precision != PolicyTrainConfig.model_fields["precision"].default:
        parts.append(precision)
    return ":".join(parts)


def _scored_samples(step: Step, epoch_samples: float | None) -> float:
    """Held-out samples the BNN report scores per run (and for the noisy input): the first
    ``score_samples`` of them, or all, whose count follows from the training episodes'
    samples and ``val_fraction`` (held-out episodes are drawn like training ones)."""
    study = step.config["study"]
    cap = float(study.get("score_samples") or 0)
    vf = float(study["val_fraction"])
    held = None if epoch_samples is None else epoch_samples * vf / (1.0 - vf)
    if held is None:
        if cap:
            return cap
        raise ConfigError(f"{step.name}: a report that scores every held-out sample needs its dataset's sample count")
    return scored_count(held, cap)


def scored_count(held: float, score_samples: float) -> float:
    """Samples the BNN report scores of ``held`` held-out ones: the first ``score_samples``
    (0 = every one)."""
    return min(held, score_samples) if score_samples else held


def _bnn_class(c: Mapping[str, Any]) -> str:
    """A BNN step's class: its time per sample depends on the batch size (on a CPU a
    sample costs more in small batches) and the architecture (hidden layers, stages), so
    the rate of one never stands in for another. The code size is left out: the study
    trains several, at nearly the same cost, and their mean rate is what it measures."""
    model = ",".join(f"{k}={v}" for k, v in sorted((c.get("model") or {}).items()))
    channels = "-".join(str(ch) for ch in c["channels"])
    return f"bnn:batch{c['train']['batch_size']}:channels{channels}" + (f":{model}" if model else "")


def measured_rates(graph: Graph, records: Mapping[str, StepRecord], epoch_samples: float | None = None) -> dict[str, float]:
    """Seconds per unit of size for each step class, from finished steps; ``epoch_samples``
    as in :func:`step_size`, for the measured study's dataset."""
    wall: dict[str, float] = {}
    size: dict[str, float] = {}
    for name, rec in records.items():
        cls, n = step_size(graph.steps[name], epoch_samples)
        wall[cls] = wall.get(cls, 0.0) + rec.cost_s
        size[cls] = size.get(cls, 0.0) + n
    return {cls: wall[cls] / size[cls] for cls in wall if size[cls] > 0}


@dataclass(frozen=True)
class Estimate:
    """A planned study's time: the sum of its steps' times and its wall time on ``workers``."""

    steps: int
    step_hours: float
    wall_hours: float
    workers: int
    by_class: dict[str, float]
    unmeasured: list[str]

    def as_dict(self) -> dict[str, Any]:
        return {"steps": self.steps, "step_hours": self.step_hours, "wall_hours": self.wall_hours,
                "workers": self.workers, "hours_by_class": self.by_class, "unmeasured": self.unmeasured}


def step_times(graph: Graph, rates: Mapping[str, float],
               epoch_samples: float | None = None) -> dict[str, tuple[str, float | None]]:
    """Each step's class and its time at the measured ``rates`` (seconds; None where no
    rate of its class was measured); ``epoch_samples`` as in :func:`step_size`."""
    out: dict[str, tuple[str, float | None]] = {}
    for name, step in graph.steps.items():
        cls, n = step_size(step, epoch_samples)
        out[name] = (cls, rates[cls] * n if cls in rates else None)
    return out


def estimate_study(graph: Graph, rates: Mapping[str, float], workers: int, epoch_samples: float | None = None) -> Estimate:
    """Step and wall hours of ``graph`` at the measured ``rates``; ``epoch_samples`` as in
    :func:`step_size`, for the planned study's dataset. A step of a class not measured
    counts 0 (and its class is listed)."""
    sized = step_times(graph, rates, epoch_samples)
    times = {name: t or 0.0 for name, (_, t) in sized.items()}
    by_class: dict[str, float] = {}
    for cls, t in sized.values():
        if t is not None:
            by_class[cls] = by_class.get(cls, 0.0) + t / 3600
    unmeasured = {cls for cls, t in sized.values() if t is None}
    return Estimate(steps=len(graph.order), step_hours=sum(times.values()) / 3600,
                    wall_hours=makespan(graph, times, workers) / 3600, workers=workers,
                    by_class={k: round(v, 2) for k, v in sorted(by_class.items())}, unmeasured=sorted(unmeasured))


def makespan(graph: Graph, times: Mapping[str, float], workers: int) -> float:
    """Wall time of a list schedule: a free worker takes the ready step with the longest
    chain of step times after it (the local executor ranks steps alike, by the graph's
    rough costs rather than these times)."""
    dependents: dict[str, list[str]] = {n: [] for n in graph.order}
    for n in graph.order:
        for dep in graph.steps[n].inputs.values():
            dependents[dep].append(n)
    rank: dict[str, float] = {}
    for n in reversed(graph.order):
        rank[n] = times[n] + max((rank[d] for d in dependents[n]), default=0.0)
    finish: dict[str, float] = {}
    free = [0.0] * workers
    todo = set(graph.order)
    while todo:
        # The earliest a step can start is when its inputs are done; pick greedily by rank
        # among steps whose inputs are scheduled, on the worker that frees first.
        ready = [n for n in todo if all(d in finish for d in graph.steps[n].inputs.values())]
        n = max(ready, key=lambda m: (rank[m], m))
        w = min(range(workers), key=lambda i: free[i])
        start = max([free[w], *(finish[d] for d in graph.steps[n].inputs.values())])
        finish[n] = start + times[n]
        free[w] = finish[n]
        todo.remove(n)
    return max(finish.values(), default=0.0)
