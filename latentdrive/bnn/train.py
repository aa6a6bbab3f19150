"""Training the bottleneck network (BNN): denoising reconstruction, then mixed-scenario training.

Two phases over one global epoch counter (paper section V-B):

1. ``pretrain`` (epochs ``[0, pretrain_epochs)``): the plain denoising reconstruction loss
   on shuffled mixed-scenario data.
2. ``mixed`` (the next ``mixed_epochs``): the same loss plus ``λ · latent_regularizer``
   (mean pairwise MMD² between the scenarios of a batch, :mod:`latentdrive.bnn.distance`)
   on batches that hold every scenario. With the default ``λ = 0`` the phase differs from
   pretraining only in its batches, which is the paper's regimen.

The loss is :func:`latentdrive.bnn.losses.step_losses`: the L2 error (paper eq. 11)
between the reconstructions of the *noisy* input and the three channel pairs of the
*clean* observation. Validation is :func:`latentdrive.bnn.evaluate.evaluate_bnn`.

Everything a run writes lives in ``run_dir``: ``config.json`` (resolved configs),
``metrics.csv`` (a row every ``log_every`` steps and one per epoch), ``tb/`` (TensorBoard)
and ``checkpoint.safetensors`` (written atomically after every epoch). ``resume=True``
continues from the last checkpoint and, given the same batches per epoch, ends with the
same weights as an uninterrupted run.
"""

from __future__ import annotations

import functools
import itertools
import json
import math
import time
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch

from latentdrive.bnn.batch import BNNBatch
from latentdrive.bnn.checkpoint import (
    CheckpointError,
    load_checkpoint,
    save_checkpoint,
)
from latentdrive.bnn.evaluate import VAL_KEYS, evaluate_bnn
from latentdrive.bnn.losses import step_losses
from latentdrive.bnn.prefetch import prefetch
from latentdrive.bnn.resume import CHECKPOINT_NAME, check_run_dir, saved_configs
from latentdrive.bnn.runlog import (
    METRICS_NAME,
    Meter,
    logged_seconds,
    metrics_log,
    peak_rss_mb,
    write_metrics,
)
from latentdrive.bnn.train_config import BNNTrainConfig
from latentdrive.config import config_hash, validate
from latentdrive.fileio import atomic_write_text
from latentdrive.models.bottleneck import BottleneckConfig, BottleneckNetwork
from latentdrive.runlock import dir_lock
from latentdrive.runtime import (
    autocast,
    resolve_device,
    resolve_precision,
    torch_settings,
)

__all__ = [
    "BEST_NAME",
    "CHECKPOINT_NAME",
    "CONFIG_NAME",
    "BNNTrainConfig",
    "check_run_dir",
    "load_trained_bottleneck",
    "train_bnn",
    "validation_score",
]

CONFIG_NAME = "config.json"
#: The weights of the epoch that scored best on validation (see :func:`validation_score`),
#: which :func:`load_trained_bottleneck` loads; ``checkpoint.safetensors`` is the last
#: epoch's, which a resumed run continues from.
BEST_NAME = "best.safetensors"

# ---------------------------------------------------------------------------------------
# Training


def train_bnn(
    cfg: BNNTrainConfig,
    model_cfg: BottleneckConfig,
    train_batches_fn: Callable[[int], Iterable[BNNBatch]],
    val_batches_fn: Callable[[], Iterable[BNNBatch]] | None,
    run_dir: str | Path,
    resume: bool = False,
    progress: bool = True,
    steps_per_epoch: int | None = None,
    observation: dict[str, Any] | None = None,
) -> dict[str, float]:
    """Train a :class:`BottleneckNetwork` and return the final epoch's metrics, with
    ``resumed_s``: the seconds of the epochs a resumed run had logged before it resumed.

    ``train_batches_fn(epoch)`` yields the :class:`BNNBatch` es of global epoch ``epoch``
    (0-based; ``cfg.phase(epoch)`` tells its phase; mixed-phase batches should hold every
    scenario). For a resumed run to match an uninterrupted one, its batches must depend
    on ``epoch`` only (see :func:`latentdrive.bnn.batch.array_batches_fn`).
    ``val_batches_fn()`` yields the validation batches (``None`` skips validation).
    ``steps_per_epoch``, the number of batches an epoch yields, sizes the per-step
    schedules (learning rate, vehicle weight); when None it is counted by iterating
    ``train_batches_fn(0)`` once. With ``cfg.epoch_steps`` an epoch stops after that many
    batches, and ``steps_per_epoch`` is capped to match. With ``cfg.val_samples`` each
    validation scores that many samples of ``val_batches_fn()`` at most.

    After each validation the weights are written to ``run_dir/best.safetensors`` when
    they score best so far (:func:`validation_score`); without validation, after every
    epoch.

    ``observation``, the dump of the :class:`~latentdrive.config.ObservationConfig` the
    training maps were drawn with, is recorded with the run's configs (``config.json``
    and the checkpoints), so that a policy reading the code can check that its own maps
    are drawn the same way (:func:`latentdrive.rl.policy.encoder_config`).

    ``resume=True`` continues from ``run_dir/checkpoint.safetensors`` (a fresh start when
    there is none); the model config and all training settings except the epoch counts,
    ``log_every``, ``device``, ``num_threads`` and ``prefetch`` must equal the saved ones
    (a setting the checkpoint predates counts as its default).
    ``resume=False`` refuses (CheckpointError) a ``run_dir`` that already holds a checkpoint.

    Returned metrics: ``epoch`` (completed), ``step``, ``train_loss``, ``train_recon``,
    ``train_reg``, the validation metrics of :data:`~latentdrive.bnn.evaluate.VAL_KEYS`
    (NaN without validation), ``samples_per_s``,
    ``peak_rss_mb`` (and ``peak_cuda_mb`` on CUDA). A finished run resumed with the same
    schedule trains no further and returns the saved metrics.
    """
    run = Path(run_dir)
    if cfg.val_samples and val_batches_fn is not None:
        val_batches_fn = functools.partial(first_samples, val_batches_fn, cfg.val_samples)
    if cfg.epoch_steps:
        train_batches_fn = functools.partial(_capped, train_batches_fn, cfg.epoch_steps)
        if steps_per_epoch is not None:
            steps_per_epoch = min(steps_per_epoch, cfg.epoch_steps)
    # One process per run directory: a second one would resume from, and overwrite, the
    # first one's checkpoints.
    with dir_lock(run, "train-bnn"):
        if steps_per_epoch is None:
            steps_per_epoch = sum(1 for _ in train_batches_fn(0))
        if steps_per_epoch < 1:
            raise ValueError("train_batches_fn(0) yielded no batches")
        return _train(cfg, model_cfg, train_batches_fn, val_batches_fn, run, resume, progress,
                      steps_per_epoch, observation)


def _capped(batches_fn: Callable[[int], Iterable[BNNBatch]], steps: int, epoch: int) -> Iterable[BNNBatch]:
    """The first ``steps`` batches of ``batches_fn(epoch)``."""
    return itertools.islice(batches_fn(epoch), steps)


def first_samples(batches_fn: Callable[[], Iterable[BNNBatch]], samples: int) -> Iterator[BNNBatch]:
    """The batches of ``batches_fn()`` up to ``samples`` samples in all (the last one cut)."""
    left = samples
    for b in batches_fn():
        n = int(b.noisy.shape[0])
        yield b if n <= left else BNNBatch(b.noisy[:left], b.clean[:left], b.scenario[:left])
        left -= n
        if left <= 0:  # before the next batch is read and decoded
            return


def validation_score(metrics: dict[str, float]) -> float:
    """How good a validated epoch is: the harmonic mean (F1) of held-out vehicle recall and
    precision, so that neither a car-free map nor a bright haze scores; −∞ when undefined."""
    r, p = metrics.get("val_vehicle_recall", math.nan), metrics.get("val_vehicle_precision", math.nan)
    if not (math.isfinite(r) and math.isfinite(p)) or r + p <= 0:
        return -math.inf
    return 2 * r * p / (r + p)


def _train(
    cfg: BNNTrainConfig,
    model_cfg: BottleneckConfig,
    train_batches_fn: Callable[[int], Iterable[BNNBatch]],
    val_batches_fn: Callable[[], Iterable[BNNBatch]] | None,
    run: Path,
    resume: bool,
    progress: bool,
    steps_per_epoch: int,
    observation: dict[str, Any] | None,
) -> dict[str, float]:
    ckpt = run / CHECKPOINT_NAME
    total_steps = steps_per_epoch * cfg.total_epochs
    # The metrics logged so far are read (and checked) here, before anything is written.
    logged = check_run_dir(run, cfg, model_cfg, resume)
    device = resolve_device(cfg.device)
    dtype = resolve_precision(cfg.precision, device)
    say: Callable[[str], None] = (lambda s: print(s, flush=True)) if progress else (lambda s: None)

    with torch_settings(cfg.deterministic, device, cfg.num_threads, dtype):
        # Seeding: the model's initial weights come from torch's global generator, the
        # trainer's own draws (validation subsampling) from a numpy generator.
        torch.manual_seed(cfg.seed)
        np_rng = np.random.default_rng(cfg.seed)
        model = BottleneckNetwork(model_cfg).to(device)
        optimizer = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)

        start_epoch, step = 0, 0
        best = -math.inf
        last: dict[str, float] = {}
        resumed = False
        resumed_s = 0.0
        if resume and ckpt.exists():
            info = load_checkpoint(
                ckpt, model, optimizer,
                torch_generator=torch.default_generator, numpy_generator=np_rng,
            )
            cuda_states = sorted(k for k in info.extra_tensors if k.startswith("cuda_rng_"))
            if device.type == "cuda" and len(cuda_states) == torch.cuda.device_count():
                torch.cuda.set_rng_state_all(
                    [info.extra_tensors[f"cuda_rng_{i}"] for i in range(len(cuda_states))]
                )
            start_epoch, step = info.epoch, info.step
            resumed_s = logged_seconds(logged or [], step, run / METRICS_NAME)
            last = {k: float(v) for k, v in info.extra.get("metrics", {}).items()}
            best = float(info.extra.get("best_score", -math.inf))
            resumed = True
            say(f"resuming {ckpt} at epoch {start_epoch}, step {step}")
        elif resume:
            say(f"no checkpoint in {run}; starting a new run")

        configs = {
            "train": cfg.model_dump(mode="json"),
            "model": model_cfg.model_dump(mode="json"),
            "model_hash": config_hash(model_cfg),
            "train_hash": config_hash(cfg),
        }
        if observation is not None:
            configs["observation"] = observation
        atomic_write_text(run / CONFIG_NAME, json.dumps(configs, indent=2, sort_keys=True) + "\n")
        log = metrics_log(run, step if resumed else None, logged)
        if device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(device)

        try:
            for epoch in range(start_epoch, cfg.total_epochs):
                phase = cfg.phase(epoch)
                lam = cfg.lambda_distance if phase == "mixed" else 0.0
                if cfg.lr_schedule != "warmup_cosine":
                    for group in optimizer.param_groups:
                        group["lr"] = cfg.epoch_lr(epoch)
                model.train()
                t_epoch = time.perf_counter()
                ep, window = Meter(), Meter()
                t_prev = time.perf_counter()
                for batch in prefetch(train_batches_fn(epoch), cfg.prefetch):
                    b = batch.to(device)
                    if cfg.lr_schedule == "warmup_cosine":
                        for group in optimizer.param_groups:
                            group["lr"] = cfg.step_lr(step, total_steps)
                    with autocast(dtype, device):
                        total, recon, reg = step_losses(
                            model, b, lam, cfg.cell_weights(step, total_steps), cfg.loss, cfg.dice_weight
                        )
                    if not torch.isfinite(total):
                        raise FloatingPointError(
                            f"non-finite loss {float(total)} at step {step} (epoch {epoch})"
                        )
                    optimizer.zero_grad(set_to_none=True)
                    total.backward()
                    if cfg.max_grad_norm > 0:
                        torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.max_grad_norm)
                    optimizer.step()
                    step += 1
                    # One device-to-host copy for the three logged values.
                    vals = torch.stack([total, recon, reg]).detach().double().cpu().numpy()
                    # Throughput counts fetching the batch as well as the step: the rate the
                    # whole loop runs at (logging, validation and checkpoints excluded).
                    dt = time.perf_counter() - t_prev
                    ep.add(vals, int(b.noisy.shape[0]), dt)
                    window.add(vals, int(b.noisy.shape[0]), dt)
                    if step % cfg.log_every == 0:
                        loss_m, recon_m, reg_m = window.means()
                        write_metrics(log, {
                            "kind": "step", "phase": phase, "epoch": epoch, "step": step,
                            "loss": loss_m, "recon": recon_m, "reg": reg_m,
                            "lr": optimizer.param_groups[0]["lr"],
                            "samples_per_s": window.rate(),
                        })
                        window = Meter()
                    t_prev = time.perf_counter()
                if ep.batches == 0:
                    raise ValueError(f"train_batches_fn({epoch}) yielded no batches")

                val: dict[str, float] = dict.fromkeys(VAL_KEYS, float("nan"))
                validate_now = (epoch + 1) % cfg.val_every == 0 or epoch + 1 == cfg.total_epochs
                if val_batches_fn is not None and validate_now:
                    val = evaluate_bnn(
                        model, val_batches_fn(), device,
                        mmd_samples=cfg.val_mmd_samples, rng=np_rng, dtype=dtype,
                        weights=cfg.cell_weights(step - 1, total_steps), loss=cfg.loss, dice=cfg.dice_weight,
                    ).metrics
                elapsed = time.perf_counter() - t_epoch
                train_loss, train_recon, train_reg = ep.means()
                last = {
                    "epoch": float(epoch + 1),
                    "step": float(step),
                    "train_loss": train_loss,
                    "train_recon": train_recon,
                    "train_reg": train_reg,
                    **val,
                    "samples_per_s": ep.rate(),
                    "peak_rss_mb": peak_rss_mb(),
                }
                if device.type == "cuda":
                    last["peak_cuda_mb"] = torch.cuda.max_memory_allocated(device) / 2**20
                write_metrics(log, {
                    "kind": "epoch", "phase": phase, "epoch": epoch, "step": step,
                    "loss": last["train_loss"], "recon": last["train_recon"],
                    "reg": last["train_reg"],
                    "lr": optimizer.param_groups[0]["lr"], **val,
                    "samples_per_s": last["samples_per_s"],
                    "peak_rss_mb": last["peak_rss_mb"], "peak_cuda_mb": last.get("peak_cuda_mb"),
                    "elapsed_s": elapsed,
                })
                extra_tensors = {}
                if device.type == "cuda":
                    states = torch.cuda.get_rng_state_all()
                    extra_tensors = {f"cuda_rng_{i}": st for i, st in enumerate(states)}
                validated = val_batches_fn is not None and validate_now
                score = validation_score(val) if validated else -math.inf
                # The first validated epoch is kept whatever it scores (a map with no bright
                # cell scores −∞), so that best.safetensors exists once anything validated.
                is_best = val_batches_fn is None or (
                    validated and (score > best or not (run / BEST_NAME).exists()))
                best = max(best, score)
                if is_best:
                    # Written before the checkpoint: a run cut off between the two resumes
                    # from the previous checkpoint and redoes this epoch, writing it again.
                    save_checkpoint(run / BEST_NAME, model, step=step, epoch=epoch + 1, config=configs,
                                    extra={"metrics": last})
                save_checkpoint(
                    ckpt, model, optimizer, step=step, epoch=epoch + 1, config=configs,
                    torch_generator=torch.default_generator, numpy_generator=np_rng,
                    extra={"metrics": last, "best_score": best}, extra_tensors=extra_tensors,
                )
                mem = f"peak rss {last['peak_rss_mb']:.0f} MB"
                if "peak_cuda_mb" in last:
                    mem += f", cuda {last['peak_cuda_mb']:.0f} MB"
                if validated:
                    held_out = (f"val {val['val_loss']:.5f} (objective {val['val_train_loss']:.5f}, "
                                f"vehicle cells {val['val_vehicle_l2']:.4f}, "
                                f"recall {val['val_vehicle_recall']:.2f}, "
                                f"precision {val['val_vehicle_precision']:.2f}) "
                                f"mmd {val['val_mmd']:.4f}{' (best)' if is_best else ''}")
                elif val_batches_fn is not None:
                    # Not "val nan": nothing went wrong, this epoch was not validated.
                    held_out = f"not validated (every {cfg.val_every} epochs and the last)"
                else:
                    held_out = "no validation data"
                say(
                    f"epoch {epoch + 1}/{cfg.total_epochs} [{phase}] step {step} "
                    f"loss {last['train_loss']:.5f} (recon {last['train_recon']:.5f}, "
                    f"reg {last['train_reg']:.4f}) {held_out} | "
                    f"{last['samples_per_s']:.0f} samples/s | {elapsed:.1f} s | {mem}"
                )
        finally:
            log.close()
    # resumed_s: the epochs' seconds of the sessions this one resumed from, so that a run
    # cut off and resumed reports what it cost (less what the cut-off session redid).
    return {**last, "resumed_s": round(resumed_s, 2)}


def load_trained_bottleneck(
    run_dir: str | Path, device: str | torch.device = "cpu"
) -> BottleneckNetwork:
    """The trained network of ``run_dir`` in eval mode with frozen parameters: the weights
    that scored best on validation (``best.safetensors``), or the last checkpoint's for a
    run written before best weights were kept.

    Its model config is taken from the checkpoint itself. Raises :class:`CheckpointError`
    when the checkpoint is missing, corrupt, or does not match its own config.
    """
    last = Path(run_dir) / CHECKPOINT_NAME
    if not last.exists():
        raise CheckpointError(f"{last}: no checkpoint in {run_dir}")
    ckpt = Path(run_dir) / BEST_NAME
    if not ckpt.exists():
        ckpt = last
    saved = saved_configs(Path(run_dir))
    if not isinstance(saved, dict):
        raise CheckpointError(f"{ckpt}: holds no training config (not a BNN checkpoint)")
    try:
        model_cfg = validate(BottleneckConfig, saved["model"])
    except (KeyError, TypeError, ValueError) as exc:
        raise CheckpointError(f"{ckpt}: unusable model config ({exc})") from None
    model = BottleneckNetwork(model_cfg)
    load_checkpoint(ckpt, model)
    model.eval().requires_grad_(False)
    return model.to(device)
