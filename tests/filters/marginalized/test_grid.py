"""vehjax.filters.marginalized.grid: the posterior of a static parameter on a fixed grid, where the grid
resolves it and where it does not, against closed forms and scipy quadrature."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import integrate

from vehjax.filters.marginalized.grid import (RESOLVED, grid_posterior, ridge_covariance, std_moments,
                                  with_resolved_std)

jax.config.update("jax_enable_x64", True)

H = 0.38  # the spacing in log sigma^2 of 25 points over a decade either side of a guess
T = jnp.asarray(np.arange(25) * H - 12 * H)


def _gauss(mode, sd):
    return -0.5 * ((T - mode) / sd) ** 2 - 3.7  # unnormalised, as the filter's are not always


@pytest.mark.parametrize("offset", [0.0, 0.13, 0.5, -0.41])
def test_laplace_is_exact_for_a_gaussian_posterior_narrower_than_the_grid(offset):
    mode, sd = 0.2 + offset * H, 0.3 * H
    post = grid_posterior(_gauss(mode, sd), T)
    assert bool(post.narrow)
    np.testing.assert_allclose(float(post.mode), mode, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(float(post.var), sd ** 2, rtol=1e-12)


def test_weighted_moments_hold_where_the_grid_resolves_the_posterior():
    """At RESOLVED spacings (and above) the weighted moments of the grid are within 2.5 % in
    variance and 1 % of the std in mean, at the worst offset (the module docstring's
    numbers); there the posterior is not flagged narrow. At 0.4 spacings the variance is off by
    more than 50 % at some offset: why the Laplace branch exists."""
    worst = {}
    for r in (0.4, RESOLVED, 1.01 * RESOLVED, 0.8):
        errs = []
        for off in np.linspace(0.0, 1.0, 21):
            mode, sd = off * H, r * H
            lw = _gauss(mode, sd)
            w = np.exp(np.asarray(lw) - float(jnp.max(lw)))
            w /= w.sum()
            m = w @ np.asarray(T)
            v = w @ (np.asarray(T) - m) ** 2
            errs.append((abs(v / sd ** 2 - 1.0), abs(m - mode) / sd))
            if r > RESOLVED:
                assert not bool(grid_posterior(lw, T).narrow)
        worst[r] = np.max(errs, axis=0)
    assert worst[RESOLVED][0] < 0.025 and worst[RESOLVED][1] < 0.01
    assert worst[0.8][0] < 1e-3
    assert worst[0.4][0] > 0.5


def test_no_laplace_at_the_grids_ends_or_on_a_flat_posterior():
    assert not bool(grid_posterior(_gauss(T[0], 0.2 * H), T).narrow)
    assert not bool(grid_posterior(_gauss(T[-1] + 0.1, 0.2 * H), T).narrow)
    assert not bool(grid_posterior(jnp.full(25, -math.log(25.0)), T).narrow)
    # a weight that underflowed beside the peak: not finite, not flagged
    lw = _gauss(0.0, 0.2 * H).at[11].set(-jnp.inf)
    assert not bool(grid_posterior(lw, T).narrow)


def test_a_skewed_posterior_spread_over_the_grid_is_not_taken_for_a_narrow_one():
    """Steep above its mode and flat below (the steering std's likelihood where the sensors'
    noise hides it): the parabola through the three largest weights is narrow, but the
    weights spread over many points, which resolve it."""
    t = np.asarray(T)
    lw = jnp.asarray(np.where(t > 0.0, -0.5 * (t / (0.2 * H)) ** 2, -0.5 * (t / (4 * H)) ** 2))
    post = grid_posterior(lw, T)
    assert float(post.var) < (RESOLVED * H) ** 2
    assert not bool(post.narrow)


def test_std_moments_against_quadrature():
    """t ~ N(m, V), sigma = exp(t / 2): the estimate sqrt(E[exp(t)]) and the mean squared
    deviation of sigma from it, by scipy quadrature."""
    m, V = math.log(0.004 ** 2), 0.07
    post = grid_posterior(_gauss(0.0, 0.2 * H), T)._replace(mode=jnp.asarray(m),
                                                             var=jnp.asarray(V))
    est, spread = (float(a) for a in std_moments(post))
    pdf = lambda t: math.exp(-0.5 * (t - m) ** 2 / V) / math.sqrt(2 * math.pi * V)  # noqa: E731
    lim = (m - 12 * math.sqrt(V), m + 12 * math.sqrt(V))
    e2 = integrate.quad(lambda t: math.exp(t) * pdf(t), *lim, epsabs=0, epsrel=1e-12)[0]
    np.testing.assert_allclose(est, math.sqrt(e2), rtol=1e-10)
    dev = integrate.quad(lambda t: (math.exp(t / 2) - est) ** 2 * pdf(t), *lim, epsabs=0,
                         epsrel=1e-12)[0]
    np.testing.assert_allclose(spread, dev, rtol=1e-7)


def test_ridge_covariance_is_the_slope_times_the_variance():
    post = grid_posterior(_gauss(0.1, 0.25 * H), T)
    b = np.array([0.3, -0.02])
    v = jnp.asarray(np.array([1.0, 0.5])[:, None] + b[:, None] * np.asarray(T))
    np.testing.assert_allclose(np.asarray(ridge_covariance(post, T, v)), b * float(post.var),
                               rtol=1e-12)


def test_resolved_std_replaces_one_entry_and_keeps_the_covariance_psd():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(6, 6))
    C = jnp.asarray(A @ A.T)
    p = jnp.asarray(rng.normal(size=6))
    post = grid_posterior(_gauss(0.05, 0.2 * H), T)
    assert bool(post.narrow)
    est, spread = std_moments(post)
    p2, C2 = with_resolved_std(p, C, 1, post, 1e-9)
    np.testing.assert_allclose(float(p2[1]), float(est), rtol=1e-14)
    np.testing.assert_allclose(float(C2[1, 1]), float(spread) + 1e-9, rtol=1e-12)
    np.testing.assert_array_equal(np.delete(np.asarray(p2), 1), np.delete(np.asarray(p), 1))
    keep = np.delete(np.delete(np.asarray(C2), 1, 0), 1, 1)
    np.testing.assert_array_equal(keep, np.delete(np.delete(np.asarray(C), 1, 0), 1, 1))
    assert np.linalg.eigvalsh(np.asarray(C2)).min() > -1e-12
    # the correlations with the other entries are kept
    corr = lambda M: M[1] / np.sqrt(M[1, 1] * np.diag(M))  # noqa: E731
    np.testing.assert_allclose(corr(np.asarray(C2)), corr(np.asarray(C)), rtol=1e-10)
    # where the grid resolves the posterior nothing changes
    wide = grid_posterior(_gauss(0.0, 2.0 * H), T)
    p3, C3 = with_resolved_std(p, C, 1, wide, 1e-9)
    np.testing.assert_array_equal(np.asarray(p3), np.asarray(p))
    np.testing.assert_array_equal(np.asarray(C3), np.asarray(C))


def test_a_wide_posterior_passes_through_with_finite_gradients():
    """Where the grid resolves the posterior nothing is replaced, and the unused Laplace branch
    does not poison gradients (a mode far off the grid would overflow exp)."""
    C = jnp.eye(3)

    def f(scale):
        post = grid_posterior(_gauss(0.0, 2.0 * H), T)._replace(mode=jnp.asarray(900.0))
        p, c = with_resolved_std(scale * jnp.ones(3), scale * C, 1, post, 0.0)
        return jnp.sum(p) + jnp.sum(c)

    assert float(f(2.0)) == 12.0
    assert float(jax.grad(f)(2.0)) == 6.0
