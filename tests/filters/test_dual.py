"""Dual and joint EKF/UKF (vehjax.filters.dual) against Kalman recursions written plainly in
numpy on a linear model with a constant bias parameter, and parameter recovery studies."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import vehjax as vj
from vehjax.filters.dual import dual_ekf, dual_ukf, joint_ekf, joint_ukf
from vehjax.filters.gaussian import ekf, ukf
from vehjax.models import KinematicBicycle, Model

# ---- linear model with a bias parameter: x' = A x + c B u + b, y = H x ------------------------
A = np.array([[0.95, 0.1], [-0.1, 0.9]])
B = np.array([[0.1], [0.05]])
H = np.array([[1.0, 0.0], [0.5, 1.0]])
Q_X = np.array([[2e-3, 3e-4], [3e-4, 1e-3]])
R_Y = np.array([[0.05, 0.01], [0.01, 0.08]])
X0 = np.array([0.2, -0.1])
P0 = np.array([[0.3, 0.05], [0.05, 0.2]])
B_TRUE = np.array([0.3, 0.1])
B_NOM = np.array([0.5, -0.2])  # model.theta: nominal b (scale of the internal units) and c = 1
B0 = np.array([0.0, 0.0])  # the filters' initial estimate
PB0 = np.array([[0.2, 0.02], [0.02, 0.1]])
QB = np.array([[1e-4, 2e-5], [2e-5, 5e-5]])
GAMMA = 0.98
T = 40

BIAS = Model(
    transition=lambda x, u, th: jnp.asarray(A) @ x + th[2] * (jnp.asarray(B) @ u) + th[:2],
    observe=lambda x, u, th: jnp.asarray(H) @ x,
    dt=0.1,
    state_names=("x1", "x2"),
    param_names=("b1", "b2", "c"),
    input_names=("u",),
    output_names=("y1", "y2"),
    theta=np.concatenate([B_NOM, [1.0]]),
)


def _bias_data(seed=0):
    rng = np.random.default_rng(seed)
    us = rng.normal(size=(T, 1))
    x = X0 + rng.multivariate_normal(np.zeros(2), P0)
    ys = []
    for t in range(T):
        x = A @ x + B @ us[t] + B_TRUE + rng.multivariate_normal(np.zeros(2), Q_X)
        ys.append(H @ x + rng.multivariate_normal(np.zeros(2), R_Y))
    ys = np.array(ys)
    ys_missing = ys.copy()
    ys_missing[[5, 20], :] = np.nan
    ys_missing[[9, 30], 0] = np.nan
    ys_missing[[14], 1] = np.nan
    return np.stack([ys, ys_missing]), us


def _gain_update(x, P, y, y_hat, Hm, N):
    """Kalman update on the observed components of y; returns x, P, e, S, o (observed mask)."""
    o = np.isfinite(y)
    if not o.any():
        return x, P, None, None, o
    Ho, No = Hm[o], N[np.ix_(o, o)]
    S = Ho @ P @ Ho.T + No
    K = P @ Ho.T @ np.linalg.inv(S)
    e = y[o] - y_hat[o]
    return x + K @ e, P - K @ S @ K.T, e, S, o


def _loglik(e, S):
    if e is None:
        return 0.0
    return -0.5 * (e @ np.linalg.solve(S, e) + np.linalg.slogdet(S)[1] + len(e) * np.log(2 * np.pi))


def _numpy_joint_kf(ys, us):
    """Kalman filter on the augmented linear system [x; b] with Q_b decaying by GAMMA."""
    F = np.block([[A, np.eye(2)], [np.zeros((2, 2)), np.eye(2)]])
    Ha = np.hstack([H, np.zeros((2, 2))])
    a, P = np.concatenate([X0, B0]), np.block([[P0, np.zeros((2, 2))], [np.zeros((2, 2)), PB0]])
    Qb = QB.copy()
    out = {"x": [], "Px": [], "b": [], "Pb": [], "ll": []}
    for y, u in zip(ys, us):
        a = F @ a + np.concatenate([B @ u, np.zeros(2)])
        P = F @ P @ F.T + np.block([[Q_X, np.zeros((2, 2))], [np.zeros((2, 2)), Qb]])
        Qb = GAMMA * Qb
        a, P, e, S, _ = _gain_update(a, P, y, Ha @ a, Ha, R_Y)
        for k, v in (("x", a[:2]), ("Px", P[:2, :2]), ("b", a[2:]), ("Pb", P[2:, 2:]),
                     ("ll", _loglik(e, S))):
            out[k].append(v)
    return {k: np.array(v) for k, v in out.items()}


def _numpy_dual_kf(ys, us, predictive=True, recurrent=False):
    """Algorithm 1 written out for the bias model (df/db = I, so Hp = H without the recurrent
    derivative; with it (Wan & Nelson), Hp = H D- with D- = A D + I the derivative of the
    predicted state in b and D = D- - K Hp that of the filtered state, K the state gain)."""
    x, P, b, Pb, Qb = X0.copy(), P0.copy(), B0.copy(), PB0.copy(), QB.copy()
    Dx = np.zeros((2, 2))
    out = {"x": [], "Px": [], "b": [], "Pb": [], "ll": []}
    for y, u in zip(ys, us):
        Pb = Pb + Qb
        x_pred = A @ x + B @ u + b
        P_pred = A @ P @ A.T + Q_X
        y_hat = H @ x_pred
        D_pred = A @ Dx + np.eye(2) if recurrent else np.eye(2)
        Hp = H @ D_pred
        x, P, e, S, o = _gain_update(x_pred, P_pred, y, y_hat, H, R_Y)
        if o.any():
            N = np.full((2, 2), np.nan)
            N[np.ix_(o, o)] = S if predictive else R_Y[np.ix_(o, o)]
            b, Pb, _, _, _ = _gain_update(b, Pb, y, y_hat, Hp, N)
            K = P_pred @ H[o].T @ np.linalg.inv(S)
            Dx = D_pred - K @ Hp[o]
        else:
            Dx = D_pred
        Qb = GAMMA * Qb
        for k, v in (("x", x), ("Px", P), ("b", b), ("Pb", Pb), ("ll", _loglik(e, S))):
            out[k].append(v)
    return {k: np.array(v) for k, v in out.items()}


def _scan_runs(est, ys, us):
    """vmap over runs of vehjax.filter from (X0, P0, B0, PB0); one compile."""

    def one(y):
        return vj.filter(est, y, us, x0=X0, P0=P0, theta0=B0, P_theta0=PB0)

    outs = jax.jit(jax.vmap(one))(jnp.asarray(ys))
    return [jax.tree.map(lambda a: np.asarray(a[i]), outs) for i in range(ys.shape[0])]


def _assert_matches(out, ref, ys):
    np.testing.assert_allclose(out.states, ref["x"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(out.covariances, ref["Px"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(out.params, ref["b"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(out.params_cov, ref["Pb"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(out.loglik, ref["ll"], rtol=0, atol=1e-9)
    np.testing.assert_array_equal(out.n_obs, np.isfinite(ys).sum(axis=1))


# bounds={}: the filters on b itself, as the numpy references (b1's positive nominal value would
# otherwise keep it positive, and B0 = 0 is on that bound)
BIAS_KW = dict(Q=Q_X, R=R_Y, Q_theta=QB, estimate=("b1", "b2"), theta_decay=GAMMA, bounds={})


@pytest.mark.parametrize("builder", [joint_ekf, joint_ukf])
def test_joint_filter_on_bias_model_equals_augmented_kalman_filter(builder):
    """The bias enters linearly: the joint EKF and UKF are the exact KF on [x; b], with NaNs."""
    ys2, us = _bias_data()
    outs = _scan_runs(builder(BIAS, **BIAS_KW), ys2, us)
    for out, ys in zip(outs, ys2):
        _assert_matches(out, _numpy_joint_kf(ys, us), ys)


@pytest.mark.parametrize(
    "builder, innovation, scale, recurrent",
    [
        (dual_ekf, "predictive", None, False),  # internal units |nominal b|
        (dual_ekf, "measurement", [1e-3, 1e4], False),  # far-off internal units, same results
        (dual_ukf, "predictive", [1e-3, 1e4], False),
        (dual_ekf, "predictive", None, True),  # the default: with the recurrent derivative
        (dual_ekf, "measurement", [1e-3, 1e4], True),
        (dual_ukf, "predictive", [1e-3, 1e4], True),
    ],
)
def test_dual_filter_on_bias_model_equals_algorithm_1_in_numpy(builder, innovation, scale,
                                                               recurrent):
    """b enters linearly, so DEKF and DUKF both equal Algorithm 1 in numpy, with NaNs, with and
    without Wan & Nelson's recurrent derivative (the gain does not depend on b here)."""
    ys2, us = _bias_data(1)
    est = builder(BIAS, **BIAS_KW, param_innovation=innovation, theta_scale=scale,
                  recurrent=recurrent)
    outs = _scan_runs(est, ys2, us)
    for out, ys in zip(outs, ys2):
        _assert_matches(out, _numpy_dual_kf(ys, us, innovation == "predictive", recurrent), ys)


# ---- all-missing steps -----------------------------------------------------------------------
KIN = KinematicBicycle(dt=0.02)
KIN_Q = np.array([1e-4, 1e-4, 4e-6, 4e-4])
KIN_R = np.array([0.1, 0.1, 0.02, 0.1]) ** 2


def _augmented_kinematic():
    """KIN with the unconstrained coordinates s of (lf, lr) appended to the state as constants,
    for the state-only filters: lf, lr = 1.5 exp(s), the default positive domain of the joint
    filters (scale = the nominal 1.5 m)."""
    def g(s):
        return 1.5 * jnp.exp(s)

    return Model(
        transition=lambda a, u, th: jnp.concatenate([KIN.transition(a[:4], u, g(a[4:])), a[4:]]),
        observe=lambda a, u, th: KIN.observe(a[:4], u, g(a[4:])),
        dt=KIN.dt,
        state_names=KIN.state_names + KIN.param_names,
        input_names=KIN.input_names,
    )


# the dual EKF by default (the same NaN rule in every form); the other three: `pytest -m slow`
@pytest.mark.parametrize("builder", [dual_ekf, pytest.param(dual_ukf, marks=pytest.mark.slow),
                                     pytest.param(joint_ekf, marks=pytest.mark.slow),
                                     pytest.param(joint_ukf, marks=pytest.mark.slow)])
def test_all_missing_step_predicts_state_and_keeps_parameters(builder):
    """A NaN measurement: the state is predicted, the parameter mean unchanged, its covariance
    grown by Q_theta. The reference is vehjax's EKF/UKF (tested against numpy and filterpy):
    at the current parameters for the dual filters, on the augmented state for the joint ones,
    whose parameter part is the log coordinate of the default positive domain (prior and random
    walk mapped by the delta method, J = diag(theta))."""
    q_th = np.array([1e-4, 4e-4])
    est = builder(KIN, KIN_Q, KIN_R, Q_theta=q_th, estimate=("lf", "lr"), theta_decay=0.5)
    x0 = np.array([1.0, -0.5, 0.1, 12.0])
    P0 = np.diag([0.2, 0.3, 0.01, 0.5])
    th0, Pth0 = np.array([1.2, 1.9]), np.array([[0.09, 0.01], [0.01, 0.04]])
    u = np.array([0.5, 0.08])
    nan = jnp.full(4, jnp.nan)
    step = jax.jit(est.step)
    s1, out = step(est.init(x0, P0, th0, Pth0), nan, u)
    np.testing.assert_allclose(out.params, th0, rtol=1e-15)
    np.testing.assert_allclose(out.params_cov, Pth0 + np.diag(q_th), rtol=1e-12)
    assert float(out.loglik) == 0.0 and float(out.nis) == 0.0 and int(out.n_obs) == 0
    state_only = ekf if builder in (dual_ekf, joint_ekf) else ukf
    if builder in (dual_ekf, dual_ukf):
        ref_est = state_only(KIN, KIN_Q, KIN_R)
        _, ref = jax.jit(ref_est.step)(ref_est.init(x0, P0, th0), nan, u)
        np.testing.assert_allclose(out.cov, ref.cov, rtol=1e-10, atol=1e-14)
    else:
        ref_est = state_only(_augmented_kinematic(), np.concatenate([KIN_Q, q_th / th0**2]),
                             KIN_R)
        P_aug = np.block([[P0, np.zeros((4, 2))], [np.zeros((2, 4)), Pth0 / np.outer(th0, th0)]])
        s0 = np.log(th0 / 1.5)
        _, ref = jax.jit(ref_est.step)(ref_est.init(np.concatenate([x0, s0]), P_aug), nan, u)
        np.testing.assert_allclose(out.cov, ref.cov[:4, :4], rtol=1e-10, atol=1e-14)
        ref = ref._replace(mean=ref.mean[:4])
    np.testing.assert_allclose(out.mean, ref.mean, rtol=1e-12)
    # the next step uses Q_theta decayed by theta_decay = 0.5
    _, out2 = step(s1, nan, u)
    np.testing.assert_allclose(out2.params_cov, Pth0 + 1.5 * np.diag(q_th), rtol=1e-12)


# ---- parameter recovery ----------------------------------------------------------------------


@pytest.fixture(scope="module")
def kinematic_study():
    model = KinematicBicycle(dt=0.05)
    scn = vj.scenarios.sine_steer(model, speed=15.0, amplitude=0.1, frequency=0.5, duration=20.0)
    qs, rs = np.array([0.01, 0.01, 0.002, 0.02]), np.array([0.1, 0.1, 0.02, 0.1])
    sim = vj.simulate(model, scn, runs=4, key=jax.random.key(1), process_std=qs, meas_std=rs)
    return model, scn, sim, qs, rs


@pytest.mark.slow  # a study: `pytest -m slow` (README)
@pytest.mark.parametrize("builder", [dual_ekf, dual_ukf, joint_ekf, joint_ukf])
def test_filters_recover_lf_lr_on_kinematic_bicycle(kinematic_study, builder):
    """4 runs of a 20 s sine steer, start (1.0, 2.0) m, truth (1.5, 1.5) m: the mean final
    error over runs is at most a third of the initial one."""
    model, scn, sim, qs, rs = kinematic_study
    est = builder(model, qs**2, rs**2, Q_theta=[1e-8, 1e-8], estimate=("lf", "lr"))
    th0 = np.array([1.0, 2.0])
    out = vj.run(est, sim.measurements, sim.inputs, x0=np.asarray(scn.x0), P0=rs**2 * np.eye(4),
                 theta0=th0, P_theta0=np.diag([0.25, 0.25]))
    assert not out.diverged.any()
    err0 = np.abs(th0 - 1.5)
    err = np.abs(out.params[:, -1, :] - np.asarray(model.theta))
    assert np.all(err.mean(axis=0) < err0 / 3), out.params[:, -1]


# ---- bad input -------------------------------------------------------------------------------
GOOD = dict(Q=KIN_Q, R=KIN_R, Q_theta=[1e-4, 1e-4], estimate=("lf", "lr"))


@pytest.mark.parametrize("builder", [dual_ekf, dual_ukf, joint_ekf, joint_ukf])
@pytest.mark.parametrize(
    "change, arg",
    [
        (dict(estimate=("lf", "wheelbase")), "estimate"),
        (dict(estimate=()), "estimate"),
        (dict(estimate=("lf", "lf")), "estimate"),
        (dict(Q_theta=[[1e-4, 2e-4], [2e-4, 1e-4]]), "Q_theta"),
        (dict(Q_theta=[1e-4, 1e-4, 1e-4]), "Q_theta"),
        (dict(Q_theta=[1e-4, -1e-4]), "Q_theta"),
        (dict(theta_decay=0.0), "theta_decay"),
        (dict(theta_decay=1.5), "theta_decay"),
        (dict(theta_decay="fast"), "theta_decay"),
        (dict(theta_scale=[1.0, -1.0]), "theta_scale"),
        (dict(theta_scale=[1.0, 1.0, 1.0]), "theta_scale"),
        (dict(Q=np.ones(3)), "Q"),
        (dict(R=-KIN_R), "R"),
    ],
)
def test_bad_configuration_raises(builder, change, arg):
    with pytest.raises(ValueError, match=arg):
        builder(KIN, **{**GOOD, **change})


def test_bad_param_innovation_raises():
    with pytest.raises(ValueError, match="param_innovation"):
        dual_ekf(KIN, **GOOD, param_innovation="paper")


@pytest.mark.parametrize("builder", [dual_ekf, joint_ukf])
def test_bad_prior_raises(builder):
    est = builder(KIN, **GOOD)
    x0, P0 = np.zeros(4), np.eye(4)
    with pytest.raises(ValueError, match="theta0"):
        est.init(x0, P0, np.array([1.5, 1.5, 1.0]), np.eye(2))
    with pytest.raises(ValueError, match="P_theta0"):
        est.init(x0, P0, np.array([1.5, 1.5]), np.array([[1.0, 2.0], [2.0, 1.0]]))
    with pytest.raises(ValueError, match="P_theta0"):
        est.init(x0, P0, np.array([1.5, 1.5]), np.eye(3))
    with pytest.raises(ValueError, match="P_theta0"):
        est.init(x0, P0, np.array([1.5, 1.5]), None)
    with pytest.raises(ValueError, match="P0"):
        est.init(x0, np.eye(3), np.array([1.5, 1.5]), np.eye(2))
    with pytest.raises(ValueError, match="theta0"):
        vj.run(est, np.zeros((1, 3, 4)), np.zeros((3, 2)), x0=x0, P0=P0, theta0=[1.5],
               P_theta0=np.eye(2))


@pytest.mark.parametrize("builder", [dual_ekf, pytest.param(dual_ukf, marks=pytest.mark.slow),
                                     pytest.param(joint_ekf, marks=pytest.mark.slow), joint_ukf])
def test_many_runs_form_equals_the_step_run_by_run(builder):
    """What run computes for many runs (the runs-last batch step, or vmap of the step when the
    filter has none) equals the step run by run, each run with its own theta0."""
    from _contract import assert_batch_equals_step

    ys2, us = _bias_data()
    ys = np.concatenate([ys2, ys2[:1] + 0.05])[:, :8]  # 3 runs, missing values in run 1
    theta0 = B0 + np.array([[0.0, 0.0], [0.1, -0.05], [-0.1, 0.05]])
    est = builder(BIAS, **BIAS_KW)
    form = assert_batch_equals_step(est, ys, us[:8], np.tile(X0, (3, 1)), P0, theta0=theta0,
                                    P_theta0=PB0)
    assert form == ("batch" if est.batch is not None else "vmap")
