"""Validation metrics: per-scenario vehicle counts add up to the overall scores."""

from __future__ import annotations

import torch

from latentdrive.bnn.batch import BNNBatch
from latentdrive.bnn.evaluate import add_counts, evaluate_bnn, vehicle_counts_by_scenario
from latentdrive.bnn.vehicles import VehicleCounts
from latentdrive.models.bottleneck import BottleneckConfig, BottleneckNetwork


def test_counts_are_kept_per_scenario() -> None:
    clean = torch.zeros(3, 2, 1, 4, 4)
    clean[0, 0, 0, 1, 1] = 0.8  # scenario 0: one HV
    clean[1, 1, 0, 2, 2] = 0.6  # scenario 2: one AV ...
    clean[2, 0, 0, 0, 0] = 0.5  # ... and one HV
    recon = clean.clone()
    recon[2] = 0.0  # the second scenario-2 vehicle is lost
    per = vehicle_counts_by_scenario(recon, clean, torch.tensor([0, 2, 2]))
    assert per == {0: VehicleCounts(1, 1, 1, 1), 2: VehicleCounts(2, 1, 1, 1)}
    assert add_counts(per, {1: VehicleCounts(1, 0, 0, 0)}) == {
        0: VehicleCounts(1, 1, 1, 1), 1: VehicleCounts(1, 0, 0, 0), 2: VehicleCounts(2, 1, 1, 1),
    }


def test_overall_scores_are_the_sum_of_the_scenarios() -> None:
    torch.manual_seed(0)
    model = BottleneckNetwork(BottleneckConfig(input_shape=(2, 8, 8), latent_dim=4, channels=(4,)))
    clean = (torch.rand(6, 4, 2, 8, 8) > 0.9).float() * 0.7
    batch = BNNBatch(clean, clean, torch.tensor([0, 1, 0, 1, 2, 2]))
    result = evaluate_bnn(model, [batch], torch.device("cpu"), mmd_samples=2)
    total = VehicleCounts.total(result.vehicles_by_scenario.values())
    assert set(result.vehicles_by_scenario) == {0, 1, 2} and total.vehicles > 0
    assert result.metrics["val_vehicle_recall"] == total.recall
