"""The bottleneck-network study: dataset → BNNs of several latent sizes and λ → evaluation.

``latentdrive bnn-study OUT`` runs, resumably:

1. ``collect`` a mixed-scenario denoising dataset into ``OUT/dataset``;
2. train one BNN per latent size (λ = 0) and, at the largest size, one per λ > 0, each in
   ``OUT/runs/<name>`` on the same episode split (validation episodes are held out);
3. evaluate every run on the held-out episodes: reconstruction error, and the 5×5
   scenario distance (MMD², :mod:`latentdrive.bnn.distance`) in its latent space and in
   a raw-input baseline space;
4. write ``OUT/report.json``, ``OUT/report.md`` and the figures in ``OUT/figures``.

Every step skips what is already done, so an interrupted study continues where it stopped.
"""

from __future__ import annotations

import functools
import json
import math
from collections.abc import Callable, Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import Field, ValidationError, field_validator

from latentdrive.bnn.batch import BNNBatch
from latentdrive.bnn.checkpoint import read_checkpoint
from latentdrive.bnn.distance import distance_matrix
from latentdrive.bnn.train import (
    CHECKPOINT_NAME,
    BNNTrainConfig,
    check_run_dir,
    first_samples,
    train_bnn,
)
from latentdrive.config import Config, ConfigError, describe_validation_error, load_preset, validate
from latentdrive.data.collect import (
    CollectConfig,
    check_collect_target,
    collect,
    dataset_specs,
    resolve_env_configs,
)
from latentdrive.data.dataset import ShardDataset
from latentdrive.data.shards import DatasetError
from latentdrive.evaluate.stats import json_values
from latentdrive.experiments.bnn_report import epoch_rows, fmt_value, format_report, read_report
from latentdrive.experiments.bnn_scores import (
    evaluate_run,
    finite_or_none,
    input_vehicle_recovery,
    mean_offdiag,
    raw_features,
    reach_references,
)
from latentdrive.experiments.heldout import held_out
from latentdrive.experiments.processes import Job, run_processes
from latentdrive.fileio import MAX_JSON_BYTES, atomic_write_text, read_json
from latentdrive.models.bottleneck import BottleneckConfig
from latentdrive.runlock import dir_lock
from latentdrive.runtime import usable_cpus

__all__ = [
    "BNNStudyConfig",
    "figures_from_study",
    "load_study_config",
    "read_study_config",
    "report_bnn_runs",
    "run_bnn_study",
    "run_name",
    "study_runs",
    "train_on_dataset",
]

PRESETS_DIR = Path(__file__).parent / "presets"
SPLIT = "split.json"
STUDY_CONFIG = "study_config.json"
STUDY_PRESETS = ("tiny", "small", "paper")


class BNNStudyConfig(Config):
    """What the BNN study collects, trains and evaluates."""

    collect: CollectConfig = Field(default_factory=lambda: CollectConfig.model_validate({}), description="The dataset.")
    train: BNNTrainConfig = Field(default_factory=lambda: BNNTrainConfig.model_validate({}), description="Training of every run (lambda_distance is set per run).")
    channels: tuple[int, ...] = Field((16, 32), min_length=1, max_length=6, description="Encoder channel widths of every run's BNN.")
    model: dict[str, Any] = Field(
        default_factory=dict,
        description="Further BottleneckConfig fields of every run's BNN (latent_dim, channels and input_shape "
        "come from the study); {head_hidden: 0, latent_norm: false} is the paper's structure.")
    latent_dims: list[int] = Field(default_factory=lambda: [16, 32, 64], min_length=1, description="Latent sizes d compared at λ = 0 (the paper's 16, 32, 64).")
    lambdas: list[float] = Field(default_factory=lambda: [0.01], description="λ > 0 values trained at the largest latent size.")
    val_fraction: float = Field(0.15, gt=0.0, lt=1.0, description="Share of each scenario's episodes held out for evaluation.")
    eval_samples: int = Field(300, ge=10, le=100_000, description="Held-out samples per scenario used for the distance matrices and figures.")
    score_samples: int = Field(
        0, ge=0, le=10_000_000,
        description="Held-out samples, over all scenarios, on which the reconstruction error and vehicle recovery "
        "are scored (mixed batches, so every scenario is in); 0 scores every held-out sample.")
    raw_pool: int = Field(4, ge=1, le=64, description="Average-pooling factor over H and W of the raw-input baseline space.")

    @field_validator("model")
    @classmethod
    def _model_fields(cls, v: dict[str, Any]) -> dict[str, Any]:
        taken = sorted(set(v) & {"latent_dim", "channels", "input_shape"})
        if taken:
            raise ValueError(f"{', '.join(taken)}: set by the study (latent_dims, channels, the observation), not by model")
        try:
            # Checked against a placeholder shape; a run's own shape comes from its dataset.
            checked = BottleneckConfig.model_validate({**v, "input_shape": (4, 32, 64)})
        except ValidationError as exc:
            raise ValueError(describe_validation_error(exc)) from None
        # The validated values, so that "0" and 0 make the same run (and the same step key).
        dumped = checked.model_dump(mode="json")
        return {k: dumped[k] for k in v}

    @field_validator("lambdas")
    @classmethod
    def _positive(cls, v: list[float]) -> list[float]:
        if any(x <= 0 for x in v):
            raise ValueError("every λ must be > 0 (λ = 0 runs are the latent_dims runs)")
        return v


def load_study_config(preset: str, overrides: dict[str, Any] | None = None) -> BNNStudyConfig:
    """A named preset (``tiny``, ``small``, ``paper``) or a YAML file, with dotted overrides."""
    return load_preset(BNNStudyConfig, preset, {p: PRESETS_DIR / f"bnn-{p}.yaml" for p in STUDY_PRESETS}, overrides)


def run_name(latent_dim: int, lam: float = 0.0) -> str:
    """Directory name of a run: ``d64`` or ``d64-lam0.01``."""
    return f"d{latent_dim}" if lam == 0 else f"d{latent_dim}-lam{lam:g}"


def _split(ds: ShardDataset, val_fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    return ds.split_by_episode(val_fraction, seed)


def train_on_dataset(
    dataset_dir: str | Path,
    run_dir: str | Path,
    train_cfg: BNNTrainConfig,
    latent_dim: int,
    channels: tuple[int, ...] = (16, 32),
    val_fraction: float = 0.15,
    resume: bool = False,
    progress: bool = True,
    model: dict[str, Any] | None = None,
) -> dict[str, float]:
    """Train one BNN on a collected dataset, holding out ``val_fraction`` of its episodes.

    ``model`` holds further :class:`BottleneckConfig` fields (``latent_activation``, ...);
    the input shape comes from the dataset.

    Pretraining batches are plainly shuffled; mixed-phase batches hold every scenario.
    The split (by episode) depends only on ``train_cfg.seed`` and is saved to
    ``run_dir/split.json``.
    """
    if not 0.0 < val_fraction < 1.0:
        # The one check of the range, for the library and `train-bnn --val-fraction` alike.
        raise ConfigError(f"val_fraction (train-bnn --val-fraction) must be in (0, 1): training validates on "
                          f"the held-out episodes, got {val_fraction}")
    ds = ShardDataset(dataset_dir)
    train_ids, val_ids = _split(ds, val_fraction, train_cfg.seed)
    if not len(train_ids) or not len(val_ids):
        side = "training" if not len(train_ids) else "validation"
        raise ConfigError(f"{dataset_dir}: no {side} episodes at val_fraction {val_fraction} "
                          f"({len(ds.episode_ids)} episodes); collect more episodes or change the fraction")
    model_cfg = _model_config(latent_dim, channels, model, ds.sample_shape)
    plain = ds.batches_fn(train_cfg.batch_size, train_ids, seed=train_cfg.seed, mixed=False)
    mixed = ds.batches_fn(train_cfg.batch_size, train_ids, seed=train_cfg.seed, mixed=True)

    def train_fn(epoch: int) -> Iterator[BNNBatch]:
        return (plain if train_cfg.phase(epoch) == "pretrain" else mixed)(epoch)

    def val_fn() -> Iterator[BNNBatch]:
        # A capped validation reads the first samples: batches holding every scenario keep
        # its scenario shares those of the held-out set.
        return ds.batches(train_cfg.batch_size, val_ids, seed=train_cfg.seed, epoch=0,
                          mixed=bool(train_cfg.val_samples))

    run = Path(run_dir)
    split = {"dataset": str(Path(dataset_dir).resolve()), "val_fraction": val_fraction,
             "train_episodes": train_ids.tolist(), "val_episodes": val_ids.tolist()}
    # Refusals come before anything is written, the lock file included; train_bnn checks
    # the run again under the lock.
    check_run_dir(run, train_cfg, model_cfg, resume)
    _check_split(run, split)
    # Held from the split record on, so a refused second run writes nothing here.
    with dir_lock(run, "train-bnn"):
        atomic_write_text(run / SPLIT, json.dumps(split) + "\n")
        # Every batch but the last is full (ShardDataset.batches), mixed or not.
        steps = math.ceil(ds.num_samples(train_ids) / train_cfg.batch_size)
        return train_bnn(train_cfg, model_cfg, train_fn, val_fn, run, resume=resume, progress=progress,
                         steps_per_epoch=steps, observation=ds.observation)


def _model_config(latent_dim: int, channels: tuple[int, ...], model: dict[str, Any] | None,
                  sample_shape: tuple[int, ...]) -> BottleneckConfig:
    """The BNN architecture of a run on samples of ``sample_shape`` ``(4, T, H, W)``."""
    _, t, h, w = sample_shape
    return validate(BottleneckConfig, {"latent_dim": latent_dim, "channels": channels, **(model or {}),
                                       "input_shape": (t, h, w)}, prefix="model.")


def _check_split(run: Path, split: dict[str, Any]) -> None:
    """Refuse to continue a trained run on other episodes than it was trained on.

    The split follows from the seed and ``val_fraction``; the seed is checked with the
    other training settings, ``val_fraction`` only here. Held-out episodes moved into
    training would make every held-out score of the run meaningless.
    """
    path = run / SPLIT
    if not (run / CHECKPOINT_NAME).exists() or not path.exists():
        return
    old = read_json(path, limit=MAX_JSON_BYTES, what="episode split", error=ConfigError)
    keys = ("train_episodes", "val_episodes")
    if not isinstance(old, dict) or any(old.get(k) != split[k] for k in keys):
        raise ConfigError(f"{path}: the run was trained on another episode split (another val_fraction "
                          "or dataset); resume it with the same settings or use a new run directory")


def run_bnn_study(cfg: BNNStudyConfig, out: str | Path, progress: bool = True,
                  say: Callable[[str], None] = print, workers: int = 1) -> dict[str, Any]:
    """Run (or resume) the whole study into ``out``; returns the report it writes.

    ``workers`` > 1 trains that many BNNs at once, each in its own process; a run whose
    config leaves ``num_threads`` at 0 then gets the machine's cores shared among the
    workers (thread counts can change results in the last bits; the runs' configs record
    them). What the study would refuse (another config's dataset in ``out``, runs that
    cannot be resumed with ``cfg``) is checked before anything is written.
    """
    if workers < 1:
        raise ConfigError(f"workers must be at least 1, got {workers}")
    out = Path(out)
    _check_study_target(cfg, out)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / STUDY_CONFIG, json.dumps(cfg.model_dump(mode="json"), indent=1) + "\n")
    say(f"[1/4] dataset -> {out / 'dataset'}")
    collect(cfg.collect, out / "dataset", progress=progress)
    runs = study_runs(cfg)
    if workers == 1:
        for i, (name, d, lam) in enumerate(runs):
            say(f"[2/4] training {name} ({i + 1}/{len(runs)}) -> {out / 'runs' / name}")
            train_on_dataset(out / "dataset", out / "runs" / name, cfg.train.replace(lambda_distance=lam), d,
                             channels=cfg.channels, val_fraction=cfg.val_fraction, resume=True, progress=progress,
                             model=cfg.model)
    else:
        _train_in_parallel(cfg, out, runs, workers, say)

    say("[3/4] evaluating on held-out episodes")
    return report_bnn_runs(cfg, out / "dataset", {name: (out / "runs" / name, d, lam) for name, d, lam in runs}, out,
                           say=say)


def _train_in_parallel(cfg: BNNStudyConfig, out: Path, runs: list[tuple[str, int, float]], workers: int,
                       say: Callable[[str], None]) -> None:
    slots = min(workers, len(runs))
    threads = cfg.train.num_threads or max(1, usable_cpus() // slots)
    say(f"[2/4] training {len(runs)} BNNs, {slots} at a time ({threads} thread(s) each) -> {out / 'runs'}")
    jobs: dict[str, Job] = {
        name: (train_on_dataset,
               (out / "dataset", out / "runs" / name, cfg.train.replace(lambda_distance=lam, num_threads=threads), d),
               {"channels": cfg.channels, "val_fraction": cfg.val_fraction, "resume": True, "progress": False,
                "model": cfg.model})
        for name, d, lam in runs
    }
    done: list[str] = []

    def report(name: str, m: dict[str, float]) -> None:
        done.append(name)
        say(f"[2/4] {name} done ({len(done)}/{len(runs)}): its last validation's recall "
            f"{fmt_value(finite_or_none(m.get('val_vehicle_recall', math.nan)), '.3f')}, precision "
            f"{fmt_value(finite_or_none(m.get('val_vehicle_precision', math.nan)), '.3f')}")

    # A failure or an interrupt stops every run at once; each continues from its last
    # epoch's checkpoint when the study is run again.
    run_processes(jobs, slots, on_done=report)


def report_bnn_runs(cfg: BNNStudyConfig, dataset: Path, runs: Mapping[str, tuple[Path, int, float]], out: Path,
                    say: Callable[[str], None] = print) -> dict[str, Any]:
    """Evaluate trained runs on the dataset's held-out episodes; writes ``out/report.json``,
    ``out/report.md`` and ``out/figures``; returns the report.

    ``runs`` maps each run's name to its directory, latent size and λ.
    """
    ds = ShardDataset(dataset)
    _, val_ids = _split(ds, cfg.val_fraction, cfg.train.seed)
    data = held_out(ds, val_ids, cfg.eval_samples, seed=cfg.train.seed)
    scored = _scored_batches(ds, val_ids, cfg)
    names, raw = distance_matrix(data.by_scenario(raw_features(data.noisy, cfg.raw_pool)))
    report: dict[str, Any] = {
        "dataset_samples": len(ds), "held_out_samples": len(data.scenario),
        "scored_samples": cfg.score_samples if 0 < cfg.score_samples < ds.num_samples(val_ids) else None,
        "raw_scenarios": names, "raw_distance": raw.tolist(), "raw_mean_between_scenario_distance": mean_offdiag(raw),
        "noisy_input_vehicles": {**input_vehicle_recovery(ds, scored),
                                 "drawn_cells_within": (refs := reach_references(data))["input"]},
        "every_cell_within": refs["every cell"],
        "runs": {},
    }
    for name, (run, d, lam) in runs.items():
        report["runs"][name] = {"latent_dim": d, "lambda": lam,
                                **evaluate_run(run, data, ds, scored)}
    report = json_values(report)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "report.json", json.dumps(report, indent=1, allow_nan=False) + "\n")
    atomic_write_text(out / "report.md", format_report(report))

    say(f"[4/4] figures -> {out / 'figures'}")
    # Imported here: matplotlib is needed only once figures are drawn, not by train-bnn.
    from latentdrive.experiments.bnn_figures import write_bnn_figures

    write_bnn_figures(out / "figures", {name: run for name, (run, _, _) in runs.items()}, data, report, cfg.train.seed)
    return report


def _scored_batches(ds: ShardDataset, val_ids: np.ndarray, cfg: BNNStudyConfig) -> Callable[[], Iterable[BNNBatch]]:
    """The held-out batches the runs and the noisy input are scored on: every held-out
    sample, or the first ``cfg.score_samples`` of mixed batches, the same for every run."""
    def every() -> Iterator[BNNBatch]:
        return ds.batches(cfg.train.batch_size, val_ids, seed=0, epoch=0, mixed=cfg.score_samples > 0)

    if cfg.score_samples == 0:
        return every
    return functools.partial(first_samples, every, cfg.score_samples)


def study_runs(cfg: BNNStudyConfig) -> list[tuple[str, int, float]]:
    """``(name, latent size, λ)`` of every run of the study."""
    runs = [(run_name(d), d, 0.0) for d in cfg.latent_dims]
    return runs + [(run_name(max(cfg.latent_dims), lam), max(cfg.latent_dims), lam) for lam in cfg.lambdas]


def _check_study_target(cfg: BNNStudyConfig, out: Path) -> None:
    """Raise what the study would refuse in ``out`` (another config's dataset, runs that
    cannot be resumed with ``cfg``), before anything is written there."""
    if out.exists() and not out.is_dir():
        raise ConfigError(f"{out}: exists and is not a folder")
    check_collect_target(cfg.collect, out / "dataset")
    sample_shape = resolve_env_configs(cfg.collect)[0].observation.shape
    split = None
    try:
        train_ids, val_ids = _split(ShardDataset(out / "dataset"), cfg.val_fraction, cfg.train.seed)
        split = {"train_episodes": train_ids.tolist(), "val_episodes": val_ids.tolist()}
    except DatasetError:  # not collected (completely) yet: no run can have trained on it
        pass
    for name, d, lam in study_runs(cfg):
        run = out / "runs" / name
        check_run_dir(run, cfg.train.replace(lambda_distance=lam), _model_config(d, cfg.channels, cfg.model, sample_shape),
                      resume=True)
        if split is not None:
            _check_split(run, split)


def read_study_config(out: Path) -> BNNStudyConfig:
    """The config a study in ``out`` was run with; a one-line :class:`ConfigError` naming the
    file when it is unusable (``FileNotFoundError`` when missing)."""
    path = out / STUDY_CONFIG
    data = read_json(path, limit=MAX_JSON_BYTES, what="study config", error=ConfigError)
    try:
        # The dataset's stored specs stand for the spec files its config names.
        return validate(BNNStudyConfig, data, context={"specs": dataset_specs(out / "dataset")})
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None


def figures_from_study(out: str | Path) -> list[Path]:
    """Redraw the figures of a finished study directory from its saved config and report.

    Every file the figures need (config, report, each run's checkpoint and training log)
    is read and checked before the first figure is redrawn: an unusable one is a
    one-line error and leaves the figures as they were.
    """
    out = Path(out)
    try:
        cfg = read_study_config(out)
        report = read_report(out)
    except FileNotFoundError as exc:
        raise ConfigError(f"{out}: not a finished study directory (missing {Path(exc.filename).name}); run `latentdrive bnn-study {out}`") from None
    for name in report["runs"]:
        read_checkpoint(out / "runs" / name / CHECKPOINT_NAME)
        epoch_rows(out / "runs" / name)
    ds = ShardDataset(out / "dataset")
    _, val_ids = _split(ds, cfg.val_fraction, cfg.train.seed)
    from latentdrive.experiments.bnn_figures import write_bnn_figures

    return write_bnn_figures(out / "figures", {name: out / "runs" / name for name in report["runs"]},
                             held_out(ds, val_ids, cfg.eval_samples, seed=cfg.train.seed), report, cfg.train.seed)
