"""The scenario distance: squared maximum mean discrepancy (MMD²) with a Gaussian kernel.

The paper introduces "a similarity metric between driving scenarios" and a regularizer
that minimizes it in the latent space, but never defines it. latentdrive defines the
distance between two scenarios as the MMD² between samples of their representations
(Gretton et al., 2012): with a characteristic kernel such as the Gaussian, the population
MMD is zero exactly when the two distributions are equal, so it compares whole
distributions rather than, say, their means.

Estimator: the **biased** (V-statistic) estimate

    MMD²_b(X, Y) = mean k(X, X) + mean k(Y, Y) − 2 mean k(X, Y),

diagonal terms included. It is chosen over the unbiased U-statistic because it equals
``‖μ̂_X − μ̂_Y‖²`` in the kernel's feature space, the squared distance between the
empirical mean embeddings. Hence it is never negative, it is exactly zero for identical
samples (so a distance matrix has a zero diagonal), and its square root satisfies the
triangle inequality across a matrix computed with one kernel. The unbiased estimate can be
negative and is undefined for a group of one sample, which happens in small mixed batches.
The difference is small and harmless for a regularizer: ``mean k(X, X)`` equals
``1/n + (n−1)/n · U_XX``, where the diagonal's ``1/n`` carries no gradient and ``U_XX`` is the
unbiased within-group term, so only the weight of the within-group terms changes (by
``(n−1)/n``). ``unbiased=True`` is available for reporting.

Kernel: ``k(a, b) = exp(−‖a − b‖² / (2 h²))``. Bandwidth ``h`` by the median heuristic:
the (lower) median of the pairwise Euclidean distances ``‖a − b‖`` over the pooled sample
(all distinct pairs of ``X ∪ Y``), computed without gradient. Treating ``h`` as a constant
makes the regularizer's gradient that of a fixed kernel; letting it flow through the median
would reward rescaling the code instead of moving the groups together. Because ``h``
scales with the data, the value is invariant to a common rescaling of all vectors. When
all points coincide (median 0) ``h = 1``; the MMD² is then 0 for any ``h``.

All functions take vectors of any trailing shape and flatten them: ``(n, ...)`` → ``(n, D)``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import torch
from torch import Tensor

__all__ = [
    "distance_matrix",
    "group_mmd2",
    "latent_regularizer",
    "median_bandwidth",
    "mmd2",
]


def _flat(x: Tensor | np.ndarray, dtype: torch.dtype | None = None) -> Tensor:
    t = torch.as_tensor(x)
    if t.ndim < 1 or t.shape[0] == 0:
        raise ValueError(f"expected a non-empty set of vectors (n, ...), got {tuple(t.shape)}")
    t = t.reshape(t.shape[0], -1)
    if dtype is not None:
        t = t.to(dtype)
    elif not t.is_floating_point():
        t = t.to(torch.get_default_dtype())
    return t


def _sq_dists(a: Tensor, b: Tensor) -> Tensor:
    """Pairwise squared Euclidean distances ``(n, m)`` via the Gram expansion (O(n·m) memory)."""
    d = (a * a).sum(1)[:, None] + (b * b).sum(1)[None, :] - 2.0 * (a @ b.T)
    # Rounding can make the expansion slightly negative for (near-)coincident points.
    return d.clamp_min(0.0)


def _median_sq(sq: Tensor) -> Tensor:
    n = sq.shape[0]
    if n < 2:
        return sq.new_ones(())
    iu = torch.triu_indices(n, n, offset=1, device=sq.device)
    return sq[iu[0], iu[1]].median()


def median_bandwidth(z: Tensor | np.ndarray) -> float:
    """Median-heuristic bandwidth ``h`` of a pooled sample ``z`` ``(n, ...)``.

    The lower median of the ``n(n−1)/2`` pairwise Euclidean distances; 1.0 when ``n < 2``
    or all points coincide.
    """
    with torch.no_grad():
        zf = _flat(z)
        h2 = float(_median_sq(_sq_dists(zf, zf)))
    return float(np.sqrt(h2)) if h2 > 0.0 else 1.0


def _kernel(z: Tensor, bandwidth: float | None) -> Tensor:
    """Gaussian kernel matrix ``(n, n)`` of the pooled sample ``z`` ``(n, D)``."""
    sq = _sq_dists(z, z)
    if bandwidth is None:
        with torch.no_grad():
            h2 = _median_sq(sq.detach())
            h2 = torch.where(h2 > 0, h2, torch.ones_like(h2))
    else:
        if not bandwidth > 0:
            raise ValueError(f"bandwidth must be positive, got {bandwidth}")
        h2 = torch.tensor(float(bandwidth) ** 2, dtype=z.dtype, device=z.device)
    return torch.exp(-sq / (2.0 * h2))


def mmd2(
    x: Tensor | np.ndarray,
    y: Tensor | np.ndarray,
    bandwidth: float | None = None,
    *,
    unbiased: bool = False,
) -> Tensor:
    """Squared MMD between samples ``x`` ``(n, ...)`` and ``y`` ``(m, ...)``: a scalar tensor.

    Differentiable in ``x`` and ``y`` (the median bandwidth itself carries no gradient).
    ``bandwidth`` is ``h`` in units of the vectors; ``None`` uses the median heuristic over
    ``x ∪ y``. The biased estimate is ≥ 0 and exactly 0 for ``y = x`` up to rounding;
    ``unbiased=True`` needs ``n, m ≥ 2`` and may be negative.
    """
    xf, yf = _flat(x), _flat(y)
    if xf.shape[1] != yf.shape[1]:
        raise ValueError(f"vector sizes differ: {xf.shape[1]} vs {yf.shape[1]}")
    yf = yf.to(device=xf.device, dtype=torch.promote_types(xf.dtype, yf.dtype))
    xf = xf.to(yf.dtype)
    n, m = xf.shape[0], yf.shape[0]
    k = _kernel(torch.cat([xf, yf]), bandwidth)
    kxx, kyy, kxy = k[:n, :n], k[n:, n:], k[:n, n:]
    if unbiased:
        if n < 2 or m < 2:
            raise ValueError(f"the unbiased estimate needs >= 2 samples per set, got {n} and {m}")
        sxx = (kxx.sum() - kxx.diagonal().sum()) / (n * (n - 1))
        syy = (kyy.sum() - kyy.diagonal().sum()) / (m * (m - 1))
        return sxx + syy - 2.0 * kxy.mean()
    return (kxx.mean() + kyy.mean() - 2.0 * kxy.mean()).clamp_min(0.0)


def group_mmd2(
    features: Tensor, labels: Tensor, bandwidth: float | None = None
) -> tuple[Tensor, Tensor]:
    """Biased MMD² between every pair of groups in one pooled sample.

    ``features`` ``(N, ...)``, ``labels`` ``(N,)`` integer group ids. Returns
    ``(groups (S,), matrix (S, S))`` with ``groups`` the sorted distinct labels and
    ``matrix[i, j]`` the MMD² between groups ``i`` and ``j``, all with one kernel whose
    bandwidth is the median over the whole pooled sample. The matrix is exactly symmetric
    with a zero diagonal and differentiable in ``features``.

    One kernel matrix serves every pair: with ``W`` the ``(N, S)`` matrix of group
    membership divided by group size, ``M = Wᵀ K W`` holds the inner products of the
    empirical mean embeddings and ``MMD²_ij = M_ii + M_jj − 2 M_ij``.
    """
    f = _flat(features)
    lab = torch.as_tensor(labels, device=f.device).reshape(-1)
    if lab.shape[0] != f.shape[0]:
        raise ValueError(f"{f.shape[0]} vectors but {lab.shape[0]} labels")
    groups, inverse, counts = torch.unique(lab, return_inverse=True, return_counts=True)
    k = _kernel(f, bandwidth)
    w = torch.zeros(f.shape[0], groups.shape[0], dtype=f.dtype, device=f.device)
    w[torch.arange(f.shape[0], device=f.device), inverse] = 1.0
    w = w / counts.to(f.dtype)[None, :]
    m = w.T @ k @ w
    m = 0.5 * (m + m.T)
    diag = m.diagonal()
    d = (diag[:, None] + diag[None, :] - 2.0 * m).clamp_min(0.0)
    # Exactly zero on the diagonal, whatever the rounding of the expression above.
    d = d * (1.0 - torch.eye(d.shape[0], dtype=d.dtype, device=d.device))
    return groups, d


def latent_regularizer(
    latents: Tensor, labels: Tensor, bandwidth: float | None = None
) -> Tensor:
    """Mean pairwise MMD² between the scenario groups present in a batch: a scalar tensor.

    ``latents`` ``(B, ...)`` (e.g. the BNN's ``(B, 3, d)``, flattened to ``(B, 3d)``),
    ``labels`` ``(B,)`` scenario ids. Averages ``MMD²(group_i, group_j)`` over the
    ``S(S−1)/2`` pairs of the ``S`` scenarios present; 0 (still attached to the graph)
    when fewer than two are present. Added to the loss with weight λ it pulls the
    scenarios' latent distributions together.
    """
    groups, d = group_mmd2(latents, labels, bandwidth)
    s = groups.shape[0]
    if s < 2:
        return latents.sum() * 0.0
    iu = torch.triu_indices(s, s, offset=1, device=d.device)
    return d[iu[0], iu[1]].mean()


def distance_matrix(
    features_by_scenario: Mapping[str, Tensor | np.ndarray],
    bandwidth: float | None = None,
    *,
    max_samples: int | None = 500,
    seed: int = 0,
) -> tuple[list[str], np.ndarray]:
    """Scenario-by-scenario MMD² matrix.

    ``features_by_scenario`` maps a scenario name to its vectors ``(n_s, ...)`` (all with
    the same trailing size). Returns ``(names, D)`` with ``names`` in the mapping's order
    and ``D`` a float64 ``(S, S)`` array, symmetric with a zero diagonal; ``D[i, j]`` is the
    biased MMD² between scenarios ``i`` and ``j``, ``sqrt(D)`` a metric between them.

    Every entry uses the same kernel, whose bandwidth (if not given) is the median over
    the union of all scenarios' (sub)samples, so entries are comparable. Each scenario is
    subsampled without replacement to at most ``max_samples`` vectors, drawn from
    ``numpy.random.default_rng(seed)``, to keep the ``(N, N)`` kernel matrix small; ``None``
    keeps everything. Computed in float64 without gradient.
    """
    names = list(features_by_scenario)
    if not names:
        raise ValueError("no scenarios given")
    rng = np.random.default_rng(seed)
    parts: list[Tensor] = []
    labels: list[Tensor] = []
    for i, name in enumerate(names):
        f = _flat(features_by_scenario[name], torch.float64).cpu()
        if max_samples is not None and f.shape[0] > max_samples:
            idx = np.sort(rng.choice(f.shape[0], size=max_samples, replace=False))
            f = f[torch.from_numpy(idx)]
        parts.append(f)
        labels.append(torch.full((f.shape[0],), i, dtype=torch.long))
    sizes: Sequence[int] = [p.shape[1] for p in parts]
    if len(set(sizes)) != 1:
        by_name = dict(zip(names, sizes, strict=True))
        raise ValueError(f"vector sizes differ between scenarios: {by_name}")
    with torch.no_grad():
        _, d = group_mmd2(torch.cat(parts), torch.cat(labels), bandwidth)
    return names, d.numpy()
