"""Vehicle recovery scores on hand-drawn maps."""

from __future__ import annotations

import math

import pytest
import torch

from latentdrive.bnn.vehicles import VehicleCounts, bright_cell_reach, label_blobs, vehicle_counts


def _maps() -> torch.Tensor:
    """Two frames of 6 × 8: frame 0 holds a 3×1 car and an L-shaped pair touching only at
    a corner (one blob under 8-connectivity); frame 1 a single 1×2 car."""
    t = torch.zeros(2, 6, 8)
    t[0, 1:4, 1] = 0.8  # vertical car, rows 1-3, column 1
    t[0, 1, 5] = 0.6
    t[0, 2, 6] = 0.6  # diagonal neighbour of (1, 5)
    t[1, 4, 3:5] = 0.4
    return t


def test_label_blobs_finds_8_connected_blobs_per_frame() -> None:
    labels = label_blobs(_maps() > 0)
    assert labels[0, 0, 0] == 0
    car = labels[0, 1:4, 1]
    assert torch.all(car == car[0]) and car[0] > 0
    assert labels[0, 1, 5] == labels[0, 2, 6] > 0
    assert labels[0, 1, 5] != car[0]
    assert torch.all(labels[1, 4, 3:5] == labels[1, 4, 3]) and labels[1, 4, 3] > 0
    assert int(torch.unique(labels[labels > 0]).numel()) == 3


def test_blobs_in_different_frames_never_merge() -> None:
    mask = torch.zeros(2, 4, 4, dtype=torch.bool)
    mask[:, 1, 1] = True  # same cell in both frames
    labels = label_blobs(mask)
    assert labels[0, 1, 1] != labels[1, 1, 1]


def test_perfect_reconstruction_recovers_every_vehicle() -> None:
    t = _maps()
    c = vehicle_counts(t.clone(), t)
    assert c == VehicleCounts(vehicles=3, recovered=3, bright_cells=7, bright_on_vehicles=7)
    assert c.recall == 1.0 and c.precision == 1.0


def test_empty_reconstruction_recovers_none() -> None:
    c = vehicle_counts(torch.zeros(2, 6, 8), _maps())
    assert c.vehicles == 3 and c.recovered == 0 and c.recall == 0.0
    assert math.isnan(c.precision)


def test_a_faded_car_counts_down_to_half_its_peak() -> None:
    t = _maps()
    r = t.clone()
    r[0, 1:4, 1] = 0.4  # exactly half of 0.8: recovered
    r[1, 4, 3:5] = 0.19  # just under half of 0.4: lost
    c = vehicle_counts(r, t)
    assert c.recovered == 2


def test_a_car_drawn_elsewhere_is_lost_and_lowers_precision() -> None:
    t = torch.zeros(1, 6, 8)
    t[0, 1, 1:3] = 1.0
    r = torch.zeros(1, 6, 8)
    r[0, 4, 5:7] = 1.0  # same car, three rows down and four columns right
    c = vehicle_counts(r, t)
    assert c == VehicleCounts(vehicles=1, recovered=0, bright_cells=2, bright_on_vehicles=0)


def test_painting_everything_bright_recalls_all_but_is_imprecise() -> None:
    t = _maps()
    c = vehicle_counts(torch.ones_like(t), t)
    assert c.recall == 1.0
    # Cells within one cell of a vehicle: 5×3 around the car, two overlapping 3×3 squares
    # (9 + 9 - 4) around the corner pair, 3×4 around frame 1's car.
    assert c.bright_cells == 96 and c.bright_on_vehicles == 15 + 14 + 12


def test_counts_add_up_over_batches() -> None:
    t = _maps()
    whole = vehicle_counts(t * 0.7, t)
    parts = vehicle_counts(t[:1] * 0.7, t[:1]).plus(vehicle_counts(t[1:] * 0.7, t[1:]))
    assert whole == parts


def test_shape_mismatch_is_refused() -> None:
    with pytest.raises(ValueError, match="equal"):
        vehicle_counts(torch.zeros(1, 4, 4), torch.zeros(1, 4, 5))


def test_a_car_one_cell_off_counts_within_the_tolerance_only() -> None:
    t = torch.zeros(1, 6, 8)
    t[0, 2, 2:4] = 0.8
    r = torch.zeros(1, 6, 8)
    r[0, 3, 3:5] = 0.8  # one row down, one column right
    assert vehicle_counts(r, t, tolerance=1) == VehicleCounts(1, 1, 2, 2)
    assert vehicle_counts(r, t, tolerance=0) == VehicleCounts(1, 0, 2, 0)
    with pytest.raises(ValueError, match="tolerance"):
        vehicle_counts(r, t, tolerance=-1)


def test_total_adds_field_by_field() -> None:
    parts = [VehicleCounts(3, 2, 10, 7), VehicleCounts(1, 1, 0, 0)]
    assert VehicleCounts.total(parts) == VehicleCounts(4, 3, 10, 7)
    assert VehicleCounts.total([]) == VehicleCounts(0, 0, 0, 0)


def test_drawn_cells_are_counted_by_their_distance_to_the_nearest_car() -> None:
    # One car at column 2 of a 1 × 12 strip; drawn cells 0, 1, 3 and 5 columns away from
    # it, one faint cell below the threshold, and one drawn in another frame with no car.
    target = torch.zeros(2, 1, 12)
    target[0, 0, 2] = 0.9
    recon = torch.zeros(2, 1, 12)
    recon[0, 0, [2, 3, 5, 7]] = 0.6
    recon[0, 0, 10] = 0.2  # below the 0.25 threshold: not drawn
    recon[1, 0, 2] = 0.6  # frame 1 has no car: far from every car
    bright, within = bright_cell_reach(recon, target, (0, 1, 2, 3, 5))
    assert bright == 5
    assert within == (1, 2, 2, 3, 4)


def test_reach_at_one_cell_is_the_precision_numerator() -> None:
    t = _maps()
    recon = torch.roll(t, shifts=2, dims=2) + 0.3 * (torch.rand(t.shape, generator=torch.Generator().manual_seed(0)) > 0.9)
    bright, (within_1,) = bright_cell_reach(recon, t, (1,))
    counts = vehicle_counts(recon, t)
    assert (bright, within_1) == (counts.bright_cells, counts.bright_on_vehicles)
    assert 0 < within_1 < bright


def test_reach_refuses_bad_shapes_and_tolerances() -> None:
    with pytest.raises(ValueError, match="shapes"):
        bright_cell_reach(torch.zeros(1, 4, 4), torch.zeros(1, 4, 5))
    with pytest.raises(ValueError, match=">= 0 cells"):
        bright_cell_reach(torch.zeros(1, 4, 4), torch.zeros(1, 4, 4), (-1,))
