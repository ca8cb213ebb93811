"""vehjax.lib.whiteness against references nobody here wrote: the textbook sample
autocorrelation (Box & Jenkins, numpy), scipy.stats.chi2's survival function, and the known
lag-1 autocorrelation of an AR(1) sequence."""

import math

import numpy as np
import pytest
from scipy.stats import chi2

from vehjax.lib import whiteness


def _acf(x, L):
    d = x - x.mean()
    return np.array([np.dot(d[:-k], d[k:]) / np.dot(d, d) for k in range(1, L + 1)])


def _ar1(phi, n, seed):
    rng = np.random.default_rng(seed)
    w = rng.standard_normal(n + 100)
    x = np.zeros_like(w)
    for t in range(1, len(w)):
        x[t] = phi * x[t - 1] + w[t]
    return x[100:]


def test_white_sequence_matches_the_references_and_is_not_rejected():
    x = np.random.default_rng(1).standard_normal(2000)
    L = 20
    rho, n = whiteness.autocorrelation(x, L)
    np.testing.assert_allclose(rho, _acf(x, L), rtol=1e-12, atol=1e-15)
    assert n == 2000
    q = whiteness.ljung_box(rho, n)
    k = np.arange(1, L + 1)
    assert q == pytest.approx(n * (n + 2) * np.sum(_acf(x, L) ** 2 / (n - k)), rel=1e-12)
    p = whiteness.chi2_sf(q, L)
    assert p == pytest.approx(chi2.sf(q, L), rel=1e-10)
    assert p > 0.01


def test_ar1_negative_coefficient_is_rejected_with_the_right_lag1():
    x = _ar1(-0.45, 5000, 2)
    rho, n = whiteness.autocorrelation(x, 20)
    assert rho[0] == pytest.approx(-0.45, abs=0.04)
    assert rho[1] == pytest.approx(0.45**2, abs=0.04)
    q = whiteness.ljung_box(rho, n)
    p = whiteness.chi2_sf(q, 20)
    assert p < 1e-100
    assert p == pytest.approx(chi2.sf(q, 20), rel=1e-6)


def test_missing_samples_are_left_out_pairwise():
    x = _ar1(-0.45, 5000, 3)
    full, _ = whiteness.autocorrelation(x, 5)
    holes = x.copy()
    holes[np.random.default_rng(4).random(x.size) < 0.2] = np.nan
    rho, n = whiteness.autocorrelation(holes, 5)
    assert n == int(np.isfinite(holes).sum())
    np.testing.assert_allclose(rho, full, atol=0.03)
    assert rho[0] == pytest.approx(-0.45, abs=0.04)
    # a hole-free copy with NaN only at the ends: the pairs are the interior ones exactly
    ends = np.concatenate([[np.nan], x[:1000], [np.nan]])
    rho_e, n_e = whiteness.autocorrelation(ends, 3)
    ref = _acf(x[:1000], 3)
    # the factor (T - k) / T of the biased estimator counts the two missing end samples
    pairs = 1000 - np.arange(1, 4)
    np.testing.assert_allclose(rho_e, ref * 1000 / pairs * (1002 - np.arange(1, 4)) / 1002,
                               rtol=1e-12)
    assert n_e == 1000
    # all missing, constant: NaN
    assert np.all(np.isnan(whiteness.autocorrelation(np.full(50, np.nan), 3)[0]))
    assert np.all(np.isnan(whiteness.autocorrelation(np.ones(50), 3)[0]))
    assert math.isnan(whiteness.ljung_box(np.array([np.nan, 0.1]), 100))


def test_runs_are_pooled_within_runs():
    x = _ar1(0.3, 4000, 5).reshape(4, 1000)
    rho, n = whiteness.autocorrelation(x, 2)
    assert n == 4000
    d = x - x.mean()
    ref = [np.sum(d[:, :-k] * d[:, k:]) / (4 * (1000 - k)) / np.mean(d**2) * (1000 - k) / 1000
           for k in (1, 2)]
    np.testing.assert_allclose(rho, ref, rtol=1e-12)


def test_chi2_with_one_dof_and_default_lags():
    for q in (0.0, 0.5, 3.84, 30.0, 500.0):
        assert whiteness.chi2_sf_1(q) == pytest.approx(chi2.sf(q, 1), rel=1e-10, abs=1e-300)
    assert math.isnan(whiteness.chi2_sf_1(float("nan")))
    assert whiteness.default_lags(1500) == 20
    assert whiteness.default_lags(50) == 10
    assert whiteness.default_lags(3) == 1
