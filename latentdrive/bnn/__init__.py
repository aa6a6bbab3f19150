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
from latentdrive.bnn.evaluate import evaluate_bnn
from latentdrive.bnn.losses import reconstruction_loss, step_losses
from latentdrive.bnn.train import BNNTrainConfig, load_trained_bottleneck, train_bnn
from latentdrive.bnn.vehicles import VehicleCounts, label_blobs, vehicle_counts

__all__ = [
    "BNNBatch",
    "BNNTrainConfig",
    "CheckpointError",
    "CheckpointInfo",
    "VehicleCounts",
    "array_batches_fn",
    "distance_matrix",
    "evaluate_bnn",
    "group_mmd2",
    "iterate_batches",
    "label_blobs",
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
    "vehicle_counts",
]
