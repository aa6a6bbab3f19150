"""``latentdrive reproduce``: run the study's graph, then gather its results and write its report.

``OUT/study.json`` holds the config the study was last run with; ``OUT/steps/`` every
step's folder; ``OUT/results.json``, ``OUT/report.md`` and ``OUT/figures/`` what the
report shows. ``latentdrive report OUT`` rebuilds the last three from the finished steps.
"""

from __future__ import annotations

import json
import math
import platform
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, NamedTuple

from latentdrive.config import ConfigError, validate
from latentdrive.experiments.estimate import Estimate, estimate_study, measured_rates
from latentdrive.experiments.executor import run_local
from latentdrive.experiments.graph import Graph, StepRecord
from latentdrive.experiments.results import gather_results
from latentdrive.experiments.study import SAMPLES_PER_EPISODE, ReproduceConfig, build_graph
from latentdrive.experiments.study_report import write_report
from latentdrive.experiments.study_runs import StudyRuns, read_runs
from latentdrive.fileio import MAX_JSON_BYTES, atomic_write_text, read_json
from latentdrive.runlock import dir_lock
from latentdrive.runtime import usable_cpus
from latentdrive.scenarios import ScenarioSpec, resolve_specs

__all__ = ["MeasuredStudy", "estimate_from", "measure_study", "read_study", "rebuild_report", "run_study"]

STUDY = "study.json"
#: Imported once by the worker processes' fork server, so each step starts in milliseconds.
PRELOAD = ("latentdrive.experiments.steps",)


def _environment() -> dict[str, Any]:
    import numpy as np
    import torch

    from latentdrive import __version__

    return {"latentdrive": __version__, "python": platform.python_version(), "torch": torch.__version__,
            "numpy": np.__version__,
            "machine": platform.machine(), "cpus": usable_cpus(), "cuda": torch.cuda.is_available(),
            "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None}


def run_study(cfg: ReproduceConfig, out: str | Path, *, workers: int = 1, preset: str = "", progress: bool = True,
              ray: str | None = None, gpu_fraction: float = 1.0, say: Callable[[str], None] = print,
              command: str | None = None) -> dict[str, Any]:
    """Run (or resume) every unfinished step, then write results.json, report.md and figures.

    Steps run in ``workers`` local processes, or as tasks on the Ray cluster at ``ray``
    (see :func:`~latentdrive.experiments.ray_executor.run_ray`); results are the same.
    """
    from latentdrive.experiments.steps import STEP_KINDS

    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"{out}: exists and is not a folder")
    if workers < 1:
        raise ConfigError(f"--workers must be at least 1, got {workers}")
    graph_specs = resolve_specs(cfg.scenarios)
    graph = build_graph(cfg, graph_specs)
    if ray:
        from latentdrive.experiments.ray_executor import check_ray_address

        check_ray_address(ray)  # before anything is written
    out.mkdir(parents=True, exist_ok=True)
    with dir_lock(out, "reproduce"):
        pending = graph.pending(out)
        where = (f"a local Ray instance of {workers} CPU(s)" if ray == "local" else f"Ray cluster {ray}") if ray \
            else f"{workers} worker(s)"
        say(f"study: {len(graph.order)} steps, {len(graph.order) - len(pending)} already finished; {where} -> {out}")
        if (out / STUDY).exists():
            try:
                before, before_preset = read_study(out)
            except ConfigError:
                before, before_preset = None, ""
            if before != cfg:
                # Allowed (more seeds reuse the finished steps), but the report will
                # describe only the new config: say so before it is replaced.
                was = f"preset {before_preset}" if before is not None and before_preset else "another config"
                say(f"note: {out} held a study of {was}; its finished steps are kept and reused where "
                    f"their keys match, and the report will describe the new config")
            try:
                stored = read_study_specs(out)
            except ConfigError:
                stored = {}
            moved = sorted(n for n in cfg.scenarios if n in stored and stored[n] != graph_specs[n])
            if moved:
                say(f"note: the spec of {', '.join(moved)} changed since {out} ran; the steps that use it run again")
        # The resolved specs, beside the config that names them: the study reports from
        # these wherever its folder lies, whatever later versions make of the presets.
        record = {"preset": preset, "config": cfg.model_dump(mode="json"),
                  "specs": {n: s.model_dump(mode="json") for n, s in graph_specs.items()}}
        atomic_write_text(out / STUDY, json.dumps(record, indent=1) + "\n")
        run_workers = f"ray {ray}" if ray else workers
        runs = StudyRuns(out, command, run_workers, len(graph.order) - len(pending), say)
        how = "failed"
        try:
            if ray:
                from latentdrive.experiments.ray_executor import run_ray

                run_ray(graph, out.resolve(), STEP_KINDS, ray, gpu_fraction=gpu_fraction, progress=progress,
                        local_cpus=workers if ray == "local" else None, on_done=runs.step_done)
            else:
                run_local(graph, out, STEP_KINDS, workers=workers, preload=PRELOAD, progress=progress,
                          on_done=runs.step_done)
            how = "finished"
        except KeyboardInterrupt:
            how = "interrupted"
            raise
        finally:
            wall = runs.end(how)
        return _report(cfg, graph, out, preset, {"workers": run_workers, "wall_s": wall, "command": command}, say)


def _report(cfg: ReproduceConfig, graph: Graph, out: Path, preset: str, run: dict[str, Any],
            say: Callable[[str], None]) -> dict[str, Any]:
    records: dict[str, StepRecord] = {}
    for n in graph.order:
        rec = graph.record(out, n)
        if rec is None:
            raise ConfigError(f"{out}: step {n} has not finished; run `latentdrive reproduce {out}` first")
        records[n] = rec
    results = gather_results(cfg, graph, out, records)
    results["meta"] = {"preset": preset, "environment": _environment(), "last_run": run,
                       "runs": read_runs(out), "config": cfg.model_dump(mode="json")}
    atomic_write_text(out / "results.json", json.dumps(results, indent=1, allow_nan=False) + "\n")
    summary = write_report(results, out)
    say(summary)
    return results


def read_study(out: Path) -> tuple[ReproduceConfig, str]:
    """The config and preset name a study in ``out`` was run with."""
    path = out / STUDY
    try:
        data = read_json(path, limit=MAX_JSON_BYTES, what="study record", error=ConfigError)
    except FileNotFoundError:
        raise ConfigError(f"{out}: not a study folder (no {STUDY}); run `latentdrive reproduce {out}`") from None
    if not isinstance(data, dict) or not isinstance(data.get("config"), dict):
        raise ConfigError(f"{path}: not a study record")
    try:
        return validate(ReproduceConfig, data["config"]), str(data.get("preset", ""))
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None


def read_study_specs(out: Path) -> dict[str, ScenarioSpec]:
    """The scenario specs a study in ``out`` ran on (empty for a study that predates the record)."""
    path = out / STUDY
    data = read_json(path, limit=MAX_JSON_BYTES, what="study record", error=ConfigError)
    specs = data.get("specs", {}) if isinstance(data, dict) else None
    if not isinstance(specs, dict):
        raise ConfigError(f"{path}: not a study record (specs is not a mapping)")
    try:
        return {str(n): validate(ScenarioSpec, s, prefix=f"specs.{n}.") for n, s in specs.items()}
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None


def rebuild_report(out: str | Path, say: Callable[[str], None] = print) -> dict[str, Any]:
    """``latentdrive report OUT``: results, report and figures again from the finished steps."""
    out = Path(out)
    cfg, preset = read_study(out)
    previous: dict[str, Any] = {}
    try:
        old = read_json(out / "results.json", limit=MAX_JSON_BYTES, what="results", error=ConfigError)
        meta = old.get("meta") if isinstance(old, dict) else None
        previous = meta.get("last_run", {}) if isinstance(meta, dict) else {}
    except (FileNotFoundError, ConfigError):
        # Rebuilding is what a missing or damaged results.json needs; the runs log still
        # knows the last run that ran to its end.
        ended = [r for r in read_runs(out) or [] if r.get("ended") == "finished"]
        if ended:
            previous = {k: ended[-1].get(k) for k in ("workers", "wall_s", "command")}
    return _report(cfg, build_graph(cfg, read_study_specs(out)), out, preset, previous, say)


class MeasuredStudy(NamedTuple):
    """What a study folder's finished steps measured."""

    config: ReproduceConfig
    #: The preset it was run with ("" for a config of its own).
    preset: str
    graph: Graph
    records: dict[str, StepRecord]
    #: Seconds per unit of size of each step class (:func:`~latentdrive.experiments.estimate.step_size`).
    rates: dict[str, float]
    #: Samples its dataset collected per episode (the default guess until it has collected).
    per_episode: float

    def epoch_samples(self, cfg: ReproduceConfig) -> float:
        """An uncapped BNN epoch's samples in study ``cfg`` (this one's, or one planned from
        it): its training episodes' samples at the samples per episode measured here."""
        return self.per_episode * cfg.bnn.collect.episodes * len(cfg.scenarios) * (1 - cfg.bnn.val_fraction)


def measure_study(out: str | Path) -> MeasuredStudy:
    """The step times the finished steps of the study in ``out`` recorded, by class (none
    when no step has finished)."""
    out = Path(out)
    cfg, preset = read_study(out)
    graph = build_graph(cfg, read_study_specs(out))
    records = {n: r for n in graph.order if (r := graph.record(out, n)) is not None}
    # An uncapped BNN epoch is the training episodes' samples: the measured dataset's count,
    # and a planned one's from the samples per episode measured (SAMPLES_PER_EPISODE until one is).
    collected = records["dataset"].summary.get("samples") if "dataset" in records else None
    episodes = cfg.bnn.collect.episodes * len(cfg.scenarios)
    per_episode = collected / episodes if isinstance(collected, int) and collected > 0 else float(SAMPLES_PER_EPISODE)
    m = MeasuredStudy(cfg, preset, graph, records, {}, per_episode)
    return m._replace(rates=measured_rates(graph, records, m.epoch_samples(cfg)))


def estimate_from(measured: str | Path, cfg: ReproduceConfig, workers: list[int],
                  speedup: Mapping[str, float] | None = None) -> list[Estimate]:
    """Estimates of the study ``cfg`` on each number of ``workers``, at the step times the
    study in ``measured`` recorded (its finished steps; at least one of each class).

    ``speedup`` maps a step class (``bnn``, ``policy:raw``, ...), or a kind standing for all
    its classes (``policy``), to how many times faster the target machine runs it than the
    measuring one did (e.g. the ratio of two ``latentdrive bench --train`` runs).
    """
    m = measure_study(measured)
    if m.config.observation != cfg.observation:
        a, b = m.config.observation.model_dump(), cfg.observation.model_dump()
        diff = ", ".join(f"{k} {a[k]} there, {b[k]} here" for k in a if a[k] != b[k])
        raise ConfigError(f"{measured} measured other observations ({diff}): its step times do not carry over")
    if not m.records:
        raise ConfigError(f"{measured}: no finished step to measure")
    rates = dict(m.rates)
    for name, factor in (speedup or {}).items():
        # A class, or a prefix of classes that ends at a ':' (policy:raw holds policy:raw:objects,
        # not policy:raw-anything).
        hit = [c for c in rates if c == name or c.startswith(f"{name}:")]
        if not hit:
            raise ConfigError(f"--speedup {name}: no such step class measured (known: {', '.join(sorted(rates))})")
        if not (math.isfinite(factor) and factor > 0):
            raise ConfigError(f"--speedup {name}: the factor must be a positive finite number, got {factor:g}")
        for c in hit:
            rates[c] /= factor
    graph = build_graph(cfg)
    return [estimate_study(graph, rates, w, epoch_samples=m.epoch_samples(cfg)) for w in workers]
