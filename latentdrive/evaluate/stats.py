"""Intervals and paired tests for evaluation numbers, computed with statsmodels and scipy.

Every function here is pure and returns a frozen dataclass; empty input gives NaN
numbers, not an exception, so a report over a scenario with no episodes still renders.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import stats as sps
from statsmodels.stats.contingency_tables import mcnemar
from statsmodels.stats.proportion import proportion_confint

__all__ = [
    "MeanCI", "PairedTest", "RateCI", "json_safe", "json_values", "mean_ci", "paired_test", "rate_ci"]


def json_values(value: Any) -> Any:
    """``value`` as plain JSON values, recursively: NaN and infinities become ``None`` (JSON
    has neither), numpy scalars Python ones, tuples lists, keys strings."""
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): json_values(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_values(v) for v in value]
    return value


def json_safe(d: dict[str, Any]) -> dict[str, Any]:
    """:func:`json_values` of a dict."""
    out: dict[str, Any] = json_values(d)
    return out


@dataclass(frozen=True)
class RateCI:
    """``k`` of ``n`` trials, the rate ``k/n`` and its Wilson score interval ``[lo, hi]``.

    Shows how precisely ``n`` independent trials pin down a rate: 0/10 still allows a
    true rate near 28%. Cannot show anything the trials did not sample (other seeds,
    scenarios, traffic); and when the trials are not independent (e.g. the agents of one
    episode) the interval is too narrow. ``n == 0`` gives NaN rate and interval.
    """

    k: int
    n: int
    rate: float
    lo: float
    hi: float

    def as_dict(self) -> dict[str, Any]:
        """``{"k", "n", "rate", "lo", "hi"}``, NaN as ``None``."""
        return json_safe(asdict(self))


def rate_ci(k: int, n: int, alpha: float = 0.05) -> RateCI:
    """Rate ``k/n`` with its ``1 - alpha`` Wilson score interval (statsmodels
    ``proportion_confint(method="wilson")``). ``n == 0`` gives NaN rate and interval."""
    k, n = int(k), int(n)
    if not 0 <= k <= n:
        raise ValueError(f"need 0 <= k <= n, got k={k}, n={n}")
    if n == 0:
        return RateCI(k, n, math.nan, math.nan, math.nan)
    lo, hi = proportion_confint(k, n, alpha=alpha, method="wilson")
    return RateCI(k, n, k / n, max(0.0, float(lo)), min(1.0, float(hi)))


@dataclass(frozen=True)
class MeanCI:
    """Sample mean of ``n`` values and its Student-t interval ``[lo, hi]``.

    Shows how precisely the mean of the sampled values is known if they are independent
    draws; it says nothing about the spread of single values (a narrow interval can hide
    a wide distribution) and is only approximate for skewed data with small ``n``.
    ``n == 0`` gives a NaN mean; ``n < 2`` a NaN interval.
    """

    mean: float
    lo: float
    hi: float
    n: int

    def as_dict(self) -> dict[str, Any]:
        """``{"mean", "lo", "hi", "n"}``, NaN as ``None``."""
        return json_safe(asdict(self))


def mean_ci(values: ArrayLike, alpha: float = 0.05) -> MeanCI:
    """Mean of ``values`` (1-D) with its ``1 - alpha`` t-interval (``scipy.stats.t.interval``
    around the standard error). Constant values give the zero-width interval."""
    x = np.asarray(values, dtype=np.float64).reshape(-1)
    n = int(x.size)
    if n == 0:
        return MeanCI(math.nan, math.nan, math.nan, 0)
    mean = float(x.mean())
    if n < 2:
        return MeanCI(mean, math.nan, math.nan, n)
    sem = float(sps.sem(x))
    if sem == 0.0:
        return MeanCI(mean, mean, mean, n)
    lo, hi = sps.t.interval(1.0 - alpha, df=n - 1, loc=mean, scale=sem)
    return MeanCI(mean, float(lo), float(hi), n)


@dataclass(frozen=True)
class PairedTest:
    """Two binary outcomes on the same ``n`` paired trials (e.g. "failed" under policies
    A and B on identical episode seeds).

    ``difference`` is ``rate_a - rate_b`` with ``[lo, hi]`` its percentile-bootstrap
    interval; ``relative`` is ``1 - rate_a / rate_b``, how much less often A is true than B
    (the paper's "47% fewer" with A the bottleneck and B the baseline), with
    ``[relative_lo, relative_hi]`` from the same kind of bootstrap (all NaN when ``rate_b``
    is 0). A resample in which B never happens but A does has no finite reduction: when
    such resamples reach the lower tail, ``relative_lo`` is ``-inf`` (no lower bound); one
    in which neither happens counts as no reduction (0). Both intervals resample
    episodes: they say how well these two policies were measured, not how other training
    seeds would do. ``a_only``/``b_only`` count the discordant pairs (true under A only / B
    only), which alone drive ``p_value``, McNemar's exact (binomial) two-sided test of
    equal rates. A small p-value says the policies differ on *these* episodes' generating
    distribution; a large one does not show they are equal (few discordant pairs mean
    little power). ``n == 0`` gives NaN numbers.
    """

    n: int
    rate_a: float
    rate_b: float
    difference: float
    lo: float
    hi: float
    a_only: int
    b_only: int
    p_value: float
    relative: float = math.nan
    relative_lo: float = math.nan
    relative_hi: float = math.nan

    def as_dict(self) -> dict[str, Any]:
        """All fields, NaN as ``None``."""
        return json_safe(asdict(self))


def _as_bool(x: ArrayLike, name: str) -> NDArray[np.bool_]:
    arr = np.asarray(x)
    if arr.ndim != 1:
        raise ValueError(f"{name} must be 1-D, got shape {arr.shape}")
    return arr.astype(bool)


def paired_test(
    a: ArrayLike,
    b: ArrayLike,
    alpha: float = 0.05,
    *,
    n_resamples: int = 9999,
    seed: int = 0,
) -> PairedTest:
    """McNemar's exact test and an interval for the difference of paired binary outcomes.

    ``a[i]`` and ``b[i]`` are outcomes of the same trial ``i`` under two conditions. The
    p-value is statsmodels ``mcnemar(table, exact=True)``. statsmodels has no interval for
    a difference of *paired* proportions, so the ``1 - alpha`` interval of ``rate_a -
    rate_b`` is a percentile bootstrap (``scipy.stats.bootstrap(paired=True,
    method="percentile")``, ``n_resamples`` resamples, ``rng`` seeded with ``seed`` so it is
    reproducible). Percentile bootstraps run narrow for small ``n``; when every pair has
    the same difference the interval is that difference, zero width.
    """
    xa, xb = _as_bool(a, "a"), _as_bool(b, "b")
    if xa.shape != xb.shape:
        raise ValueError(f"paired outcomes need equal lengths, got {xa.size} and {xb.size}")
    n = int(xa.size)
    a_only = int(np.sum(xa & ~xb))
    b_only = int(np.sum(~xa & xb))
    if n == 0:
        nan = math.nan
        return PairedTest(0, nan, nan, nan, nan, nan, 0, 0, nan)
    both = int(np.sum(xa & xb))
    table = np.array([[both, a_only], [b_only, n - both - a_only - b_only]])
    p_value = min(1.0, float(mcnemar(table, exact=True).pvalue))
    fa, fb = xa.astype(np.float64), xb.astype(np.float64)
    rate_a, rate_b = float(fa.mean()), float(fb.mean())
    diff = rate_a - rate_b
    d = fa - fb
    if np.all(d == d[0]):
        lo = hi = diff
    else:
        lo, hi = _paired_bootstrap(fa, fb, _difference, alpha, n_resamples, seed)
    rel = rel_lo = rel_hi = math.nan
    if rate_b > 0:
        rel = 1.0 - rate_a / rate_b
        rel_lo, rel_hi = (rel, rel) if np.all(d == d[0]) else _paired_bootstrap(fa, fb, _relative, alpha,
                                                                                  n_resamples, seed)
    return PairedTest(n, rate_a, rate_b, diff, lo, hi, a_only, b_only, p_value, rel, rel_lo, rel_hi)


def _difference(x: NDArray[np.float64], y: NDArray[np.float64], axis: int) -> NDArray[np.float64]:
    return np.mean(x, axis=axis) - np.mean(y, axis=axis)


def _relative(x: NDArray[np.float64], y: NDArray[np.float64], axis: int) -> NDArray[np.float64]:
    mx, my = np.mean(x, axis=axis), np.mean(y, axis=axis)
    # A resample where B never happens: no reduction is defined; -inf (A happened) or 0
    # (neither did) keeps the percentiles finite-ordered instead of NaN.
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(my > 0, 1.0 - mx / my, np.where(mx > 0, -np.inf, 0.0))


def _paired_bootstrap(fa: NDArray[np.float64], fb: NDArray[np.float64], statistic: Any, alpha: float,
                      n_resamples: int, seed: int) -> tuple[float, float]:
    with np.errstate(invalid="ignore"):  # the standard error of a distribution holding -inf
        res = sps.bootstrap(
            (fa, fb),
            statistic,
            paired=True,
            vectorized=True,
            batch=256,  # bounds memory at 256 * n; all at once is ~1 GB and slower at n=5000
            n_resamples=n_resamples,
            confidence_level=1.0 - alpha,
            method="percentile",
            rng=np.random.default_rng(seed),
        )
    return float(res.confidence_interval.low), float(res.confidence_interval.high)
