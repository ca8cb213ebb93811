"""Whiteness of a sequence: sample autocorrelations with missing samples, the Ljung-Box
portmanteau statistic and the chi-square survival function it is judged by.

A consistent filter's normalised innovations ``e_t / sqrt(S_t)`` are white with unit variance
(Mehra 1970, "On the identification of variances and adaptive Kalman filtering"; Bar-Shalom,
Li & Kirubarajan 2001, "Estimation with applications to tracking and navigation", sec. 5.4):
a model error that the noise cannot absorb (a wrong yaw inertia, a missing lag) shows up as
correlation between successive innovations long before it moves their mean square.

Missing samples (NaN) are left out: the autocovariance at lag k averages the products over the
pairs (t, t + k) where both samples are present, and is scaled back to the biased
(``1 / n``) form of the complete-data estimator (Box, Jenkins & Reinsel, "Time series
analysis", sec. 2.1.5), so that without missing samples :func:`autocorrelation` is exactly the
usual ``sum_t d_t d_{t+k} / sum_t d_t^2`` with ``d`` the deviations from the mean. Several
sequences (runs) are pooled: one mean, the pairs within each sequence, the lag-k products of
all sequences together.

Everything here is numpy on the host, plus ``jax.scipy.special.gammaincc`` (the regularised
upper incomplete gamma function) for the survival function; no scipy.
"""

from __future__ import annotations

import math

import jax.scipy.special
import numpy as np

__all__ = ["autocorrelation", "ljung_box", "chi2_sf", "chi2_sf_1", "default_lags"]

#: the most lags :func:`default_lags` takes (Ljung & Box 1978 use 20 to 30 for series of a few
#: hundred samples; more lags dilute a short-memory colouring, the kind a model error gives)
MAX_LAGS = 20


def default_lags(n: int) -> int:
    """The number of lags of a Ljung-Box test on sequences of ``n`` samples:
    ``min(MAX_LAGS, n // 5)``, at least 1 (the statistic's chi-square approximation needs the
    lags to be a small fraction of n)."""
    return max(1, min(MAX_LAGS, int(n) // 5))


def autocorrelation(z, lags: int) -> tuple[np.ndarray, int]:
    """Sample autocorrelations at lags 1..``lags`` of one sequence (T,) or of several pooled
    (R, T) (module docstring), NaN samples missing.

    ``rho_k = (c_k / c_0) (T - k) / T`` with ``c_k`` the mean of ``d_t d_{t+k}`` over the
    pairs where both are present (within each row), ``c_0`` the mean of ``d_t^2`` over the
    present samples, ``d`` the deviations from the mean of all present samples; the factor
    makes it the biased estimator of the complete-data case.

    Returns:
        (rho (lags,), n the number of present samples); rho_k is NaN where no pair is present
        or the sequence is constant.
    """
    z = np.atleast_2d(np.asarray(z, dtype=float))
    T = z.shape[1]
    present = np.isfinite(z)
    n = int(present.sum())
    rho = np.full(int(lags), np.nan)
    if n == 0:
        return rho, 0
    d = np.where(present, z - z[present].mean(), 0.0)
    c0 = float(np.sum(d * d)) / n
    if not c0 > 0:
        return rho, n
    for k in range(1, min(int(lags), T - 1) + 1):
        pairs = int(np.sum(present[:, :-k] & present[:, k:]))
        if pairs:
            ck = float(np.sum(d[:, :-k] * d[:, k:])) / pairs
            rho[k - 1] = ck / c0 * (T - k) / T
    return rho, n


def ljung_box(rho, n: int) -> float:
    """The Ljung-Box statistic ``Q = n (n + 2) sum_{k=1..L} rho_k^2 / (n - k)`` (Ljung & Box
    1978, "On a measure of lack of fit in time series models"), L = len(rho); about
    chi-square with L degrees of freedom for a white sequence of n samples. NaN when a rho is
    NaN or n <= L."""
    rho = np.asarray(rho, dtype=float)
    L = rho.shape[0]
    if n <= L or not np.all(np.isfinite(rho)):
        return float("nan")
    k = np.arange(1, L + 1)
    return float(n * (n + 2) * np.sum(rho**2 / (n - k)))


def chi2_sf(q: float, dof: int) -> float:
    """P(X > q) for X chi-square with ``dof`` degrees of freedom: the regularised upper
    incomplete gamma function ``Q(dof / 2, q / 2)`` (``jax.scipy.special.gammaincc``; float64
    as vehjax sets it);
    NaN for a NaN q. Below about 1e-300 it is 0 (underflow)."""
    if not np.isfinite(q):
        return float("nan") if np.isnan(q) else 0.0
    if q <= 0:
        return 1.0
    return float(jax.scipy.special.gammaincc(np.float64(dof / 2.0), np.float64(q / 2.0)))


def chi2_sf_1(q: float) -> float:
    """P(X > q) for X chi-square with one degree of freedom: ``erfc(sqrt(q / 2))`` (exact, and
    accurate far into the tail, where ``1 - cdf`` would round to 0); NaN for a NaN or negative
    q."""
    if not (np.isfinite(q) and q >= 0):
        return 0.0 if q == np.inf else float("nan")
    return math.erfc(math.sqrt(q / 2.0))
