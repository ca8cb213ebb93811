"""vehjax.calibrate: PMMH with the bootstrap PF and particle Gibbs with ancestor sampling recover
posteriors computed here on grids from the exact Kalman likelihood (numpy) and the priors
(scipy); split R-hat and ESS against BDA3 written out here, tensorflow-probability, and the AR(1)
closed form."""

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

import vehjax as vj
from vehjax.calibrate import (Adaptation, Chains, LogNormal, Normal, RandomWalk, Sweep, Uniform,
                              effective_sample_size, particle_gibbs, pmmh, split_rhat)

A, Q, SIGMA_R, T = 0.8, 0.3**2, 0.5, 40


def _data():
    rng = np.random.default_rng(11)
    x, ys = 0.0, []
    for _ in range(T):
        x = A * x + math.sqrt(Q) * rng.standard_normal()
        ys.append(x + SIGMA_R * rng.standard_normal())
    return np.array(ys)[:, None]


def _kalman_loglik(ys, a, q, r, m0=0.0, p0=1.0):
    """The scalar Kalman filter's exact log-likelihood, written out."""
    m, p, ll = m0, p0, 0.0
    for y in ys[:, 0]:
        m, p = a * m, a * a * p + q
        s = p + r
        ll += -0.5 * (math.log(2 * math.pi * s) + (y - m) ** 2 / s)
        k = p / s
        m, p = m + k * (y - m), (1 - k) * p
    return ll


def _model():
    return vj.models.Model(transition=lambda x, u, th: th[0] * x, observe=lambda x, u, th: x,
                           dt=1.0, state_names=("x",), param_names=("a",), input_names=(),
                           output_names=("y",), theta=[A])


def test_pmmh_recovers_the_grid_posterior_of_a_noise_std():
    ys = _data()
    prior = LogNormal(median=0.6, sigma=0.5)
    grid = np.linspace(0.05, 1.6, 3000)
    logpost = np.array([_kalman_loglik(ys, A, Q, s**2) for s in grid]) + stats.lognorm.logpdf(
        grid, s=0.5, scale=0.6)
    w = np.exp(logpost - logpost.max())
    w /= w.sum()
    mean = float(np.sum(w * grid))
    std = float(np.sqrt(np.sum(w * (grid - mean) ** 2)))
    assert w[0] < 1e-8 and w[-1] < 1e-8                          # the grid holds the posterior

    res = pmmh(functools.partial(vj.filters.bootstrap_pf, n_particles=100), _model(), ys, None,
               x0=[0.0], P0=[1.0], Q=[Q], R=[1.0], priors={"R[y]": prior},
               key=jax.random.key(3), chains=Chains(n=4, samples=600, warmup=150))
    assert res.samples.shape == (4, 600, 1) and res.names == ("R[y]",)
    assert np.all(res.rhat < 1.05), res.rhat
    ess = float(res.ess[0])
    assert ess > 300, ess
    # Monte-Carlo errors: mean std / sqrt(ESS), std about std / sqrt(2 ESS); 4 of them allowed
    assert abs(res.mean[0] - mean) < 4 * std / math.sqrt(ess), (res.mean, mean, std, ess)
    assert abs(res.std[0] - std) < 4 * std / math.sqrt(2 * ess), (res.std, std, ess)
    assert 0.15 < res.acceptance.mean() < 0.9
    assert "R[y]" in res.summary()


@pytest.mark.slow  # two runs, each compiles its sampler (~10 s CPU each)
def test_pmmh_is_reproducible_from_one_key():
    """The same call twice (the grid-posterior test's): the same draws, bit for bit."""
    ys = _data()
    kw = dict(x0=[0.0], P0=[1.0], Q=[Q], R=[1.0], priors={"R[y]": LogNormal(median=0.6, sigma=0.5)},
              key=jax.random.key(3), chains=Chains(n=4, samples=600, warmup=150))
    pf = functools.partial(vj.filters.bootstrap_pf, n_particles=100)
    res = pmmh(pf, _model(), ys, None, **kw)
    again = pmmh(pf, _model(), ys, None, **kw)
    np.testing.assert_array_equal(again.samples, res.samples)


def _kalman_loglik_grid(ys, a, q, r, m0=0.0, p0=1.0):
    """The same recursion vectorised over arrays of a and r (any broadcastable shapes)."""
    m, p, ll = np.zeros(np.broadcast(a, r).shape) + m0, np.zeros(np.broadcast(a, r).shape) + p0, 0.0
    for y in ys[:, 0]:
        m, p = a * m, a * a * p + q
        s = p + r
        ll = ll - 0.5 * (np.log(2 * np.pi * s) + (y - m) ** 2 / s)
        k = p / s
        m, p = m + k * (y - m), (1 - k) * p
    return ll


@pytest.mark.slow  # a sampler study (PMMH's stays in the default run): `pytest -m slow` (README)
def test_particle_gibbs_recovers_a_two_parameter_grid_posterior():
    ys = _data()
    a_grid = np.linspace(-1.0, 2.2, 500)[:, None]
    s_grid = np.linspace(0.05, 1.6, 400)[None, :]
    logpost = (_kalman_loglik_grid(ys, a_grid, Q, s_grid**2) + stats.norm.logpdf(a_grid, 0.5, 0.5)
               + stats.lognorm.logpdf(s_grid, s=0.5, scale=0.6))
    w = np.exp(logpost - logpost.max())
    w /= w.sum()
    assert w[0].max() < 1e-8 and w[-1].max() < 1e-8 and w[:, 0].max() < 1e-8
    assert w[:, -1].max() < 1e-8                                    # the grid holds it
    marg = {"a": (a_grid[:, 0], w.sum(axis=1)), "R[y]": (s_grid[0], w.sum(axis=0))}
    res = particle_gibbs(_model(), ys, None, x0=[0.0], P0=[1.0], Q=[Q], R=[1.0],
                         priors={"a": Normal(0.5, 0.5), "R[y]": LogNormal(0.6, 0.5)},
                         key=jax.random.key(5), chains=Chains(n=4, samples=600, warmup=100),
                         sweep=Sweep(n_particles=20), proposal=RandomWalk(std=[0.1, 0.3]))
    assert np.all(res.rhat < 1.05), res.rhat
    for k, name in enumerate(res.names):
        grid, p = marg[name]
        mean = float(np.sum(p * grid))
        std = float(np.sqrt(np.sum(p * (grid - mean) ** 2)))
        ess = float(res.ess[k])
        assert ess > 150, (name, ess)
        assert abs(res.mean[k] - mean) < 4 * std / math.sqrt(ess), (name, res.mean[k], mean, ess)
        assert abs(res.std[k] - std) < 4 * std / math.sqrt(2 * ess), (name, res.std[k], std, ess)


def _rhat_bda3(x):
    """BDA3 split R-hat written out with plain loops."""
    m0, n0 = x.shape
    n = n0 // 2
    halves = [c[:n] for c in x] + [c[n0 - n:] for c in x]
    means = [sum(h) / n for h in halves]
    grand = sum(means) / len(halves)
    B = n / (len(halves) - 1) * sum((mj - grand) ** 2 for mj in means)
    W = sum(sum((v - mj) ** 2 for v in h) / (n - 1) for h, mj in zip(halves, means)) / len(halves)
    return math.sqrt(((n - 1) / n * W + B / n) / W)


def _ar1_chains(rho, m, n, seed, shift=0.0):
    rng = np.random.default_rng(seed)
    x = np.empty((m, n))
    x[:, 0] = rng.standard_normal(m)
    for t in range(1, n):
        x[:, t] = rho * x[:, t - 1] + math.sqrt(1 - rho**2) * rng.standard_normal(m)
    return x + shift * np.arange(m)[:, None]


def test_rhat_and_ess_on_synthetic_chains():
    x = _ar1_chains(0.7, 4, 600, 0)
    assert split_rhat(x) == pytest.approx(_rhat_bda3(x), rel=1e-12)
    assert split_rhat(x) < 1.02
    shifted = _ar1_chains(0.7, 4, 600, 1, shift=1.0)
    assert split_rhat(shifted) == pytest.approx(_rhat_bda3(shifted), rel=1e-12)
    assert split_rhat(shifted) > 1.5                               # chains that disagree
    # (chains, draws, d) gives each column's value
    both = np.stack([x, shifted], axis=-1)
    np.testing.assert_allclose(split_rhat(both), [split_rhat(x), split_rhat(shifted)])
    # ESS: an AR(1) chain of coefficient rho has ESS = N (1 - rho) / (1 + rho)
    for rho in (0.0, 0.5, 0.9):
        y = _ar1_chains(rho, 4, 5000, 2)
        theory = y.size * (1 - rho) / (1 + rho)
        assert effective_sample_size(y) == pytest.approx(theory, rel=0.15), rho


def test_ess_and_rhat_agree_with_tensorflow_probability():
    tfp = pytest.importorskip("tensorflow_probability.substrates.jax")
    x = _ar1_chains(0.6, 4, 400, 5)
    ref_r = float(tfp.mcmc.potential_scale_reduction(x.T, split_chains=True))
    # tfp returns Brooks & Gelman's (1998) corrected form on the variance scale, built from the
    # same B and W: (m + 1) / m var+ / W - (n - 1) / (m n), with m = 8 half-chains of n = 200
    m, n = 8, 200
    assert (m + 1) / m * split_rhat(x) ** 2 - (n - 1) / (m * n) == pytest.approx(ref_r, rel=1e-9)
    ref_ess = float(tfp.mcmc.effective_sample_size(x.T, cross_chain_dims=1,
                                                   filter_beyond_positive_pairs=True))
    assert effective_sample_size(x) == pytest.approx(ref_ess, rel=0.05)


def test_priors_and_bad_input():
    for p, x in ((Normal(1.0, 2.0), 0.3), (LogNormal(2.0, 0.4), 1.3), (Uniform(-1.0, 3.0), 0.5)):
        z = p.to_unconstrained(x)
        assert float(p.from_unconstrained(z)) == pytest.approx(x, rel=1e-12)
        # log |dx/dz| by a central difference
        h = 1e-6
        jac = (float(p.from_unconstrained(z + h)) - float(p.from_unconstrained(z - h))) / (2 * h)
        assert float(p.log_jacobian(z)) == pytest.approx(math.log(jac), abs=1e-7)
    assert float(LogNormal(2.0, 0.4).log_density(1.3)) == pytest.approx(
        stats.lognorm.logpdf(1.3, s=0.4, scale=2.0), rel=1e-12)
    assert float(Normal(1.0, 2.0).log_density(0.3)) == pytest.approx(
        stats.norm.logpdf(0.3, 1.0, 2.0), rel=1e-12)
    assert float(Uniform(-1.0, 3.0).log_density(0.5)) == pytest.approx(math.log(0.25))
    with pytest.raises(ValueError, match="Normal.std"):
        Normal(0.0, -1.0)
    ys = _data()
    kw = dict(x0=[0.0], P0=[1.0], Q=[Q], R=[1.0], key=jax.random.key(0))
    with pytest.raises(ValueError, match="priors: unknown name 'b'"):
        pmmh(vj.filters.bootstrap_pf, _model(), ys, None, priors={"b": Normal(0, 1)}, **kw)
    with pytest.raises(ValueError, match=r"priors: 'R\[z\]'"):
        pmmh(vj.filters.bootstrap_pf, _model(), ys, None, priors={"R[z]": Normal(0, 1)}, **kw)
    with pytest.raises(ValueError, match=r"priors: 'R:y': quantities are spelled R\[y\]"):
        pmmh(vj.filters.bootstrap_pf, _model(), ys, None, priors={"R:y": Normal(0, 1)}, **kw)
    with pytest.raises(ValueError, match=r"priors: 'R\[y,y\]': calibrate samples standard"):
        pmmh(vj.filters.bootstrap_pf, _model(), ys, None, priors={"R[y,y]": Normal(0, 1)}, **kw)
    with pytest.raises(ValueError, match="priors"):
        pmmh(vj.filters.bootstrap_pf, _model(), ys, None, priors={"a": (0, 1)}, **kw)
    with pytest.raises(ValueError, match="chains"):
        pmmh(vj.filters.bootstrap_pf, _model(), ys, None, priors={"a": Normal(0, 1)},
             chains=Chains(n=1), **kw)
    with pytest.raises(ValueError, match="key"):
        pmmh(vj.filters.bootstrap_pf, _model(), ys, None, priors={"a": Normal(0, 1)},
             **{**kw, "key": 0})
    with pytest.raises(ValueError, match="n_particles"):
        particle_gibbs(_model(), ys, None, priors={"a": Normal(0, 1)},
                       sweep=Sweep(n_particles=1), **kw)
    with pytest.raises(ValueError, match=r"priors: 'Q\[z\]': no 'z'"):
        particle_gibbs(_model(), ys, None, priors={"Q[z]": Normal(0, 1)}, **kw)


def test_adaptation_mathematics_against_numpy_and_scipy():
    """The warm-up's pieces: the shrunk window covariance (numpy), the scale update (scipy's
    normal quantiles), the proposal factor, the target acceptance and the windows."""
    from vehjax import calibrate as C

    rng = np.random.default_rng(4)
    z = rng.standard_normal((200, 3)) @ np.array([[1.0, 0, 0], [0.9, 0.3, 0], [0.2, -0.5, 2.0]])
    prev = np.diag([0.5, 2.0, 1.0])
    got = np.asarray(C.adapted_covariance(z.sum(0), z.T @ z, z.shape[0], prev, 30.0))
    want = (200 * np.cov(z.T, ddof=1) + 30 * prev) / 230
    np.testing.assert_allclose(got, want, rtol=1e-10)
    for a, target in ((0.11, 0.234), (0.5, 0.234), (0.3, 0.441)):
        step = float(C.scale_update(0.2, a, target)) - 0.2
        assert step == pytest.approx(math.log(stats.norm.ppf(target / 2) / stats.norm.ppf(a / 2)),
                                     rel=1e-10)
    assert float(C.scale_update(0.0, 0.0, 0.234)) == pytest.approx(          # a clipped to 0.005
        math.log(stats.norm.ppf(0.117) / stats.norm.ppf(0.0025)), rel=1e-10)
    assert float(C.scale_update(0.0, 0.9, 0.001)) == pytest.approx(math.log(4.0))  # factor clipped
    assert float(C.scale_update(0.0, 1.0, 0.234)) > 0                   # too small: grow
    L = np.asarray(C.proposal_factor(want, 0.3, np.eye(3)))
    np.testing.assert_allclose(L @ L.T, math.exp(0.6) * 2.38**2 / 3 * want, rtol=1e-8)
    bad = np.asarray(C.proposal_factor(-np.eye(3), 0.0, 7 * np.eye(3)))
    np.testing.assert_array_equal(bad, 7 * np.eye(3))                    # not PD: keep the old
    # 2 Phi(-sqrt(2.38^2 + 2 s^2) / 2), relative to its s = 0 value, times the d-table's value
    assert C.target_acceptance(50) == pytest.approx(0.234, rel=1e-12)
    assert 2 * stats.norm.cdf(-1.19) == pytest.approx(0.234, abs=1e-4)  # the large-d optimum
    assert C.target_acceptance(1) == pytest.approx(0.441)
    assert C.target_acceptance(8, 1.2) == pytest.approx(
        0.255 * stats.norm.cdf(-math.sqrt(2.38**2 + 2 * 1.44) / 2) / stats.norm.cdf(-1.19))
    ends = C.adaptation_windows(2000, 5)
    np.testing.assert_array_equal(ends, np.round(1600 * np.cumsum(2.0 ** np.arange(5)) / 31))
    assert list(C.adaptation_windows(100, 5)) == [8, 18, 39, 80]          # a 3-long window merged
    assert C.adaptation_windows(100, 0).size == 0


@pytest.mark.slow  # a sampler study on a correlated target (one compile, 4 x 6000 iterations)
def test_adaptive_random_walk_mixes_on_a_correlated_gaussian():
    """The adapted random walk on a 5-d Gaussian whose first three coordinates correlate at
    0.995 / -0.99 with scales 1e-3 to 10 (as the drive's offset, eps and gyro bias): split
    R-hat < 1.05, ESS >= 200 for each, the mean and std within Monte-Carlo error, and the
    proposal's correlation that of the target."""
    from vehjax import calibrate as C

    sd = np.array([1e-3, 10.0, 0.5, 2.0, 0.05])
    corr = np.eye(5)
    corr[0, 1] = corr[1, 0] = 0.995
    corr[0, 2] = corr[2, 0] = -0.99
    corr[1, 2] = corr[2, 1] = -0.985
    cov = corr * np.outer(sd, sd)
    mean = np.array([2e-3, -5.0, 1.0, 0.0, 0.3])
    Lc = np.linalg.cholesky(cov)

    def loglik(v, key):
        e = jax.scipy.linalg.solve_triangular(Lc, v - mean, lower=True)
        return -0.5 * jax.numpy.sum(e**2)

    priors = tuple(Normal(0.0, 1e4 * s) for s in sd)                      # flat over the target
    warmup, samples, chains = 3000, 3000, 4
    run = C.marginal.sampler(loglik, priors, warmup + samples, C.adaptation_windows(warmup, 5),
                     C.target_acceptance(5), 25.0)
    L0 = np.diag(sd * 3.0)                                                 # 3x too wide, no corr.
    z0 = np.tile(mean + 2 * sd, (chains, 1))
    zs, lls, acc, L, _ = run(jax.random.split(jax.random.key(0), chains), z0, L0)
    res = C.diagnostics.result(tuple("abcde"), priors, zs, lls, acc, L, warmup)
    assert np.all(res.rhat < 1.05), res.rhat
    assert np.all(res.ess >= 200), res.ess
    np.testing.assert_array_less(np.abs(res.mean - mean), 4 * sd / np.sqrt(res.ess))
    np.testing.assert_array_less(np.abs(res.std - sd), 4 * sd / np.sqrt(2 * res.ess))
    pc = res.proposal_cov
    pcorr = pc / np.sqrt(np.outer(np.diag(pc), np.diag(pc)))
    np.testing.assert_allclose(pcorr[:3, :3], corr[:3, :3], atol=0.02)
    assert 0.15 < res.acceptance.mean() < 0.4


# -- the marginalized PF's likelihood with fixed noise statistics (calibrate.fixed_noise_mpf) --
_MPF_A, _MPF_B, _MPF_D = np.array([[0.8, 0.0], [0.1, 1.0]]), np.array([0.5, 0.0]), 0.3
_MPF_Q, _MPF_R = np.array([0.05, 0.05]) ** 2, np.array([0.2, 0.1]) ** 2


def _mpf_model(a=0.8, c=_MPF_D):
    """x_t = A x_{t-1} + B (u_t + w_t) + v_t, y_t = (x1 + c u_t, x2) + e_t: the input noise w
    in the transition only; a and c are parameters (they reach the filter through theta0)."""
    def f(x, u, th):
        return jnp.stack([th[0] * x[0] + _MPF_B[0] * u[0], x[1] + 0.1 * x[0]])

    def h(x, u, th):
        return jnp.stack([x[0] + th[1] * u[0], x[1]])

    return vj.models.Model(f, h, 0.1, ("x1", "x2"), param_names=("a", "c"), input_names=("u",),
                           output_names=("y1", "y2"), theta=[a, c])


def _kalman_loglik_input_noise(ys, us, A, B, D, Q, R, s, m0, P0):
    """The exact log-likelihood of x_t = A x + B (u + w) + v, y = C x + D u + e (C = I) with
    w ~ N(0, s^2): the Kalman filter with Q + B s^2 B^T, written out in numpy."""
    m, P, ll = np.array(m0, float), np.diag(P0).astype(float), 0.0
    Qe = np.diag(Q) + s**2 * np.outer(B, B)
    for y, u in zip(ys, us):
        m, P = A @ m + B * u[0], A @ P @ A.T + Qe
        e = y - (m + np.array([D * u[0], 0.0]))
        S = P + np.diag(R)
        L = np.linalg.cholesky(S)
        z = np.linalg.solve(L, e)
        ll += -0.5 * (z @ z) - np.log(np.diag(L)).sum() - np.log(2 * np.pi)
        K = np.linalg.solve(S, P).T  # P S^-1 (S, P symmetric)
        m, P = m + K @ e, P - K @ S @ K.T
    return ll


def _mpf_data(T, s=0.5, seed=0):
    rng = np.random.default_rng(seed)
    us = rng.normal(size=(T, 1))
    x, ys = np.zeros(2), []
    for u in us:
        x = _MPF_A @ x + _MPF_B * (u[0] + s * rng.normal()) + np.sqrt(_MPF_Q) * rng.normal(size=2)
        ys.append(x + np.array([_MPF_D * u[0], 0.0]) + np.sqrt(_MPF_R) * rng.normal(size=2))
    return np.array(ys), us


def test_fixed_noise_mpf_likelihood_is_unbiased_against_the_exact_kalman_filter():
    """The marginalized PF with fixed noise statistics estimates exp(loglik) without bias:
    over 256 keys the mean of exp(ll_hat - ll_exact) is 1 within 4 Monte-Carlo errors; the
    exact value from the numpy Kalman filter with Q + B s^2 B^T (input noise in the transition
    only; with it also in y1 the ratio would be far from 1)."""
    from vehjax.calibrate import fixed_noise_mpf, log_likelihood_fn

    ys, us = _mpf_data(30)
    a, s = 0.75, 0.45  # not the model's nominal a: theta0 must reach the filter
    exact = _kalman_loglik_input_noise(ys, us, np.array([[a, 0.0], [0.1, 1.0]]), _MPF_B, _MPF_D,
                                       _MPF_Q, _MPF_R, s, np.zeros(2), np.ones(2))
    ll = log_likelihood_fn(functools.partial(fixed_noise_mpf, n_particles=32), _mpf_model(), ys,
                           us, x0=np.zeros(2), P0=np.ones(2), Q=_MPF_Q, R=_MPF_R,
                           names=("a", "input[u]"))
    lls = np.asarray(jax.jit(jax.vmap(lambda k: ll(jnp.array([a, s]), k)))(
        jax.random.split(jax.random.key(5), 256)))
    r = np.exp(lls - exact)
    assert 0.05 < lls.std() < 1.0, lls.std()         # a particle estimate, and a usable one
    assert abs(r.mean() - 1.0) < 4 * r.std(ddof=1) / math.sqrt(r.size), (r.mean(), r.std())


@pytest.mark.slow  # a sampler study (one compile, 4 x 700 MPF runs)
def test_pmmh_with_the_marginalized_pf_recovers_the_grid_posterior():
    """PMMH with calibrate.fixed_noise_mpf's likelihood recovers the posterior of the input
    noise's std, computed on a grid from the exact numpy Kalman likelihood and the prior."""
    from vehjax.calibrate import fixed_noise_mpf

    ys, us = _mpf_data(40, s=0.5, seed=3)
    prior = LogNormal(median=0.4, sigma=0.5)
    grid = np.linspace(0.02, 2.0, 1500)
    logpost = np.array([_kalman_loglik_input_noise(ys, us, _MPF_A, _MPF_B, _MPF_D, _MPF_Q,
                                                   _MPF_R, g, np.zeros(2), np.ones(2))
                        for g in grid]) + stats.lognorm.logpdf(grid, s=0.5, scale=0.4)
    w = np.exp(logpost - logpost.max())
    w /= w.sum()
    mean = float(np.sum(w * grid))
    std = float(np.sqrt(np.sum(w * (grid - mean) ** 2)))
    assert w[0] < 1e-8 and w[-1] < 1e-8                          # the grid holds the posterior

    res = pmmh(functools.partial(fixed_noise_mpf, n_particles=32), _mpf_model(), ys, us,
               x0=np.zeros(2), P0=np.ones(2), Q=_MPF_Q, R=_MPF_R, priors={"input[u]": prior},
               key=jax.random.key(4), chains=Chains(n=4, samples=600, warmup=100))
    assert np.all(res.rhat < 1.05), res.rhat
    ess = float(res.ess[0])
    assert ess > 300, ess
    assert abs(res.mean[0] - mean) < 4 * std / math.sqrt(ess), (res.mean, mean, std, ess)
    assert abs(res.std[0] - std) < 4 * std / math.sqrt(2 * ess), (res.std, std, ess)


def test_starting_values_outside_the_support_raise_naming_init():
    """The priors' maps (vehjax.lib.transforms) take a value on or beyond a bound to a finite z;
    the starting values are checked against the support before they are mapped."""
    from vehjax.calibrate.priors import starting_values

    for prior, bad in ((LogNormal(1.0, 0.5), -1.0), (LogNormal(1.0, 0.5), 0.0),
                       (Uniform(0.0, 1.0), 1.0), (Uniform(0.0, 1.0), 2.0)):
        with pytest.raises(ValueError, match="^init"):
            starting_values((prior,), {"a": bad}, ("a",))
    z0 = starting_values((Normal(0.0, 1.0), LogNormal(2.0, 0.1), Uniform(-1.0, 3.0)), None,
                         ("a", "b", "c"))
    np.testing.assert_allclose(z0, [0.0, math.log(2.0), 0.0], atol=1e-15)


#: each option's record, made with the one bad value (the records check their fields when made)
_OPTION = {
    "proposal.adaptation.acceptance": lambda v: dict(
        proposal=RandomWalk(adaptation=Adaptation(acceptance=v))),
    "chains.n": lambda v: dict(chains=Chains(n=v, samples=4, warmup=2)),
    "proposal.std": lambda v: dict(proposal=RandomWalk(std=v)),
}


@pytest.mark.parametrize("sampler", ["pmmh", "particle_gibbs"])
@pytest.mark.parametrize("arg, value, match", [
    ("proposal.adaptation.acceptance", 23.4,
     r"^proposal\.adaptation\.acceptance: expected a number in \(0, 1\)"),
    ("proposal.adaptation.acceptance", 0.0, r"^proposal\.adaptation\.acceptance"),
    ("chains.n", 1, r"^chains"),
    ("proposal.std", [0.1, 0.2, 0.3], r"^proposal\.std: expected a positive number or 1 positive"),
])
def test_samplers_check_the_same_options_the_same_way(sampler, arg, value, match):
    """The same bad value gives the same error in every sampler that takes the option (issue
    46), before anything is run, naming the argument."""
    ys = np.zeros((5, 1))
    kw = dict(x0=[0.0], P0=[1.0], Q=[0.1], R=[1.0], priors={"R[y]": LogNormal(0.6, 0.5)},
              key=jax.random.key(0), chains=Chains(samples=4, warmup=2))
    with pytest.raises(ValueError, match=match):
        kw.update(_OPTION[arg](value))
        if sampler == "pmmh":
            pmmh(functools.partial(vj.filters.bootstrap_pf, n_particles=4), _model(), ys, None,
                 **kw)
        else:
            particle_gibbs(_model(), ys, None, sweep=Sweep(n_particles=4), **kw)
