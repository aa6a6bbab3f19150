"""The settings of a BNN training run (:class:`BNNTrainConfig`): epochs, objective, schedules,
precision. The per-step schedules (learning rate, vehicle weight) are pure functions of the
step and the run's total, so a resumed run follows the same curves."""

from __future__ import annotations

import math
from typing import Literal

from pydantic import Field, field_validator

from latentdrive.bnn.losses import CellWeights, LossKind
from latentdrive.config import Config
from latentdrive.runtime import Precision, check_device

__all__ = ["BNNTrainConfig", "Phase"]

Phase = Literal["pretrain", "mixed"]




class BNNTrainConfig(Config):
    """Training of the bottleneck network."""

    pretrain_epochs: int = Field(
        10, ge=0, le=100_000,
        description="Epochs of plain reconstruction training on shuffled mixed data "
        "(phase 'pretrain').",
    )
    mixed_epochs: int = Field(
        90, ge=0, le=100_000,
        description="Epochs of training on batches holding every scenario, with the λ-weighted "
        "scenario-distance term (phase 'mixed'). The paper trains 100 epochs in all.",
    )
    epoch_steps: int = Field(
        0, ge=0, le=1 << 30,
        description="Batches per epoch at most (0: one pass over the training episodes). "
        "Every epoch reads the training shards in a new random order, so successive capped "
        "epochs see different parts of the training set: on a large dataset this sets how "
        "often validation runs and how many steps the schedules count without shrinking "
        "the data.",
    )
    batch_size: int = Field(
        64, ge=1, le=1 << 20,
        description="Observations per batch, samples. The batch functions decide the batches; "
        "array_batches_fn takes this value.",
    )
    lr: float = Field(1e-3, gt=0.0, le=1.0, description="AdamW (peak) learning rate, per step.")
    lr_schedule: Literal["constant", "cosine", "warmup_cosine"] = Field(
        "warmup_cosine",
        description="'constant': lr throughout. 'cosine': lr in the first epoch, then down a "
        "half cosine to lr_final_fraction·lr in the last one, set per epoch. "
        "'warmup_cosine': set per step: a linear warm-up over the first warmup_fraction of "
        "the run's steps, then a half cosine down to lr_final_fraction·lr at its last step "
        "(needs the number of steps per epoch, which train-bnn and the studies know). Both "
        "follow from the step or epoch and the totals, so a resumed run follows the same "
        "curve (unless the epoch counts change on resumption).",
    )
    lr_final_fraction: float = Field(
        0.05, ge=0.0, le=1.0,
        description="The cosine schedules' last learning rate, as a fraction of lr.",
    )
    warmup_fraction: float = Field(
        0.05, ge=0.0, lt=1.0,
        description="Share of the run's steps spent warming the learning rate up linearly "
        "('warmup_cosine' only).",
    )
    weight_decay: float = Field(
        0.0, ge=0.0, le=1.0,
        description="AdamW decoupled weight decay, per step (multiplied by lr).",
    )
    lambda_distance: float = Field(
        0.0, ge=0.0, le=1e6,
        description="λ: weight of the latent scenario-distance regularizer (mean pairwise MMD², "
        "dimensionless) in the mixed phase. 0 trains on reconstruction only.",
    )
    loss: LossKind = Field(
        "bce",
        description="Per-cell reconstruction error: 'l2' (squared error of the sigmoid output, "
        "the paper's eq. 11) or 'bce' (binary cross-entropy with the decoder's logits, which "
        "learns vehicle cells without the sigmoid's damping; see "
        "latentdrive.bnn.losses.reconstruction_error). Validation reports the plain MSE and "
        "the loss under the training weights.",
    )
    foreground_weight: float = Field(
        20.0, ge=1.0, le=1e4,
        description="Weight, in the reconstruction loss, of vehicle cells (non-zero clean target in the HV, "
        "AV and MV channels) at the first step; other cells weigh 1 (times their channel "
        "weight), and the loss is divided by the total weight. 1 with road_weight = "
        "av_weight = 1 and loss 'l2' is the paper's plain L2 (eq. 11). Vehicles cover about "
        "1% of mostly empty maps, so a plain mean is nearly minimized by drawing no vehicle "
        "at all; a weight > 1 makes missing them costly.",
    )
    foreground_weight_final: float | None = Field(
        None, ge=1.0, le=1e4,
        description="Vehicle-cell weight at the last step, reached linearly over the run's "
        "steps: a high weight buys recall early (every car drawn), a lower one precision late "
        "(no halo around them). None keeps foreground_weight throughout.",
    )
    dice_weight: float = Field(
        0.0, ge=0.0, le=100.0,
        description="Weight of a soft-Dice term over the vehicle channels added to the "
        "reconstruction loss (latentdrive.bnn.losses.vehicle_dice_loss): unlike the per-cell "
        "error it charges everything drawn off the cars, the halo that costs precision. "
        "0 (the default) leaves the loss as it was.",
    )
    road_weight: float = Field(
        0.3, gt=0.0, le=1e4,
        description="Weight of the road-layout channel's cells. The noise-free road is "
        "otherwise most of the loss (1 is the paper's plain mean).",
    )
    av_weight: float = Field(
        1.0 / 3.0, gt=0.0, le=1e4,
        description="Weight of each of the three copies of the AV channel (one per pair): "
        "1/3 makes the AV channel weigh as one channel in all; 1 is the paper's plain mean, "
        "where it counts three times.",
    )
    val_every: int = Field(
        2, ge=1, le=100_000,
        description="Validate every this many epochs, and after the last one. Validation "
        "scores every vehicle of the held-out maps, a noticeable share of a short epoch.",
    )
    val_samples: int = Field(
        0, ge=0, le=1 << 30,
        description="Held-out samples scored at each validation during training, the first "
        "ones the validation batches yield (0: all of them); train-bnn and the studies then "
        "draw validation batches that hold every scenario in proportion. Studies score their "
        "final weights apart from this, on the samples their score_samples names.",
    )
    precision: Precision = Field(
        "auto",
        description="'auto' (bf16 autocast on CPUs with AMX-BF16 whose oneDNN kernels "
        "pass a probe, fp32 elsewhere, CUDA included), 'fp32' or 'bf16'. Weights, optimizer state and losses stay float32. "
        "bf16 results are reproducible on one machine, not bitwise across machines.",
    )
    prefetch: int = Field(
        2, ge=0, le=64,
        description="Batches prepared ahead on a background thread while the model trains "
        "(0: none). Does not change results.",
    )
    max_grad_norm: float = Field(
        0.0, ge=0.0,
        description="Clip the global gradient L2 norm to this value; 0 disables clipping.",
    )
    seed: int = Field(
        0, ge=0, le=2**63 - 1,
        description="Seed of the weight initialization and of the trainer's numpy generator.",
    )
    device: str = Field(
        "auto", description="'auto' (CUDA if available, else CPU), 'cpu', 'cuda' or 'cuda:N'."
    )
    num_threads: int = Field(
        0, ge=0, le=1024,
        description="CPU threads for torch operations during the run (restored after); 0 keeps "
        "torch's default. On a shared machine fewer threads than cores avoids oversubscription, "
        "which can slow small models several-fold. Results may differ in the last bits "
        "between thread counts.",
    )
    deterministic: bool = Field(
        True,
        description="Use deterministic algorithms (strict on CPU; warn-only on CUDA, where some "
        "kernels have no deterministic variant).",
    )
    log_every: int = Field(
        10, ge=1, description="Optimizer steps between metric rows in metrics.csv and TensorBoard."
    )
    val_mmd_samples: int = Field(
        256, ge=2, le=100_000,
        description="Validation latents per scenario (samples, drawn without replacement) used "
        "for the validation scenario distance.",
    )

    _check_device = field_validator("device")(check_device)

    @property
    def total_epochs(self) -> int:
        """Pretraining plus mixed epochs."""
        return self.pretrain_epochs + self.mixed_epochs

    def _cosine(self, frac: float) -> float:
        final = self.lr_final_fraction
        return self.lr * (final + (1.0 - final) * 0.5 * (1.0 + math.cos(math.pi * frac)))

    def epoch_lr(self, epoch: int) -> float:
        """Learning rate of global epoch ``epoch`` (0-based) under the 'cosine' or 'constant' schedule."""
        if self.lr_schedule == "constant" or self.total_epochs <= 1:
            return self.lr
        return self._cosine(min(epoch, self.total_epochs - 1) / (self.total_epochs - 1))

    def step_lr(self, step: int, total_steps: int) -> float:
        """Learning rate of optimizer step ``step`` (0-based) of ``total_steps`` under 'warmup_cosine'."""
        warm = int(self.warmup_fraction * total_steps)
        if step < warm:
            return self.lr * (step + 1) / warm
        rest = total_steps - warm
        return self._cosine(min(step - warm, rest - 1) / (rest - 1)) if rest > 1 else self.lr

    def cell_weights(self, step: int, total_steps: int) -> CellWeights:
        """The loss's cell weights at step ``step`` of ``total_steps`` (see :attr:`foreground_weight_final`)."""
        fg = self.foreground_weight
        if self.foreground_weight_final is not None and total_steps > 1:
            frac = min(step, total_steps - 1) / (total_steps - 1)
            fg += (self.foreground_weight_final - fg) * frac
        return CellWeights(fg, self.road_weight, self.av_weight)

    def phase(self, epoch: int) -> Phase:
        """The phase of global epoch ``epoch`` (0-based)."""
        return "pretrain" if epoch < self.pretrain_epochs else "mixed"
