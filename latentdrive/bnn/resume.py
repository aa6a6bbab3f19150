"""Whether a BNN run directory may be (re)started: what a checkpoint there allows."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from latentdrive.bnn.checkpoint import CheckpointError, read_checkpoint
from latentdrive.bnn.runlog import read_metrics
from latentdrive.config import Config
from latentdrive.models.bottleneck import BottleneckConfig

__all__ = ["CHECKPOINT_NAME", "check_resumable", "check_run_dir", "saved_configs"]

CHECKPOINT_NAME = "checkpoint.safetensors"
# Fields that may change between a run and its resumption: they extend the schedule or
# change logging only, not the computation of the epochs already done.
_RESUMABLE_CHANGES = frozenset(
    {"pretrain_epochs", "mixed_epochs", "log_every", "device", "num_threads", "prefetch"}
)


def saved_configs(run_dir: Path) -> dict[str, Any] | None:
    p = run_dir / CHECKPOINT_NAME
    if not p.exists():
        return None
    config: dict[str, Any] | None = read_checkpoint(p)[1].get("config")
    return config


def changed_fields(saved: Any, cfg: Config, ignore: frozenset[str] = frozenset()) -> list[str]:
    """Fields of ``cfg`` whose value differs from the saved JSON dump ``saved``, as
    ``name (saved → now)``. A field missing from ``saved`` (a checkpoint written before the
    field existed) counts as its default, which is what that run used."""
    old = saved if isinstance(saved, dict) else {}
    new = cfg.model_dump(mode="json")
    defaults = type(cfg)().model_dump(mode="json")
    return [
        f"{k} ({old.get(k, defaults[k])} → {new[k]})"
        for k in sorted(new)
        if k not in ignore and old.get(k, defaults[k]) != new[k]
    ]


def check_resumable(
    ckpt: Path, saved: dict[str, Any], cfg: Config, model_cfg: BottleneckConfig
) -> None:
    changed = changed_fields(saved.get("model"), model_cfg)
    if changed:
        raise CheckpointError(
            f"{ckpt}: checkpoint was made with another model config ({', '.join(changed)}); "
            "pass the saved values or use a new run_dir"
        )
    changed = changed_fields(saved.get("train"), cfg, _RESUMABLE_CHANGES)
    if changed:
        raise CheckpointError(
            f"{ckpt}: checkpoint was made with other training settings ({', '.join(changed)}); "
            "pass the saved values or use a new run_dir"
        )


def check_run_dir(run_dir: str | Path, cfg: Config, model_cfg: BottleneckConfig,
                  resume: bool) -> list[dict[str, str]] | None:
    """Raise what :func:`train_bnn` would refuse in ``run_dir``, writing nothing.

    Returns the rows of the run's metrics.csv when the run resumes from a checkpoint
    (see :func:`~latentdrive.bnn.runlog.read_metrics`), None when it starts afresh.

    A run directory holding a checkpoint is refused without ``resume``, and with it when
    the checkpoint is unreadable or was made with another model config or other training
    settings (see :func:`train_bnn`), or when the run's metrics.csv, which the resumed run
    rewrites, is damaged. Callers that write files of their own into the run
    directory check first, so that a refused run leaves them as they were.
    """
    ckpt = Path(run_dir) / CHECKPOINT_NAME
    if not ckpt.exists():
        return None
    if not resume:
        raise CheckpointError(
            f"{ckpt} exists: resume it (resume=True, --resume) or choose a new run directory"
        )
    saved = read_checkpoint(ckpt)[1].get("config")
    if not isinstance(saved, dict):
        raise CheckpointError(f"{ckpt}: not a BNN checkpoint (no saved configs)")
    check_resumable(ckpt, saved, cfg, model_cfg)
    return read_metrics(Path(run_dir))
