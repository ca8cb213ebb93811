"""Bootstrap particle filter against the exact Kalman filter (numpy, written out below)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import vehjax as vj
from vehjax.filters import Resampling
from vehjax.filters.particle import bootstrap_pf

# A 2-state linear-Gaussian model (position and velocity), both observed.
DT = 0.1
A = np.array([[1.0, DT], [0.0, 0.95]])
Q = np.array([[0.02, 0.005], [0.005, 0.05]])
R_FULL = np.array([[0.09, 0.02], [0.02, 0.16]])
R_DIAG = np.diag([0.09, 0.16])
X0 = np.array([0.5, -0.2])
P0 = np.array([[0.5, 0.1], [0.1, 0.3]])


def _model():
    return vj.models.Model(
        transition=lambda x, u, th: jnp.asarray(A) @ x + u,
        observe=lambda x, u, th: x,
        dt=DT,
        state_names=("p", "v"),
        input_names=("up", "uv"),
        output_names=("yp", "yv"),
    )


def _simulate(T, R, seed, missing=()):
    """Truth and measurements of the linear model; ``missing``: (t, component) set to NaN."""
    rng = np.random.default_rng(seed)
    us = np.stack([np.zeros(T), 0.1 * np.sin(0.3 * np.arange(T))], axis=1)
    x = rng.multivariate_normal(X0, P0)
    xs, ys = [], []
    for t in range(T):
        x = A @ x + us[t] + rng.multivariate_normal(np.zeros(2), Q)
        xs.append(x)
        ys.append(x + rng.multivariate_normal(np.zeros(2), R))
    ys = np.array(ys)
    for t, i in missing:
        ys[t, i] = np.nan
    return np.array(xs), ys, us


def _kalman(ys, us, R):
    """Exact filtered means, covariances and log p(y_t | y_1:t-1) of the observed components."""
    x, P = X0.copy(), P0.copy()
    means, covs, lls = [], [], []
    for y, u in zip(ys, us):
        x = A @ x + u
        P = A @ P @ A.T + Q
        o = ~np.isnan(y)
        ll = 0.0
        if o.any():
            H = np.eye(2)[o]
            S = H @ P @ H.T + R[np.ix_(o, o)]
            e = y[o] - H @ x
            K = P @ H.T @ np.linalg.inv(S)
            x = x + K @ e
            P = P - K @ S @ K.T
            ll = -0.5 * (e @ np.linalg.solve(S, e) + np.linalg.slogdet(2 * np.pi * S)[1])
        means.append(x)
        covs.append(P)
        lls.append(ll)
    return np.array(means), np.array(covs), np.array(lls)


_RUNNERS = {}


def _run(est, ys, us, keys, x0=X0, P0_=P0):
    """lax.scan over steps, vmap over keys (runs), all on the same data; one jit per estimator."""
    if id(est) not in _RUNNERS:

        def one(key, ys, us, x0, P0_):
            res = vj.filter(est, ys, us, x0=x0, P0=P0_, key=key)
            return res.state, res

        _RUNNERS[id(est)] = (est, jax.jit(jax.vmap(one, in_axes=(0, None, None, None, None))))
    return _RUNNERS[id(est)][1](keys, jnp.asarray(ys), jnp.asarray(us), jnp.asarray(x0),
                                jnp.asarray(P0_))


def _keys(n, seed=0):
    return jax.random.split(jax.random.key(seed), n)


@pytest.mark.slow  # a convergence study over particle counts: `pytest -m slow` (README)
def test_close_to_kalman_and_error_shrinks_with_particles():
    """Full (correlated) R here; the diagonal-R code path is checked in the scheme test."""
    R = R_FULL
    T = 40
    _, ys, us = _simulate(T, R, seed=1, missing=[(5, 0), (6, 1), (7, 0), (7, 1)])
    m_kf, P_kf, _ = _kalman(ys, us, R)
    err = {}
    for n in (100, 3000):
        _, out = _run(bootstrap_pf(_model(), Q, R, n_particles=n), ys, us, _keys(6))
        mean, cov = np.asarray(out.states), np.asarray(out.covariances)
        assert np.all(np.isfinite(mean)) and np.all(np.isfinite(cov))
        # error in units of the exact posterior standard deviation
        err[n] = np.sqrt(np.mean((mean - m_kf) ** 2 / np.diagonal(P_kf, axis1=1, axis2=2)))
        if n == 3000:
            rel_cov = np.abs(cov.mean(axis=0) - P_kf) / np.sqrt(
                np.diagonal(P_kf, axis1=1, axis2=2)[:, :, None]
                * np.diagonal(P_kf, axis1=1, axis2=2)[:, None, :]
            )
            assert rel_cov.max() < 0.1, rel_cov.max()
            n_obs = np.asarray(out.n_obs[0])
            assert n_obs[5] == 1 and n_obs[7] == 0 and n_obs[8] == 2
    # Monte-Carlo error ~ 1/sqrt(N): a 30-fold increase should cut it about 5.5-fold
    assert err[3000] < 0.06, err
    assert err[3000] < err[100] / 3.0, err


def test_loglik_estimate_is_unbiased():
    """exp(sum loglik) is an unbiased estimate of p(y_1:T): E[exp(ll_pf - ll_kf)] = 1."""
    T, runs = 10, 600
    _, ys, us = _simulate(T, R_DIAG, seed=2, missing=[(3, 1)])
    _, _, ll_kf = _kalman(ys, us, R_DIAG)
    _, out = _run(bootstrap_pf(_model(), Q, R_DIAG, n_particles=64), ys, us, _keys(runs, 3))
    diff = np.asarray(out.loglik).sum(axis=1) - ll_kf.sum()
    ratio = np.exp(diff)
    # The ratio is a product of averages of bounded likelihoods, so it has finite variance and
    # its sample mean is asymptotically normal: 4 standard errors is a 6e-5 false-alarm rate.
    se = ratio.std(ddof=1) / np.sqrt(runs)
    assert se < 0.05  # the test has power: the estimator is not too noisy to say anything
    assert abs(ratio.mean() - 1.0) < 4.0 * se, (ratio.mean(), se)
    # The log of an unbiased estimate is biased low (Jensen); for many particles the error of
    # the log-likelihood is close to normal, N(-s^2 / 2, s^2) (Berard, Del Moral & Doucet 2014).
    se_diff = diff.std(ddof=1) / np.sqrt(runs)
    assert diff.mean() < -4.0 * se_diff
    assert abs(diff.mean() + 0.5 * diff.var(ddof=1)) < 4.0 * se_diff


@pytest.mark.parametrize(
    "scheme, threshold",
    # each scheme is checked against references in tests/filters/test_resampling.py; two of them
    # through the whole filter here by default, the other two with `pytest -m slow`
    [("systematic", 0.5), pytest.param("stratified", 1.0, marks=pytest.mark.slow),
     pytest.param("multinomial", 0.5, marks=pytest.mark.slow), ("residual", 0.5)],
)
def test_every_scheme_tracks_the_kalman_filter(scheme, threshold):
    T = 20
    _, ys, us = _simulate(T, R_DIAG, seed=4)
    m_kf, P_kf, _ = _kalman(ys, us, R_DIAG)
    est = bootstrap_pf(_model(), Q, R_DIAG, n_particles=1000, resampling=Resampling(scheme=scheme,
                                                                                    ess_threshold=threshold))
    state, out = _run(est, ys, us, _keys(4))
    z = (np.asarray(out.states) - m_kf) / np.sqrt(np.diagonal(P_kf, axis1=1, axis2=2))
    assert np.sqrt(np.mean(z**2)) < 0.1
    if threshold == 1.0:  # resampled after every step: equal weights
        np.testing.assert_allclose(np.asarray(state.weights), 1.0 / 1000)


def test_zero_ess_threshold_never_resamples():
    T = 15
    _, ys, us = _simulate(T, R_DIAG, seed=5)
    state, _ = _run(bootstrap_pf(_model(), Q, R_DIAG, n_particles=200,
                                 resampling=Resampling(ess_threshold=0.0)), ys, us, _keys(2))
    w = np.asarray(state.weights)
    assert np.all(np.ptp(w, axis=1) > 0)  # never resampled: weights accumulate
    assert np.all(np.asarray(state.ess) < 20)  # and degenerate
    np.testing.assert_allclose(w.sum(axis=1), 1.0, rtol=1e-12)
    np.testing.assert_allclose(np.exp(np.asarray(state.log_weights)), w, rtol=1e-9, atol=1e-300)


@pytest.mark.slow  # two PF compiles (NaN measurements for every filter: test_entry_points.py): `pytest -m slow`
def test_missing_component_is_the_same_as_not_measuring_it():
    """y = (a, NaN) must give exactly what a model observing only the first state gives."""
    T = 12
    _, ys, us = _simulate(T, R_FULL, seed=6)
    ys_nan = ys.copy()
    ys_nan[:, 1] = np.nan
    one_output = vj.models.Model(
        transition=lambda x, u, th: jnp.asarray(A) @ x + u,
        observe=lambda x, u, th: x[:1],
        dt=DT,
        state_names=("p", "v"),
        input_names=("up", "uv"),
        output_names=("yp",),
    )
    _, out_nan = _run(bootstrap_pf(_model(), Q, R_FULL, n_particles=300), ys_nan, us, _keys(2))
    _, out_one = _run(bootstrap_pf(one_output, Q, R_FULL[:1, :1], n_particles=300), ys[:, :1], us, _keys(2))
    for field in ("states", "covariances", "loglik", "nis"):
        np.testing.assert_allclose(getattr(out_nan, field), getattr(out_one, field), rtol=1e-9,
                                   atol=1e-12, err_msg=field)
    assert np.all(np.asarray(out_nan.n_obs) == 1)


@pytest.fixture(scope="module")
def one_step():
    """A 20000-particle filter with full R, its jitted step and its initial state."""
    est = bootstrap_pf(_model(), Q, R_FULL, n_particles=20000)
    state = est.init(jnp.asarray(X0), jnp.asarray(P0), key=jax.random.key(1))
    return est, jax.jit(est.step), state


def test_all_missing_is_a_pure_prediction(one_step):
    _, step, state = one_step
    state2, out = step(state, jnp.array([jnp.nan, jnp.nan]), jnp.zeros(2))
    assert float(out.loglik) == 0.0 and float(out.nis) == 0.0 and int(out.n_obs) == 0
    np.testing.assert_array_equal(state2.weights, state.weights)
    # the particle mean moved with the model
    np.testing.assert_allclose(out.mean, A @ np.asarray(state.particles).mean(axis=1), atol=0.05)


def test_nis_uses_predicted_particle_moments(one_step):
    _, step, state = one_step
    y = np.array([1.3, -0.4])
    _, out = step(state, jnp.asarray(y), jnp.zeros(2))
    S = A @ P0 @ A.T + Q + R_FULL
    e = y - A @ X0
    np.testing.assert_allclose(float(out.nis), e @ np.linalg.solve(S, e), rtol=0.05)


def test_process_noise_is_gaussian_with_covariance_q():
    stats = pytest.importorskip("scipy.stats")
    zero = vj.models.Model(
        transition=lambda x, u, th: 0.0 * x, observe=lambda x, u, th: x,
        dt=DT, state_names=("p", "v"), input_names=(), output_names=("yp", "yv"),
    )
    est = bootstrap_pf(zero, Q, R_DIAG, n_particles=50000)
    state = est.init(jnp.asarray(X0), jnp.asarray(P0), key=jax.random.key(7))
    state, _ = jax.jit(est.step)(state, jnp.array([jnp.nan, jnp.nan]), jnp.zeros(0))
    v = np.asarray(state.particles).T  # (N, nx): the process noise of one step
    np.testing.assert_allclose(np.cov(v.T), Q, rtol=0.03, atol=2e-4)
    white = np.linalg.solve(np.linalg.cholesky(Q), v.T)
    for comp in white:
        assert stats.kstest(comp, "norm").pvalue > 1e-3
    np.testing.assert_allclose(np.corrcoef(white), np.eye(2), atol=0.02)


def test_weights_underflow_reinitialises_with_finite_outputs():
    T = 25
    _, ys, us = _simulate(T, R_DIAG, seed=7)
    ys_bad = ys.copy()
    ys_bad[10] = [1e4, -1e4]  # 1e4 / 0.3 standard deviations away: every weight underflows
    est = bootstrap_pf(_model(), Q, R_DIAG, n_particles=500)
    state, out = _run(est, ys_bad, us, _keys(3))
    for field in ("states", "covariances", "loglik", "nis"):
        assert np.all(np.isfinite(np.asarray(getattr(out, field)))), field
    assert np.all(np.asarray(state.flag_diverged)) and np.all(np.asarray(state.n_reinit) == 1)
    mean, cov = np.asarray(out.states), np.asarray(out.covariances)
    # the diverged step moves the last estimate with the model and widens it by Q
    np.testing.assert_allclose(mean[:, 10], mean[:, 9] @ A.T + us[10], rtol=1e-12)
    np.testing.assert_allclose(cov[:, 10], cov[:, 9] + Q, rtol=1e-12)
    assert np.all(np.asarray(out.loglik)[:, 10] < -1e6)
    # and the filter recovers: back near the exact filter on the clean measurements after
    m_kf, P_kf, _ = _kalman(ys, us, R_DIAG)
    z = (mean[:, 20:] - m_kf[20:]) / np.sqrt(np.diagonal(P_kf[20:], axis1=1, axis2=2))
    assert np.sqrt(np.mean(z**2)) < 0.3
    # without the outlier nothing is flagged
    state, _ = _run(est, ys, us, _keys(3))
    assert not np.any(np.asarray(state.flag_diverged))


def test_non_finite_particles_get_zero_weight_and_a_nan_model_never_leaks():
    # transition NaN for particles with negative position: they get weight zero
    half_nan = vj.models.Model(
        transition=lambda x, u, th: jnp.stack([x[0] + jnp.sqrt(x[0]) * 0.0, x[1]]),
        observe=lambda x, u, th: x,
        dt=DT, state_names=("p", "v"), input_names=(), output_names=("yp", "yv"),
    )
    est = bootstrap_pf(half_nan, Q, R_DIAG, n_particles=1000,
                       resampling=Resampling(ess_threshold=0.0))
    state = est.init(jnp.array([0.0, 0.0]), jnp.eye(2), key=jax.random.key(0))
    state, out = jax.jit(est.step)(state, jnp.array([0.5, 0.0]), jnp.zeros(0))
    assert np.all(np.isfinite(out.mean)) and np.all(np.isfinite(out.cov))
    assert not bool(state.flag_diverged)
    p = np.asarray(state.particles)
    w = np.asarray(state.weights)
    assert 0.3 < np.mean(w == 0.0) < 0.7 and np.all(w[w > 0] > 0)
    assert np.all(np.isfinite(p))
    # a model that is NaN everywhere: every step diverges, outputs stay finite
    all_nan = vj.models.Model(
        transition=lambda x, u, th: x * jnp.nan, observe=lambda x, u, th: x,
        dt=DT, state_names=("p", "v"), input_names=(), output_names=("yp", "yv"),
    )
    est = bootstrap_pf(all_nan, Q, R_DIAG, n_particles=100)
    step = jax.jit(est.step)
    state = est.init(jnp.asarray(X0), jnp.asarray(P0), key=jax.random.key(0))
    for y in _simulate(5, R_DIAG, seed=0)[1]:
        state, out = step(state, jnp.asarray(y), jnp.zeros(0))
        for field in ("mean", "cov", "loglik", "nis"):
            assert np.all(np.isfinite(np.asarray(getattr(out, field)))), field
    np.testing.assert_allclose(out.mean, X0)  # the model gives nothing finite: the prior stays
    assert int(state.n_reinit) == 5 and bool(state.flag_diverged)


def test_float32_prior_runs_in_float32():
    T = 20
    _, ys, us = _simulate(T, R_DIAG, seed=8)
    m_kf, P_kf, _ = _kalman(ys, us, R_DIAG)
    est = bootstrap_pf(_model(), Q, R_DIAG, n_particles=1000)
    state, out = _run(est, ys.astype(np.float32), us.astype(np.float32), _keys(2),
                      x0=X0.astype(np.float32), P0_=P0.astype(np.float32))
    assert out.states.dtype == jnp.float32 and state.particles.dtype == jnp.float32
    assert out.covariances.dtype == jnp.float32 and out.loglik.dtype == jnp.float32
    z = (np.asarray(out.states) - m_kf) / np.sqrt(np.diagonal(P_kf, axis1=1, axis2=2))
    assert np.sqrt(np.mean(z**2)) < 0.15


@pytest.mark.slow  # a small study (tracking error over runs): `pytest -m slow` (README)
def test_dynamic3dof_follows_the_truth():
    model = vj.models.Dynamic3DOF(dt=0.01)
    scn = vj.scenarios.sine_steer(model, speed=20.0, duration=0.4)
    Qd = np.diag([0.05, 0.05, 0.01]) ** 2
    Rd = np.diag([0.2, 0.2, 0.05]) ** 2
    sim = vj.simulate(model, scn, runs=2, key=jax.random.key(0),
                      process_std=np.sqrt(np.diag(Qd)), meas_std=np.sqrt(np.diag(Rd)))
    est = bootstrap_pf(model, Qd, Rd, n_particles=300)

    def one(key, ys):
        return vj.filter(est, ys, sim.inputs, x0=jnp.asarray(scn.x0),
                         P0=jnp.asarray(np.diag([0.1, 0.05, 0.01]) ** 2), key=key)

    out = jax.jit(jax.vmap(one))(_keys(2), sim.measurements)
    err = np.sqrt(np.mean((np.asarray(out.states) - np.asarray(sim.states)) ** 2, axis=(0, 1)))
    meas_err = np.sqrt(np.mean((np.asarray(sim.measurements - sim.states)) ** 2, axis=(0, 1)))
    assert np.all(err < 0.7 * meas_err), (err, meas_err)


def test_estimator_contract(one_step):
    est, step, state = one_step
    assert est.needs_key and est.nx == 2 and est.param_names == () and est.name == "bootstrap_pf"
    assert state.particles.shape == (2, 20000) and state.flag_diverged.dtype == jnp.bool_
    variances = est.init(jnp.asarray(X0), jnp.asarray([0.5, 0.3]), key=jax.random.key(0))
    np.testing.assert_allclose(np.cov(np.asarray(variances.particles)), np.diag([0.5, 0.3]),
                               atol=0.02)
    _, out = step(state, jnp.array([0.1, 0.2]), jnp.zeros(2))
    assert out.params.shape == (0,) and out.params_cov.shape == (0, 0)
    assert out.n_obs.dtype == jnp.int32 and out.mean.shape == (2,) and out.cov.shape == (2, 2)


def test_bad_input_raises_value_error_naming_it():
    m = _model()
    for n in (0, -3, 2.5, True, "100"):
        with pytest.raises(ValueError, match="n_particles"):
            bootstrap_pf(m, Q, R_DIAG, n_particles=n)
    with pytest.raises(ValueError, match="^scheme.*systematic.*stratified.*multinomial.*resid"):
        bootstrap_pf(m, Q, R_DIAG, resampling=Resampling(scheme="bogus"))
    for thr in (-0.1, 1.5, "half", float("nan")):
        with pytest.raises(ValueError, match="ess_threshold"):
            bootstrap_pf(m, Q, R_DIAG, resampling=Resampling(ess_threshold=thr))
    with pytest.raises(ValueError, match="Q"):
        bootstrap_pf(m, np.eye(3), R_DIAG)
    with pytest.raises(ValueError, match="Q"):
        bootstrap_pf(m, np.array([[1.0, 2.0], [2.0, 1.0]]), R_DIAG)
    with pytest.raises(ValueError, match="R"):
        bootstrap_pf(m, Q, -np.eye(2))
    with pytest.raises(ValueError, match="model"):
        bootstrap_pf(object(), Q, R_DIAG)
    est = bootstrap_pf(m, Q, R_DIAG, n_particles=10)
    with pytest.raises(ValueError, match="key"):
        est.init(jnp.asarray(X0), jnp.asarray(P0))
    with pytest.raises(ValueError, match="x0"):
        est.init(jnp.zeros(3), jnp.asarray(P0), key=jax.random.key(0))
    with pytest.raises(ValueError, match="P0"):
        est.init(jnp.asarray(X0), -jnp.eye(2), key=jax.random.key(0))
    with pytest.raises(ValueError, match="theta0"):
        est.init(jnp.asarray(X0), jnp.asarray(P0), theta0=jnp.zeros(2), key=jax.random.key(0))


def test_works_with_vehjax_run():
    run_mod = pytest.importorskip("vehjax.run")
    T = 15
    _, ys, us = _simulate(T, R_DIAG, seed=9)
    est = bootstrap_pf(_model(), Q, R_DIAG, n_particles=200)
    res = run_mod.run(est, np.stack([ys, ys]), us, x0=X0, P0=P0, key=jax.random.key(0))
    m_kf, _, _ = _kalman(ys, us, R_DIAG)
    assert res.states.shape == (2, T, 2) and not np.any(res.diverged)
    assert np.max(np.abs(res.states - m_kf)) < 0.3


# ----------------------------------------------------------------------------------------------
# the step's mathematics, function by function, against numpy / scipy


def test_propagate_is_the_model_plus_scaled_normals_per_particle():
    from vehjax.filters.particle import propagate

    rng = np.random.default_rng(0)
    x, z = rng.normal(size=(2, 7)), rng.normal(size=(2, 7))
    u, L = np.array([0.3, -0.1]), np.linalg.cholesky(Q)
    got = np.asarray(propagate(_model().transition, jnp.asarray(x), jnp.asarray(u), None,
                               jnp.asarray(L), jnp.asarray(z)))
    ref = np.stack([A @ x[:, i] + u + L @ z[:, i] for i in range(7)], axis=1)
    np.testing.assert_allclose(got, ref, rtol=1e-13, atol=1e-15)
    # input noise: particle i runs with its own input u + Lu z_u[:, i]
    Lu, z_u = np.diag([0.2, 0.5]), rng.normal(size=(2, 7))
    got = np.asarray(propagate(_model().transition, jnp.asarray(x), jnp.asarray(u), None,
                               jnp.asarray(L), jnp.asarray(z), jnp.asarray(Lu), jnp.asarray(z_u)))
    ref = np.stack([A @ x[:, i] + u + Lu @ z_u[:, i] + L @ z[:, i] for i in range(7)], axis=1)
    np.testing.assert_allclose(got, ref, rtol=1e-13, atol=1e-15)


def test_residuals_flag_particles_that_are_not_finite():
    from vehjax.filters.particle import residuals

    x = np.array([[0.1, np.nan, 2.0, 1e308], [0.2, 0.0, -1.0, 1e308]])
    y = np.array([1.0, np.nan])
    square = lambda x, u, th: x * x  # noqa: E731 - overflows for the last particle
    obs, e, bad, x_out = (np.asarray(a) for a in residuals(square, jnp.asarray(x),
                                                           jnp.asarray(y), None, None))
    assert obs.tolist() == [True, False] and bad.tolist() == [False, True, False, True]
    np.testing.assert_allclose(e[0], [1.0 - 0.01, 0.0, 1.0 - 4.0, 0.0])
    assert np.all(e[1] == 0.0)  # the missing component
    np.testing.assert_array_equal(x_out[:, [1, 3]], 0.0)
    np.testing.assert_array_equal(x_out[:, [0, 2]], x[:, [0, 2]])


@pytest.mark.parametrize("diagonal", [False, True], ids=["full", "diagonal"])
def test_measurement_logliks_are_gaussian_log_densities_of_the_observed_part(diagonal):
    stats = pytest.importorskip("scipy.stats")
    from vehjax.filters.particle import measurement_logliks

    rng = np.random.default_rng(1)
    Rm = R_DIAG if diagonal else R_FULL
    e = rng.normal(size=(2, 5))
    for obs in ([True, True], [True, False]):
        o = np.array(obs)
        got = measurement_logliks(jnp.asarray(np.where(o[:, None], e, 0.0)), jnp.asarray(o),
                                  jnp.asarray(Rm), jnp.asarray(np.diagonal(Rm)) if diagonal
                                  else None)
        ref = stats.multivariate_normal(np.zeros(o.sum()), Rm[np.ix_(o, o)]).logpdf(e[o].T)
        np.testing.assert_allclose(np.asarray(got), ref, rtol=1e-12)


def test_predicted_nis_from_weighted_moments_of_the_residuals():
    from vehjax.filters.particle import predicted_nis

    rng = np.random.default_rng(2)
    e, w = rng.normal(size=(2, 9)), rng.uniform(size=9)
    bad = np.zeros(9, bool)
    bad[4] = True
    got = float(predicted_nis(jnp.asarray(e), jnp.asarray(w), jnp.asarray(bad),
                              jnp.asarray(R_FULL), jnp.ones(2, bool)))
    wk = np.where(bad, 0.0, w) / w[~bad].sum()
    r = e @ wk
    S = ((e - r[:, None]) * wk) @ (e - r[:, None]).T + R_FULL
    assert got == pytest.approx(r @ np.linalg.solve(S, r), rel=1e-12)
    # a missing component: the NIS of the observed one alone
    e1 = np.where([[True], [False]], e, 0.0)
    got1 = float(predicted_nis(jnp.asarray(e1), jnp.asarray(w), jnp.asarray(bad),
                               jnp.asarray(R_FULL), jnp.asarray([True, False])))
    var = wk @ (e[0] - e[0] @ wk) ** 2 + R_FULL[0, 0]
    assert got1 == pytest.approx((e[0] @ wk) ** 2 / var, rel=1e-12)


def test_reinit_factor_and_moved_estimate():
    from vehjax.filters.particle import moved_estimate, reinit_factor

    LQ = np.linalg.cholesky(Q)
    np.testing.assert_allclose(np.asarray(reinit_factor(jnp.asarray(P0), jnp.asarray(Q),
                                                        jnp.asarray(LQ))),
                               np.linalg.cholesky(P0 + Q), rtol=1e-13)
    broken = np.full((2, 2), np.nan)
    np.testing.assert_array_equal(reinit_factor(jnp.asarray(broken), jnp.asarray(Q),
                                                jnp.asarray(LQ)), LQ)
    f = _model().transition
    m, u = np.array([0.5, -1.0]), np.array([0.1, 0.2])
    np.testing.assert_allclose(moved_estimate(f, jnp.asarray(m), jnp.asarray(u), None),
                               A @ m + u, rtol=1e-14)
    nan_model = lambda x, u, th: x * jnp.nan  # noqa: E731
    np.testing.assert_array_equal(moved_estimate(nan_model, jnp.asarray(m), None, None), m)


def test_resample_or_restart_keeps_the_genealogy():
    from vehjax.filters import smc
    from vehjax.filters.particle import resample_or_restart

    n = 6
    x = jnp.asarray(np.arange(2.0 * n).reshape(2, n))
    lw = np.log([0.01, 0.01, 0.9, 0.06, 0.01, 0.01])
    rw = smc.reweight(jnp.full(n, -np.log(n)), jnp.asarray(lw))
    u = jnp.asarray([0.3])
    no, yes = jnp.asarray(False), jnp.asarray(True)
    xn, _, wn, anc = resample_or_restart(smc.resample, x, rw, u, "systematic", 0.5, no, no)
    anc = np.asarray(anc)
    # systematic indices: the first i whose cumulative weight exceeds (j + u) / n
    ref = np.searchsorted(np.cumsum(np.exp(lw)), (np.arange(n) + 0.3) / n, side="right")
    np.testing.assert_array_equal(anc, ref)
    np.testing.assert_array_equal(np.asarray(xn), np.asarray(x)[:, anc])
    np.testing.assert_allclose(np.asarray(wn), 1.0 / n)
    for pending, diverged in ((yes, no), (no, yes)):
        _, _, wn, anc = resample_or_restart(smc.resample, x, rw, u, "systematic", 0.5, pending,
                                            diverged)
        np.testing.assert_array_equal(anc, np.arange(n))  # drawn afresh: no genealogy
    np.testing.assert_allclose(np.asarray(wn), 1.0 / n)  # after a divergence: equal weights


# ----------------------------------------------------------------------------------------------
# the resampling function as an argument; the many-runs form equals the step


def test_resample_argument_is_called_and_validated():
    from vehjax.filters import smc

    T = 12
    _, ys, us = _simulate(T, R_DIAG, seed=4)
    calls = []

    def counting(*args):
        calls.append(args[4:])
        return smc.resample(*args)

    k = jax.random.key(2)
    plain = vj.filter(bootstrap_pf(_model(), Q, R_DIAG, n_particles=50), ys, us, x0=X0, P0=P0, key=k)
    mine = vj.filter(bootstrap_pf(_model(), Q, R_DIAG, n_particles=50,
                                  resampling=Resampling(scheme="stratified", ess_threshold=0.9,
                                                        resample=counting)), ys, us, x0=X0, P0=P0, key=k)
    assert calls and all(c == ("stratified", 0.9) for c in calls)  # traced with its arguments
    sg = vj.filter(bootstrap_pf(_model(), Q, R_DIAG, n_particles=50,
                                resampling=Resampling(resample=smc.resample_stop_gradient)),
                   ys, us, x0=X0, P0=P0, key=k)
    np.testing.assert_array_equal(sg.states, plain.states)  # same forward pass
    np.testing.assert_array_equal(sg.loglik, plain.loglik)
    assert not np.array_equal(mine.states, plain.states)  # another scheme and threshold
    for bad in (42, "systematic"):
        with pytest.raises(ValueError, match="^resample: expected None or a resampling func"):
            bootstrap_pf(_model(), Q, R_DIAG, n_particles=50, resampling=Resampling(resample=bad))


def test_many_runs_form_equals_the_step_run_by_run():
    from _contract import assert_batch_equals_step

    T, runs = 8, 3
    ys = np.stack([_simulate(T, R_FULL, seed=s, missing=[(2, 0)])[1] for s in range(runs)])
    _, _, us = _simulate(T, R_FULL, seed=0)
    x0 = X0 + np.arange(runs)[:, None] * 0.1
    est = bootstrap_pf(_model(), Q, R_FULL, n_particles=64,
                       resampling=Resampling(ess_threshold=0.8))
    form = assert_batch_equals_step(est, ys, us, x0, P0, keys=jax.random.split(jax.random.key(0),
                                                                               runs))
    assert form == ("batch" if est.batch is not None else "vmap")
