"""The scenario distance: Gaussian-kernel MMD² with the median-heuristic bandwidth."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from latentdrive.bnn.distance import (
    distance_matrix,
    group_mmd2,
    latent_regularizer,
    median_bandwidth,
    mmd2,
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _gauss(n: int, mean: float, seed: int, dim: int = 2) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.randn(n, dim, generator=g, dtype=torch.float64) + mean


def test_identical_samples_have_zero_distance() -> None:
    x = _gauss(50, 0.0, 0)
    assert abs(float(mmd2(x, x))) < 1e-12
    assert abs(float(mmd2(x, x.clone(), bandwidth=0.3))) < 1e-12


def test_literal_two_points() -> None:
    # k(0,0) = k(1,1) = 1, k(0,1) = exp(-1/2) with h = 1.
    value = mmd2(torch.tensor([[0.0]]), torch.tensor([[1.0]]), bandwidth=1.0)
    assert float(value) == pytest.approx(2.0 - 2.0 * math.exp(-0.5), abs=1e-6)
    # The median heuristic on two points picks h = their distance, whatever the scale.
    for scale in (1.0, 7.0):
        v = mmd2(torch.tensor([[0.0]]), torch.tensor([[scale]]))
        assert float(v) == pytest.approx(2.0 - 2.0 * math.exp(-0.5), abs=1e-6)


def test_median_bandwidth_literal() -> None:
    # Pairwise distances of 0, 1, 3 on a line: 1, 3, 2 → median 2.
    assert median_bandwidth(np.array([[0.0], [1.0], [3.0]])) == pytest.approx(2.0)
    assert median_bandwidth(np.zeros((4, 3))) == 1.0
    assert median_bandwidth(np.zeros((1, 3))) == 1.0


@pytest.mark.parametrize("bandwidth", [None, 1.0])
def test_separated_gaussians_are_further_apart_than_overlapping(bandwidth: float | None) -> None:
    x = _gauss(100, 0.0, 1)
    far = mmd2(x, _gauss(100, 4.0, 2), bandwidth)
    near = mmd2(x, _gauss(100, 0.1, 3), bandwidth)
    assert float(far) > 5 * float(near)
    assert float(near) >= 0.0


def test_median_heuristic_is_scale_invariant() -> None:
    x, y = _gauss(40, 0.0, 4), _gauss(40, 1.0, 5)
    assert float(mmd2(10 * x, 10 * y)) == pytest.approx(float(mmd2(x, y)), rel=1e-9)


def test_unbiased_estimate() -> None:
    x, y = _gauss(200, 0.0, 6), _gauss(200, 3.0, 7)
    b = float(mmd2(x, y, 1.0))
    u = float(mmd2(x, y, 1.0, unbiased=True))
    assert u == pytest.approx(b, abs=0.02)
    with pytest.raises(ValueError, match=">= 2 samples"):
        mmd2(x[:1], y, unbiased=True)


def test_input_errors() -> None:
    with pytest.raises(ValueError, match="vector sizes differ"):
        mmd2(torch.zeros(3, 2), torch.zeros(3, 4))
    with pytest.raises(ValueError, match="non-empty"):
        mmd2(torch.zeros(0, 2), torch.zeros(3, 2))
    with pytest.raises(ValueError, match="bandwidth"):
        mmd2(torch.zeros(3, 2), torch.ones(3, 2), bandwidth=0.0)


def test_group_matrix_matches_pairwise_mmd() -> None:
    f = torch.cat([_gauss(20, 0.0, 8), _gauss(30, 2.0, 9), _gauss(25, 5.0, 10)])
    labels = torch.tensor([7] * 20 + [3] * 30 + [5] * 25)
    h = median_bandwidth(f)
    groups, d = group_mmd2(f, labels)
    assert groups.tolist() == [3, 5, 7]
    by_label = {int(g): f[labels == g] for g in groups}
    for i, a in enumerate(groups.tolist()):
        for j, b in enumerate(groups.tolist()):
            expected = float(mmd2(by_label[a], by_label[b], bandwidth=h))
            assert float(d[i, j]) == pytest.approx(expected, abs=1e-10)


def test_distance_matrix_is_symmetric_with_zero_diagonal() -> None:
    rng = np.random.default_rng(0)
    feats: dict[str, np.ndarray | torch.Tensor] = {
        "roundabout": rng.normal(0.0, 1.0, (60, 3, 4)),
        "merge": torch.from_numpy(rng.normal(0.2, 1.0, (50, 3, 4))),
        "highway": rng.normal(3.0, 1.0, (70, 12)).astype(np.float32),
    }
    names, d = distance_matrix(feats)
    assert names == ["roundabout", "merge", "highway"]
    assert d.shape == (3, 3) and d.dtype == np.float64
    assert np.array_equal(d, d.T)
    assert np.all(np.diag(d) == 0.0)
    assert d[0, 2] > d[0, 1] > 0.0
    # One kernel for every entry: sqrt(MMD²) is a metric, so the triangle inequality holds.
    r = np.sqrt(d)
    for i in range(3):
        for j in range(3):
            for k in range(3):
                assert r[i, j] <= r[i, k] + r[k, j] + 1e-12
    # Subsampling is seeded.
    _, d2 = distance_matrix(feats, max_samples=30, seed=1)
    _, d3 = distance_matrix(feats, max_samples=30, seed=1)
    assert np.array_equal(d2, d3)
    with pytest.raises(ValueError, match="vector sizes differ"):
        distance_matrix({"a": np.zeros((3, 2)), "b": np.zeros((3, 5))})


def test_regularizer_is_the_mean_pairwise_mmd_and_has_gradients() -> None:
    latents = torch.cat([_gauss(8, 0.0, 11, 6), _gauss(8, 1.0, 12, 6), _gauss(8, 2.0, 13, 6)])
    latents = latents.view(24, 3, 2).requires_grad_(True)
    labels = torch.tensor([0] * 8 + [1] * 8 + [4] * 8)
    reg = latent_regularizer(latents, labels)
    _, d = group_mmd2(latents.detach(), labels)
    assert float(reg.detach()) == pytest.approx(float((d[0, 1] + d[0, 2] + d[1, 2]) / 3), abs=1e-12)
    reg.backward()
    assert latents.grad is not None
    assert torch.isfinite(latents.grad).all() and latents.grad.abs().sum() > 0
    # A gradient step on the latents pulls the scenarios together.
    with torch.no_grad():
        moved = latents - 0.5 * latents.grad
    assert float(latent_regularizer(moved, labels)) < float(reg.detach())


def test_regularizer_with_one_scenario_is_zero_and_differentiable() -> None:
    z = torch.rand(5, 3, 4, requires_grad=True)
    reg = latent_regularizer(z, torch.zeros(5, dtype=torch.long))
    assert float(reg.detach()) == 0.0
    reg.backward()
    assert z.grad is not None and torch.all(z.grad == 0)
