"""vehjax.smooth: the filters' own RTS smoothers against a numpy RTS written here from the
textbook recursion (Rauch, Tung & Striebel 1965; Särkkä, Bayesian Filtering and Smoothing, Alg.
4.3 and 8.2), square-root forms against plain ones, the smoother moments against the filter
step, joint filters, NaN components, divergence, bad input."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import vehjax as vj
from vehjax.smoothing import smooth_one_run

from _linear import linear_gaussian_data

A = np.array([[1.0, 0.1, 0.0], [0.0, 0.95, 0.1], [0.0, -0.2, 0.9]])
B = np.array([[0.0], [0.1], [0.05]])
H = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
Q = np.diag([1e-3, 4e-3, 2e-3])
R = np.diag([0.05, 0.02])
X0 = np.array([0.5, -0.2, 0.1])
P0 = np.diag([0.3, 0.2, 0.1])
T = 25


def linear_model():
    return vj.models.Model(
        transition=lambda x, u, th: jnp.asarray(A) @ x + jnp.asarray(B) @ u,
        observe=lambda x, u, th: jnp.asarray(H) @ x,
        dt=0.1, state_names=("p", "v", "a"), input_names=("u",), output_names=("y1", "y2"))


def numpy_rts(ys, us):
    """Kalman filter + RTS smoother in numpy, missing (NaN) components dropped from the update.
    Returns smoothed means (T, n), covariances (T, n, n), lag-one cross-covariances (T-1, n, n)
    Cov(x_t, x_{t+1} | y) and the log-likelihood per step."""
    m, P = X0.copy(), P0.copy()
    mf, Pf, mp_, Pp_, ll = [], [], [], [], []
    for t in range(len(ys)):
        mp = A @ m + B @ us[t]
        Pp = A @ P @ A.T + Q
        obs = np.isfinite(ys[t])
        Ho, Ro = H[obs], R[np.ix_(obs, obs)]
        S = Ho @ Pp @ Ho.T + Ro
        e = ys[t][obs] - Ho @ mp
        K = Pp @ Ho.T @ np.linalg.inv(S)
        m = mp + K @ e
        P = Pp - K @ S @ K.T
        k = obs.sum()
        ll.append(-0.5 * (e @ np.linalg.solve(S, e) + np.linalg.slogdet(S)[1] + k * np.log(2 * np.pi)))
        mf.append(m), Pf.append(P), mp_.append(mp), Pp_.append(Pp)
    ms, Ps = [mf[-1]], [Pf[-1]]
    cross = []
    for t in range(len(ys) - 2, -1, -1):
        G = Pf[t] @ A.T @ np.linalg.inv(Pp_[t + 1])
        cross.insert(0, G @ Ps[0])
        ms.insert(0, mf[t] + G @ (ms[0] - mp_[t + 1]))
        Ps.insert(0, Pf[t] + G @ (Ps[0] - Pp_[t + 1]) @ G.T)
    return np.array(ms), np.array(Ps), np.array(cross), np.array(ll)


@pytest.fixture(scope="module")
def data():
    ys, us = linear_gaussian_data(A, B, H, Q, R, X0, P0, T, seed=3)
    ys[4, 0] = np.nan
    ys[9] = np.nan
    ys[17, 1] = np.nan
    return ys, us


BUILDERS = {
    "ekf": lambda m: vj.filters.ekf(m, Q, R),
    "ukf": lambda m: vj.filters.ukf(m, Q, R),
    "ukf_small_alpha": lambda m: vj.filters.ukf(m, Q, R, points=vj.filters.SigmaPoints(alpha=0.5)),
    "ckf": lambda m: vj.filters.ckf(m, Q, R),
    "sr_ukf": lambda m: vj.filters.ukf(m, Q, R, sqrt=True),
    "sr_ckf": lambda m: vj.filters.ckf(m, Q, R, sqrt=True),
}


@pytest.mark.parametrize("name", list(BUILDERS))
def test_rts_equals_numpy_textbook_rts(name, data):
    """On a linear-Gaussian model every Gaussian smoother is the exact RTS smoother: same
    means, covariances, cross-covariances and log-likelihood as the numpy recursion, to 1e-10,
    with NaN components skipped (also a step with all missing)."""
    ys, us = data
    ref_m, ref_P, ref_C, ref_ll = numpy_rts(ys, us)
    est = BUILDERS[name](linear_model())
    sm = vj.smooth(est, ys, us, x0=X0, P0=P0)
    assert not bool(sm.diverged)
    np.testing.assert_allclose(sm.states, ref_m, atol=1e-10)
    np.testing.assert_allclose(sm.covariances, ref_P, atol=1e-10)
    np.testing.assert_allclose(sm.cross_covariances, ref_C, atol=1e-10)
    np.testing.assert_allclose(sm.loglik, ref_ll, atol=1e-10)
    assert sm.params.shape == (T, 0)


def test_parallel_rts_equals_numpy_textbook_rts(data):
    """parallel=True (associative-scan filter and smoother on the UKF's own statistical
    linearisation) gives the same numbers, NaN components included."""
    ys, us = data[0][:8], data[1][:8]     # short: the associative scan is compiled per level
    ref_m, ref_P, ref_C, ref_ll = numpy_rts(ys, us)
    est = BUILDERS["ukf"](linear_model())
    sm = jax.jit(lambda y, u: vj.smooth(est, y, u, x0=X0, P0=P0,
                                                  method=vj.smoothers.RTS(parallel=True)))(ys, us)
    np.testing.assert_allclose(sm.states, ref_m, atol=1e-9)
    np.testing.assert_allclose(sm.covariances, ref_P, atol=1e-9)
    np.testing.assert_allclose(sm.cross_covariances, ref_C, atol=1e-9)
    np.testing.assert_allclose(sm.loglik, ref_ll, atol=1e-9)


def _pendulum(dt=0.05):
    """A nonlinear model (pendulum, observed through sin): x = (angle, rate)."""
    def f(x, u, th):
        return jnp.array([x[0] + dt * x[1], x[1] - dt * th[0] * jnp.sin(x[0]) + dt * u[0]])

    def h(x, u, th):
        return jnp.array([jnp.sin(x[0]), x[1]])

    return vj.models.Model(transition=f, observe=h, dt=dt, state_names=("a", "w"),
                           param_names=("g",), input_names=("u",), output_names=("s", "w"),
                           theta=np.array([9.81]))


def _pendulum_data(T=30, seed=0):
    rng = np.random.default_rng(seed)
    model = _pendulum()
    x = np.array([0.8, 0.0])
    us = 0.3 * np.sin(np.arange(T) * 0.2)[:, None]
    ys = []
    for t in range(T):
        x = np.asarray(model.transition(x, us[t], model.theta)) + rng.normal(0, [0.01, 0.05])
        ys.append(np.asarray(model.observe(x, us[t], model.theta)) + rng.normal(0, [0.1, 0.1]))
    return model, np.array(ys), us


def test_square_root_equals_plain_on_nonlinear_model():
    """The square-root unscented RTS (Cholesky factors throughout; alpha = 0.5 gives a negative
    centre weight, removed by a downdate) gives the plain one's results on a nonlinear model
    (the cubature forms are compared on the linear model above)."""
    model, ys, us = _pendulum_data()
    Qp, Rp = np.diag([1e-4, 2.5e-3]), np.diag([0.01, 0.01])
    a = vj.smooth(vj.filters.ukf(model, Qp, Rp, points=vj.filters.SigmaPoints(alpha=0.5),
                                 sqrt=True), ys, us, x0=[0.7, 0.0],
                  P0=[0.1, 0.1])
    b = vj.smooth(vj.filters.ukf(model, Qp, Rp, points=vj.filters.SigmaPoints(alpha=0.5)), ys, us,
                  x0=[0.7, 0.0],
                  P0=[0.1, 0.1])
    assert vj.filters.sigma.unscented_rule(2, 0.5).wc[0] < 0
    np.testing.assert_allclose(a.states, b.states, atol=1e-10)
    np.testing.assert_allclose(a.covariances, b.covariances, atol=1e-10)
    np.testing.assert_allclose(a.cross_covariances, b.cross_covariances, atol=1e-10)


@pytest.mark.parametrize("name, noise", [("ekf", {"u": 0.3}), ("ukf", {"u": 0.3}),
                                         ("sr_ckf", {"u": 0.3}), ("sr_ckf", None)])
def test_smoother_prediction_is_the_filter_step(name, noise):
    """Estimator.smoother.predict is the step's own prediction: the step with every component
    missing (a pure prediction) reports the same mean and covariance, with and without input
    noise (which must reach the smoother through the step's prediction code)."""
    model, ys, us = _pendulum_data(T=3)
    Qp, Rp = np.diag([1e-4, 2.5e-3]), np.diag([0.01, 0.01])
    build = {"ekf": lambda **k: vj.filters.ekf(model, Qp, Rp, **k),
             "ukf": lambda **k: vj.filters.ukf(model, Qp, Rp, **k),
             "sr_ckf": lambda **k: vj.filters.ckf(model, Qp, Rp, sqrt=True, **k)}[name]
    est = build() if noise is None else build(input_noise=noise)
    state = est.init(jnp.array([0.4, 0.2]), jnp.array([[0.2, 0.05], [0.05, 0.3]]))
    _, out = est.step(state, jnp.full(2, jnp.nan), jnp.asarray(us[1]))
    m, S, aux = est.smoother.split(state)
    pred = est.smoother.predict(m, S, jnp.asarray(us[1]), aux)
    if est.smoother.sqrt:
        P_pred = pred[1] @ pred[1].T
        P = S @ S.T
        # the joint factor reproduces the state's own covariance: L21 L21^T + L22 L22^T = P
        np.testing.assert_allclose(pred[2] @ pred[2].T + pred[3] @ pred[3].T, P, atol=1e-12)
    else:
        P_pred = pred[1]
    np.testing.assert_allclose(pred[0], out.mean, atol=1e-12)
    np.testing.assert_allclose(P_pred, out.cov, atol=1e-12)


def test_joint_filter_smooths_parameters_as_states():
    """A joint EKF on a linear model with one parameter of a bias random walk (the parameter
    enters linearly): the smoothed state and parameter equal a numpy RTS on the augmented
    linear model, and the smoothed parameter covariance shrinks below the filtered one at t=0."""
    Tj = 20
    model = vj.models.Model(
        transition=lambda x, u, th: jnp.array([0.9 * x[0] + th[0] + u[0]]),
        observe=lambda x, u, th: jnp.array([x[0]]),
        dt=0.1, state_names=("x",), param_names=("b",), input_names=("u",),
        output_names=("y",), theta=np.array([0.0]))
    rng = np.random.default_rng(1)
    us = rng.normal(size=(Tj, 1))
    x, ys = 0.0, []
    for t in range(Tj):
        x = 0.9 * x + 0.5 + us[t, 0] + rng.normal(0, 0.1)
        ys.append([x + rng.normal(0, 0.2)])
    ys = np.array(ys)
    qx, qb, r = 0.01, 1e-4, 0.04
    est = vj.filters.joint_ekf(model, [qx], [r], Q_theta=[qb], estimate="b", bounds={})
    sm = vj.smooth(est, ys, us, x0=[0.0], P0=[0.5], theta0=[0.0], P_theta0=[1.0])
    # numpy RTS on z = (x, b): z' = [[0.9, 1], [0, 1]] z + [u, 0], y = [1, 0] z
    Aa, Qa, Ha = np.array([[0.9, 1.0], [0.0, 1.0]]), np.diag([qx, qb]), np.array([[1.0, 0.0]])
    m, P = np.zeros(2), np.diag([0.5, 1.0])
    mf, Pf, mp_, Pp_ = [], [], [], []
    for t in range(Tj):
        mp, Pp = Aa @ m + np.array([us[t, 0], 0.0]), Aa @ P @ Aa.T + Qa
        S = Ha @ Pp @ Ha.T + r
        K = Pp @ Ha.T / S
        m, P = mp + (K * (ys[t] - Ha @ mp)).ravel(), Pp - K @ S @ K.T
        mf.append(m), Pf.append(P), mp_.append(mp), Pp_.append(Pp)
    ms, Ps = [mf[-1]], [Pf[-1]]
    for t in range(Tj - 2, -1, -1):
        G = Pf[t] @ Aa.T @ np.linalg.inv(Pp_[t + 1])
        ms.insert(0, mf[t] + G @ (ms[0] - mp_[t + 1]))
        Ps.insert(0, Pf[t] + G @ (Ps[0] - Pp_[t + 1]) @ G.T)
    ms, Ps = np.array(ms), np.array(Ps)
    np.testing.assert_allclose(sm.states[:, 0], ms[:, 0], atol=1e-10)
    np.testing.assert_allclose(sm.params[:, 0], ms[:, 1], atol=1e-10)
    np.testing.assert_allclose(sm.params_cov[:, 0, 0], Ps[:, 1, 1], atol=1e-10)
    np.testing.assert_allclose(sm.covariances[:, 0, 0], Ps[:, 0, 0], atol=1e-10)
    assert sm.params_cov[0, 0, 0] < 0.5 * sm.filtered.params_cov[0, 0, 0]


def test_jit_vmap_and_one_divergent_run_flagged(data):
    """smooth_one_run under jit and vmap over three runs; a run whose data are absurd (1e200)
    is flagged diverged and reports finite held values; the other runs are unchanged."""
    ys, us = data
    est = vj.filters.ukf(linear_model(), Q, R)
    bad = ys.copy()
    bad[5:] = 1e200
    Y = jnp.asarray(np.stack([ys, bad, ys[::-1].copy()]))

    @jax.jit
    def many(Y):
        return jax.vmap(lambda y: smooth_one_run(est, y, jnp.asarray(us), jnp.asarray(X0),
                                                 jnp.asarray(P0)))(Y)

    out = many(Y)
    assert [bool(v) for v in out.diverged] == [False, True, False]
    assert np.all(np.isfinite(out.states)) and np.all(np.isfinite(out.covariances))
    one = vj.smooth(est, ys, us, x0=X0, P0=P0)
    np.testing.assert_allclose(out.states[0], one.states, atol=1e-12)
    ref_m = numpy_rts(ys[::-1].copy(), us)[0]
    np.testing.assert_allclose(out.states[2], ref_m, atol=1e-10)


def test_loglik_gradient_equals_finite_differences(data):
    """d/dq of the smoothed run's log-likelihood (the RTS reports the filter's) by jax.grad
    equals central finite differences of the same function."""
    ys, us = data
    model = linear_model()

    def ll(q):
        est = vj.filters.ckf(model, q * Q, R)
        return vj.smooth(est, ys, us, x0=X0, P0=P0).loglik.sum()

    g = jax.jit(jax.grad(ll))(1.3)
    llj = jax.jit(ll)
    h = 1e-5
    fd = (llj(1.3 + h) - llj(1.3 - h)) / (2 * h)
    assert np.isfinite(g)
    np.testing.assert_allclose(g, fd, rtol=1e-6)


def test_bad_input_names_the_argument(data):
    ys, us = data
    model = linear_model()
    est = vj.filters.ekf(model, Q, R)
    cases = [
        (dict(estimator=vj.filters.dual_ekf(_pendulum(), np.diag([1e-4, 1e-3]), [0.01, 0.01],
                                            Q_theta=[0.1], estimate="g")), "estimator"),
        (dict(method="nope"), "method"),
        (dict(method="ipls"), "method"),                  # the EKF iterates Jacobians
        # the records check their fields when made (inside the check below)
        (dict(method=functools.partial(vj.smoothers.IEKS, max_iter=0)), "max_iter"),
        (dict(method=functools.partial(vj.smoothers.IEKS, tol=0.0)), "tol"),
        (dict(method=vj.smoothers.IEKS(initial=np.zeros((3, 3)))), "initial"),
        (dict(P0=np.eye(2)), "P0"),
        (dict(inputs=us[:-1]), "inputs"),
        (dict(method=vj.smoothers.FFBSi(n_trajectories=10)), "method"),  # a particle filter's
        (dict(method=functools.partial(vj.smoothers.RTS, parallel="yes")), "parallel"),
    ]
    for kw, arg in cases:
        call = dict(estimator=est, measurements=ys, inputs=us, x0=X0, P0=P0)
        call.update(kw)
        if kw.get("estimator") is not None and kw["estimator"].name.startswith("D"):
            call.update(measurements=np.zeros((5, 2)), inputs=np.zeros((5, 1)), x0=[0.1, 0.0],
                        P0=[0.1, 0.1], P_theta0=[1.0])
        with pytest.raises(ValueError, match=arg):
            if isinstance(call.get("method"), functools.partial):
                call["method"] = call["method"]()
            vj.smooth(**call)
    with pytest.raises(ValueError, match="method"):
        vj.smooth(vj.filters.ukf(model, Q, R), ys, us, x0=X0, P0=P0, method="ieks")


@pytest.mark.parametrize("kw", [dict(parallel=True), dict(tol=1e-3), dict(max_iter=5),
                                dict(initial=np.zeros((3, 2)))])
def test_options_are_checked_against_the_estimator_family(data, kw):
    """An option that does not apply is refused naming it, with the reason (issue 46): the
    Gaussian smoothers' options for a particle filter, the iteration options for the plain RTS
    smoother; a particle filter's own options for a Gaussian filter. The options are fields of
    the method's record (vehjax.smoothers): a Gaussian record is refused for a particle filter,
    naming ``method``; the plain RTS record has no iteration option at all."""
    ys, us = data
    model = linear_model()
    name = next(iter(kw))
    pf = vj.filters.bootstrap_pf(model, Q, R, n_particles=16)
    record = vj.smoothers.RTS(**kw) if name == "parallel" else vj.smoothers.IEKS(**kw)
    with pytest.raises(ValueError, match=r"^method: .* is one of the Gaussian smoothers; "
                                         r"'bootstrap_pf' is a particle filter"):
        vj.smooth(pf, ys, us, x0=X0, P0=P0, key=jax.random.key(0), method=record)
    if name in ("tol", "max_iter", "initial"):
        with pytest.raises(TypeError, match=name):  # only the iterated smoothers iterate
            vj.smoothers.RTS(**kw)


def test_joint_ukf_smooths_parameters_as_constant_states():
    """The joint UKF's smoothing (issue 29, item 1's "parameters smoothed as constant states")
    through ``vehjax.smooth``: on a model whose parameter (an acceleration bias) enters linearly
    the augmented model z = (p, v, b) is linear-Gaussian, where the unscented RTS is exact; it
    equals a numpy Kalman filter + RTS on z written here (the decaying random walk
    Q_b gamma^(t-1), NaN components skipped) in means, covariances, the lag-one state
    cross-covariances and the log-likelihood, and ``vehjax.run(smooth=True)`` gives the same."""
    Tj, dt, gamma = 30, 0.1, 0.97
    model = vj.models.Model(
        transition=lambda x, u, th: jnp.array([x[0] + dt * x[1],
                                               0.95 * x[1] + dt * (u[0] + th[0])]),
        observe=lambda x, u, th: x,
        dt=dt, state_names=("p", "v"), param_names=("b",), input_names=("u",),
        output_names=("yp", "yv"), theta=np.array([0.0]))
    rng = np.random.default_rng(7)
    us = rng.normal(size=(Tj, 1))
    x, ys = np.zeros(2), []
    for t in range(Tj):
        x = np.array([x[0] + dt * x[1], 0.95 * x[1] + dt * (us[t, 0] + 0.8)])
        x = x + rng.normal(0, [0.02, 0.05])
        ys.append(x + rng.normal(0, [0.1, 0.2]))
    ys = np.array(ys)
    ys[3, 1] = ys[11] = ys[20, 0] = np.nan
    qx, qb, rr = np.array([4e-4, 2.5e-3]), 1e-3, np.array([0.01, 0.04])
    x0, P0, th0, Pth0 = np.array([0.1, 0.0]), np.array([0.2, 0.3]), np.array([0.0]), np.array([1.0])
    est = vj.filters.joint_ukf(model, qx, rr, Q_theta=[qb], estimate="b", bounds={}, theta_scale=1.0,
                               theta_decay=gamma)
    sm = vj.smooth(est, ys, us, x0=x0, P0=P0, theta0=th0, P_theta0=Pth0)

    F = np.array([[1.0, dt, 0.0], [0.0, 0.95, dt], [0.0, 0.0, 1.0]])
    Hz = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    m, P = np.r_[x0, th0], np.diag(np.r_[P0, Pth0])
    mf, Pf, mp_, Pp_, ll = [], [], [], [], []
    for t in range(Tj):
        Qz = np.diag(np.r_[qx, qb * gamma**t])
        mp, Pp = F @ m + np.array([0.0, dt * us[t, 0], 0.0]), F @ P @ F.T + Qz
        obs = np.isfinite(ys[t])
        Ho, Ro = Hz[obs], np.diag(rr[obs])
        S = Ho @ Pp @ Ho.T + Ro
        e = ys[t][obs] - Ho @ mp
        K = np.linalg.solve(S, Ho @ Pp).T
        m, P = mp + K @ e, Pp - K @ S @ K.T
        ll.append(-0.5 * (e @ np.linalg.solve(S, e) + np.linalg.slogdet(S)[1]
                          + obs.sum() * np.log(2 * np.pi)))
        mf.append(m), Pf.append(P), mp_.append(mp), Pp_.append(Pp)
    ms, Ps, cross = [mf[-1]], [Pf[-1]], []
    for t in range(Tj - 2, -1, -1):
        G = np.linalg.solve(Pp_[t + 1], F @ Pf[t]).T
        cross.insert(0, G @ Ps[0])
        ms.insert(0, mf[t] + G @ (ms[0] - mp_[t + 1]))
        Ps.insert(0, Pf[t] + G @ (Ps[0] - Pp_[t + 1]) @ G.T)
    ms, Ps, cross = np.array(ms), np.array(Ps), np.array(cross)

    assert not bool(sm.diverged)
    np.testing.assert_allclose(sm.states, ms[:, :2], atol=1e-10)
    np.testing.assert_allclose(sm.params[:, 0], ms[:, 2], atol=1e-10)
    np.testing.assert_allclose(sm.covariances, Ps[:, :2, :2], atol=1e-10)
    np.testing.assert_allclose(sm.params_cov[:, 0, 0], Ps[:, 2, 2], atol=1e-10)
    np.testing.assert_allclose(sm.cross_covariances, cross[:, :2, :2], atol=1e-10)
    np.testing.assert_allclose(sm.loglik, ll, atol=1e-9)
    # the bias is constant over the drive and learned from all of it: at t = 1 the smoothed
    # variance is a fraction of the filtered one
    assert sm.params_cov[0, 0, 0] < 0.2 * sm.filtered.params_cov[0, 0, 0]
    out = vj.run(est, ys[None], us, x0=x0, P0=P0, theta0=th0, P_theta0=Pth0, smooth=True,
                 return_covariances=True, progress=False)
    np.testing.assert_allclose(out.states[0], sm.states, atol=1e-12)
    np.testing.assert_allclose(out.params[0], sm.params, atol=1e-12)
    np.testing.assert_allclose(out.params_cov[0], sm.params_cov, atol=1e-12)


def test_a_filter_without_smoother_is_named_whatever_the_options():
    """The fixed-grid MPF has no smoother: asked with a particle smoother's option, the message
    names the estimator, not the option (issue 46)."""
    from vehjax.filters import NiW, marginalized_pf_grid

    m = vj.models.Model(lambda x, u, th: jnp.stack([0.9 * x[0] + 0.1 * u[0],
                                                    0.95 * x[1] + 0.05 * x[0]]),
                        lambda x, u, th: jnp.stack([x[0], x[1]]), dt=0.1, state_names=("v", "w"),
                        input_names=("u",), output_names=("y", "z"))
    est = marginalized_pf_grid(m, 8, noisy_input="u", sensors=("y",), linear_states=("w",),
                               known_std={"z": 0.2}, Q=0.05 ** 2,
                               niw=NiW(std0={"u": 0.5, "y": 0.3}))
    with pytest.raises(ValueError, match="^estimator: 'marginalized_pf_grid' has no smoother"):
        vj.smooth(est, np.zeros((5, 2)), np.zeros((5, 1)), x0=np.zeros(2), P0=np.eye(2),
                  key=jax.random.key(0), method=vj.smoothers.AncestorPaths(n_trajectories=4))
