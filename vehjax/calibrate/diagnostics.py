"""The draws of a particle MCMC run and their diagnostics.

Split R-hat (:func:`split_rhat`, Gelman et al., BDA3 sec. 11.4) and the effective sample size
(:func:`effective_sample_size`, BDA3 sec. 11.5 with Geyer's initial positive sequence) of every
quantity; :class:`PMMHResult` holds the chains' draws after warm-up with both (:func:`result`).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .priors import to_physical

__all__ = ["PMMHResult", "result", "split_rhat", "effective_sample_size"]


class PMMHResult(NamedTuple):
    """The draws of :func:`pmmh` after warm-up and their diagnostics.

    Attributes:
        names: the calibrated quantities, d names.
        samples: (chains, samples, d) draws in physical units.
        loglik: (chains, samples) the likelihood estimate held with each draw.
        acceptance: (chains,) acceptance rate after warm-up.
        mean, std: (d,) posterior mean and std over all chains' draws.
        rhat: (d,) split R-hat (< 1.01 to 1.05 for well-mixed chains).
        ess: (d,) effective sample size over all chains.
        proposal_cov: (d, d) the random walk's covariance after warm-up (unconstrained units).
    """

    names: tuple
    samples: np.ndarray
    loglik: np.ndarray
    acceptance: np.ndarray
    mean: np.ndarray
    std: np.ndarray
    rhat: np.ndarray
    ess: np.ndarray
    proposal_cov: np.ndarray

    def summary(self) -> str:
        """A table: name, mean, std, 2.5 / 97.5 % quantiles, R-hat, ESS."""
        flat = self.samples.reshape(-1, len(self.names))
        lines = [f"{'quantity':>14} {'mean':>12} {'std':>11} {'2.5%':>12} {'97.5%':>12} "
                 f"{'R-hat':>6} {'ESS':>7}"]
        for k, name in enumerate(self.names):
            lo, hi = np.percentile(flat[:, k], [2.5, 97.5])
            lines.append(f"{name:>14} {self.mean[k]:12.5g} {self.std[k]:11.4g} {lo:12.5g} "
                         f"{hi:12.5g} {self.rhat[k]:6.3f} {self.ess[k]:7.0f}")
        lines.append(f"acceptance {np.mean(self.acceptance):.2f} ({self.samples.shape[0]} chains "
                     f"x {self.samples.shape[1]} draws)")
        return "\n".join(lines)


def result(names, prs, zs, lls, acc, L, warmup) -> PMMHResult:
    """The chains' draws after ``warmup`` in physical units, with their summaries: zs (chains,
    draws, d) unconstrained, lls the log-likelihood (or joint) per draw, acc the acceptances,
    L the proposal's Cholesky factor."""
    zs = np.asarray(zs)[:, warmup:]
    x = np.asarray(jax.vmap(jax.vmap(lambda z: to_physical(prs, z)))(jnp.asarray(zs)))
    flat = x.reshape(-1, len(names))
    L = np.asarray(L)
    return PMMHResult(
        names=names, samples=x, loglik=np.asarray(lls)[:, warmup:],
        acceptance=np.asarray(acc)[:, warmup:].mean(axis=1),
        mean=flat.mean(axis=0), std=flat.std(axis=0, ddof=1),
        rhat=split_rhat(x), ess=effective_sample_size(x), proposal_cov=L @ L.T)


def _as_chains(draws) -> np.ndarray:
    x = np.asarray(draws, float)
    if x.ndim == 2:
        x = x[..., None]
    if x.ndim != 3 or x.shape[0] < 1 or x.shape[1] < 4:
        raise ValueError(f"draws: expected (chains, draws) or (chains, draws, d) with at least 4 "
                         f"draws, got shape {np.shape(draws)}")
    return x


def _split(x: np.ndarray) -> np.ndarray:
    """(M, N, d) -> (2M, N // 2, d): each chain's first and second half (a middle draw of an odd
    N dropped)."""
    n = x.shape[1] // 2
    return np.concatenate([x[:, :n], x[:, x.shape[1] - n:]], axis=0)


def split_rhat(draws) -> np.ndarray:
    """Split R-hat (Gelman et al., BDA3 eq. 11.4) of every quantity: (d,) or () for 2-D input.

    The chains (M, N[, d]) are cut in halves, giving m = 2M chains of n draws; with B the
    between-chain variance n / (m - 1) sum_j (mean_j - mean)^2 and W the mean within-chain
    variance (ddof 1), var+ = (n - 1) / n W + B / n and R-hat = sqrt(var+ / W).
    """
    x0 = np.asarray(draws)
    x = _split(_as_chains(draws))
    n = x.shape[1]
    means = x.mean(axis=1)
    B = n * means.var(axis=0, ddof=1)
    W = x.var(axis=1, ddof=1).mean(axis=0)
    var_plus = (n - 1) / n * W + B / n
    r = np.sqrt(var_plus / W)
    return r[0] if x0.ndim == 2 else r


def _autocov(x: np.ndarray) -> np.ndarray:
    """Biased autocovariance (divisor n) along axis 1 by FFT: (m, n, d) -> (m, n, d)."""
    n = x.shape[1]
    xc = x - x.mean(axis=1, keepdims=True)
    size = 1 << (2 * n - 1).bit_length()
    f = np.fft.rfft(xc, size, axis=1)
    return np.fft.irfft(f * np.conj(f), size, axis=1)[:, :n] / n


def effective_sample_size(draws) -> np.ndarray:
    """Effective sample size over all chains (BDA3 sec. 11.5, on split chains): (d,) or ().

    rho_t = 1 - (W - mean_j acov_j(t)) / var+, summed as tau = -1 + 2 sum_k (rho_2k + rho_2k+1)
    over Geyer's initial positive sequence (pairs while positive, made non-increasing);
    ESS = m n / tau.
    """
    x0 = np.asarray(draws)
    x = _split(_as_chains(draws))
    m, n, d = x.shape
    acov = _autocov(x)
    W = (acov[:, 0] * n / (n - 1)).mean(axis=0)
    B_over_n = x.mean(axis=1).var(axis=0, ddof=1)
    var_plus = (n - 1) / n * W + B_over_n
    rho = 1.0 - (W[None] - acov.mean(axis=0)) / var_plus[None]          # (n, d)
    ess = np.empty(d)
    for k in range(d):
        pairs = rho[: 2 * (n // 2), k].reshape(-1, 2).sum(axis=1)
        stop = np.flatnonzero(pairs <= 0.0)
        pairs = pairs[: stop[0] if stop.size else len(pairs)]
        pairs = np.minimum.accumulate(pairs) if pairs.size else pairs
        tau = max(-1.0 + 2.0 * pairs.sum(), 1.0 / np.log10(max(m * n, 10)))
        ess[k] = m * n / tau
    return ess[0] if x0.ndim == 2 else ess
