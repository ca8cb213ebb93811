"""Correlated pseudo-marginal PMMH (vehjax.calibrate.correlated, pmmh(Correlated(...))):
the bootstrap PF's likelihood as a function of its random numbers is unbiased against an exact
Kalman likelihood written here in numpy; the Crank-Nicolson move correlates successive
estimates (measured against independent ones); the Hilbert index and systematic resampling
against plain-Python transcriptions; a correlated chain recovers a grid posterior (slow)."""

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

import vehjax as vj
from vehjax import calibrate
from vehjax.calibrate import correlated
from vehjax.calibrate import Chains, Correlated, LogNormal, pmmh

# a 2-state linear-Gaussian model with noise through its input, a missing component and a bias
DT, A22, B2, SU, BIAS = 0.1, 0.9, 0.5, 0.4, 0.3
QD = np.array([0.02, 0.05]) ** 2
RD = np.array([0.3, 0.2]) ** 2
P0 = np.array([0.1, 0.1])


def _lg_model():
    return vj.models.Model(
        transition=lambda x, u, th: jnp.stack([x[0] + DT * x[1], th[0] * x[1] + B2 * u[0]]),
        observe=lambda x, u, th: x, dt=DT, state_names=("p", "v"), param_names=("a",),
        input_names=("u",), output_names=("yp", "yv"), theta=[A22])


def _lg_data(T=20, seed=1):
    rng = np.random.default_rng(seed)
    us = np.sin(0.3 * np.arange(T))[:, None]
    A, Bm = np.array([[1.0, DT], [0.0, A22]]), np.array([0.0, B2])
    x, ys = rng.standard_normal(2) * np.sqrt(P0), []
    for t in range(T):
        x = (A @ x + Bm * (us[t, 0] + SU * rng.standard_normal())
             + np.sqrt(QD) * rng.standard_normal(2))
        ys.append(x + np.sqrt(RD) * rng.standard_normal(2) + [BIAS, 0.0])
    ys = np.array(ys)
    ys[::4, 1] = np.nan
    return ys, us


def _kalman_loglik(ys, us, bias):
    """The exact log-likelihood of _lg_model's data: Kalman filter with Q + B su^2 B^T, written
    out in numpy (observed components only)."""
    A, Bm = np.array([[1.0, DT], [0.0, A22]]), np.array([0.0, B2])
    Qt, R = np.diag(QD) + SU**2 * np.outer(Bm, Bm), np.diag(RD)
    m, P, ll = np.zeros(2), np.diag(P0), 0.0
    for y, u in zip(ys, us):
        m, P = A @ m + Bm * u[0], A @ P @ A.T + Qt
        o = np.isfinite(y)
        H = np.eye(2)[o]
        S = H @ P @ H.T + R[np.ix_(o, o)]
        e = y[o] - bias[o] - H @ m
        L = np.linalg.cholesky(S)
        z = np.linalg.solve(L, e)
        ll += -0.5 * z @ z - np.log(np.diag(L)).sum() - 0.5 * o.sum() * math.log(2 * math.pi)
        K = np.linalg.solve(S, H @ P).T
        m, P = m + K @ e, P - K @ S @ K.T
    return ll


def test_cpm_likelihood_is_unbiased_against_the_exact_kalman_filter():
    """exp(log p_hat(y | aux)) averaged over aux ~ N(0, I) equals the Kalman likelihood within
    4 Monte-Carlo standard errors (delta method on the mean of the exponentials); the 2-D
    state goes through the Hilbert sort, the input noise and the bias are calibrated names."""
    ys, us = _lg_data()
    loglik, draw = calibrate.cpm_log_likelihood_fn(
        Correlated(functools.partial(vj.filters.bootstrap_pf, n_particles=32), 0.999),
        _lg_model(), ys, us, x0=np.zeros(2), P0=P0, Q=QD, R=RD, names=("input[u]", "bias[yp]"))
    v = jnp.array([SU, BIAS])
    M = 2000
    lls = np.asarray(jax.jit(jax.vmap(lambda k: loglik(v, draw(k))))(
        jax.random.split(jax.random.key(0), M)))
    w = np.exp(lls - lls.max())
    est = math.log(w.mean()) + lls.max()
    se = w.std(ddof=1) / w.mean() / math.sqrt(M)
    exact = _kalman_loglik(ys, us, np.array([BIAS, 0.0]))
    assert 0.3 < np.std(lls) < 3.0                       # a noisy estimate, not a constant
    assert abs(est - exact) < 4 * se, (est, exact, se)
    # the log of the estimate is biased low (Jensen): the test can tell the two apart
    assert np.mean(lls) < exact - 4 * np.std(lls) / math.sqrt(M)


def _ar1():
    rng = np.random.default_rng(3)
    x, ys = 0.0, []
    for _ in range(100):
        x = 0.8 * x + 0.3 * rng.standard_normal()
        ys.append(x + 0.5 * rng.standard_normal())
    model = vj.models.Model(transition=lambda x, u, th: th[0] * x, observe=lambda x, u, th: x,
                            dt=1.0, state_names=("x",), param_names=("a",), input_names=(),
                            output_names=("y",), theta=[0.8])
    return model, np.array(ys)[:, None]


def test_crank_nicolson_move_correlates_the_estimates():
    """On a 1-state model (100 steps, N = 32) the log-likelihood difference between aux and its
    Crank-Nicolson move (rho = 0.999) at the same values has a std under a fifth of that of
    two independent estimates' difference (sqrt(2) x the estimate's std; 1 - rho^2 of the
    move's variance is fresh)."""
    model, ys = _ar1()
    sd_diff, sd = calibrate.log_likelihood_difference_spread(
        Correlated(functools.partial(vj.filters.bootstrap_pf, n_particles=32), 0.999), model, ys,
        None, x0=[0.0], P0=[1.0], Q=[0.09], R=[0.25], values={"R[y]": 0.5},
        key=jax.random.key(1), n_evals=64)
    assert sd > 0.5, sd                                    # the estimate is noisy
    assert sd_diff < 0.2 * math.sqrt(2.0) * sd, (sd_diff, sd)
    # the move itself: rho a + sqrt(1 - rho^2) e, leaf by leaf
    a = correlated.draw_aux(jax.random.key(2), 3, 4, 2, 1)
    e = correlated.draw_aux(jax.random.key(3), 3, 4, 2, 1)
    b = correlated.crank_nicolson(a, e, 0.6)
    for la, le, lb in zip(a, e, b):
        np.testing.assert_allclose(np.asarray(lb), 0.6 * np.asarray(la) + 0.8 * np.asarray(le),
                                   rtol=1e-14, atol=1e-15)


def _xy2d(n, x, y):
    """Hilbert index of cell (x, y) on an n x n grid (the classic iterative form)."""
    d, s = 0, n // 2
    while s > 0:
        rx, ry = int(x & s > 0), int(y & s > 0)
        d += s * s * ((3 * rx) ^ ry)
        if ry == 0:
            if rx == 1:
                x, y = s - 1 - x, s - 1 - y
            x, y = y, x
        s //= 2
    return d


def test_hilbert_index_and_systematic_resampling_against_transcriptions():
    pts = np.array([(i, j) for i in range(16) for j in range(16)], dtype=np.uint64)
    h = np.asarray(correlated.hilbert_index(jnp.asarray(pts), 4))
    assert [int(v) for v in h] == [_xy2d(16, int(x), int(y)) for x, y in pts]
    # 3-D: a bijection of the 8^3 cells whose consecutive cells are grid neighbours
    cube = np.array([(i, j, k) for i in range(8) for j in range(8) for k in range(8)], np.uint64)
    h3 = np.asarray(correlated.hilbert_index(jnp.asarray(cube), 3))
    assert sorted(h3.tolist()) == list(range(512))
    path = cube[np.argsort(h3)].astype(int)
    assert np.all(np.abs(np.diff(path, axis=0)).sum(axis=1) == 1)
    # systematic resampling: ancestor of position (i + u) / N in the cumulative weights
    w = np.array([0.1, 0.0, 0.35, 0.05, 0.5])
    for u in (0.0, 0.3, 0.99):
        c, ref = np.cumsum(w), []
        for i in range(5):
            ref.append(int(np.flatnonzero(c > (i + u) / 5)[0]))
        assert np.asarray(correlated.systematic_ancestors(jnp.asarray(w), u)).tolist() == ref
    # sorting: 1-D by the state, the projection's key continuous in a fixed sign
    x = jnp.asarray(np.random.default_rng(0).standard_normal((50, 2)) @ [[1.0, 0.9], [0.0, 0.3]])
    a, _, _ = correlated.sort_direction(x, jnp.full(50, 0.02))
    assert a[0] > 0 and a[1] > 0 and abs(float(jnp.linalg.norm(a)) - 1) < 1e-12
    assert np.all(np.diff(np.asarray(x[correlated.sort_order(x[:, :1], jnp.full(50, 0.02)), 0])) >= 0)


def test_correlation_is_checked():
    model, ys = _ar1()
    kw = dict(x0=[0.0], P0=[1.0], Q=[0.09], R=[0.25], priors={"R[y]": LogNormal(0.5, 0.5)},
              key=jax.random.key(0), chains=Chains(n=2, samples=4, warmup=2))
    for bad in (0.0, 1.0, -0.5, 1.5, float("nan"), True, [0.9], "0.9"):
        with pytest.raises(ValueError, match="correlation"):
            pmmh(Correlated(vj.filters.bootstrap_pf, bad), model, ys, None, **kw)
    with pytest.raises(ValueError, match="bootstrap_pf only"):
        pmmh(Correlated(vj.filters.ekf, 0.9), model, ys, None, **kw)
    with pytest.raises(ValueError, match="builder"):
        pmmh(Correlated(functools.partial(vj.filters.bootstrap_pf, n_particles=8,
                                          ess_threshold=0.5), 0.9), model, ys, None, **kw)
    with pytest.raises(ValueError, match="builder"):
        pmmh(Correlated(functools.partial(vj.filters.bootstrap_pf, n_particles=8,
                                          resampling="multinomial"), 0.9), model, ys, None, **kw)


@pytest.mark.slow  # a sampler study (three compiles, 3 x 4 x 1500 iterations)
def test_correlated_pmmh_recovers_the_grid_posterior_of_a_noise_std():
    """test_calibrate's grid posterior (an AR(1) observed in noise, the noise std unknown, the
    exact Kalman likelihood on a grid times the log-normal prior) from a correlated chain with
    few particles (N = 10, rho = 0.99): mean and std within 4 Monte-Carlo errors, and more than
    twice the effective sample size of the independent-estimate chain with the same N, key
    and iterations; the same call twice gives the same draws."""
    A, Q, T = 0.8, 0.3**2, 40
    rng = np.random.default_rng(11)
    x, ys = 0.0, []
    for _ in range(T):
        x = A * x + math.sqrt(Q) * rng.standard_normal()
        ys.append(x + 0.5 * rng.standard_normal())
    ys = np.array(ys)[:, None]
    grid = np.linspace(0.05, 1.6, 3000)
    m, p, ll = np.zeros_like(grid), np.ones_like(grid), 0.0
    for y in ys[:, 0]:
        m, p = A * m, A * A * p + Q
        s = p + grid**2
        ll = ll - 0.5 * (np.log(2 * np.pi * s) + (y - m) ** 2 / s)
        k = p / s
        m, p = m + k * (y - m), (1 - k) * p
    logpost = ll + stats.lognorm.logpdf(grid, s=0.5, scale=0.6)
    w = np.exp(logpost - logpost.max())
    w /= w.sum()
    assert w[0] < 1e-8 and w[-1] < 1e-8
    mean = float(np.sum(w * grid))
    std = float(np.sqrt(np.sum(w * (grid - mean) ** 2)))
    model = vj.models.Model(transition=lambda x, u, th: th[0] * x, observe=lambda x, u, th: x,
                            dt=1.0, state_names=("x",), param_names=("a",), input_names=(),
                            output_names=("y",), theta=[A])
    kw = dict(x0=[0.0], P0=[1.0], Q=[Q], R=[1.0], priors={"R[y]": LogNormal(median=0.6, sigma=0.5)},
              key=jax.random.key(3), chains=Chains(n=4, samples=1200, warmup=300))
    pf = functools.partial(vj.filters.bootstrap_pf, n_particles=10)
    res = pmmh(Correlated(pf, 0.99), model, ys, None, **kw)
    again = pmmh(Correlated(pf, 0.99), model, ys, None, **kw)
    np.testing.assert_array_equal(again.samples, res.samples)      # one key, the same draws
    indep = pmmh(pf, model, ys, None, **kw)
    assert np.all(res.rhat < 1.05), res.rhat
    ess = float(res.ess[0])
    assert ess > 150 and ess > 2 * float(indep.ess[0]), (ess, indep.ess)
    assert abs(res.mean[0] - mean) < 4 * std / math.sqrt(ess), (res.mean, mean, std, ess)
    assert abs(res.std[0] - std) < 4 * std / math.sqrt(2 * ess), (res.std, std, ess)
