"""Variational-Bayes adaptive Kalman filters (vehjax.filters.vb): Särkkä & Nummenmaa 2009 and
Huang et al. 2017 against numpy transcriptions of the papers' algorithms written here, the
Kalman filter as the point-mass limit, convergence to a known R, biases as Kalman states, bad
input and a diverging run in a batch."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _linear import linear_gaussian_data

import vehjax as vj
from vehjax.filters import vb
from vehjax.models import Model

# ---- a linear-Gaussian model ---------------------------------------------------------------
A = np.array([[1.0, 0.1], [0.0, 0.95]])
B = np.array([[0.005], [0.1]])
H = np.array([[1.0, 0.0], [1.0, 1.0]])
Q = np.diag([1e-4, 1e-3])
R_TRUE = np.diag([0.5 ** 2, 0.2 ** 2])
X0 = np.array([0.0, 0.5])
P0 = np.diag([0.1, 0.1])

LINEAR = Model(
    transition=lambda x, u, th: jnp.asarray(A) @ x + jnp.asarray(B) @ u,
    observe=lambda x, u, th: jnp.asarray(H) @ x,
    dt=0.1, state_names=("p", "v"), input_names=("a",), output_names=("y1", "y2"),
    units={"y1": "m", "y2": "m", "a": "m/s^2"},
)


def h_nl(x):
    return np.array([x[0] + 0.1 * x[1] ** 2, np.sin(x[1])])


NONLIN = Model(
    transition=lambda x, u, th: jnp.asarray(A) @ x + jnp.asarray(B) @ u,
    observe=lambda x, u, th: jnp.stack([x[0] + 0.1 * x[1] ** 2, jnp.sin(x[1])]),
    dt=0.1, state_names=("p", "v"), input_names=("a",), output_names=("y1", "y2"),
)


# ---- numpy transcriptions of the papers -----------------------------------------------------
def np_kf(ys, us, x, P, R):
    """Textbook Kalman filter: states, covariances, log-likelihood."""
    xs, Ps, ll = [], [], 0.0
    for y, u in zip(ys, us):
        x = A @ x + B @ u
        P = A @ P @ A.T + Q
        S = H @ P @ H.T + R
        e = y - H @ x
        K = np.linalg.solve(S, H @ P).T
        x = x + K @ e
        P = P - K @ S @ K.T
        ll += -0.5 * (e @ np.linalg.solve(S, e) + np.linalg.slogdet(2 * np.pi * S)[1])
        xs.append(x)
        Ps.append(P)
    return np.array(xs), np.array(Ps), ll


def np_vb_r_step(x, P, alpha, beta, y, u, rho, N):
    """Särkkä & Nummenmaa 2009, the VB-AKF step for y = H x + r, r ~ N(0, diag(sigma^2))."""
    xp, Pp = A @ x + B @ u, A @ P @ A.T + Q
    alpha_p, beta_p = rho * (alpha - 1) + 1, rho * beta
    alpha_n, beta_n = alpha_p + 0.5, beta_p.copy()
    for _ in range(N):
        Rh = np.diag(beta_n / alpha_n)
        S = H @ Pp @ H.T + Rh
        K = np.linalg.solve(S, H @ Pp).T
        xn = xp + K @ (y - H @ xp)
        Pn = Pp - K @ S @ K.T
        beta_n = beta_p + 0.5 * (y - H @ xn) ** 2 + 0.5 * np.diag(H @ Pn @ H.T)
    return xn, Pn, alpha_n, beta_n


def np_vb_pr_step(x, P, u_dof, U, y, u, tau, rho, N):
    """Huang et al. 2017, Algorithm 1 (linear)."""
    n, m = len(x), len(y)
    xp, Pt = A @ x + B @ u, A @ P @ A.T + Q
    t_hat, T_hat = n + tau + 1, tau * Pt
    u_hat, U_hat = rho * (u_dof - m - 1) + m + 1, rho * U
    xi, Pi = xp, Pt
    for _ in range(N):
        d = xi - xp
        t, T = t_hat + 1, np.outer(d, d) + Pi + T_hat
        e = y - H @ xi
        uu, UU = u_hat + 1, np.outer(e, e) + H @ Pi @ H.T + U_hat
        Pk, Rk = T / (t - n - 1), UU / (uu - m - 1)
        S = H @ Pk @ H.T + Rk
        K = np.linalg.solve(S, H @ Pk).T
        xi = xp + K @ (y - H @ xp)
        Pi = Pk - K @ H @ Pk
    return xi, Pi, uu, UU


def np_cubature(x, P):
    n = len(x)
    L = np.linalg.cholesky(P)
    return np.concatenate([x + np.sqrt(n) * L.T, x - np.sqrt(n) * L.T])  # (2n, n)


def np_vb_r_ckf_step(x, P, alpha, beta, y, u, rho, N):
    """Särkkä & Hartikainen's nonlinear VB-AKF with the cubature rule, h = h_nl, f linear."""
    X = np_cubature(x, P) @ A.T + B @ u
    xp = X.mean(0)
    Pp = (X - xp).T @ (X - xp) / len(X) + Q
    alpha_p, beta_p = rho * (alpha - 1) + 1, rho * beta
    alpha_n, beta_n = alpha_p + 0.5, beta_p.copy()
    Xp = np_cubature(xp, Pp)
    Z = np.array([h_nl(p) for p in Xp])
    zh = Z.mean(0)
    S0 = (Z - zh).T @ (Z - zh) / len(Z)
    C = (Xp - xp).T @ (Z - zh) / len(Z)
    for _ in range(N):
        S = S0 + np.diag(beta_n / alpha_n)
        K = np.linalg.solve(S, C.T).T
        xn = xp + K @ (y - zh)
        Pn = Pp - K @ S @ K.T
        Zn = np.array([h_nl(p) for p in np_cubature(xn, Pn)])
        beta_n = beta_p + 0.5 * np.mean((y - Zn) ** 2, axis=0)
    return xn, Pn, alpha_n, beta_n


# ---- tests -----------------------------------------------------------------------------------
def _data(T, seed=0, R=R_TRUE):
    return linear_gaussian_data(A, B, H, Q, R, X0, P0, T, seed)


@pytest.mark.parametrize("form", ["ekf", "ckf"])
def test_vb_r_one_step_matches_numpy_transcription(form):
    rng = np.random.default_rng(1)
    x, y, u = rng.normal(size=2), rng.normal(size=2), rng.normal(size=1)
    P = np.array([[0.3, 0.05], [0.05, 0.2]])
    alpha, beta = np.array([3.0, 5.0]), np.array([0.4, 0.1])
    est = vb.vbakf_r(LINEAR, Q, [0.1, 0.1], form=form, forgetting=0.97, iterations=4)
    s0 = vb.VBState(jnp.asarray(x), jnp.asarray(P), jnp.asarray(alpha), jnp.asarray(beta),
                    jnp.zeros(0))
    s1, out = jax.jit(est.step)(s0, jnp.asarray(y), jnp.asarray(u))
    xr, Pr, ar, br = np_vb_r_step(x, P, alpha, beta, y, u, 0.97, 4)
    np.testing.assert_allclose(s1.x, xr, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(s1.P, Pr, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(s1.alpha, ar, rtol=1e-12)
    np.testing.assert_allclose(s1.beta, br, rtol=1e-10)
    np.testing.assert_allclose(out.params, np.sqrt(br / ar), rtol=1e-10)
    # the one-step change is not trivial (iterations moved beta off its prediction)
    assert np.all(np.abs(br - 0.97 * beta) > 1e-3)


def test_vb_r_cubature_one_step_matches_numpy_nonlinear():
    rng = np.random.default_rng(2)
    x, u = np.array([0.3, 0.8]), rng.normal(size=1)
    y = h_nl(A @ x) + np.array([0.2, -0.1])
    P = np.array([[0.2, 0.03], [0.03, 0.15]])
    alpha, beta = np.array([4.0, 2.0]), np.array([0.3, 0.05])
    est = vb.vbakf_r(NONLIN, Q, [0.1, 0.1], form="ckf", forgetting=0.99, iterations=3)
    s0 = vb.VBState(jnp.asarray(x), jnp.asarray(P), jnp.asarray(alpha), jnp.asarray(beta),
                    jnp.zeros(0))
    s1, _ = jax.jit(est.step)(s0, jnp.asarray(y), jnp.asarray(u))
    xr, Pr, ar, br = np_vb_r_ckf_step(x, P, alpha, beta, y, u, 0.99, 3)
    np.testing.assert_allclose(s1.x, xr, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(s1.P, Pr, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(s1.beta, br, rtol=1e-10)


@pytest.mark.parametrize("form", ["ekf", "ukf"])
def test_vb_pr_one_step_matches_numpy_transcription(form):
    rng = np.random.default_rng(3)
    x, y, u = rng.normal(size=2), rng.normal(size=2), rng.normal(size=1)
    P = np.array([[0.3, 0.05], [0.05, 0.2]])
    u_dof, U = 9.0, np.array([[1.2, 0.1], [0.1, 0.6]])
    est = vb.vbakf_pr(LINEAR, Q, [0.1, 0.1], form=form, forgetting=0.98, iterations=5, tau=3.0)
    s0 = vb.VBPRState(jnp.asarray(x), jnp.asarray(P), jnp.asarray(u_dof), jnp.asarray(U),
                      jnp.asarray(P), jnp.zeros(0))
    s1, out = jax.jit(est.step)(s0, jnp.asarray(y), jnp.asarray(u))
    xr, Pr, ur, Ur = np_vb_pr_step(x, P, u_dof, U, y, u, 3.0, 0.98, 5)
    np.testing.assert_allclose(s1.x, xr, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(s1.P, Pr, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(s1.u, ur, rtol=1e-12)
    np.testing.assert_allclose(s1.U, Ur, rtol=1e-10)
    np.testing.assert_allclose(out.params, np.sqrt(np.diag(Ur) / (ur - 3)), rtol=1e-10)


def test_point_mass_prior_is_the_kalman_filter():
    ys, us = _data(60, seed=4)
    xs, Ps, ll = np_kf(ys, us, X0, P0, R_TRUE)
    r = vb.vbakf_r(LINEAR, Q, np.diag(R_TRUE), form="ekf", forgetting=1.0, iterations=2,
                   dof0=1e13)
    p = vb.vbakf_pr(LINEAR, Q, R_TRUE, form="ckf", forgetting=1.0, iterations=2, tau=1e13,
                    dof0=1e13)
    for est in (r, p):
        res = vj.filter(est, ys, us, x0=X0, P0=P0)
        np.testing.assert_allclose(res.states, xs, rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(res.covariances, Ps, rtol=1e-6, atol=1e-12)
        np.testing.assert_allclose(float(res.loglik.sum()), ll, rtol=1e-8)
        np.testing.assert_allclose(res.params[-1], np.sqrt(np.diag(R_TRUE)), rtol=1e-6)


def test_converges_to_the_true_R_from_a_wrong_prior():
    T = 1500
    ys, us = _data(T, seed=5)
    truth = np.sqrt(np.diag(R_TRUE))
    est = vb.vbakf_r(LINEAR, Q, 4.0 * np.diag(R_TRUE), form="ckf", iterations=3, dof0=1.0)
    res = vj.filter(est, ys, us, x0=X0, P0=P0)
    std, sd = np.asarray(res.params[-1]), np.sqrt(np.diag(res.params_cov[-1]))
    assert not bool(res.diverged)
    # started at twice the truth; ends within 5 % and within 3 reported standard deviations
    np.testing.assert_allclose(std, truth, rtol=0.05)
    assert np.all(np.abs(std - truth) < 3 * sd), (std, truth, sd)
    # the reported uncertainty is about the sampling spread of a std from T samples
    np.testing.assert_allclose(sd / truth, 1 / np.sqrt(2 * T), rtol=0.3)
    # the first steps still sit near the prior (not a trivially converged output)
    assert np.all(res.params[0] > 1.5 * truth)


def test_huang_filter_learns_R_with_a_wrong_nominal_Q():
    T = 1500
    ys, us = _data(T, seed=6)
    truth = np.sqrt(np.diag(R_TRUE))
    est = vb.vbakf_pr(LINEAR, 10.0 * Q, 4.0 * R_TRUE, form="ekf", iterations=5, tau=3.0,
                      forgetting=1.0)
    res = vj.filter(est, ys, us, x0=X0, P0=P0)
    np.testing.assert_allclose(res.params[-1], truth, rtol=0.1)


def test_bias_and_input_offset_as_kalman_states():
    T, bias, offset = 1500, 0.3, 0.2
    rng = np.random.default_rng(7)
    us = rng.normal(size=(T, 1))
    ys, _ = linear_gaussian_data(A, B, H, Q, R_TRUE, X0, P0, T, seed=7)
    # the same noise with a bias on y1 and the model driven by a + offset
    x, Y = X0.copy(), []
    rng = np.random.default_rng(8)
    for t in range(T):
        x = A @ x + B @ (us[t] + offset) + rng.multivariate_normal(np.zeros(2), Q)
        Y.append(H @ x + rng.multivariate_normal(np.zeros(2), R_TRUE) + np.array([bias, 0.0]))
    est = vb.vbakf_r(LINEAR, Q, np.diag(R_TRUE), form="ekf",
                     augment=vb.Augmentation(biases=("y1",), input_offsets=("a",), bias_std0=1.0,
                                             offset_std0=1.0), iterations=3)
    assert est.param_names == ("a_offset", "y1_bias", "y1_std", "y2_std")
    assert vb.param_units(LINEAR, est) == ("m/s^2", "m", "m", "m")
    res = vj.filter(est, np.array(Y), us, x0=X0, P0=P0)
    th, sd = np.asarray(res.params[-1]), np.sqrt(np.diag(res.params_cov[-1]))
    truth = np.array([offset, bias, 0.5, 0.2])
    assert np.all(np.abs(th - truth) < 4 * sd), (th, truth, sd)
    assert np.all(sd[:2] < 0.1)  # identified, not a wide prior left as it was


@pytest.mark.parametrize("build", [vb.vbakf_r, vb.vbakf_pr])
def test_bad_input_raises_naming_it(build):
    R0 = [0.1, 0.1]
    for rho in (0.0, -0.5, 1.5, float("nan")):
        with pytest.raises(ValueError, match="forgetting"):
            build(LINEAR, Q, R0, forgetting=rho)
    for n in (0, -1, 2.5, True):
        with pytest.raises(ValueError, match="iterations"):
            build(LINEAR, Q, R0, iterations=n)
    with pytest.raises(ValueError, match="form"):
        build(LINEAR, Q, R0, form="pf")
    with pytest.raises(ValueError, match="^R: "):
        build(LINEAR, Q, [0.1, 0.1, 0.1])
    with pytest.raises(ValueError, match="sensors"):
        build(LINEAR, Q, R0, sensors=("nope",))
    with pytest.raises(ValueError, match="biases"):
        build(LINEAR, Q, [0.1], sensors=("y1",), augment=vb.Augmentation(biases=("y2",)))
    with pytest.raises(ValueError, match="known_std"):
        build(LINEAR, Q, R0, sensors=("y1", "y2"), known_std={"y1": 0.1})
    build(LINEAR, Q, R0, forgetting=1.0, iterations=1)  # the edges are allowed


def test_bad_dof_and_tau():
    with pytest.raises(ValueError, match="dof0"):
        vb.vbakf_r(LINEAR, Q, [0.1, 0.1], dof0=0.0)
    with pytest.raises(ValueError, match="dof0"):
        vb.vbakf_pr(LINEAR, Q, [0.1, 0.1], dof0=3.0)  # must exceed m + 1 = 3
    with pytest.raises(ValueError, match="tau"):
        vb.vbakf_pr(LINEAR, Q, [0.1, 0.1], tau=-1.0)


def test_a_diverging_run_is_flagged_and_does_not_poison_the_batch():
    T = 40
    ys = np.stack([_data(T, seed=s)[0] for s in range(3)])
    us = _data(T, seed=0)[1]
    ys[1, 10:] = 1e200  # its squared residual overflows
    est = vb.vbakf_r(LINEAR, Q, np.diag(R_TRUE), form="ckf", iterations=2)
    out = vj.run(est, ys, us, x0=X0, P0=P0)
    assert list(np.asarray(out.diverged)) == [False, True, False]
    assert np.all(np.isfinite(out.states)) and np.all(np.isfinite(out.params))
    for r in (0, 2):
        one = vj.filter(est, ys[r], us, x0=X0, P0=P0)
        np.testing.assert_allclose(out.states[r], one.states, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(out.params[r], one.params, rtol=1e-10)


def test_missing_components_leave_their_statistics():
    ys, us = _data(5, seed=9)
    ys[2, 0] = np.nan
    est = vb.vbakf_r(LINEAR, Q, np.diag(R_TRUE), form="ekf", forgetting=0.9, iterations=2)
    s, step = est.init(X0, P0), jax.jit(est.step)
    for t in range(3):
        prev = s
        s, out = step(s, jnp.asarray(ys[t]), jnp.asarray(us[t]))
    # step 2: y1 missing: its alpha, beta only predicted; y2 updated
    np.testing.assert_allclose(s.alpha[0], 0.9 * (prev.alpha[0] - 1) + 1, rtol=1e-12)
    np.testing.assert_allclose(s.beta[0], 0.9 * prev.beta[0], rtol=1e-12)
    assert float(s.beta[1]) > 0.9 * float(prev.beta[1])
    assert int(out.n_obs) == 1


def test_per_name_bias_stds():
    aug = vb.Augmentation(biases=("y1", "y2"), bias_std0={"y1": 2.0, "y2": 0.5},
                          bias_walk={"y1": 0.0, "y2": 0.01})
    est = vb.vbakf_r(LINEAR, Q, [0.1, 0.1], augment=aug)
    _, P = est.param_prior
    np.testing.assert_allclose(np.diag(P)[:2], [4.0, 0.25])
    with pytest.raises(ValueError, match="bias_std0"):
        vb.vbakf_r(LINEAR, Q, [0.1, 0.1], augment=vb.Augmentation(biases=("y1", "y2"),
                                                                  bias_std0={"y1": 2.0}))
    with pytest.raises(ValueError, match="bias_walk"):
        vb.vbakf_r(LINEAR, Q, [0.1, 0.1], augment=vb.Augmentation(biases=("y1",), bias_walk=-1.0))


def test_vbakf_r_refuses_a_full_R0_rather_than_dropping_its_correlations():
    """vbakf_r learns one variance per sensor: a full R0 would lose its correlations silently,
    so it is refused naming R0 and the way out (issue 46); its diagonal is accepted."""
    R_full = np.array([[0.1, 0.03], [0.03, 0.1]])
    with pytest.raises(ValueError, match="^R: vbakf_r learns one variance per sensor.*vbakf_pr"):
        vb.vbakf_r(LINEAR, Q, R_full)
    vb.vbakf_r(LINEAR, Q, np.diag(np.diag(R_full)))  # a diagonal matrix is the variances
