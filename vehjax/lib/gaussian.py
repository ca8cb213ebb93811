"""The Gaussian log-density, once: log N(e; 0, S) of the observed components of a residual.

Every filter, sampler and prior of vehjax scores a residual e against a Gaussian N(0, S) the same
way. With L the lower Cholesky factor of S (of its observed block, and the identity on the missing
components: :func:`vehjax.lib.entrywise.chol_masked`), the whitened residual w = L^-1 e (zeros on
the missing components), q = w^T w = e^T S^-1 e the squared Mahalanobis distance and
log det S = 2 sum_i log L_ii (the identity rows add 0):

    log N(e; 0, S) = -(q + log det S + n_obs log(2 pi)) / 2

over the n_obs observed components (the density of the observed sub-vector; a residual with no
observed component has log-density 0). :func:`log_density` is that formula; its callers compute
q and log det S in their own layout (matrices with the batch axes first, entries of
:mod:`vehjax.lib.entrywise`, particles in columns, diagonal variances), and
:func:`log_density_entries` is the entry-wise composition the entry-form Kalman updates share.

Reference: any multivariate-statistics text, e.g. Bishop (2006), Pattern Recognition and Machine
Learning, eq. 2.43. Limits: S must be positive definite on the observed components (a factor with
NaN entries gives NaN); nothing is validated here.
"""

from __future__ import annotations

import math

import jax.numpy as jnp

__all__ = ["LOG_2PI", "log_density", "logdet_entries", "log_density_entries"]

#: log(2 pi), the constant of the Gaussian log-density.
LOG_2PI = math.log(2.0 * math.pi)


def log_density(q, logdet, n_obs):
    """log N(e; 0, S) of ``n_obs`` observed components from ``q`` = e^T S^-1 e (the squared norm
    of the whitened residual) and ``logdet`` = log det S (of the observed block). Arrays that
    broadcast together (or Python numbers); ``n_obs`` (an integer or a float count) takes the
    floating dtype of ``q`` and ``logdet``."""
    n = jnp.asarray(n_obs).astype(jnp.result_type(q, logdet))
    return -0.5 * (q + logdet + n * LOG_2PI)


def logdet_entries(L):
    """log det(L L^T) = 2 sum_i log L_ii of a lower Cholesky factor given as nested lists
    (:mod:`vehjax.lib.entrywise`; the diagonal entries arrays of one shape)."""
    return 2.0 * sum(jnp.log(L[i][i]) for i in range(len(L)))


def log_density_entries(w, L, n_obs):
    """:func:`log_density` from a whitened residual ``w`` = L^-1 e (a list of entries, zeros on
    the missing components) and the factor ``L`` of S (nested lists, identity rows on the missing
    components). Returns (log-density, q = w^T w)."""
    q = 0.0
    for v in w:
        q = q + v * v
    return log_density(q, logdet_entries(L), n_obs), q
