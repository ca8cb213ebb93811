"""The one particle core: weights, effective sample size, resampling, re-initialisation, moments
and random draws, shared by every particle filter (bootstrap PF, Liu-West PF + UKF, the
noise-adaptive marginalized PF).

Layout: the particle axis is the LAST axis of every leaf of a particle pytree: states (n, N),
per-particle vectors (d, N), per-particle matrices (d, d, N), weights (N,). Each component is
then one contiguous vector over the particles, which XLA on CPU runs as one vectorised loop
instead of a loop over particles of short rows (``vehjax bench particle``'s "model (N, nx)" and
"model (nx, N)" rows measure the two layouts).

One step of a particle filter with this core::

    r = reweight(log_w_prior, log_lik)          # normalised weights, loglik increment, underflow
    particles, log_w, w, did = resample(particles, r.w, r.log_w, u, scheme, threshold)
    mean, cov = moments(w, x)

Weights stay in log space. ``reweight``'s increment ``log sum_i W_i l_i`` is the standard
unbiased estimator of p(y_t | y_1:t-1) in log form (Del Moral 2004). When every particle's
likelihood underflows (the increment below ``log(finfo.tiny)``, about -708 in float64, or not
finite), ``underflow`` is set: the weights carry no information and the filter re-initialises in
its own way (:func:`reinitialise` gives it uniform weights and fresh particles) and reports
``StepOutput.reinit``.

Random numbers: keys are raw (2,) uint32 Threefry keys carried in the filter state.
:func:`normals` and :func:`uniforms` hash counters in straight-line code
(:mod:`vehjax.runtime.prng`, which says why that is cheaper than ``jax.random`` in float64 on CPU:
no rolled hash loop, no 64-bit uniforms and inverse error function).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import validation
from ..runtime import prng
from . import resampling as _rs
from ..lib.gaussian import log_density
from ..lib.linalg import cholesky, logdet_from_chol, solve_lower

__all__ = [
    "Reweighted", "reweight", "ess", "resample", "resample_stop_gradient", "check_resample",
    "equal_weights", "stop_gradient_weights", "reinitialise", "moments", "mixture",
    "normals",
    "uniforms", "split", "raw_key", "log_tiny", "check_n_particles",
    "check_ess_threshold", "gaussian_logliks", "step_loglik",
]

_UNROLL = 64  # matrices with at most this many entries are handled with unrolled scalar code


class Reweighted(NamedTuple):
    """Result of :func:`reweight`.

    Attributes:
        log_w: (N,) normalised log weights (``logsumexp == 0``); NaN entries on underflow.
        w: (N,) the same weights, ``exp(log_w)``.
        loglik: the increment log sum_i W_i^prior l_i, scalar (-inf or NaN on underflow).
        underflow: bool scalar, the increment is below ``log(finfo.tiny)`` or not finite.
    """

    log_w: jnp.ndarray
    w: jnp.ndarray
    loglik: jnp.ndarray
    underflow: jnp.ndarray


def log_tiny(dtype) -> float:
    """log of the smallest normal number of ``dtype``: the underflow threshold."""
    return float(np.log(np.finfo(np.dtype(dtype)).tiny))


def check_n_particles(n_particles, name: str = "n_particles") -> int:
    """``n_particles`` as an int in [2, 2**30] (one particle has no weights to compare or
    resample), else ValueError naming it (``name``, e.g. a record's field): the one rule of
    every particle filter and sampler."""
    return validation.integer(name, n_particles, 2, 2**30)


def check_ess_threshold(ess_threshold) -> float:
    """A resampling threshold in [0, 1], else ValueError naming ``ess_threshold``."""
    return validation.number("ess_threshold", ess_threshold, 0.0, 1.0, low_open=False,
                            high_open=False)


def reweight(log_w_prior, log_lik) -> Reweighted:
    """Multiply weights by likelihoods and normalise, in log space.

    Args:
        log_w_prior: (N,) normalised log weights before the update.
        log_lik: (N,) log-likelihood of each particle; NaN counts as -inf (weight zero).
    """
    lw_un = log_w_prior + jnp.where(jnp.isnan(log_lik), -jnp.inf, log_lik)
    top = jnp.max(lw_un)
    top = jnp.where(jnp.isfinite(top), top, 0.0)
    w_un = jnp.exp(lw_un - top)
    total = jnp.sum(w_un)
    incr = top + jnp.log(total)
    return Reweighted(lw_un - incr, w_un / total, incr, ~(incr > log_tiny(lw_un.dtype)))


def gaussian_logliks(e, obs, L=None, var=None):
    """Per-particle log N(e_i; 0, S) over the observed components: e (ny, N) residuals with zeros
    on the missing ones, ``obs`` (ny,) bool; S given by ``L = cholesky_observed(S, obs)``
    (:func:`vehjax.lib.entrywise.cholesky_observed`) or, for a diagonal S, by its variances
    ``var`` (ny,) (cheaper). :func:`vehjax.lib.gaussian.log_density` with the particles in
    columns. Returns (N,)."""
    n_obs = jnp.sum(obs)
    if var is not None:
        q = jnp.sum(e * e * (1.0 / var)[:, None], axis=0)
        logdet = jnp.sum(jnp.where(obs, jnp.log(var), 0.0))
    else:
        q = jnp.sum(solve_lower(L, e) ** 2, axis=0)
        logdet = logdet_from_chol(L)
    return log_density(q, logdet, n_obs)


def step_loglik(r: Reweighted):
    """The step's reported log-likelihood: the increment when finite, ``log(finfo.tiny)`` after
    an underflow (a run that re-initialises keeps a finite log-likelihood)."""
    return jnp.where(jnp.isfinite(r.loglik), r.loglik, log_tiny(r.log_w.dtype))


def ess(w):
    """Effective sample size 1 / sum_i w_i^2 of normalised weights w (N,)."""
    return 1.0 / jnp.sum(w * w)


def _gather(a, idx):
    """``a[..., idx]``; small 2-D leaves row by row (one gather per contiguous row, which XLA
    on CPU vectorises, rather than one gather of short columns)."""
    if a.ndim == 2 and 0 < a.shape[0] and a.shape[0] * a.shape[0] <= _UNROLL:
        return jnp.stack([a[i][idx] for i in range(a.shape[0])])
    return jnp.take(a, idx, axis=-1)


def _resample(particles, w, log_w, u, scheme: str, threshold: float, resampled_weights):
    """The part every resampling function shares: when ESS < threshold * N, gather every leaf
    of ``particles`` along its last axis by the scheme's ancestor indices and give the
    resampled particles the weights ``resampled_weights(log_w_ancestors (N,), n) -> (log_w,
    w)``; otherwise everything as it was. Arguments and result as :func:`resample`.

    The indices are computed from ``stop_gradient(w)``: they are integers, piecewise constant
    in the weights, so this changes no value and no gradient; it keeps the index computation
    out of differentiation."""
    n = w.shape[-1]
    if threshold <= 0.0:
        return particles, log_w, w, jnp.zeros((), bool)
    idx = _rs.indices_from_uniforms(scheme, jax.lax.stop_gradient(w), u, n)
    do = ess(w) < threshold * n
    particles = jax.tree.map(lambda a: jnp.where(do, _gather(a, idx), a), particles)
    lw_new, w_new = resampled_weights(jnp.take(log_w, idx), n)
    return particles, jnp.where(do, lw_new, log_w), jnp.where(do, w_new, w), do


def equal_weights(log_w_ancestors, n: int):
    """Weights of N resampled particles: log W = -log N and W = 1/N for each, whatever its
    ancestor's log weight ``log_w_ancestors`` (N,). Returns Python floats (constants)."""
    del log_w_ancestors
    return -math.log(n), 1.0 / n


def stop_gradient_weights(log_w_ancestors, n: int):
    """Weights of N resampled particles for stop-gradient resampling (Scibior & Wood 2021,
    "Differentiable particle filtering without modifying the forward pass"): particle i with
    ancestor a gets log W_i = -log N + log W_a - stop_gradient(log W_a), equal in value to
    :func:`equal_weights` (-log N, 1/N), with the ancestor's log weight in the gradient.
    An ancestor whose log weight is not finite contributes 0 (value and gradient).

    Args:
        log_w_ancestors: (N,) normalised log weights of each resampled particle's ancestor.
        n: number of particles N.

    Returns:
        (log_w (N,), w (N,)).
    """
    lw_a = log_w_ancestors
    corr = jnp.where(jnp.isfinite(lw_a), lw_a - jax.lax.stop_gradient(lw_a), 0.0)  # 0 in value
    return corr - math.log(n), (1.0 / n) * jnp.exp(corr)


def resample(particles, w, log_w, u, scheme: str, threshold: float):
    """Resample when ESS < threshold * N, gathering every leaf of ``particles`` along its last
    axis.

    Args:
        particles: pytree of arrays, particle axis last (N).
        w, log_w: (N,) normalised weights and their logs.
        u: uniforms in [0, 1) for the scheme, ``uniforms_needed(scheme, N)`` of them
            (:func:`uniforms`).
        scheme: "systematic", "stratified", "multinomial" or "residual".
        threshold: in [0, 1]; 0 never resamples.

    Returns:
        (particles, log_w, w, resampled): resampled ones get equal weights 1/N.
    """
    return _resample(particles, w, log_w, u, scheme, threshold, equal_weights)


def resample_stop_gradient(particles, w, log_w, u, scheme: str, threshold: float):
    """:func:`resample` with stop-gradient weights (:func:`stop_gradient_weights`): the same
    values (particles, indices, decisions, weights), and after a resampling each particle's
    log weight carries its ancestor's log weight in the gradient, so that the gradient of a
    particle filter's log-likelihood estimate is the Fisher-identity estimate of the score
    (consistent, bias O(1/N)). Same signature and result as :func:`resample`; pass it to a
    particle filter's builder as ``resample=`` (``bootstrap_pf``, ``liu_west_ukf``)."""
    return _resample(particles, w, log_w, u, scheme, threshold, stop_gradient_weights)


def check_resample(resample_fn):
    """The resampling function a particle filter's builder was given: None is :func:`resample`;
    a callable with :func:`resample`'s signature ``(particles, w, log_w, u, scheme, threshold)
    -> (particles, log_w, w, resampled)`` is itself; anything else raises ValueError naming
    ``resample``."""
    if resample_fn is None:
        return resample
    if not callable(resample_fn):
        raise ValueError(
            f"resample: expected None or a resampling function with the signature of "
            f"vehjax.filters.smc.resample(particles, w, log_w, u, scheme, threshold) (e.g. "
            f"vehjax.filters.smc.resample_stop_gradient), got {resample_fn!r}")
    return resample_fn


@dataclasses.dataclass(frozen=True)
class Resampling:
    """How a particle filter resamples, the option ``resampling`` of
    :func:`~vehjax.filters.bootstrap_pf`, :func:`~vehjax.filters.liu_west_ukf` and
    :func:`~vehjax.filters.marginalized_pf`.

    Attributes:
        scheme: "systematic", "stratified", "multinomial" or "residual"
            (:mod:`vehjax.filters.resampling`).
        ess_threshold: resample when ESS < ess_threshold * N, in [0, 1]; 0 never resamples, 1
            whenever the weights are not all equal.
        resample: the resampling function, None (default) for :func:`resample`; a callable with
            its signature ``(particles, w, log_w, u, scheme, threshold) -> (particles, log_w,
            w, resampled)``, e.g. :func:`resample_stop_gradient` (the same forward pass, the
            resampling's score in the gradient: what :mod:`vehjax.tune` differentiates).
    """

    scheme: str = "systematic"
    ess_threshold: float = 0.5
    resample: Any = None

    def __post_init__(self):
        _rs.check_scheme(self.scheme, "scheme")
        object.__setattr__(self, "ess_threshold", check_ess_threshold(self.ess_threshold))
        check_resample(self.resample)

    def function(self):
        """The resampling function: ``resample``, or :func:`resample` for None."""
        return check_resample(self.resample)


def reinitialise(underflow, fresh, particles, log_w, w):
    """Where ``underflow``: the ``fresh`` particles (same pytree structure) with equal weights;
    otherwise everything as it was. Returns (particles, log_w, w)."""
    n = w.shape[-1]
    particles = jax.tree.map(lambda a, b: jnp.where(underflow, a, b), fresh, particles)
    return particles, jnp.where(underflow, -math.log(n), log_w), jnp.where(underflow, 1.0 / n, w)


def moments(w, x):
    """Weighted mean (n,) and symmetric covariance (n, n) of the columns of x (n, N), weights
    w (N,) summing to 1. For small n row by row (full reductions, cheap on CPU)."""
    n = x.shape[0]
    if n * n > _UNROLL:
        mean = x @ w
        d = x - mean[:, None]
        cov = (d * w) @ d.T
        return mean, 0.5 * (cov + cov.T)
    cols = [x[i] for i in range(n)]
    mean = jnp.stack([jnp.sum(w * c) for c in cols])
    d = [c - mean[i] for i, c in enumerate(cols)]
    wd = [w * di for di in d]
    entries = {}
    for i in range(n):
        for j in range(i, n):
            entries[i, j] = entries[j, i] = jnp.sum(wd[i] * d[j])
    cov = jnp.stack([jnp.stack([entries[i, j] for j in range(n)]) for i in range(n)])
    return mean, cov


def mixture(w, means, covs=None, start: int = 0):
    """Mean (n,) and covariance (n, n) of a mixture of N Gaussians with weights w (N,) summing
    to 1 and means the columns of ``means`` (n, N): the spread of the means (:func:`moments`)
    plus the weighted mean of the components' covariances ``covs`` (n - start, n - start, N),
    which cover the trailing states from index ``start`` (the earlier states, e.g. a
    marginalized filter's sampled ones, are point masses in each component); None: all
    point masses (the particles' moments)."""
    mean, cov = moments(w, means)
    if covs is not None:
        cov = cov.at[start:, start:].add(jnp.einsum("ijn,n->ij", covs, w))
    return mean, cov


def shrink_move(z, particles, mean, V, a: float):
    """Liu & West's (2001) kernel move of static-parameter particles (p, M): each to
    N(a theta_i + (1 - a) mean, (1 - a^2) V), z (p, M) standard normals, V (p, p).

    With weights W summing to 1 whose weighted mean and covariance of ``particles`` are
    ``mean`` and ``V``, the moved cloud has the same weighted mean and covariance in expectation
    (the shrinkage a in (0, 1) offsets the jitter's added variance).
    """
    L_V = cholesky(V)
    return a * particles + (1.0 - a) * mean[:, None] + math.sqrt(1.0 - a * a) * (L_V @ z)


def normals(key, rows: int, n: int, dtype, stream: int = 0):
    """(rows, n) standard normals from a raw key, by counter hashing and Box-Muller (see
    :func:`vehjax.runtime.prng.std_normal_rows`: resolution ~1e-7, |z| <= 5.77)."""
    return prng.std_normal_rows(key, rows, n, dtype, stream=stream)


def uniforms(key, scheme: str, n: int, dtype, stream: int = 0):
    """The uniforms :func:`resample` needs for ``scheme`` and N = n, from a raw key."""
    return prng.uniforms(key, _rs.uniforms_needed(scheme, n), dtype, stream=stream)


def split(key):
    """(next key, sub-key) from a raw (2,) uint32 key."""
    return prng.split(key)


def raw_key(key):
    """A raw (2,) uint32 key from any JAX PRNG key."""
    return prng.raw_key(key)
