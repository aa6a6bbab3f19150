"""The soft-Dice term of the BNN objective, on literal pair tensors."""

from __future__ import annotations

import pytest
import torch

from latentdrive.bnn.losses import CellWeights, reconstruction_error, vehicle_dice_loss

SHAPE = (1, 3, 2, 1, 4, 4)  # (B, pairs, members, T, H, W)
BIG = 30.0  # a logit whose sigmoid is 1 to float precision


def _target() -> torch.Tensor:
    t = torch.zeros(SHAPE)
    t[0, 0, 0, 0, 1, 1] = 1.0  # one HV cell
    t[0, 1, 0] = 1.0  # the road everywhere (not a vehicle channel)
    return t


def _logits(cells: dict[tuple[int, int, int, int, int, int], float]) -> torch.Tensor:
    x = torch.full(SHAPE, -BIG)
    x[0, 1, 0] = BIG  # the road drawn right
    for idx, value in cells.items():
        x[idx] = value
    return x


def test_dice_is_zero_for_a_perfect_reconstruction_and_ignores_the_road() -> None:
    assert float(vehicle_dice_loss(_logits({(0, 0, 0, 0, 1, 1): BIG}), _target())) == pytest.approx(0.0, abs=1e-6)
    # Nothing to draw and nothing drawn: perfect too.
    assert float(vehicle_dice_loss(torch.full(SHAPE, -BIG), torch.zeros(SHAPE))) == pytest.approx(0.0, abs=1e-6)


def test_dice_charges_a_halo_that_a_per_cell_error_finds_cheap() -> None:
    t = _target()
    car = (0, 0, 0, 0, 1, 1)
    # The car drawn, plus a faint halo: its eight neighbours at 0.2.
    halo = {car: BIG, **{(0, 0, 0, 0, 1 + dr, 1 + dc): float(torch.logit(torch.tensor(0.2)))
                         for dr in (-1, 0, 1) for dc in (-1, 0, 1) if (dr, dc) != (0, 0)}}
    # Literal: Σ r·t = 1, Σ r² = 1 + 8·0.04 = 1.32, Σ t² = 1, Dice = 2 / 2.32.
    assert float(vehicle_dice_loss(_logits(halo), t)) == pytest.approx(1 - 2 / 2.32, rel=1e-5)
    # Missing the car altogether: Dice 0, loss 1.
    assert float(vehicle_dice_loss(_logits({}), t)) == pytest.approx(1.0, abs=1e-5)


def test_the_dice_term_adds_to_the_reconstruction_error_and_has_gradients() -> None:
    t = _target()
    logits = _logits({(0, 0, 0, 0, 1, 1): 0.0}).requires_grad_()
    w = CellWeights(foreground=10.0, road=0.3, av_share=1 / 3)
    plain = reconstruction_error(logits, t, w, "bce")
    both = reconstruction_error(logits, t, w, "bce", dice=2.0)
    assert float((both - plain).detach()) == pytest.approx(2.0 * float(vehicle_dice_loss(logits, t).detach()), rel=1e-6)
    both.backward()
    assert logits.grad is not None and float(logits.grad[0, 0, 0, 0, 1, 1]) < 0  # draw the car brighter


def test_a_negative_dice_weight_is_refused() -> None:
    with pytest.raises(ValueError, match="Dice weight must be at least 0"):
        reconstruction_error(_logits({}), _target(), dice=-1.0)
