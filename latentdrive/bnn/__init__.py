"""Bottleneck-network training: the scenario distance, checkpoints and the training loop."""

from latentdrive.bnn.batch import BNNBatch, array_batches_fn, iterate_batches, synthetic_dataset
from latentdrive.bnn.checkpoint import (
    CheckpointError,
    CheckpointInfo,
    load_checkpoint,
    read_checkpoint,
    save_checkpoint,
)
from latentdrive.bnn.distance import (
    distance_matrix,
    group_mmd2,
    latent_regularizer,
    median_bandwidth,
    mmd2,
)
from latentdrive.bnn.train import (
    BNNTrainConfig,
    evaluate_bnn,
    load_trained_bottleneck,
    reconstruction_loss,
    step_losses,
    train_bnn,
)

__all__ = [
    "BNNBatch",
    "BNNTrainConfig",
    "CheckpointError",
    "CheckpointInfo",
    "array_batches_fn",
    "distance_matrix",
    "evaluate_bnn",
    "group_mmd2",
    "iterate_batches",
    "latent_regularizer",
    "load_checkpoint",
    "load_trained_bottleneck",
    "median_bandwidth",
    "mmd2",
    "read_checkpoint",
    "reconstruction_loss",
    "save_checkpoint",
    "step_losses",
    "synthetic_dataset",
    "train_bnn",
]
