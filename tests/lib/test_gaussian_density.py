"""The one Gaussian log-density (vehjax.lib.gaussian) against scipy.stats.multivariate_normal
on the observed components: from a matrix factor, from entries, with components missing (NaN),
and the per-particle and diagonal compositions of vehjax.filters.smc."""

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.stats import multivariate_normal, norm

from vehjax.filters import smc
from vehjax.lib import gaussian
from vehjax.lib.entrywise import chol_masked, cholesky_observed, entries
from vehjax.lib.linalg import forward_entries, logdet_from_chol, solve_lower

# observation patterns of a 4-component residual: all, some missing, one, none
MASKS = [(1, 1, 1, 1), (1, 0, 1, 0), (0, 0, 1, 0), (0, 0, 0, 0)]


def _case(seed, n=4):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, n))
    S = A @ A.T + n * np.eye(n)
    return S, rng.normal(size=n) * 2.0


def _reference(e, S, obs):
    o = np.asarray(obs, bool)
    if not o.any():
        return 0.0
    return multivariate_normal.logpdf(e[o], mean=np.zeros(o.sum()), cov=S[np.ix_(o, o)])


@pytest.mark.parametrize("mask", MASKS)
def test_log_density_from_a_whitened_residual_is_the_observed_components_logpdf(mask):
    S, e = _case(0)
    obs = jnp.asarray(mask, bool)
    y = np.where(obs, e, np.nan)  # missing components are NaN
    e0 = jnp.where(jnp.isfinite(y), y, 0.0)
    L = cholesky_observed(jnp.asarray(S), obs)
    w = solve_lower(L, e0)
    got = gaussian.log_density(w @ w, logdet_from_chol(L), jnp.sum(obs))
    np.testing.assert_allclose(float(got), _reference(e, S, mask), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("mask", MASKS)
def test_log_density_entries_is_the_observed_components_logpdf(mask):
    S, e = _case(1)
    obs = [jnp.asarray(bool(m)) for m in mask]
    L = chol_masked(entries(jnp.asarray(S)), obs)
    w = forward_entries(L, [jnp.where(o, v, 0.0) for o, v in zip(obs, jnp.asarray(e))])
    got, q = gaussian.log_density_entries(w, L, sum(o.astype(jnp.int32) for o in obs))
    np.testing.assert_allclose(float(got), _reference(e, S, mask), rtol=1e-12, atol=1e-12)
    o = np.asarray(mask, bool)
    nis = e[o] @ np.linalg.solve(S[np.ix_(o, o)], e[o]) if o.any() else 0.0
    np.testing.assert_allclose(float(q), nis, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("mask", MASKS)
@pytest.mark.parametrize("diagonal", [False, True])
def test_per_particle_and_diagonal_compositions(mask, diagonal):
    S, _ = _case(2)
    if diagonal:
        S = np.diag(np.diag(S))
    E = np.random.default_rng(3).normal(size=(4, 5))  # 5 particles in columns
    obs = jnp.asarray(mask, bool)
    e0 = jnp.where(obs[:, None], jnp.asarray(E), 0.0)
    if diagonal:
        got = smc.gaussian_logliks(e0, obs, var=jnp.asarray(np.diag(S)))
    else:
        got = smc.gaussian_logliks(e0, obs, L=cholesky_observed(jnp.asarray(S), obs))
    want = [_reference(E[:, i], S, mask) for i in range(E.shape[1])]
    np.testing.assert_allclose(np.asarray(got), want, rtol=1e-12, atol=1e-12)


def test_one_dimensional_is_the_normal_logpdf_and_keeps_the_dtype():
    z = np.linspace(-3.0, 3.0, 7)
    got = gaussian.log_density(jnp.asarray(z) ** 2, 2.0 * np.log(0.7), 1)
    np.testing.assert_allclose(np.asarray(got), norm.logpdf(0.7 * z, scale=0.7), rtol=1e-12)
    q32 = jnp.asarray(z, jnp.float32) ** 2
    assert gaussian.log_density(q32, jnp.float32(0.0), jnp.int32(1)).dtype == jnp.float32
