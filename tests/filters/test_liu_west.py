"""Liu-West PF + UKF (Dutta et al. 2019, Alg. 3) against an exact grid posterior (numpy, below)."""

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import vehjax as vj
from vehjax.lib.transforms import Transform
from vehjax.filters.gaussian import GaussianState, ukf
from vehjax.filters import smc
from vehjax.filters import LiuWestKernel, Resampling
from vehjax.filters.liu_west import liu_west_ukf
from vehjax.filters.smc import shrink_move
from vehjax.lib.entrywise import cholesky_observed

from _records import grouped

# Scalar linear model with an unknown input gain b: x' = A x + b u + w, y = x + v.
A, QV, RV, B_TRUE = 0.9, 0.05, 0.1, 1.0
LOW, HIGH = 0.0, 2.0


def _gain_model():
    return vj.models.Model(
        transition=lambda x, u, th: A * x + th[0] * u,
        observe=lambda x, u, th: x,
        dt=0.1,
        state_names=("x",),
        param_names=("b",),
        input_names=("u",),
        theta=[B_TRUE],
    )


def _gain_data(T, seed):
    rng = np.random.default_rng(seed)
    us = rng.normal(size=T)
    x, ys = 0.0, []
    for t in range(T):
        x = A * x + B_TRUE * us[t] + rng.normal() * np.sqrt(QV)
        ys.append(x + rng.normal() * np.sqrt(RV))
    return np.array(ys)[:, None], us[:, None]


def _grid_posterior(ys, us, grid, gain=lambda b: b, mode=False):
    """Exact posterior mean and std of b under the uniform prior: a Kalman filter per grid b
    (input gain ``gain(b)``); with ``mode`` also the posterior mode."""
    x, P = np.zeros_like(grid), np.ones_like(grid)
    ll = np.zeros_like(grid)
    k = gain(grid)
    for y, u in zip(ys[:, 0], us[:, 0]):
        x, P = A * x + k * u, A * A * P + QV
        S = P + RV
        e = y - x
        ll += -0.5 * (e * e / S + np.log(2 * np.pi * S))
        K = P / S
        x, P = x + K * e, P * (1 - K)
    w = np.exp(ll - ll.max())
    w /= w.sum()
    m = w @ grid
    if mode:
        return m, np.sqrt(w @ (grid - m) ** 2), grid[np.argmax(w)]
    return m, np.sqrt(w @ (grid - m) ** 2)


def test_recovers_the_gain_like_the_exact_posterior():
    T, runs = 80, 3
    data = [_gain_data(T, s) for s in range(runs)]
    ys, us = np.stack([d[0] for d in data]), np.stack([d[1] for d in data])
    est = liu_west_ukf(_gain_model(), Q=[QV], R=[RV], n_particles=300, estimate=("b",),
                       theta_low=[LOW], theta_high=[HIGH], kernel=LiuWestKernel(gamma=1.0))
    out = vj.run(est, ys, us, x0=[0.0], P0=[[1.0]], theta0=[1.0], P_theta0=[[1 / 3]],
                 key=jax.random.key(0), return_covariances=True)
    assert not out.diverged.any()
    prior_std = (HIGH - LOW) / np.sqrt(12)
    grid = np.linspace(LOW, HIGH, 4001)
    for r in range(runs):
        m, s = _grid_posterior(ys[r], us[r], grid)
        assert s < 0.15 * prior_std  # the data are informative
        est_m, est_s = out.params[r, -1, 0], np.sqrt(out.params_cov[r, -1, 0, 0])
        assert abs(est_m - m) < 3 * s
        assert 0.5 * s < est_s < 2 * s


@pytest.mark.slow  # a 50-run study: `pytest -m slow` (README)
def test_tracks_the_exact_posterior_mean_when_it_is_skewed():
    """x' = A x + u / g + w: the posterior of g is skewed (mean above mode). Over 50 runs the
    final estimate (default: kernel after resampling only) lies on the exact grid posterior
    mean, within a small fraction of the posterior std on average and per run (issue #17)."""
    T, runs, g_true, low, high = 300, 50, 1.0, 0.3, 3.0
    rng = np.random.default_rng(1)
    us = 0.3 * rng.normal(size=(runs, T))
    ys, x = np.zeros((runs, T)), np.zeros(runs)
    for t in range(T):
        x = A * x + us[:, t] / g_true + rng.normal(size=runs) * np.sqrt(QV)
        ys[:, t] = x + rng.normal(size=runs) * np.sqrt(RV)
    grid = np.linspace(low, high, 4001)
    exact = np.array([_grid_posterior(ys[r, :, None], us[r, :, None], grid, lambda g: 1.0 / g,
                                      mode=True) for r in range(runs)])
    mean, std, mode = exact.T
    assert np.mean((mean - mode) / std) > 0.1  # skewed: a Gaussian fit would sit off the mean
    model = vj.models.Model(transition=lambda x, u, th: A * x + u / th[0],
                            observe=lambda x, u, th: x, dt=0.1, state_names=("x",),
                            param_names=("g",), input_names=("u",), theta=[g_true])
    est = liu_west_ukf(model, Q=[QV], R=[RV], n_particles=500, estimate=("g",),
                       theta_low=[low], theta_high=[high])
    out = vj.run(est, ys[:, :, None], us[:, :, None], x0=[0.0], P0=[[1.0]],
                 key=jax.random.key(0), progress=False)
    z = (np.asarray(out.params[:, -1, 0]) - mean) / std
    assert abs(z.mean()) < 0.15
    assert np.sqrt(np.mean(z**2)) < 0.35


def test_kernel_keeps_weighted_mean_and_covariance():
    rng = np.random.default_rng(1)
    M = 200_000
    scale = np.array([1700.0, 1.5e5])
    corr = np.array([[1.0, 0.6], [0.6, 1.0]])
    parts = scale * (1.0 + 0.1 * rng.multivariate_normal(np.zeros(2), corr, size=M))
    w = rng.gamma(0.5, size=M)  # far from uniform
    w /= w.sum()
    mean = w @ parts
    V = ((parts - mean) * w[:, None]).T @ (parts - mean)
    a = 0.9
    # the normals the filter draws: the particle core's counter-based ones
    z = smc.normals(smc.raw_key(jax.random.key(3)), 2, M, jnp.float64)
    moved = np.asarray(shrink_move(z, jnp.asarray(parts.T), jnp.asarray(mean),
                               jnp.asarray(V), a)).T  # particles (p, M) in the filter
    new_mean = w @ moved
    new_V = ((moved - new_mean) * w[:, None]).T @ (moved - new_mean)
    ess = 1.0 / np.sum(w**2)
    se = np.sqrt(np.diagonal(V) / ess)
    assert np.all(np.abs(new_mean - mean) < 4 * se)
    assert np.allclose(new_V, V, rtol=0.03)
    # the particles did move, towards the mean by a, with spread (1 - a^2) V
    resid = moved - (a * parts + (1 - a) * mean)
    assert np.allclose(np.cov(resid.T), (1 - a * a) * V, rtol=0.03)


@pytest.mark.parametrize("bounds", [{"b": (1000.0, 2500.0)}, {}], ids=["box-domain", "unbounded"])
def test_step_without_information_keeps_the_cloud(bounds):
    """Measurements that do not depend on b: weights stay equal, the kernel (``move="every"``:
    at a step that does not resample) keeps the moments
    of the cloud in the coordinate it acts on (the particles: logit of the prior box here,
    b itself with bounds={}, where they are those of the uniform prior: mean at the centre,
    variance width^2 / 12), and the estimate is the moments of the particles in physical units
    (inside the box by default)."""
    model = vj.models.Model(
        transition=lambda x, u, th: A * x + 0.0 * th[0], observe=lambda x, u, th: x, dt=0.1,
        state_names=("x",), param_names=("b",), input_names=("u",), theta=[1.0],
    )
    M = 20_000
    est = liu_west_ukf(model, Q=[QV], R=[RV], n_particles=M, estimate="b", theta_low=[1000.0],
                       theta_high=[2500.0], kernel=LiuWestKernel(a=0.8,
                                                                 move="every"), resampling=Resampling(ess_threshold=0.0), bounds=bounds)
    to_physical = Transform(*est.bounds).to_physical
    state = est.init(jnp.zeros(1), jnp.eye(1), key=jax.random.key(0))
    before = np.asarray(state.particles[0])  # particles (p, M)
    state, out = jax.jit(est.step)(state, jnp.array([0.3]), jnp.array([0.0]))
    after = np.asarray(state.particles[0])
    assert np.allclose(np.asarray(state.log_weights), -np.log(M))
    assert not np.allclose(after, before)
    assert abs(after.mean() - before.mean()) < 4 * before.std() / np.sqrt(M)
    assert np.isclose(after.var(), before.var(), rtol=0.03)
    phys = np.asarray(to_physical(state.particles, axis=0)[0])
    assert np.isclose(phys.mean(), out.params[0]) and np.isclose(phys.var(), out.params_cov[0, 0])
    if bounds:
        assert 1000.0 < phys.min() and phys.max() < 2500.0
    else:
        np.testing.assert_array_equal(phys, after)
        assert abs(out.params[0] - 1750.0) < 4 * 1500.0 / np.sqrt(12 * M)
        assert np.isclose(out.params_cov[0, 0], 1500.0**2 / 12, rtol=0.03)


def _two_output_model(outputs=(0, 1)):
    return vj.models.Model(
        transition=lambda x, u, th: jnp.array([A * x[0] + th[0] * u[0], 0.8 * x[1] + th[1] * u[0]]),
        observe=lambda x, u, th: x[jnp.array(outputs)],
        dt=0.1, state_names=("x1", "x2"), param_names=("b1", "b2"), input_names=("u",),
        theta=[1.0, 0.5],
    )


_SCANS = {}


def _scan(est, ys, us, key):
    """vehjax.filter over one run, prior N(0, I): (final state, result); one jit per estimator."""
    if id(est) not in _SCANS:

        def one(ys, us, key):
            res = vj.filter(est, ys, us, x0=jnp.zeros(2), P0=jnp.eye(2), key=key)
            return res.state, res

        _SCANS[id(est)] = (est, jax.jit(one))
    return _SCANS[id(est)][1](jnp.asarray(ys), jnp.asarray(us), key)


def _two_output_est(**kw):
    return liu_west_ukf(_two_output_model(), Q=[0.05, 0.05], R=[0.1, 0.2], n_particles=64,
                        estimate=("b1", "b2"), theta_low=[0.0, 0.0], theta_high=[2.0, 1.0],
                        **grouped(kw))


EST2 = _two_output_est()


def _two_output_data(T=15):
    rng = np.random.default_rng(5)
    us = rng.normal(size=(T, 1))
    ys = np.cumsum(rng.normal(size=(T, 2)), axis=0) * 0.3 + us
    return ys, us


@pytest.mark.slow  # two Liu-West compiles: `pytest -m slow` (README)
def test_missing_component_is_the_same_as_not_measuring_it():
    ys, us = _two_output_data()
    ys_nan = ys.copy()
    ys_nan[:, 1] = np.nan
    kw = dict(n_particles=64, estimate=("b1", "b2"), theta_low=[0.0, 0.0], theta_high=[2.0, 1.0])
    one = liu_west_ukf(_two_output_model((0,)), Q=[0.05, 0.05], R=[0.1], **kw)
    s_nan, o_nan = _scan(EST2, ys_nan, us, jax.random.key(7))  # EST2 is `one` with both outputs
    s_one, o_one = _scan(one, ys[:, :1], us, jax.random.key(7))
    for a, b in zip(jax.tree.leaves((s_nan, o_nan)), jax.tree.leaves((s_one, o_one))):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-9, atol=1e-12)
    assert np.all(np.asarray(o_nan.n_obs) == 1)


def test_all_missing_is_a_pure_prediction():
    ys, us = _two_output_data()  # the length the other tests use: their compiled scan
    est = EST2
    state, _ = _scan(est, ys, us, jax.random.key(1))
    new, out = jax.jit(est.step)(state, jnp.full(2, jnp.nan), jnp.asarray(us[0]))
    np.testing.assert_array_equal(new.particles, state.particles)
    np.testing.assert_array_equal(new.log_weights, state.log_weights)
    np.testing.assert_allclose(out.params, state.theta_mean, rtol=1e-12)
    # the UKF only predicts, at the parameter estimate
    ref = ukf(_two_output_model(), Q=[0.05, 0.05], R=[0.1, 0.2])
    prior = GaussianState(state.x, state.P, state.theta_mean)
    _, r_out = jax.jit(ref.step)(prior, jnp.full(2, jnp.nan), jnp.asarray(us[0]))
    np.testing.assert_allclose(out.mean, r_out.mean, rtol=1e-12)
    np.testing.assert_allclose(out.cov, r_out.cov, rtol=1e-12)
    assert int(out.n_obs) == 0 and float(out.loglik) == 0.0


def test_same_key_same_result_other_key_other_result():
    ys, us = _two_output_data()
    est = EST2
    _, o1 = _scan(est, ys, us, jax.random.key(3))
    _, o2 = _scan(est, ys, us, jax.random.key(3))
    _, o3 = _scan(est, ys, us, jax.random.key(4))
    np.testing.assert_array_equal(o1.params, o2.params)
    np.testing.assert_array_equal(o1.states, o2.states)
    assert not np.allclose(o1.params, o3.params)


def test_weights_underflow_reinitialises_from_the_box_with_finite_outputs():
    ys, us = _two_output_data(6)
    ys[3] = 1e200  # no particle can explain this
    est = EST2
    state, out = _scan(est, ys[:4], us[:4], jax.random.key(2))
    assert bool(state.flag_diverged) and int(state.n_reinit) == 1
    assert np.all(np.isfinite(np.asarray(out.params))) and np.all(np.isfinite(out.params_cov))
    p = np.asarray(Transform(*est.bounds).to_physical(state.particles, axis=0)).T  # (M, p)
    assert np.all((p >= [0.0, 0.0]) & (p <= [2.0, 1.0]))
    np.testing.assert_allclose(state.log_weights, -np.log(64))


@pytest.mark.slow  # a small study on a vehicle model: `pytest -m slow` (README)
def test_works_with_vehjax_run_on_the_kinematic_bicycle():
    model = vj.models.KinematicBicycle(dt=0.1)
    scn = vj.scenarios.sine_steer(model, speed=10.0, amplitude=0.3, frequency=0.5, duration=10.0)
    meas_std = np.array([0.1, 0.1, 0.02, 0.1])
    sim = vj.simulate(model, scn, runs=2, key=jax.random.key(0), process_std=0.01,
                      meas_std=meas_std)
    low, high = np.array([0.5, 0.5]), np.array([3.0, 3.0])
    # 1000 particles: with 100-300 the parameter covariance is over-confident (liu_west docstring)
    est = liu_west_ukf(model, Q=np.full(4, 1e-4), R=meas_std**2, n_particles=1000,
                       estimate=("lf", "lr"), theta_low=low, theta_high=high)
    prior_cov = np.diag((high - low) ** 2 / 12)
    out = vj.run(est, sim.measurements, sim.inputs, x0=scn.x0, P0=np.diag([1, 1, 0.2, 2.0]),
                 theta0=(low + high) / 2, P_theta0=prior_cov, key=jax.random.key(1),
                 return_covariances=True)
    assert out.params.shape == (2, sim.measurements.shape[1], 2)
    assert not out.diverged.any()
    std = np.sqrt(np.diagonal(out.params_cov[:, -1], axis1=1, axis2=2))
    assert np.all(std < 0.5 * np.sqrt(np.diagonal(prior_cov)))  # learnt from the data
    assert np.all(np.abs(out.params[:, -1] - 1.5) < 3 * std)  # and consistent with the truth


def test_estimator_contract():
    est = liu_west_ukf(_gain_model(), Q=[QV], R=[RV], n_particles=10, estimate=["b"],
                       theta_low=[LOW], theta_high=[HIGH])
    assert est.needs_key and est.param_names == ("b",) and est.nx == 1
    state = est.init(np.zeros(1), np.eye(1), np.array([1.0]), np.eye(1), jax.random.key(0))
    _, out = jax.jit(est.step)(state, jnp.array([0.1]), jnp.array([0.2]))
    assert out.params.shape == (1,) and out.params_cov.shape == (1, 1)
    assert out.mean.shape == (1,) and out.cov.shape == (1, 1)


@pytest.mark.parametrize(
    "kwargs, name",
    [
        (dict(n_particles=0), "n_particles"),
        (dict(n_particles=2.5), "n_particles"),
        (dict(theta_low=[2.0], theta_high=[1.0]), "theta_low"),
        (dict(theta_low=[0.0, 0.0]), "theta_low"),
        (dict(theta_high=[1.0, 2.0]), "theta_high"),
        (dict(theta_high=[np.inf]), "theta_high"),
        (dict(estimate=("b", "c")), "estimate"),
        (dict(estimate=()), "estimate"),
        (dict(a=1.0), "a"),
        (dict(a=0.0), "a"),
        (dict(gamma=0.0), "gamma"),
        (dict(gamma=1.5), "gamma"),
        (dict(resampling="bogus"), "scheme"),
        (dict(ess_threshold=2.0), "ess_threshold"),
        (dict(likelihood="exact"), "likelihood"),
        (dict(move="sometimes"), "move"),
        (dict(Q=[-1.0]), "Q"),
        (dict(R=[[1.0, 0.0]]), "R"),
    ],
)
def test_bad_input_raises_value_error_naming_it(kwargs, name):
    args = dict(Q=[QV], R=[RV], n_particles=10, estimate=("b",), theta_low=[LOW],
                theta_high=[HIGH])
    args.update(kwargs)
    with pytest.raises(ValueError, match=name):
        liu_west_ukf(_gain_model(), **grouped(args))


def test_bad_init_raises_value_error_naming_it():
    est = liu_west_ukf(_gain_model(), Q=[QV], R=[RV], n_particles=10, estimate=("b",),
                       theta_low=[LOW], theta_high=[HIGH])
    with pytest.raises(ValueError, match="key"):
        est.init(np.zeros(1), np.eye(1))
    with pytest.raises(ValueError, match="theta0"):
        est.init(np.zeros(1), np.eye(1), np.zeros(2), key=jax.random.key(0))
    with pytest.raises(ValueError, match="P0"):
        est.init(np.zeros(1), -np.eye(1), key=jax.random.key(0))


def test_default_domain_is_positive_for_a_positive_box_else_the_box():
    """bounds=None: (0, inf) (log coordinate) for a box with theta_low > 0, the box itself
    otherwise (issue #17: the logit of the box biased the estimates)."""
    est = liu_west_ukf(_two_output_model(), Q=[0.05, 0.05], R=[0.1, 0.2], n_particles=8,
                       estimate=("b1", "b2"), theta_low=[0.5, -1.0], theta_high=[2.0, 1.0])
    low, high = (np.asarray(b, float) for b in est.bounds[:2])
    np.testing.assert_array_equal(low, [0.0, -1.0])
    np.testing.assert_array_equal(high, [np.inf, 1.0])


# ----------------------------------------------------------------------------------------------
# the step's mathematics, function by function, against numpy / scipy / finite differences


def test_full_theta_and_residual_weight():
    from vehjax.filters.liu_west import full_theta, residual_weight

    base = np.array([1.0, 2.0, 3.0, 4.0])
    vals = np.array([[10.0, 30.0], [11.0, 31.0], [12.0, 32.0]])  # (M, p)
    got = np.asarray(full_theta(jnp.asarray(base), np.array([0, 2], np.int32), jnp.asarray(vals)))
    ref = np.tile(base, (3, 1))
    ref[:, [0, 2]] = vals
    np.testing.assert_array_equal(got, ref)
    rng = np.random.default_rng(0)
    w = rng.dirichlet(np.ones(7))
    for gamma in (0.3, 0.9):
        lw = np.asarray(residual_weight(jnp.asarray(np.log(w)), gamma))
        np.testing.assert_allclose(np.exp(lw), gamma * w + (1 - gamma) / 7, rtol=1e-13)
    np.testing.assert_array_equal(residual_weight(jnp.asarray(np.log(w)), 1.0), np.log(w))


def test_predictions_and_weights_of_the_particles():
    """predict_particles: h(f(x + D (th_i - th_bar), u, th_i)) per particle (numpy loop);
    weigh: log W_i + log N(y; y_i, S) renormalised (scipy), a particle predicting NaN at 0."""
    stats = pytest.importorskip("scipy.stats")
    from vehjax.filters.liu_west import predict_particles, weigh

    model = _two_output_model()
    f, h = model.transition, model.observe
    x, u = np.array([0.4, -0.3]), np.array([0.7])
    th = np.array([[0.9, 1.1, 1.3], [0.2, 0.4, 0.6]])  # (p, M)
    D, th_bar = np.array([[0.5, 0.1], [-0.2, 0.3]]), np.array([1.0, 0.5])
    base, idx = jnp.asarray(model.theta), np.array([0, 1], np.int32)
    pred = jax.jit(partial(predict_particles, f, h, idx=idx))
    got = np.asarray(pred(jnp.asarray(x), jnp.asarray(u), base, theta_i=jnp.asarray(th),
                          D=jnp.asarray(D), theta_mean=jnp.asarray(th_bar)))

    def ref_one(xi, ti):
        fx = np.array([A * xi[0] + ti[0] * u[0], 0.8 * xi[1] + ti[1] * u[0]])
        return fx

    ref = np.stack([ref_one(x + D @ (th[:, i] - th_bar), th[:, i]) for i in range(3)])
    np.testing.assert_allclose(got, ref, rtol=1e-14)
    plain = np.asarray(pred(jnp.asarray(x), jnp.asarray(u), base, theta_i=jnp.asarray(th)))
    np.testing.assert_allclose(plain, np.stack([ref_one(x, th[:, i]) for i in range(3)]),
                               rtol=1e-14)

    S = np.array([[0.3, 0.05], [0.05, 0.2]])
    y = np.array([0.5, 0.1])
    y_i = np.vstack([ref, [np.nan, 0.0]])  # a fourth particle whose prediction is not finite
    lw0 = np.log(np.array([0.1, 0.2, 0.3, 0.4]))
    obs = jnp.ones(2, bool)
    rw = jax.jit(weigh)(jnp.asarray(lw0), jnp.asarray(y_i), jnp.asarray(y), obs,
                        cholesky_observed(jnp.asarray(S), obs))
    ll = stats.multivariate_normal(np.zeros(2), S).logpdf(y - ref)
    un = np.exp(lw0[:3] + ll)
    np.testing.assert_allclose(np.asarray(rw.w), np.append(un / un.sum(), 0.0), rtol=1e-12)
    assert float(rw.loglik) == pytest.approx(np.log(un.sum()), rel=1e-12)


def test_likelihood_factor_is_the_ukf_innovation_covariance_or_r():
    from vehjax.filters import sigma
    from vehjax.filters.liu_west import likelihood_factor

    model = _two_output_model()
    f, h = model.transition, model.observe
    x, P, u = np.array([0.4, -0.3]), np.array([[0.5, 0.1], [0.1, 0.3]]), np.array([0.7])
    Qm, Rm, th = np.diag([0.05, 0.05]), np.diag([0.1, 0.2]), jnp.asarray([1.0, 0.5])
    obs = jnp.ones(2, bool)
    rule = sigma.unscented_rule(2, 1.0, 2.0, 0.0)
    L = np.asarray(likelihood_factor(rule, f, h, jnp.asarray(x), jnp.asarray(P),
                                     jnp.asarray(u), th, jnp.asarray(Qm), jnp.asarray(Rm), obs,
                                     True))
    # the model is linear: the unscented S is exactly F P F^T + Q + R (observe = identity)
    F = np.diag([A, 0.8])
    np.testing.assert_allclose(L @ L.T, F @ P @ F.T + Qm + Rm, rtol=1e-12)
    L = np.asarray(likelihood_factor(rule, f, h, jnp.asarray(x), jnp.asarray(P),
                                     jnp.asarray(u), th, jnp.asarray(Qm), jnp.asarray(Rm),
                                     jnp.asarray([True, False]), False))
    np.testing.assert_allclose(L, np.diag([np.sqrt(0.1), 1.0]), rtol=1e-14)


def test_ukf_recurrent_derivative_is_the_jacobian_of_the_ukf_step():
    """ukf_with_derivative: D' = d x'(th) / d th at theta_bar, x'(th) the UKF's updated mean
    from x + D (th - theta_bar) with parameters th: against central finite differences."""
    from vehjax.filters.liu_west import ukf_with_derivative

    model = _two_output_model()
    step = ukf(model, Q=[0.05, 0.05], R=[0.1, 0.2]).step
    x, P = jnp.asarray([0.4, -0.3]), jnp.asarray([[0.5, 0.1], [0.1, 0.3]])
    D, th_bar = jnp.asarray([[0.5, 0.1], [-0.2, 0.3]]), jnp.asarray([1.0, 0.5])
    y, u = jnp.asarray([0.5, 0.1]), jnp.asarray([0.7])
    base, idx = jnp.asarray(model.theta), np.array([0, 1], np.int32)
    with_d = jax.jit(lambda rec: ukf_with_derivative(step, x, P, D, base, idx, th_bar, y, u,
                                                     rec)[:2], static_argnums=0)
    D_next, st = with_d(True)
    x_next_j = jax.jit(lambda th: step(GaussianState(x + D @ (th - th_bar), P, th), y, u)[0].x)

    def x_next(th):
        return np.asarray(x_next_j(th))

    eps = 1e-6
    fd = np.stack([(x_next(th_bar + eps * e) - x_next(th_bar - eps * e)) / (2 * eps)
                   for e in np.eye(2)], axis=1)
    np.testing.assert_allclose(np.asarray(D_next), fd, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(np.asarray(st.x), x_next(th_bar), rtol=1e-14)
    D_same, st2 = with_d(False)
    np.testing.assert_array_equal(np.asarray(D_same), np.asarray(D))
    np.testing.assert_allclose(np.asarray(st2.x), x_next(th_bar), rtol=1e-14)


def test_liu_west_move_only_where_it_should():
    from vehjax.filters.liu_west import liu_west_move

    M = 8
    parts = jnp.asarray(np.linspace(-1.0, 1.0, 2 * M).reshape(2, M))
    w = jnp.full(M, 1.0 / M)
    lw = jnp.log(w)
    z = smc.normals(smc.raw_key(jax.random.key(0)), 2, M, jnp.float64)
    u = smc.uniforms(smc.raw_key(jax.random.key(1)), "systematic", M, jnp.float64)
    jit = jnp.eye(2) * 1e-9

    @partial(jax.jit, static_argnums=1)
    def move(keep, every):
        moved = liu_west_move(smc.resample, parts, w, lw, u, "systematic", 0.5, z, jit, 0.9,
                              keep, every)
        mean, V = smc.moments(w, parts)
        return moved, shrink_move(z, parts, mean, V + jit, 0.9)

    no, yes = jnp.asarray(False), jnp.asarray(True)
    # equal weights: ESS = M, no resampling; moved only with every=True
    (p1, l1), _ = move(no, False)
    np.testing.assert_array_equal(np.asarray(p1), np.asarray(parts))
    (p2, _), kernel = move(no, True)
    np.testing.assert_allclose(np.asarray(p2), np.asarray(kernel), rtol=1e-14)
    (p3, l3), _ = move(yes, True)  # keep: nothing moves
    np.testing.assert_array_equal(np.asarray(p3), np.asarray(parts))
    np.testing.assert_array_equal(np.asarray(l3), np.asarray(lw))


# ----------------------------------------------------------------------------------------------
# the resampling function as an argument; refusals; the many-runs form equals the step


def test_resample_argument_is_called_and_validated():
    """The step resamples through the function it was built with, with its scheme and
    threshold (traced only: same forward values as smc.resample are test_resampling's)."""
    calls = []

    def counting(*args):
        calls.append(args[4:])
        return smc.resample_stop_gradient(*args)

    est = _two_output_est(resample=counting, resampling="stratified", ess_threshold=0.7)
    state = est.init(jnp.zeros(2), jnp.eye(2), key=jax.random.key(0))
    jax.make_jaxpr(est.step)(state, jnp.array([0.1, 0.2]), jnp.array([0.3]))
    assert calls == [("stratified", 0.7)]
    with pytest.raises(ValueError, match="^resample: expected None or a resampling function"):
        _two_output_est(resample="systematic")


@pytest.mark.parametrize("arg", ["theta_low", "theta_high"])
def test_complex_box_is_refused_as_complex(arg):
    args = dict(Q=[QV], R=[RV], n_particles=10, estimate=("b",), theta_low=[LOW],
                theta_high=[HIGH])
    args[arg] = [1.0 + 0.5j]
    with pytest.raises(ValueError, match=rf"^{arg}: .*complex") as err:
        liu_west_ukf(_gain_model(), **grouped(args))
    assert "numbers" not in str(err.value)


def test_many_runs_form_equals_the_step_run_by_run():
    from _contract import assert_batch_equals_step

    runs, T = 3, 5
    ys = np.stack([_two_output_data(T)[0] + 0.1 * r for r in range(runs)])
    ys[1, 2, 0] = np.nan
    us = _two_output_data(T)[1]
    # a light configuration (no recurrent derivative, S = R): two compiles of a small step
    est = _two_output_est(ess_threshold=0.9, recurrent=False, likelihood="measurement")
    form = assert_batch_equals_step(est, ys, us, np.zeros((runs, 2)), np.eye(2),
                                    keys=jax.random.split(jax.random.key(0), runs))
    assert form == ("batch" if est.batch is not None else "vmap")
