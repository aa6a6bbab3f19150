"""Fitting linear probes: ridge for continuous targets, logistic regression for flags.

A probe is a linear read-out of one target from a frozen feature vector. Features are
standardized with the training split's statistics; the penalty is chosen by
cross-validation on the training split only (folds hold out whole episodes); the chosen
probe is refitted on the whole training split and scored on the test split:

- continuous targets: ridge regression, held-out R² beside the R² of predicting the
  training mean (about 0, slightly below when the two splits' means differ);
- boolean targets: L2-penalized logistic regression, held-out accuracy beside the
  accuracy of always answering the training split's majority class. Flags such as "the
  lane on the left is free" are imbalanced, and an accuracy reads only against it.

Why episodes, not samples, are split: consecutive samples of one episode are one policy
step apart (vehicles move a few metres) and their stacks share all but one frame, so a
split by sample puts near-copies of test samples in the training set and measures how
well a probe memorizes, not what the features encode. The same holds for the folds that
choose the penalty.

With more features than training samples (the raw VelocityMap), the standardized training
matrix is replaced by its coordinates in its own row space (a thin SVD), and test samples
are projected on the same basis. Both penalized fits have their weight vector in the span
of the training rows (the penalty only grows along any other direction), so this changes
no prediction of any fold or of the final fit, and every fit then works on at most
n_train features instead of F (32,768 at the default grid).

Same inputs, same numbers: folds, solvers and the SVD involve no randomness, and the
fit runs on one BLAS thread by default (:func:`fit_probes`).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray
from sklearn.exceptions import ConvergenceWarning
from sklearn.linear_model import LogisticRegression, Ridge
from sklearn.model_selection import GroupKFold, KFold
from sklearn.preprocessing import StandardScaler
from threadpoolctl import threadpool_limits

__all__ = ["ALPHAS", "INVERSE_PENALTIES", "ProbeScore", "fit_probes", "reduce_features", "split_by_episode"]

FArr = NDArray[np.float64]

#: Ridge penalties tried (on standardized features), a decade apart.
ALPHAS: tuple[float, ...] = tuple(float(a) for a in np.logspace(-2, 6, 9))
#: Logistic regression's inverse penalties C tried, a decade apart.
INVERSE_PENALTIES: tuple[float, ...] = tuple(float(c) for c in np.logspace(-4, 2, 7))
#: Folds of the penalty's cross-validation (fewer when the training split has fewer episodes).
FOLDS = 5
#: Probabilities are clipped this far from 0 and 1 in the fold log-loss.
_EPS = 1e-6


class ProbeScore(NamedTuple):
    """How well a linear probe reads one target on the test split."""

    metric: str  # "r2" or "accuracy"
    value: float  # held-out R² or accuracy; NaN when the test split cannot score it
    baseline: float  # the same metric of the constant predictor (training mean / majority class)
    penalty: float  # the chosen penalty strength: ridge alpha, or 1/C of the logistic fit
    n_train: int  # samples with a value of this target in each split
    n_test: int


def split_by_episode(episode: NDArray[np.integer], scenario: NDArray[np.object_] | NDArray[np.str_],
                     test_fraction: float, seed: int) -> NDArray[np.bool_]:
    """Which samples form the test split: ``round(test_fraction · episodes)`` whole episodes
    of every scenario (at least one, and never all of a scenario's episodes when it has
    two or more), drawn with ``seed``.

    Args:
        episode: ``(n,)`` episode id of each sample (unique across scenarios).
        scenario: ``(n,)`` scenario name of each sample.

    Returns:
        ``(n,)`` bool, True for test samples.
    """
    if not 0.0 < test_fraction < 1.0:
        raise ValueError(f"test_fraction must be in (0, 1), got {test_fraction}")
    names = np.asarray(scenario)
    rng = np.random.default_rng(seed)
    test_eps: list[NDArray[np.integer]] = []
    for name in sorted(set(names.tolist())):
        eps = np.unique(np.asarray(episode)[names == name])
        k = min(max(1, round(test_fraction * eps.size)), max(eps.size - 1, 1))
        test_eps.append(rng.permutation(eps)[:k])
    return np.isin(episode, np.concatenate(test_eps)) if test_eps else np.zeros(episode.shape, dtype=bool)


def reduce_features(train_X: NDArray[np.floating], test_X: NDArray[np.floating]) -> tuple[FArr, FArr]:
    """Standardized features ``(n_train, F)``, ``(n_test, F)``, in the training rows' own
    basis when ``F > n_train`` (see the module docstring); float64."""
    scaler = StandardScaler().fit(train_X)
    a, b = scaler.transform(train_X), scaler.transform(test_X)
    if a.shape[1] > a.shape[0]:
        u, s, vt = np.linalg.svd(a, full_matrices=False)
        # Directions of (numerically) zero variance carry no sample: dropping them is exact.
        keep = s > s[:1].max(initial=0.0) * max(a.shape) * np.finfo(a.dtype).eps
        a, b = u[:, keep] * s[keep], b @ vt[keep].T
    return np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)


def _splits(n: int, groups: NDArray[np.integer] | None) -> list[tuple[NDArray[np.intp], NDArray[np.intp]]]:
    if groups is None:
        # Contiguous blocks: samples stored episode by episode stay mostly together.
        if n < 2:
            raise ValueError("cross-validation needs at least two training samples")
        return list(KFold(min(FOLDS, n)).split(np.zeros(n)))
    k = np.unique(groups).size
    if k < 2:
        raise ValueError("cross-validation needs at least two training episodes")
    return list(GroupKFold(min(FOLDS, k)).split(np.zeros(n), groups=groups))


def _r2(y: FArr, pred: FArr) -> float:
    ss = float(((y - y.mean()) ** 2).sum()) if y.size else 0.0
    return math.nan if y.size < 2 or ss == 0.0 else 1.0 - float(((y - pred) ** 2).sum()) / ss


def _ridge(z: FArr, y: FArr, zt: FArr, yt: FArr, splits: list[tuple[NDArray[np.intp], NDArray[np.intp]]]) -> ProbeScore:
    errors = np.zeros(len(ALPHAS))
    for tr, va in splits:
        for i, alpha in enumerate(ALPHAS):
            errors[i] += float(((Ridge(alpha=alpha).fit(z[tr], y[tr]).predict(z[va]) - y[va]) ** 2).sum())
    alpha = ALPHAS[int(np.argmin(errors))]
    value = _r2(yt, Ridge(alpha=alpha).fit(z, y).predict(zt)) if yt.size else math.nan
    baseline = _r2(yt, np.full(yt.shape, y.mean())) if yt.size else math.nan
    return ProbeScore("r2", value, baseline, alpha, y.size, yt.size)


def _proba(z: FArr, y: NDArray[np.bool_], zq: FArr, c: float) -> FArr:
    """P(True) of the logistic probe with inverse penalty ``c``; a constant when ``y`` is."""
    if y.all() or not y.any():
        return np.full(zq.shape[0], float(y[0]) if y.size else 0.5)
    with warnings.catch_warnings():
        # A weak penalty on separable folds stops at the iteration cap; the held-out loss
        # that chooses the penalty judges such fits like any other.
        warnings.simplefilter("ignore", ConvergenceWarning)
        model = LogisticRegression(C=c, max_iter=1000).fit(z, y)
    return np.asarray(model.predict_proba(zq)[:, 1], dtype=np.float64)


def _logistic(z: FArr, y: NDArray[np.bool_], zt: FArr, yt: NDArray[np.bool_],
              splits: list[tuple[NDArray[np.intp], NDArray[np.intp]]]) -> ProbeScore:
    losses = np.zeros(len(INVERSE_PENALTIES))
    for tr, va in splits:
        for i, c in enumerate(INVERSE_PENALTIES):
            p = np.clip(_proba(z[tr], y[tr], z[va], c), _EPS, 1.0 - _EPS)
            losses[i] -= float(np.where(y[va], np.log(p), np.log1p(-p)).sum())
    c = INVERSE_PENALTIES[int(np.argmin(losses))]
    majority = bool(y.mean() >= 0.5) if y.size else False
    value = float(((_proba(z, y, zt, c) >= 0.5) == yt).mean()) if yt.size else math.nan
    baseline = float((yt == majority).mean()) if yt.size else math.nan
    return ProbeScore("accuracy", value, baseline, 1.0 / c, y.size, yt.size)


def fit_probes(train_X: NDArray[np.floating], train_targets: Mapping[str, NDArray[np.generic]],
               test_X: NDArray[np.floating], test_targets: Mapping[str, NDArray[np.generic]],
               groups: NDArray[np.integer] | None = None, threads: int | None = 1) -> dict[str, ProbeScore]:
    """Fit one linear probe per target and score it on the test split.

    Args:
        train_X: ``(n_train, F)`` features of the training samples.
        train_targets: ``{name: (n_train,)}``; bool arrays get a logistic probe, float
            arrays a ridge probe (NaN marks samples without a value, which both splits
            leave out for that target).
        test_X: ``(n_test, F)``.
        test_targets: ``{name: (n_test,)}``, the same names.
        groups: ``(n_train,)`` episode id of each training sample: the penalty's
            cross-validation folds hold out whole episodes. Without it, folds are
            contiguous blocks of samples.
        threads: BLAS threads while fitting. One gives the same numbers on every machine,
            and spares the many small solver steps thread hand-offs that made them an
            order of magnitude slower on a busy two-core machine; None keeps the
            libraries' default.

    Returns:
        ``{name: ProbeScore}`` in ``train_targets``' order.

    Raises:
        ValueError: fewer than two training episodes (or samples, without ``groups``).
    """
    with threadpool_limits(limits=threads, user_api="blas"):
        z, zt = reduce_features(train_X, test_X)
        out: dict[str, ProbeScore] = {}
        for name, y_all in train_targets.items():
            yt_all = np.asarray(test_targets[name])
            y_all = np.asarray(y_all)
            if y_all.dtype == np.bool_:
                rows, test_rows = np.ones(y_all.shape, dtype=bool), np.ones(yt_all.shape, dtype=bool)
            else:
                rows, test_rows = np.isfinite(y_all), np.isfinite(yt_all)
            g = None if groups is None else np.asarray(groups)[rows]
            splits = _splits(int(rows.sum()), g)
            zr, zq = z[rows], zt[test_rows]
            if y_all.dtype == np.bool_:
                out[name] = _logistic(zr, y_all[rows].astype(bool), zq, yt_all[test_rows].astype(bool), splits)
            else:
                out[name] = _ridge(zr, y_all[rows].astype(np.float64), zq, yt_all[test_rows].astype(np.float64),
                                   splits)
    return out
