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

import json
import math
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from pydantic import Field, ValidationError, field_validator
from torch import Tensor

from latentdrive.bnn.batch import BNNBatch
from latentdrive.bnn.checkpoint import read_checkpoint
from latentdrive.bnn.distance import distance_matrix
from latentdrive.bnn.evaluate import add_counts, evaluate_bnn, vehicle_counts_by_scenario
from latentdrive.bnn.train import (
    CHECKPOINT_NAME,
    BNNTrainConfig,
    check_run_dir,
    load_trained_bottleneck,
    train_bnn,
)
from latentdrive.bnn.vehicles import REACH_CELLS, VehicleCounts, bright_cell_reach
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
from latentdrive.experiments.bnn_report import epoch_rows, read_report
from latentdrive.experiments.heldout import HeldOut, held_out
from latentdrive.experiments.processes import Job, run_processes
from latentdrive.fileio import MAX_JSON_BYTES, atomic_write_text, read_json
from latentdrive.models.bottleneck import BottleneckConfig, BottleneckNetwork, channel_pairs
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
                         steps_per_epoch=steps)


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


@torch.no_grad()
def encode(model: BottleneckNetwork, x: np.ndarray, batch: int = 128) -> np.ndarray:
    """Latents ``(n, 3·d)`` of observations ``x`` ``(n, 4, T, H, W)``."""
    out = [model.encode(torch.from_numpy(x[i:i + batch])).flatten(1).numpy() for i in range(0, len(x), batch)]
    return np.concatenate(out) if out else np.zeros((0, model.latent_size), np.float32)


@torch.no_grad()
def reconstruct(model: BottleneckNetwork, x: np.ndarray) -> np.ndarray:
    """Reconstructions ``(n, 3, 2, T, H, W)`` of noisy observations ``x``."""
    return model(torch.from_numpy(x))[0].numpy()


def raw_features(x: np.ndarray, pool: int) -> np.ndarray:
    """The raw-input baseline space: ``x`` average-pooled by ``pool`` over H, W and flattened."""
    t = torch.from_numpy(x)
    n, _c, _tt, _h, _w = t.shape
    pooled = F.avg_pool3d(t, kernel_size=(1, pool, pool), ceil_mode=True) if pool > 1 else t
    return pooled.reshape(n, -1).numpy()


def _mean_offdiag(m: np.ndarray) -> float:
    s = m.shape[0]
    return float(m[~np.eye(s, dtype=bool)].mean()) if s > 1 else float("nan")


def _finite_or_none(v: float) -> float | None:
    return v if math.isfinite(v) else None


def _fmt(v: float | None, spec: str) -> str:
    return "–" if v is None or not math.isfinite(v) else format(v, spec)


def _recall_by_name(ds: ShardDataset, per: dict[int, VehicleCounts]) -> dict[str, float | None]:
    return {ds.scenario_names[s]: _finite_or_none(c.recall) for s, c in per.items() if c.vehicles}


def input_vehicle_recovery(ds: ShardDataset, val_ids: np.ndarray, batch_size: int) -> dict[str, Any]:
    """The noisy input scored as if it were a reconstruction of the clean target, over the
    held-out episodes: the reference for the runs' vehicle scores
    (:mod:`latentdrive.bnn.vehicles`). Returns ``vehicle_recall``, ``vehicle_precision``,
    ``vehicles`` and ``by_scenario`` (name → recall); undefined values are None.
    """
    per: dict[int, VehicleCounts] = {}
    for b in ds.batches(batch_size, val_ids, seed=0, epoch=0, mixed=False):
        per = add_counts(per, vehicle_counts_by_scenario(channel_pairs(b.noisy)[:, 0], channel_pairs(b.clean)[:, 0],
                                                         b.scenario))
    total = VehicleCounts.total(per.values())
    return {"vehicle_recall": _finite_or_none(total.recall),
            "vehicle_precision": _finite_or_none(total.precision), "vehicles": total.vehicles,
            "by_scenario": _recall_by_name(ds, per)}


@torch.no_grad()
def drawn_cell_reach(data: HeldOut, draw: Callable[[Tensor], Tensor], batch: int = 128) -> dict[str, float | None]:
    """Share of drawn vehicle cells within k cells of a real vehicle of their frame and
    channel, for each k of :data:`~latentdrive.bnn.vehicles.REACH_CELLS`, over the samples
    of ``data``: ``{"1": share, "2": share, ...}`` (None when nothing is drawn).

    ``draw`` maps noisy observations ``(B, 4, T, H, W)`` to the HV+AV pair it draws,
    ``(B, 2, T, H, W)`` in [0, 1]; cells ≥ 0.25 count as drawn. See :func:`reach_references`
    for the noisy input and chance.
    """
    bright, within = 0, np.zeros(len(REACH_CELLS), np.int64)
    h, w = data.clean.shape[-2:]
    for i in range(0, len(data.scenario), batch):
        noisy, clean = torch.from_numpy(data.noisy[i:i + batch]), torch.from_numpy(data.clean[i:i + batch])
        b, k = bright_cell_reach(draw(noisy).reshape(-1, h, w), channel_pairs(clean)[:, 0].reshape(-1, h, w))
        bright += b
        within += np.asarray(k)
    return {str(k): (float(n) / bright if bright else None) for k, n in zip(REACH_CELLS, within.tolist(), strict=True)}


def reach_references(data: HeldOut) -> dict[str, dict[str, float | None]]:
    """:func:`drawn_cell_reach` of two references: the noisy input itself (``"input"``) and
    a map drawn bright everywhere (``"every cell"``: the share of all HV and AV cells within
    k cells of a vehicle, what drawing at random would score)."""
    def pair(x: Tensor) -> Tensor:
        return channel_pairs(x)[:, 0]

    return {"input": drawn_cell_reach(data, pair),
            "every cell": drawn_cell_reach(data, lambda x: torch.ones_like(pair(x)))}


def evaluate_run(run_dir: Path, data: HeldOut, ds: ShardDataset, val_ids: np.ndarray, batch_size: int) -> dict[str, Any]:
    """Held-out reconstruction error and latent scenario distances of one trained run."""
    model = load_trained_bottleneck(run_dir)
    metrics, per = evaluate_bnn(model, ds.batches(batch_size, val_ids, seed=0, epoch=0, mixed=False),
                                         torch.device("cpu"), mmd_samples=2)
    names, lat = distance_matrix(data.by_scenario(encode(model, data.noisy)))
    return {"val_recon": metrics["val_loss"], "val_vehicle_l2": metrics["val_vehicle_l2"],
            # None, not NaN, when undefined (no vehicles, nothing drawn): JSON has no NaN.
            "vehicle_recall": _finite_or_none(metrics["val_vehicle_recall"]),
            "vehicle_precision": _finite_or_none(metrics["val_vehicle_precision"]),
            "vehicle_recall_by_scenario": _recall_by_name(ds, per),
            "drawn_cells_within": drawn_cell_reach(data, lambda x: model(x)[0][:, 0]),
            "latent_scenarios": names, "latent_distance": lat.tolist(),
            "mean_between_scenario_distance": _mean_offdiag(lat)}


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
            f"{_fmt(_finite_or_none(m.get('val_vehicle_recall', math.nan)), '.3f')}, precision "
            f"{_fmt(_finite_or_none(m.get('val_vehicle_precision', math.nan)), '.3f')}")

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
    names, raw = distance_matrix(data.by_scenario(raw_features(data.noisy, cfg.raw_pool)))
    report: dict[str, Any] = {
        "dataset_samples": len(ds), "held_out_samples": len(data.scenario),
        "raw_scenarios": names, "raw_distance": raw.tolist(), "raw_mean_between_scenario_distance": _mean_offdiag(raw),
        "noisy_input_vehicles": {**input_vehicle_recovery(ds, val_ids, cfg.train.batch_size),
                                 "drawn_cells_within": (refs := reach_references(data))["input"]},
        "every_cell_within": refs["every cell"],
        "runs": {},
    }
    for name, (run, d, lam) in runs.items():
        report["runs"][name] = {"latent_dim": d, "lambda": lam,
                                **evaluate_run(run, data, ds, val_ids, cfg.train.batch_size)}
    report = json_values(report)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "report.json", json.dumps(report, indent=1, allow_nan=False) + "\n")
    atomic_write_text(out / "report.md", format_report(report))

    say(f"[4/4] figures -> {out / 'figures'}")
    # Imported here: matplotlib is needed only once figures are drawn, not by train-bnn.
    from latentdrive.experiments.bnn_figures import write_bnn_figures

    write_bnn_figures(out / "figures", {name: run for name, (run, _, _) in runs.items()}, data, report, cfg.train.seed)
    return report


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


def _matrix_md(names: list[str], m: list[list[float]]) -> str:
    lines = ["| | " + " | ".join(names) + " |", "|---" * (len(names) + 1) + "|"]
    lines += [f"| {n} | " + " | ".join(f"{v:.3f}" for v in row) + " |" for n, row in zip(names, m, strict=True)]
    return "\n".join(lines)


def _recall_table(report: dict[str, Any]) -> list[str]:
    """Vehicles recovered per scenario and run (Markdown), when the report has them."""
    rows = {n: r.get("vehicle_recall_by_scenario") for n, r in report["runs"].items()}
    ref = (report.get("noisy_input_vehicles") or {}).get("by_scenario")
    if ref:
        rows = {"noisy input (reference)": ref, **rows}
    rows = {n: r for n, r in rows.items() if r}
    if not rows:
        return []
    scen = list(next(iter(rows.values())))
    lines = ["", "## Held-out vehicles recovered, per scenario", "",
             "| run | " + " | ".join(scen) + " |", "|---" * (len(scen) + 1) + "|"]
    lines += [f"| {n} | " + " | ".join(_fmt(r.get(s), ".1%") for s in scen) + " |" for n, r in rows.items()]
    return lines


def _reach_table(report: dict[str, Any]) -> list[str]:
    """Where each run's drawn vehicle cells lie (absent from reports written before it was measured)."""
    rows = {n: r["drawn_cells_within"] for n, r in report["runs"].items() if r.get("drawn_cells_within")}
    if not rows:
        return []
    ref = report.get("noisy_input_vehicles") or {}
    if ref.get("drawn_cells_within"):
        rows["noisy input (reference)"] = ref["drawn_cells_within"]
    if report.get("every_cell_within"):
        rows["every cell (chance)"] = report["every_cell_within"]
    ks = [str(k) for k in REACH_CELLS]
    return ["", "## Where the drawn vehicle cells lie", "",
            f"Share of reconstructed HV and AV cells ≥ 0.25 within k cells of a real vehicle, on the "
            f"{report['held_out_samples']} held-out samples of the figures (k = 1 is the precision above, "
            "on these samples). The chance row is the share of all cells within k cells of a vehicle: what "
            "cells drawn at random would score.", "",
            "| run | " + " | ".join(f"≤ {k} cell{'s' if k != '1' else ''}" for k in ks) + " |",
            "|---" * (len(ks) + 1) + "|"] + [
        f"| {n} | " + " | ".join(_fmt(r.get(k), ".1%") for k in ks) + " |" for n, r in rows.items()]


def format_report(report: dict[str, Any]) -> str:
    """The study's findings as Markdown tables."""
    runs = report["runs"]
    lines = [
        "# Bottleneck network study",
        "",
        f"Dataset: {report['dataset_samples']} samples; whole episodes held out. Reconstruction error and "
        f"vehicles are scored on every held-out sample, scenario distances and figures on "
        f"{report['held_out_samples']} of them.",
        "",
        "## Reconstruction error and scenario distance per run",
        "",
        "| run | d | λ | held-out L2 (mean per element) | held-out L2 on vehicle cells "
        "| vehicles recovered | precision of bright cells | mean between-scenario MMD² (latent) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    lines += [f"| {n} | {r['latent_dim']} | {r['lambda']:g} | {_fmt(r['val_recon'], '.6f')} | {_fmt(r.get('val_vehicle_l2'), '.4f')} "
              f"| {_fmt(r.get('vehicle_recall'), '.1%')} | {_fmt(r.get('vehicle_precision'), '.1%')} "
              f"| {_fmt(r['mean_between_scenario_distance'], '.4f')} |" for n, r in runs.items()]
    ref = report.get("noisy_input_vehicles")
    if ref is not None:
        lines += [f"| noisy input (reference) | – | – | – | – | {_fmt(ref['vehicle_recall'], '.1%')} "
                  f"| {_fmt(ref['vehicle_precision'], '.1%')} | – |"]
    lines += _recall_table(report)
    lines += ["", "A vehicle (a blob of cells in a clean HV or AV frame) is *recovered* when the "
              "reconstruction reaches half its peak value on it or within one cell of it; *precision* is "
              "the share of reconstructed cells ≥ 0.25 within one cell of a real vehicle "
              "(`latentdrive.bnn.vehicles`). The reference row scores the noisy input itself as a "
              "reconstruction of the clean target."]
    lines += _reach_table(report)
    lines += ["", f"Raw-input baseline space: mean between-scenario MMD² {_fmt(report['raw_mean_between_scenario_distance'], '.4f')}.",
              "", "## Scenario distance (MMD²), raw-input baseline space", "",
              _matrix_md(report["raw_scenarios"], report["raw_distance"])]
    for n, r in runs.items():
        lines += ["", f"## Scenario distance (MMD²), latent space of {n}", "",
                  _matrix_md(r["latent_scenarios"], r["latent_distance"])]
    return "\n".join(lines) + "\n"
