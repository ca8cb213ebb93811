"""Resampling schemes for particle filters, as pure functions returning ancestor indices.

Every scheme takes a PRNG key and log weights (unnormalised is fine; they are normalised with
``logsumexp``) and returns ``n`` ancestor indices, int array of shape (n,): particle ``i`` is
copied ``N_i = sum(idx == i)`` times, with ``E[N_i] = n w_i`` for all four schemes. They differ in
the variance of the offspring counts ``N_i`` (Douc, Cappe & Moulines 2005):

    multinomial  n iid draws from w:                        Var N_i = n w_i (1 - w_i)
    residual     floor(n w_i) copies, the rest multinomial:  Var N_i = f_i (1 - f_i / r)
    stratified   one uniform in each of n strata:            between systematic and multinomial
    systematic   one uniform shifted over n strata:          Var N_i = f_i (1 - f_i), the least
                                                             any unbiased integer count can have

with ``f_i = n w_i - floor(n w_i)`` and ``r = sum_i f_i``. All are jit- and vmap-friendly: static
shapes, no Python loops. Systematic and stratified cost O(N) (a scatter-add and a cumulative sum
instead of a binary search); multinomial and residual use ``searchsorted``.

Particles with weight zero (log weight -inf) never get offspring. Log weights that are all -inf
or NaN have no distribution to draw from; the indices are then ``arange(n) % N`` (callers detect
that case themselves, see :func:`vehjax.filters.particle.bootstrap_pf`).
"""

from __future__ import annotations

import operator

import jax
import jax.numpy as jnp
from jax.scipy.special import logsumexp

SCHEMES = ("systematic", "stratified", "multinomial", "residual")


def check_scheme(scheme, arg: str = "resampling") -> str:
    """``scheme`` if it names a resampling scheme, else ValueError naming ``arg`` (the caller's
    argument: ``resampling`` of the filter builders, ``scheme`` of :func:`resample`) and listing
    the valid names."""
    if not isinstance(scheme, str) or scheme not in SCHEMES:
        raise ValueError(f"{arg}: expected one of {SCHEMES}, got {scheme!r}")
    return scheme


def _check_log_weights(log_weights):
    log_weights = jnp.asarray(log_weights)
    if log_weights.ndim != 1 or log_weights.shape[0] < 1:
        raise ValueError(
            f"log_weights: expected a 1-D array of at least one log weight, got shape "
            f"{log_weights.shape}"
        )
    if not jnp.issubdtype(log_weights.dtype, jnp.floating):
        log_weights = log_weights.astype(jnp.result_type(float))
    return log_weights


def _check_n(n, default: int) -> int:
    if n is None:
        return default
    try:
        value = operator.index(n)
    except TypeError:
        value = 0
    if isinstance(n, bool) or value < 1:
        raise ValueError(f"n: expected a positive int number of indices, got {n!r}")
    return value


def normalised_cdf(log_weights):
    """Cumulative sum of the normalised weights, (N,), with the last entry exactly 1.

    All-(-inf)/NaN log weights give the uniform distribution's CDF, so that the indices drawn
    from it stay in range; the caller decides what such a draw means.
    """
    lw = log_weights - logsumexp(log_weights)
    w = jnp.exp(lw)
    return cdf_from_weights(w)


def cdf_from_weights(w):
    """CDF of normalised-or-not weights ``w`` (N,) >= 0, last entry exactly 1; see above."""
    cs = jnp.cumsum(jnp.where(jnp.isfinite(w), w, 0.0))
    total = cs[-1]
    ok = total > 0.0
    n = w.shape[0]
    uniform = jnp.arange(1, n + 1, dtype=cs.dtype) / n
    return jnp.where(ok, cs / jnp.where(ok, total, 1.0), uniform)


def _counts_to_indices(counts, n: int, n_particles: int):
    """Ancestor indices (n,) from non-decreasing cumulative offspring counts ``counts`` (N,).

    ``counts[i]`` is the number of offspring of particles 0..i, so the k-th offspring belongs to
    the first particle whose cumulative count exceeds k: ``idx_k = #{i : counts[i] <= k}``. A
    histogram of the counts followed by a cumulative sum gives that in O(N + n).
    """
    counts = jnp.clip(counts, 0, n)
    hist = jnp.zeros(n + 1, dtype=jnp.int32).at[counts].add(1, mode="promise_in_bounds")
    idx = jnp.cumsum(hist[:n], dtype=jnp.int32)
    return jnp.minimum(idx, n_particles - 1)


# -- cores: CDF (N,) and uniforms in [0, 1) -> indices; the particle filter calls these ----------


def _systematic_from_cdf(cdf, u, n: int):
    """Systematic: points (k + u) / n, k = 0..n-1, for one uniform ``u``."""
    counts = jnp.ceil(n * cdf - u).astype(jnp.int32)
    return _counts_to_indices(counts, n, cdf.shape[0])


def _stratified_from_cdf(cdf, u, n: int):
    """Stratified: points (k + u_k) / n for ``u`` of shape (n,).

    Particle i's cumulative count is #{k : k + u_k < n cdf_i}: all k below floor(n cdf_i), plus
    k0 = floor(n cdf_i) itself when u_k0 < frac(n cdf_i).
    """
    x = n * cdf
    k0 = jnp.floor(x)
    k0i = jnp.clip(k0.astype(jnp.int32), 0, n - 1)
    extra = (u[k0i] < x - k0) & (k0 < n)
    counts = k0.astype(jnp.int32) + extra.astype(jnp.int32)
    return _counts_to_indices(counts, n, cdf.shape[0])


def _multinomial_from_cdf(cdf, u):
    """Multinomial: iid points ``u`` (n,) through the inverse CDF."""
    idx = jnp.searchsorted(cdf, u, side="right").astype(jnp.int32)
    return jnp.minimum(idx, cdf.shape[0] - 1)


def _residual_from_weights(w, u, n: int):
    """Residual: floor(n w_i) copies of particle i, the remaining r = n - sum floor(n w_i)
    offspring drawn iid from the residual weights n w_i - floor(n w_i). ``w`` normalised (N,),
    ``u`` (n,) uniforms of which the last r are used.
    """
    nw = n * jnp.where(jnp.isfinite(w), w, 0.0)
    det = jnp.floor(nw)
    counts = jnp.cumsum(det.astype(jnp.int32))
    n_det = counts[-1]
    idx_det = _counts_to_indices(counts, n, w.shape[0])
    idx_res = _multinomial_from_cdf(cdf_from_weights(nw - det), u)
    return jnp.where(jnp.arange(n) < n_det, idx_det, idx_res)


def _uniforms(key, shape, dtype):
    return jax.random.uniform(key, shape, dtype=dtype)


# -- public schemes ---------------------------------------------------------------------------


def systematic(key, log_weights, n: int | None = None):
    """Systematic resampling (Kitagawa 1996; Carpenter, Clifford & Fearnhead 1999).

    Args:
        key: PRNG key.
        log_weights: log weights, (N,), possibly unnormalised.
        n: number of indices to draw; N when omitted.

    Returns:
        Ancestor indices, (n,) int32, non-decreasing.
    """
    log_weights = _check_log_weights(log_weights)
    n = _check_n(n, log_weights.shape[0])
    u = _uniforms(key, (), log_weights.dtype)
    return _systematic_from_cdf(normalised_cdf(log_weights), u, n)


def stratified(key, log_weights, n: int | None = None):
    """Stratified resampling (Kitagawa 1996): one independent uniform in each of n strata.

    Args and returns as :func:`systematic`.
    """
    log_weights = _check_log_weights(log_weights)
    n = _check_n(n, log_weights.shape[0])
    u = _uniforms(key, (n,), log_weights.dtype)
    return _stratified_from_cdf(normalised_cdf(log_weights), u, n)


def multinomial(key, log_weights, n: int | None = None):
    """Multinomial resampling: n independent draws from the weights (Gordon et al. 1993).

    Args and returns as :func:`systematic`; the indices are in draw order, not sorted.
    """
    log_weights = _check_log_weights(log_weights)
    n = _check_n(n, log_weights.shape[0])
    u = _uniforms(key, (n,), log_weights.dtype)
    return _multinomial_from_cdf(normalised_cdf(log_weights), u)


def residual(key, log_weights, n: int | None = None):
    """Residual resampling (Liu & Chen 1998): deterministic copies, multinomial remainder.

    Args and returns as :func:`systematic`.
    """
    log_weights = _check_log_weights(log_weights)
    n = _check_n(n, log_weights.shape[0])
    u = _uniforms(key, (n,), log_weights.dtype)
    lw = log_weights - logsumexp(log_weights)
    return _residual_from_weights(jnp.exp(lw), u, n)


_PUBLIC = {
    "systematic": systematic,
    "stratified": stratified,
    "multinomial": multinomial,
    "residual": residual,
}


def resample(key, log_weights, scheme: str = "systematic", n: int | None = None):
    """Ancestor indices (n,) int32 from ``log_weights`` (N,) with the named scheme.

    Args:
        key: PRNG key.
        log_weights: log weights, (N,), possibly unnormalised.
        scheme: one of ``SCHEMES``: "systematic", "stratified", "multinomial", "residual".
        n: number of indices to draw; N when omitted.
    """
    return _PUBLIC[check_scheme(scheme, "scheme")](key, log_weights, n)


def uniforms_needed(scheme: str, n: int) -> int:
    """How many uniforms a scheme's core consumes for n indices (1 for systematic, else n)."""
    return 1 if check_scheme(scheme, "scheme") == "systematic" else n


def indices_from_uniforms(scheme: str, w, u, n: int):
    """Ancestor indices (n,) from normalised weights ``w`` (N,) and uniforms ``u`` in [0, 1).

    ``u`` has shape (uniforms_needed(scheme, n),); a scalar is accepted for systematic. This is
    the core the particle filter calls with uniforms it draws together with its process noise.
    """
    scheme = check_scheme(scheme, "scheme")
    if scheme == "residual":
        return _residual_from_weights(w, u, n)
    cdf = cdf_from_weights(w)
    if scheme == "systematic":
        return _systematic_from_cdf(cdf, jnp.reshape(u, (-1,))[0], n)
    if scheme == "stratified":
        return _stratified_from_cdf(cdf, u, n)
    return _multinomial_from_cdf(cdf, u)
