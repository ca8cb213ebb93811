"""The posterior of a static parameter on a fixed grid uniform in t, reported whether or not the
grid resolves it: the steering variance of the consistent marginalized PF (t = log sigma_w^2,
``marginalized_pf_grid``), each particle a Kalman filter at its own
grid value, never resampled, so the log weights are the log posterior at the grid points (exact
given the sensor covariances).

Resolved. While the grid is fine against the posterior, the weighted moments are the
posterior's: for a Gaussian of std s sampled at spacing h, the worst relative error of the
variance over the grid's offsets is 0.02 % at s = 0.8 h, 2.3 % at 0.6 h, 14 % at 0.5 h and
59 % at 0.4 h (the error falls as exp(-2 pi^2 s^2 / h^2), Poisson summation); the mean's, in
units of s, 0.6 % at 0.6 h. :data:`RESOLVED` is 0.6.

Narrower, the weights fall on one or two points: the estimate is the nearest point, up to h / 2
from the posterior's mode, and the reported spread is anywhere from zero to h^2 / 4. There the
three log weights about the largest give the Laplace approximation: the parabola through them,
its vertex the mode and minus its inverse curvature the variance (exact for a Gaussian
posterior in t, the quadratic log-likelihood of many steps). It is used only where both the
parabola and the weights are narrower than :data:`RESOLVED` spacings: a skewed posterior, steep
on one side and flat on the other (the steering std's on paper 004's simulation, where the
sensors' noise hides the smaller values), has a sharp parabola but weights spread over many
points, which resolve it (paper 004's simulation unchanged: ``python benchmarks/
mpf_consistent_steering.py learn 100 180 25 jeffreys 1``).

Measured (``python benchmarks/mpf_grid_resolution.py 100 22 POINTS [known] [weighted]``: a
user-written linear bank model, 100 runs x 400 steps, data that pin sigma_w to about 6 %), the
steering std's 95 % interval's coverage with 25 points over a decade either side of the guess
(h = 0.38 in t, 19 % in sigma_w):

    =====================================  ==================  ===============  ==========
    sensor covariances                     weighted moments    with _grid       100 points
    =====================================  ==================  ===============  ==========
    known (guesses at the truth)           0.65 (reported std  0.98             0.98
                                           down to 1.2 %)
    learnt (scored, guesses twice truth)   0.80                0.95 (seed 21:   0.98 (0.96)
                                                               0.93)
    =====================================  ==================  ===============  ==========
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp

#: the grid resolves a posterior whose std in t is at least this many grid spacings (module
#: docstring): the weighted moments there, the Laplace approximation below
RESOLVED = 0.6


class GridPosterior(NamedTuple):
    """What :func:`grid_posterior` reads off the log weights (scalars): ``narrow`` whether the
    grid does not resolve the posterior; ``mode``, ``var`` the Laplace approximation's mean and
    variance of t (meaningful where ``narrow``); ``k`` the middle of its three points."""

    narrow: jnp.ndarray
    mode: jnp.ndarray
    var: jnp.ndarray
    k: jnp.ndarray


def grid_posterior(log_w, t) -> GridPosterior:
    """The Laplace approximation of the posterior over the grid ``t`` (N,) (uniform, ascending)
    from its log weights ``log_w`` (N,), normalised or not, and whether the grid resolves it.

    The parabola through (t_k-1, t_k, t_k+1) with k the largest weight's point: curvature c =
    (l_k-1 - 2 l_k + l_k+1) / h^2, mode t_k + h (l_k-1 - l_k+1) / (2 h^2 c), variance -1 / c.
    ``narrow`` where the largest weight is not at an end of the grid, the parabola is concave
    and finite, and both its std and the weights' own std are below :data:`RESOLVED` spacings
    (the parabola alone would take a skewed posterior, steep on one side of its mode and flat
    on the other, for a narrow one).
    """
    n = t.shape[0]
    w = jnp.exp(log_w - jnp.max(log_w))
    w = w / jnp.sum(w)
    mean = jnp.sum(w * t)
    var_w = jnp.sum(w * (t - mean) ** 2)
    top = jnp.argmax(log_w)
    k = jnp.clip(top, 1, n - 2)
    h = t[1] - t[0]
    lm, l0, lp = log_w[k - 1], log_w[k], log_w[k + 1]
    second = lm - 2.0 * l0 + lp
    ok = (top > 0) & (top < n - 1) & jnp.isfinite(second) & (second < 0.0)
    safe = jnp.where(ok, second, -1.0)
    mode = t[k] + 0.5 * h * (lm - lp) / safe
    var = -(h * h) / safe
    narrow = ok & jnp.isfinite(mode) & (jnp.maximum(var, var_w) < (RESOLVED * h) ** 2)
    return GridPosterior(narrow=narrow, mode=mode, var=var, k=k)


def ridge_covariance(post: GridPosterior, t, v):
    """Cov(v, t) of values ``v`` (m, N) that vary smoothly along the grid, under the Laplace
    approximation: the slope of v at the mode's point (central difference) times its variance,
    (m,)."""
    k = post.k
    slope = (v[:, k + 1] - v[:, k - 1]) / (t[k + 1] - t[k - 1])
    return slope * post.var


def std_moments(post: GridPosterior):
    """The std exp(t / 2) of t ~ N(mode, var): its reported estimate, the root of the mean
    variance E[exp(t)] = exp(mode + var / 2), and the mean squared deviation from it (as the
    grid's weighted spread about its estimate), 2 E[exp(t)] - 2 est E[exp(t / 2)]."""
    m, v = post.mode, post.var
    est = jnp.exp(0.5 * m + 0.25 * v)
    spread = 2.0 * jnp.exp(m + 0.5 * v) - 2.0 * jnp.exp(m + 0.375 * v)
    return est, spread


def with_resolved_std(params, params_cov, i, post: GridPosterior, within):
    """``params`` (p,), ``params_cov`` (p, p) with entry ``i`` (the std of the grid's
    parameter) from the Laplace approximation where the grid does not resolve the posterior:
    the estimate and spread of :func:`std_moments`, plus ``within`` (a within-point variance
    already in the weighted entry); its row and column scaled by the ratio of the stds, which
    keeps the matrix positive semi-definite (zero where the weighted variance was)."""
    # finite where not narrow too (the unused branch of a where still meets gradients)
    est, spread = std_moments(post._replace(mode=jnp.where(post.narrow, post.mode, 0.0),
                                            var=jnp.where(post.narrow, post.var, 1.0)))
    new = spread + within
    old = params_cov[i, i]
    a = jnp.where(old > 0.0, jnp.sqrt(new / jnp.where(old > 0.0, old, 1.0)), 0.0)
    scale = jnp.ones(params.shape[0], params.dtype).at[i].set(a)
    cov = params_cov * scale[:, None] * scale[None, :]
    cov = cov.at[i, i].set(new)
    return (jnp.where(post.narrow, params.at[i].set(est), params),
            jnp.where(post.narrow, cov, params_cov))
