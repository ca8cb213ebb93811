"""Jeffreys' prior over a grid of one variance parameter, from the covariance part of the
expected Fisher information of a Gaussian predictive (``marginalized_pf_grid``'s default
``InputStdGrid(input_std_prior="jeffreys")``).

Why. A variance that enters the data beside other noise (the steering noise sigma_w^2 seen
through vy and r beside the sensors' noise) is a variance component: the predictive covariance
is S(sigma) = a sigma^2 + c, the data say little about sigma once a sigma^2 << c, and the
log-likelihood is flat below the truth and steep above it (paper 004's simulation, 180 s:
0.5x the truth costs 2.7 nats per run, 2x costs 33). Under a flat prior in log sigma the
posterior then keeps mass far below the truth, and the states' covariance, which scales with
sigma^2, is too small (NEES of (vy, r) 1.23 per dof with the sensor noise known). Jeffreys'
prior, p(theta) proportional to sqrt(I(theta)) (Jeffreys 1946), is invariant to the
parametrisation and, for one parameter, matches frequentist coverage to first order (Welch &
Peers 1963); here it weighs each grid point by how much the experiment can tell about sigma
there, so the flat low end loses its weight.

The information. For Gaussian predictives y_t | y_1:t-1 ~ N(m_t(theta), S_t(theta)), the
expected Fisher information of theta over the data to t is (the innovations form, e.g. Cavanaugh
& Shumway 1996)

    I_t(theta) = sum_s [ 0.5 tr((S_s^-1 dS_s)^2) + E(dm_s^T S_s^-1 dm_s) ],

d the total derivative in theta. Only the first (covariance) term is computed: it needs each
grid point's S_s and their derivative, which the grid gives by central differences over its
neighbours (each neighbour's S_s already carries the whole history at its own theta); the second
needs a sensitivity recursion of the means. The covariance term is a lower bound of about
the same shape: on paper 004's simulation (the sensor noise known, 8 runs x 180 s) it is 0.41,
0.46 and 0.65 of a Monte-Carlo estimate of the whole information at 1, 2 and 4 times the true
std, and both grow about 13-fold from 1 to 2 times (``python benchmarks/
mpf_consistent_steering.py information 8 180``). The prior is
recomputed from the information so far at every step (the grid is never resampled, so the
posterior is the likelihood times the current prior): at each time, the posterior is the one
Jeffreys' rule gives for the experiment run so far. For a linear model with the other
covariances known S_s depends on the inputs alone, so the prior does not look at the
measurements; with the sensor covariance learnt it sees them through that estimate.

theta here is log sigma^2 (the grid is uniform in it); any other smooth parametrisation
changes I by a constant factor over a log-uniform grid, which the normalisation removes.
"""

from __future__ import annotations

import jax.numpy as jnp

from ...lib.entrywise import chol_masked, entries
from ...lib.linalg import forward_entries

__all__ = ["grid_derivative", "covariance_information", "log_prior"]


def grid_derivative(S, theta):
    """dS / dtheta at each grid point by central differences over its neighbours (one-sided at
    the ends): ``S`` (..., N) values at the grid ``theta`` (N,), increasing, N >= 2.
    Second-order accurate on a uniform grid."""
    return jnp.gradient(S, theta, axis=-1)


def covariance_information(S, dS, obs):
    """0.5 tr((S^-1 dS)^2) per grid point over the observed components: the covariance part of
    the Fisher information of one Gaussian predictive.

    Args:
        S: (n, n, N) predictive covariances, one per grid point (particles last).
        dS: (n, n, N) their derivatives in the parameter.
        obs: (n,) bool, the observed components (the others contribute nothing).

    Returns:
        (N,) information, >= 0; 0 where S or dS is not finite.
    """
    n = S.shape[0]
    ob = [obs[i] for i in range(n)]
    L = chol_masked(entries(S), ob)  # entry by entry over the grid (N,): no batched LAPACK
    dSe = [[jnp.where(ob[i] & ob[j], dS[i, j], 0.0) for j in range(n)] for i in range(n)]
    # S^-1 dS is similar to B = L^-1 dS L^-T (symmetric), whose squared Frobenius norm is the
    # trace of its square
    X = [forward_entries(L, [dSe[i][j] for i in range(n)]) for j in range(n)]  # X[j][i]
    B = [forward_entries(L, [X[i][j] for i in range(n)]) for j in range(n)]
    info = 0.5 * sum(B[j][i] * B[j][i] for i in range(n) for j in range(n))
    return jnp.where(jnp.isfinite(info), info, 0.0)


def log_prior(info):
    """Jeffreys' log prior weights 0.5 log I over the grid, normalised (N,). Where every point's
    information is still zero (before any datum), equal weights."""
    tiny = jnp.finfo(info.dtype).tiny
    lp = 0.5 * jnp.log(jnp.maximum(info, tiny))
    lp = jnp.where(jnp.max(info) > 0.0, lp, 0.0)
    return lp - jnp.log(jnp.sum(jnp.exp(lp - jnp.max(lp)))) - jnp.max(lp)
