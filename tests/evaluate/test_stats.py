"""Intervals and paired tests against values worked out by hand."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from latentdrive.evaluate.stats import mean_ci, paired_test, rate_ci


def test_wilson_zero_of_ten() -> None:
    r = rate_ci(0, 10)
    # Wilson upper bound at k=0 is z²/(n+z²) with z = 1.959964: 3.841459/13.841459.
    assert (r.k, r.n, r.rate, r.lo) == (0, 10, 0.0, 0.0)
    assert r.hi == pytest.approx(0.277533, abs=1e-6)


def test_wilson_half_is_symmetric() -> None:
    r = rate_ci(5, 10)
    assert r.rate == 0.5
    assert r.lo == pytest.approx(0.236593, abs=1e-6)
    assert r.hi == pytest.approx(1 - r.lo, abs=1e-12)


def test_wilson_all_of_ten_mirrors_none() -> None:
    assert rate_ci(10, 10).lo == pytest.approx(1 - 0.277533, abs=1e-6)
    assert rate_ci(10, 10).hi == 1.0


def test_rate_of_nothing_is_nan_and_json_safe() -> None:
    r = rate_ci(0, 0)
    assert math.isnan(r.rate) and math.isnan(r.lo) and math.isnan(r.hi)
    assert r.as_dict() == {"k": 0, "n": 0, "rate": None, "lo": None, "hi": None}
    json.dumps(r.as_dict(), allow_nan=False)


def test_rate_rejects_k_above_n() -> None:
    with pytest.raises(ValueError, match="k <= n"):
        rate_ci(3, 2)


def test_mean_t_interval() -> None:
    m = mean_ci([1.0, 2.0, 3.0])
    # mean 2, sd 1, sem 1/sqrt(3), t(0.975, df=2) = 4.302653
    half = 4.302653 / math.sqrt(3)
    assert m.n == 3 and m.mean == 2.0
    assert m.lo == pytest.approx(2 - half, abs=1e-5) and m.hi == pytest.approx(2 + half, abs=1e-5)


def test_mean_of_few_values() -> None:
    one = mean_ci([4.0])
    assert one.mean == 4.0 and math.isnan(one.lo) and math.isnan(one.hi)
    assert one.as_dict() == {"mean": 4.0, "lo": None, "hi": None, "n": 1}
    assert math.isnan(mean_ci([]).mean)
    flat = mean_ci([2.5, 2.5, 2.5])
    assert (flat.lo, flat.hi) == (2.5, 2.5)


def test_mcnemar_exact_all_discordant_one_way() -> None:
    a = np.array([False] * 6 + [True] * 3 + [False] * 5)
    b = np.array([True] * 6 + [True] * 3 + [False] * 5)
    t = paired_test(a, b)
    assert (t.n, t.a_only, t.b_only) == (14, 0, 6)
    assert t.p_value == pytest.approx(2 * 0.5**6)  # 0.03125
    assert t.rate_a == pytest.approx(3 / 14) and t.rate_b == pytest.approx(9 / 14)
    assert t.difference == pytest.approx(-6 / 14)
    assert t.lo <= t.difference <= t.hi < 0


def test_mcnemar_exact_mixed_discordance() -> None:
    # a_only=1, b_only=7: p = 2 * P(X <= 1), X ~ Bin(8, 1/2) = 2 * 9/256
    a = np.array([True] + [False] * 7 + [True] * 2)
    b = np.array([False] + [True] * 7 + [True] * 2)
    t = paired_test(a, b)
    assert (t.a_only, t.b_only) == (1, 7)
    assert t.p_value == pytest.approx(18 / 256)


def test_identical_outcomes() -> None:
    x = np.array([True, False, True, True, False])
    t = paired_test(x, x)
    assert t.p_value == 1.0 and t.difference == 0.0 and (t.lo, t.hi) == (0.0, 0.0)
    assert (t.a_only, t.b_only) == (0, 0)


def test_bootstrap_interval_is_reproducible() -> None:
    rng = np.random.default_rng(1)
    a, b = rng.random(40) < 0.5, rng.random(40) < 0.3
    assert paired_test(a, b) == paired_test(a, b)


def test_paired_length_mismatch() -> None:
    with pytest.raises(ValueError, match="equal lengths") as err:
        paired_test([True, False], [True])
    assert "\n" not in str(err.value)


def test_paired_empty_is_nan_and_json_safe() -> None:
    t = paired_test([], [])
    assert t.n == 0 and math.isnan(t.p_value)
    json.dumps(t.as_dict(), allow_nan=False)


def test_relative_reduction_and_its_interval() -> None:
    # B fails 9 of 14, A 3 of the same 14 (A fails only where B does): 1 - 3/9 = 2/3 fewer.
    a = np.array([False] * 6 + [True] * 3 + [False] * 5)
    b = np.array([True] * 6 + [True] * 3 + [False] * 5)
    t = paired_test(a, b)
    assert t.relative == pytest.approx(2 / 3)
    assert 0 < t.relative_lo <= t.relative <= t.relative_hi <= 1
    # The reverse is an increase: negative.
    assert paired_test(b, a).relative == pytest.approx(1 - 9 / 3)


def test_relative_reduction_of_a_rate_that_is_zero_is_undefined() -> None:
    t = paired_test([True, False, False], [False, False, False])
    assert math.isnan(t.relative) and t.as_dict()["relative"] is None


def test_an_unbounded_reduction_is_minus_infinity_not_undefined() -> None:
    # B fails once, A twice: some resamples hold A's failures and none of B's.
    t = paired_test([True, True] + [False] * 18, [False, False, True] + [False] * 17)
    assert t.relative == pytest.approx(1 - 2 / 1) and t.relative_lo == -math.inf and t.relative_hi <= 1
