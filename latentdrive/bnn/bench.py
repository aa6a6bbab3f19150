"""``latentdrive bench --bottleneck``: how fast the BNN trains, per precision, in one run.

Two rates per precision (``fp32`` and ``bf16``, :mod:`latentdrive.runtime`):

- **network**: samples/s of the optimizer step alone (forward, loss, backward, AdamW) on
  one batch held in memory: the rate the hardware allows this network;
- **loop**: samples/s of :func:`latentdrive.bnn.train.train_bnn` over an epoch of
  batches, as its ``metrics.csv`` reports it (batch preparation included, validation and
  checkpoints excluded): the rate a training run gets.

Batches are :func:`~latentdrive.bnn.batch.synthetic_dataset` maps of the observation's
shape (the cost does not depend on the content). Ratios are of rates measured in the same
process, seconds apart.
"""

from __future__ import annotations

import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

from latentdrive.bnn.batch import BNNBatch, array_batches_fn, synthetic_dataset
from latentdrive.bnn.losses import step_losses
from latentdrive.bnn.train import BNNTrainConfig, train_bnn
from latentdrive.models.bottleneck import BottleneckConfig, BottleneckNetwork
from latentdrive.runtime import (
    PRECISIONS,
    autocast,
    cpu_bf16_gradients_sound,
    cpu_has_bf16,
    resolve_device,
    resolve_precision,
    torch_settings,
)

__all__ = ["BottleneckBenchRow", "bench_bottleneck", "bench_precisions", "format_bottleneck_bench"]


def bench_precisions(spec: str, device: torch.device) -> tuple[str, ...]:
    """The precisions ``bench --bottleneck`` measures for ``--set precision=spec``.

    ``auto``: fp32, and bf16 where ``auto`` resolves to it (a CPU with AMX-BF16; on
    CUDA ``bf16`` measures it). Elsewhere bf16 is slower than fp32 (emulated, or without oneDNN where its
    bf16 kernels are unsound), and its pass would take long to tell only that: ``bf16``
    measures it anyway. ``fp32``: fp32 only.
    """
    if spec not in PRECISIONS:
        raise ValueError(f"precision must be one of {', '.join(PRECISIONS)}, got {spec!r}")
    native = resolve_precision(spec if spec == "auto" else "fp32", device) == torch.bfloat16
    if spec == "bf16" or (spec == "auto" and native):
        return ("fp32", "bf16")
    return ("fp32",)


@dataclass(frozen=True)
class BottleneckBenchRow:
    """One precision's measurements."""

    precision: str
    batch_size: int
    network_samples_per_s: float
    loop_samples_per_s: float

    def as_dict(self) -> dict[str, float | int | str]:
        return asdict(self)


def _network_rate(model_cfg: BottleneckConfig, cfg: BNNTrainConfig, batch: BNNBatch, steps: int,
                  device: torch.device, dtype: torch.dtype) -> float:
    torch.manual_seed(cfg.seed)
    model = BottleneckNetwork(model_cfg).to(device)
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr)
    b = batch.to(device)
    weights = cfg.cell_weights(0, 1)

    def step() -> None:
        with autocast(dtype, device):
            total, _, _ = step_losses(model, b, 0.0, weights, cfg.loss, cfg.dice_weight)
        opt.zero_grad(set_to_none=True)
        total.backward()
        opt.step()

    step()  # warm-up: first-call allocations and kernel selection
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    t0 = time.perf_counter()
    for _ in range(steps):
        step()
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    return steps * b.noisy.shape[0] / (time.perf_counter() - t0)


def bench_bottleneck(
    model_cfg: BottleneckConfig,
    *,
    batch_size: int = 64,
    steps: int = 20,
    precisions: tuple[str, ...] = ("fp32", "bf16"),
    threads: int = 1,
    device: str = "auto",
    seed: int = 0,
) -> list[BottleneckBenchRow]:
    """Network and loop samples/s of ``model_cfg`` per precision; ``steps`` optimizer
    steps of ``batch_size`` samples are timed for each rate."""
    if steps < 1 or batch_size < 1:
        raise ValueError(f"need steps and batch_size >= 1, got {steps} and {batch_size}")
    dev = resolve_device(device)
    clean, noisy, scenario = synthetic_dataset(batch_size * steps, model_cfg.observation_shape, 3, seed=seed)
    one = BNNBatch(torch.from_numpy(noisy[:batch_size]), torch.from_numpy(clean[:batch_size]),
                   torch.from_numpy(scenario[:batch_size]))
    rows = []
    for precision in precisions:
        cfg = BNNTrainConfig.model_validate({
            "pretrain_epochs": 1, "mixed_epochs": 0, "batch_size": batch_size, "precision": precision,
            "device": device, "num_threads": threads, "log_every": max(1, steps), "seed": seed,
        })
        dtype = resolve_precision(precision, dev)
        with torch_settings(cfg.deterministic, dev, threads, dtype):
            net = _network_rate(model_cfg, cfg, one, steps, dev, dtype)
        fn = array_batches_fn(clean, noisy, scenario, batch_size=batch_size, seed=seed)
        with tempfile.TemporaryDirectory() as tmp:
            metrics = train_bnn(cfg, model_cfg, fn, None, Path(tmp) / "run", progress=False, steps_per_epoch=steps)
        rows.append(BottleneckBenchRow(precision, batch_size, net, float(metrics["samples_per_s"])))
    return rows


def format_bottleneck_bench(rows: list[BottleneckBenchRow], model_cfg: BottleneckConfig, threads: int) -> str:
    """The rows as a table, with each precision's speed relative to the first row's."""
    base = rows[0]
    units = "AMX-BF16 present" if cpu_has_bf16() else "no AMX-BF16 on this CPU"
    if cpu_has_bf16() and not cpu_bf16_gradients_sound():
        units += ", its oneDNN bf16 gradients unsound"
    lines = [
        f"BNN training, d = {model_cfg.latent_dim}, channels {list(model_cfg.channels)}, "
        f"observations {model_cfg.observation_shape}, batch {base.batch_size}, {threads} thread(s); {units}",
        "| precision | network samples/s | × | loop samples/s | × |",
        "|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r.precision} | {r.network_samples_per_s:.0f} | "
            f"{r.network_samples_per_s / base.network_samples_per_s:.2f} | {r.loop_samples_per_s:.0f} | "
            f"{r.loop_samples_per_s / base.loop_samples_per_s:.2f} |"
        )
    return "\n".join(lines)
