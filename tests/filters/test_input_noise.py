"""Noise through the inputs (vehjax.filters.input_noise and every filter's input_noise=).

References nobody here wrote: the textbook Kalman filter written out in numpy with the process
noise Q + B Sigma_u B^T (linear model x' = A x + B u, y = H x), and its mean for the particle
filter within Monte-Carlo error. Data are drawn here with numpy, independently of vehjax.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import vehjax as vj
from vehjax.filters import input_noise as inoise
from vehjax.filters import sigma

DT = 0.1
A = np.array([[1.0, DT], [0.0, 0.9]])
B = np.array([[0.0, 0.5 * DT], [DT, 0.2]])  # two inputs: "a" (m/s^2) and "d" (rad)
H = np.array([[1.0, 0.0]])
SIG = {"a": 0.3, "d": 0.05}
SIGMA_U = np.diag([0.3**2, 0.05**2])
Q = np.diag([1e-4, 4e-4])
R = np.array([[0.04]])
X0, P0 = np.array([0.1, -0.2]), np.diag([0.5, 0.3])
T = 25


def model(nonlinear=False):
    """The linear model; ``nonlinear`` adds a sin(d) term for the Jacobian checks."""

    def f(x, u, th):
        out = jnp.asarray(A) @ x + jnp.asarray(B) @ u
        if nonlinear:
            out = out + jnp.array([0.0, 0.3 * jnp.sin(u[1]) * x[0]])
        return out

    return vj.models.Model(
        transition=f, observe=lambda x, u, th: jnp.asarray(H) @ x, dt=DT,
        state_names=("p", "v"), input_names=("a", "d"), output_names=("y",),
        units={"p": "m", "v": "m/s", "a": "m/s^2", "d": "rad", "y": "m"})


def data(seed=0, T=T):
    rng = np.random.default_rng(seed)
    us = rng.normal(size=(T, 2))
    x = X0 + rng.multivariate_normal(np.zeros(2), P0)
    ys = np.zeros((T, 1))
    for t in range(T):
        w_u = rng.multivariate_normal(np.zeros(2), SIGMA_U)
        x = A @ x + B @ (us[t] + w_u) + rng.multivariate_normal(np.zeros(2), Q)
        ys[t] = H @ x + rng.multivariate_normal(np.zeros(1), R)
    ys[7] = np.nan  # a missing measurement
    return ys, us


def numpy_kalman(ys, us, Qtot, offset=0.0):
    """Textbook Kalman filter: filtered means (T, nx), covariances (T, nx, nx), loglik (T,);
    ``offset`` is added to the second state at every prediction."""
    x, P = X0.copy(), P0.copy()
    xs, Ps, lls = [], [], []
    for t in range(len(ys)):
        x, P = A @ x + B @ us[t] + np.array([0.0, offset]), A @ P @ A.T + Qtot
        ll = 0.0
        if np.all(np.isfinite(ys[t])):
            S = H @ P @ H.T + R
            e = ys[t] - H @ x
            K = np.linalg.solve(S, H @ P).T
            x, P = x + K @ e, P - K @ S @ K.T
            ll = -0.5 * (e @ np.linalg.solve(S, e) + np.log(np.linalg.det(2 * np.pi * S)))
        xs.append(x), Ps.append(P), lls.append(ll)
    return np.array(xs), np.array(Ps), np.array(lls)


# ----------------------------------------------------------------------------------------------
# the mathematics on its own


def test_input_factor_from_names_and_covariances():
    names = ("a", "d", "s")
    Lu = inoise.input_factor({"d": 0.1, "a": 2.0}, names)
    assert Lu.shape == (3, 2)
    np.testing.assert_allclose(Lu @ Lu.T, np.diag([4.0, 0.01, 0.0]))
    S = np.array([[2.0, 0.5, 0.0], [0.5, 1.0, 0.0], [0.0, 0.0, 0.0]])  # rank 2, PSD
    Lc = inoise.input_factor(S, names)
    assert Lc.shape == (3, 2)
    np.testing.assert_allclose(Lc @ Lc.T, S, atol=1e-14)
    assert inoise.input_factor(None, names) is None


@pytest.mark.parametrize("bad, match", [
    ({"x": 0.1}, "unknown input"), ({"a": 0.0}, "> 0"), ({"a": np.nan}, "> 0"), ({}, "at least"),
    (np.eye(2), "shape"), (-np.eye(3), "semi-definite"), (np.zeros((3, 3)), "zero"),
    ({"a": [0.1, 0.2]}, "number"),
])
def test_input_factor_refuses_bad_input(bad, match):
    with pytest.raises(ValueError, match="input_noise.*" + match):
        inoise.input_factor(bad, ("a", "d", "s"))


def test_linearized_input_noise_is_g_sigma_gt():
    """G Sigma_u G^T with G = df/du by jacfwd, against G by central differences in numpy."""
    rng = np.random.default_rng(3)
    W = rng.normal(size=(3, 2))
    f = lambda x, u: jnp.tanh(jnp.asarray(W) @ u) * x + jnp.sin(u[0]) * x[::-1]  # noqa: E731
    x, u = np.array([0.3, -1.0, 2.0]), np.array([0.2, -0.4])
    Lu = inoise.input_factor(np.array([[0.5, 0.1], [0.1, 0.2]]), ("a", "b"))
    got = inoise.linearized_input_noise(f, jnp.asarray(x), jnp.asarray(u), Lu)
    h = 1e-6
    G = np.stack([(np.asarray(f(x, u + h * e)) - np.asarray(f(x, u - h * e))) / (2 * h)
                  for e in np.eye(2)], axis=1)
    np.testing.assert_allclose(got, G @ (Lu @ Lu.T) @ G.T, rtol=1e-8, atol=1e-12)


@pytest.mark.parametrize("rule", [sigma.unscented_rule(4, 1.0, 2.0, 0.0), sigma.cubature_rule(4),
                                  sigma.unscented_rule(4, 0.3, 2.0, 0.0)])
def test_augmented_sigma_prediction_is_exact_on_a_linear_map(rule):
    """Points of N([x; 0], blockdiag(P, I)) through A x + B (u + Lu e): mean A x + B u and
    covariance A P A^T + B Sigma_u B^T + Q, for any rule that matches two moments."""
    x, u = jnp.asarray(X0), jnp.array([0.4, -0.1])
    P = jnp.asarray(P0 + 0.1)
    Lu = inoise.input_factor(SIG, ("a", "d"))
    f = lambda v, w: jnp.asarray(A) @ v + jnp.asarray(B) @ w  # noqa: E731
    m, C = inoise.sigma_predict(rule, x, P, f, u, Lu, jnp.asarray(Q))
    np.testing.assert_allclose(m, A @ X0 + B @ np.asarray(u), rtol=1e-12)
    np.testing.assert_allclose(C, A @ np.asarray(P) @ A.T + B @ SIGMA_U @ B.T + Q, rtol=1e-12)
    if rule.kind == "cubature" or rule.wc[0] >= 0:
        ms, Ls = inoise.sqrt_sigma_predict(rule, x, jnp.linalg.cholesky(P), f, u, Lu,
                                           jnp.linalg.cholesky(jnp.asarray(Q)))
        np.testing.assert_allclose(ms, m, rtol=1e-12)
        np.testing.assert_allclose(Ls @ Ls.T, C, rtol=1e-12)


def test_perturbed_inputs_have_the_input_covariance():
    Lu = inoise.input_factor(SIG, ("a", "d"))
    z = jax.random.normal(jax.random.key(0), (2, 200_000))
    us = np.asarray(inoise.perturbed_inputs(jnp.array([1.0, 2.0]), Lu, z))
    np.testing.assert_allclose(us.mean(axis=1), [1.0, 2.0], atol=4 * 0.3 / np.sqrt(2e5))
    np.testing.assert_allclose(np.cov(us), SIGMA_U, rtol=0.02,  # 4 MC standard errors
                               atol=4 * 0.3 * 0.05 / np.sqrt(2e5))


# ----------------------------------------------------------------------------------------------
# the filters against the numpy Kalman filter with Q + B Sigma_u B^T

GAUSSIAN = [
    ("ekf", lambda m, Q_, **k: vj.filters.ekf(m, Q_, R, **k)),
    ("ukf", lambda m, Q_, **k: vj.filters.ukf(m, Q_, R, **k)),
    ("ukf-small-alpha", lambda m, Q_, **k: vj.filters.ukf(m, Q_, R,
                                                          points=vj.filters.SigmaPoints(alpha=0.5), **k)),
    ("ckf", lambda m, Q_, **k: vj.filters.ckf(m, Q_, R, **k)),
    ("sr-ukf", lambda m, Q_, **k: vj.filters.ukf(m, Q_, R, sqrt=True, **k)),
    ("sr-ckf", lambda m, Q_, **k: vj.filters.ckf(m, Q_, R, sqrt=True, **k)),
]


@pytest.mark.parametrize("name, build", GAUSSIAN, ids=[g[0] for g in GAUSSIAN])
def test_gaussian_filters_equal_kalman_with_input_noise(name, build):
    ys, us = data()
    est = build(model(), Q, input_noise=SIG)
    assert est.batch is None  # input noise: run vmaps this per-run step
    out = vj.filter(est, ys, us, x0=X0, P0=P0)
    xs, Ps, lls = numpy_kalman(ys, us, Q + B @ SIGMA_U @ B.T)
    np.testing.assert_allclose(out.states, xs, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(out.covariances, Ps, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(out.loglik, lls, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("name, build", [GAUSSIAN[0], GAUSSIAN[3], GAUSSIAN[4]],
                         ids=["ekf", "ckf", "sr-ukf"])
def test_zero_q_with_input_noise_is_accepted(name, build):
    """Q = 0: all the process noise comes through the inputs (B Sigma_u B^T is positive
    definite here)."""
    ys, us = data(seed=1)
    out = vj.filter(build(model(), np.zeros((2, 2)), input_noise=SIGMA_U), ys, us, x0=X0, P0=P0)
    xs, Ps, _ = numpy_kalman(ys, us, B @ SIGMA_U @ B.T)
    np.testing.assert_allclose(out.states, xs, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(out.covariances, Ps, rtol=1e-9, atol=1e-12)
    assert not bool(out.diverged)


def test_ekf_input_noise_uses_the_jacobian_at_the_filtered_mean():
    """On a model nonlinear in the input, one EKF step's predicted covariance is
    F P F^T + Q + G Sigma_u G^T with F, G by numpy central differences at (x0, u_0)."""
    m = model(nonlinear=True)
    est = vj.filters.ekf(m, Q, R, input_noise=SIG)
    u0 = np.array([0.3, 0.4])
    st = est.init(jnp.asarray(X0), jnp.asarray(P0))
    _, out = est.step(st, jnp.array([np.nan]), jnp.asarray(u0))  # missing y: prediction only
    f = lambda x, u: np.asarray(m.transition(jnp.asarray(x), jnp.asarray(u), m.theta))  # noqa
    h = 1e-6
    F = np.stack([(f(X0 + h * e, u0) - f(X0 - h * e, u0)) / (2 * h) for e in np.eye(2)], 1)
    G = np.stack([(f(X0, u0 + h * e) - f(X0, u0 - h * e)) / (2 * h) for e in np.eye(2)], 1)
    np.testing.assert_allclose(out.cov, F @ P0 @ F.T + Q + G @ SIGMA_U @ G.T, rtol=1e-7)


def test_entry_by_entry_ekf_algebra_equals_numpy():
    """The EKF's entry-by-entry kernels (vehjax.filters.kalman.*_entries, the step of models
    with at most 8 states and outputs) against numpy: the Jacobian of a nonlinear map and the
    predicted covariance F P F^T + Q + B B^T, and the Joseph-form update with the second of
    three measurement components missing (the Kalman update on the observed subset, and its
    log-likelihood, written out here)."""
    from vehjax.filters import kalman

    rng = np.random.default_rng(5)
    z = np.array([0.3, -0.7, 1.1])
    g = lambda v: jnp.stack([jnp.sin(v[0]) * v[1], v[2] ** 2 + v[0], jnp.exp(0.1 * v[1])])  # noqa
    val, J = kalman.jacobian_entries(g, jnp.asarray(z))
    Jn = np.array([[np.cos(z[0]) * z[1], np.sin(z[0]), 0.0], [1.0, 0.0, 2 * z[2]],
                   [0.0, 0.1 * np.exp(0.1 * z[1]), 0.0]])
    np.testing.assert_allclose(np.array(J, dtype=float), Jn, rtol=1e-14, atol=1e-15)
    np.testing.assert_allclose(np.array(val, dtype=float), np.asarray(g(z)), rtol=1e-15)
    F, Bm = rng.normal(size=(3, 3)), rng.normal(size=(3, 2))
    M = rng.normal(size=(3, 3))
    Pm, Qm = M @ M.T + np.eye(3), np.diag([0.1, 0.0, 0.2])
    ent = lambda A: [[jnp.asarray(v) for v in row] for row in A]  # noqa: E731
    Pp = kalman.predict_entries(ent(F), ent(Pm), kalman.cov_entries(Qm), ent(Bm))
    np.testing.assert_allclose(np.array(Pp, dtype=float), F @ Pm @ F.T + Qm + Bm @ Bm.T,
                               rtol=1e-13)
    Hm, Rm = rng.normal(size=(3, 3)), np.diag([0.3, 0.5, 0.2])
    Pp = np.array(Pp, dtype=float)
    C, S = kalman.measure_entries(ent(Pp), ent(Hm), kalman.cov_entries(Rm))
    np.testing.assert_allclose(np.array(S, dtype=float), Hm @ Pp @ Hm.T + Rm, rtol=1e-13)
    xp, yh, y = rng.normal(size=3), rng.normal(size=3), np.array([0.4, np.nan, -0.2])
    r = kalman.masked_update_entries(list(jnp.asarray(xp)), ent(Pp), jnp.asarray(y),
                                     list(jnp.asarray(yh)), S, C,
                                     joseph=(ent(Hm), kalman.cov_entries(Rm)))
    o = [0, 2]  # the observed components: the textbook update on them
    Ho, So = Hm[o], (Hm @ Pp @ Hm.T + Rm)[np.ix_(o, o)]
    K = np.linalg.solve(So, Ho @ Pp).T
    e = y[o] - yh[o]
    A_ = np.eye(3) - K @ Ho
    np.testing.assert_allclose(r.x, xp + K @ e, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(r.P, A_ @ Pp @ A_.T + K @ Rm[np.ix_(o, o)] @ K.T, rtol=1e-12,
                               atol=1e-14)
    ll = -0.5 * (e @ np.linalg.solve(So, e) + np.log(np.linalg.det(2 * np.pi * So)))
    np.testing.assert_allclose(r.loglik, ll, rtol=1e-12)
    assert int(r.n_obs) == 2 and float(r.innovation[1]) == 0.0


def test_run_with_input_noise_equals_the_per_run_filter():
    """vehjax.run (which vmaps the per-run step, batch=None) gives vehjax.filter's results."""
    ys1, us1 = data(seed=2)
    ys2, _ = data(seed=3)
    est = vj.filters.ckf(model(), Q, R, input_noise=SIG)
    out = vj.run(est, np.stack([ys1, ys2]), us1, x0=X0, P0=P0, progress=False)
    for r, ys in enumerate((ys1, ys2)):
        one = vj.filter(est, ys, us1, x0=X0, P0=P0)
        np.testing.assert_allclose(out.states[r], one.states, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(out.loglik[r], one.loglik.sum(), rtol=1e-12)


@pytest.mark.slow  # a Monte-Carlo check (4 x 1000 particles, two filters): `pytest -m slow`
def test_particle_filter_with_input_noise_matches_kalman_mean():
    """Bootstrap PF (4 independent runs of 1000 particles) against the exact filter with
    Q + B Sigma_u B^T: the errors of its means, in the exact filter's standard deviations, are
    of Monte-Carlo size (rms ~ 1/sqrt(N_eff), measured 0.08-0.10); the same PF without the input
    noise (the control) is off by 0.24-0.38 of a standard deviation (a test that can fail)."""
    ys, us = data(seed=4, T=40)
    xs, Ps, _ = numpy_kalman(ys, us, Q + B @ SIGMA_U @ B.T)
    sd = np.sqrt(np.diagonal(Ps, axis1=1, axis2=2))
    rms = {}
    for label, kw in (("input", {"input_noise": SIG}), ("control", {})):
        est = vj.filters.bootstrap_pf(model(), Q, R, n_particles=1000, **kw)
        runs = jax.jit(jax.vmap(lambda k: vj.filter(est, ys, us, x0=X0, P0=P0, key=k)))
        out = runs(jax.random.split(jax.random.key(1), 4))
        assert not np.any(out.diverged)
        rms[label] = np.sqrt((((np.asarray(out.states) - xs) / sd) ** 2).mean(axis=(0, 1)))
    assert np.all(rms["input"] < 0.15), rms
    assert np.all(rms["control"] > 1.5 * rms["input"]), rms


def test_particle_filter_with_zero_q_uses_only_input_noise():
    """Q = 0: the particles' spread after one prediction step (no measurement) is
    A P0 A^T + B Sigma_u B^T within sampling error."""
    n = 20_000
    est = vj.filters.bootstrap_pf(model(), np.zeros((2, 2)), R, n_particles=n,
                                  input_noise=SIGMA_U)
    u0 = jnp.array([0.5, -0.3])
    one = jax.jit(lambda k: est.step(est.init(jnp.asarray(X0), jnp.asarray(P0), key=k),
                                     jnp.array([np.nan]), u0)[1])
    out = one(jax.random.key(2))
    C = A @ P0 @ A.T + B @ SIGMA_U @ B.T
    sd = np.sqrt(np.diag(C))
    mean = A @ X0 + B @ np.asarray(u0)
    assert np.all(np.abs(np.asarray(out.mean) - mean) < 4 * sd / np.sqrt(n))
    # sample covariance: standard error of entry (i, j) about sd_i sd_j sqrt(2 / n) at most
    assert np.all(np.abs(np.asarray(out.cov) - C) < 4 * np.outer(sd, sd) * np.sqrt(2 / n))


def test_adaptive_ckf_with_input_noise():
    """ACKF adapting nothing is the CKF: equal to the Kalman filter with Q + B Sigma_u B^T; with
    adapt=("R",) Q0 = 0 is accepted (the noise comes through the inputs); adapting Q needs a
    positive-definite Q0 (the metric of its projection), refused naming Q0."""
    ys, us = data(seed=5)
    out = vj.filter(vj.filters.ackf(model(), Q, R, adapt=(), input_noise=SIG), ys, us,
                    x0=X0, P0=P0)
    xs, Ps, lls = numpy_kalman(ys, us, Q + B @ SIGMA_U @ B.T)
    np.testing.assert_allclose(out.states, xs, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(out.covariances, Ps, rtol=1e-9, atol=1e-12)
    one = vj.filter(vj.filters.ackf(model(), np.zeros(2), R, adapt=("R",), input_noise=SIG),
                    ys, us, x0=X0, P0=P0)
    assert np.all(np.isfinite(one.states)) and not bool(one.diverged)
    with pytest.raises(ValueError, match="^Q: "):
        vj.filters.ackf(model(), np.zeros(2), R, adapt=("Q", "R"), input_noise=SIG)


def param_model():
    """The linear model plus a parameter c: x' = A x + B u + (0, 0.05 c)."""
    return vj.models.Model(
        transition=lambda x, u, th: (jnp.asarray(A) @ x + jnp.asarray(B) @ u
                                     + jnp.array([0.0, 0.05]) * th[0]),
        observe=lambda x, u, th: jnp.asarray(H) @ x, dt=DT, state_names=("p", "v"),
        input_names=("a", "d"), output_names=("y",), param_names=("c",), theta=[1.0])


DUAL = ["dual_ekf", "dual_ukf", "joint_ekf", "joint_ukf"]


@pytest.mark.parametrize("name", DUAL)
def test_dual_and_joint_filters_with_input_noise(name):
    """The parameter known to 1e-12 (P_theta0, Q_theta tiny): the state estimates are the
    Kalman filter's with Q + B Sigma_u B^T (and without the input noise they are not)."""
    ys, us = data(seed=6)
    build = getattr(vj.filters, name)
    est = build(param_model(), Q, R, Q_theta=[1e-30], estimate=("c",), input_noise=SIG)
    out = vj.filter(est, ys, us, x0=X0, P0=P0, theta0=[1.0], P_theta0=[1e-24])
    xs, Ps, _ = numpy_kalman(ys, us, Q + B @ SIGMA_U @ B.T, offset=0.05)
    np.testing.assert_allclose(out.states, xs, rtol=1e-8, atol=1e-11)
    np.testing.assert_allclose(out.covariances, Ps, rtol=1e-8, atol=1e-11)
    np.testing.assert_allclose(out.params[:, 0], 1.0, rtol=1e-9)
    xq, _, _ = numpy_kalman(ys, us, Q, offset=0.05)
    assert np.max(np.abs(xq - xs)) > 1e-3  # the input noise matters here
