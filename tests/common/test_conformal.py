"""Split-conformal calibration reaches its coverage, and no more than the theory allows."""

import math

import numpy as np
import pytest

from toolkit.common.training.conformal import (
    ConformalBound,
    calibrate,
    conformal_rank,
    coverage_interval,
    min_calibration_cases,
)


def _task(rng, n):
    """A heteroscedastic regression: the error of a fixed predictor is |N(0, sigma(x))| with
    sigma(x) = 0.1 + x; the estimate's scale is sigma(x) times a misjudged factor 0.3 (a scale
    right in shape, wrong in size: the calibration must fix the size)."""
    x = rng.uniform(0.0, 2.0, n)
    sigma = 0.1 + x
    return np.abs(rng.normal(0.0, sigma)), 0.3 * sigma


@pytest.mark.parametrize(("n", "coverage"), [(19, 0.95), (50, 0.9), (200, 0.9)])
def test_coverage_over_calibration_draws(n, coverage):
    """Mean coverage over R independent calibration sets (each tested on 2,000 new cases) is
    k / (n + 1) (exact for continuous ratios). With R = 400 the Monte Carlo standard error of
    that mean is at most sqrt(Var Beta(k, n + 1 - k) / R) + sqrt(1/4 / (R * 2000)) < 0.003
    (Var Beta <= 0.0023 at n = 19), so 4 standard errors (0.012) separate a correct calibration
    from the naive empirical quantile, which at n = 19, 95 % expects 0.931."""
    rng = np.random.default_rng(0)
    lo, expected = coverage_interval(n, coverage)
    assert lo <= expected < coverage + 1.0 / (n + 1)
    k = conformal_rank(n, coverage)
    var = k * (n + 1 - k) / ((n + 1) ** 2 * (n + 2)) / 400 + 0.25 / (400 * 2000)
    covered = []
    for _ in range(400):
        bound = calibrate(*_task(rng, n), coverage)
        e, s = _task(rng, 2000)
        covered.append(np.mean(e <= bound.bound(s)))
    assert abs(np.mean(covered) - expected) < 4 * math.sqrt(var)
    assert np.mean(covered) >= coverage - 4 * math.sqrt(var)


def test_naive_quantile_undercovers_so_the_test_can_fail():
    """The check above distinguishes the finite-sample rank from np.quantile's interpolation."""
    rng = np.random.default_rng(1)
    covered = []
    for _ in range(400):
        e, s = _task(rng, 19)
        q = np.quantile(e / s, 0.95)
        e2, s2 = _task(rng, 2000)
        covered.append(np.mean(e2 <= q * s2))
    assert np.mean(covered) < 0.95 - 0.012


def test_minimum_cases_and_refusals():
    assert min_calibration_cases(0.9) == 9
    assert min_calibration_cases(0.95) == 19
    calibrate(np.ones(9), np.ones(9), 0.9)
    with pytest.raises(ValueError, match="at least 9"):
        calibrate(np.ones(8), np.ones(8), 0.9)
    with pytest.raises(ValueError, match="coverage"):
        calibrate(np.ones(20), np.ones(20), 1.0)
    with pytest.raises(ValueError, match="scales must be > 0"):
        calibrate(np.ones(20), np.r_[np.ones(19), 0.0], 0.9)
    with pytest.raises(ValueError, match="one value per calibration case"):
        calibrate(np.ones(20), np.ones(19), 0.9)
    with pytest.raises(ValueError, match="finite"):
        calibrate(np.r_[np.ones(19), np.nan], np.ones(20), 0.9)


def test_round_trip_and_other_coverage():
    rng = np.random.default_rng(2)
    b = calibrate(*_task(rng, 100), 0.9)
    assert ConformalBound.from_dict(b.to_dict()) == b
    b95 = b.at(0.95)
    assert b95.factor >= b.factor and b95.n == b.n == 100
    assert b95.factor == b.ratios[conformal_rank(100, 0.95) - 1]
    assert b.expected_coverage() == pytest.approx(91 / 101)
