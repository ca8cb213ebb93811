"""EKF, UKF, CKF and their square-root forms against references written outside vehjax:
the exact Kalman filter in plain numpy, filterpy's UnscentedKalmanFilter / CubatureKalmanFilter,
numpy Cholesky."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
from _linear import linear_gaussian_data
import pytest
from filterpy.kalman import CubatureKalmanFilter, MerweScaledSigmaPoints, UnscentedKalmanFilter
from filterpy.kalman.CubatureKalmanFilter import spherical_radial_sigmas

import vehjax as vj  # float64
from vehjax.filters import SigmaPoints
from vehjax.filters.gaussian import ckf, ekf, masked_update, ukf, validate_prior
from vehjax.filters.sigma import (
    chol_update,
    cholesky,
    cubature_rule,
    sigma_points,
    solve_lower,
    triangularize,
    unscented_rule,
)
from vehjax.models import KinematicBicycle, Model

T = 50

# ---- a linear-Gaussian model -------------------------------------------------------------------
A = np.array(
    [[1.0, 0.1, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.9, 0.2], [0.0, 0.0, -0.2, 0.9]]
)
B = np.array([[0.005, 0.0], [0.1, 0.0], [0.0, 0.3], [0.1, -0.2]])
H = np.array([[1.0, 0.0, 0.5, 0.0], [0.0, 0.0, 1.0, -0.3]])
Q_LIN = np.array(
    [[1e-3, 2e-4, 0.0, 0.0], [2e-4, 1e-2, 0.0, 1e-3], [0.0, 0.0, 5e-3, 0.0], [0.0, 1e-3, 0.0, 2e-3]]
)
R_LIN = np.array([[0.1, 0.02], [0.02, 0.05]])
X0_LIN = np.array([0.0, 1.0, 0.5, -0.5])
P0_LIN = np.array(
    [[1.0, 0.1, 0.0, 0.0], [0.1, 0.5, 0.0, 0.0], [0.0, 0.0, 0.3, 0.05], [0.0, 0.0, 0.05, 0.2]]
)

LINEAR = Model(
    transition=lambda x, u, th: jnp.asarray(A) @ x + jnp.asarray(B) @ u,
    observe=lambda x, u, th: jnp.asarray(H) @ x,
    dt=0.1,
    state_names=("p", "v", "a", "b"),
    input_names=("u1", "u2"),
    output_names=("y1", "y2"),
)


def _linear_data(seed=0):
    return linear_gaussian_data(A, B, H, Q_LIN, R_LIN, X0_LIN, P0_LIN, T, seed)


def _numpy_kf(ys, us, R=R_LIN, Q=Q_LIN):
    """The Kalman filter written out; NaN components are dropped from H, R and y."""
    x, P = X0_LIN.copy(), P0_LIN.copy()
    means, covs, lls, niss = [], [], [], []
    for y, u in zip(ys, us):
        x = A @ x + B @ u
        P = A @ P @ A.T + Q
        o = np.isfinite(y)
        ll = nis = 0.0
        if o.any():
            Ho, Ro = H[o], R[np.ix_(o, o)]
            S = Ho @ P @ Ho.T + Ro
            K = P @ Ho.T @ np.linalg.inv(S)
            e = y[o] - Ho @ x
            nis = e @ np.linalg.solve(S, e)
            ll = -0.5 * (nis + np.linalg.slogdet(S)[1] + o.sum() * np.log(2 * np.pi))
            x = x + K @ e
            P = (np.eye(4) - K @ Ho) @ P @ (np.eye(4) - K @ Ho).T + K @ Ro @ K.T
        means.append(x)
        covs.append(P)
        lls.append(ll)
        niss.append(nis)
    return np.array(means), np.array(covs), np.array(lls), np.array(niss)


def _scan(est, ys, us, x0, P0):
    """One run through vehjax.filter: (final state, FilterResult)."""

    @jax.jit
    def go(ys, us, x0, P0):
        res = vj.filter(est, ys, us, x0=x0, P0=P0)
        return res.state, res

    return go(jnp.asarray(ys), jnp.asarray(us), jnp.asarray(x0), jnp.asarray(P0))


LINEAR_FILTERS = {
    "ekf": lambda m, Q, R: ekf(m, Q, R),
    "ukf": lambda m, Q, R: ukf(m, Q, R),
    "ckf": lambda m, Q, R: ckf(m, Q, R),
    "sr_ukf": lambda m, Q, R: ukf(m, Q, R, sqrt=True),
    "sr_ukf_negw0": lambda m, Q, R: ukf(m, Q, R, points=SigmaPoints(alpha=0.5, beta=2.0,
                                                                    kappa=-1.0), sqrt=True),
    "sr_ckf": lambda m, Q, R: ckf(m, Q, R, sqrt=True),
}


def _missing_pattern(ys):
    ys = ys.copy()
    ys[[4, 17, 30], :] = np.nan  # all missing: pure prediction
    ys[[8, 9, 22], 0] = np.nan  # partially missing
    ys[[12, 40], 1] = np.nan
    return ys


@pytest.mark.parametrize("name", list(LINEAR_FILTERS))
def test_linear_gaussian_equals_kalman_filter(name):
    """To 1e-9, with complete measurements and with some (all or part) NaN; one compile."""
    ys, us = _linear_data()
    ys2 = np.stack([ys, _missing_pattern(ys)])
    est = LINEAR_FILTERS[name](LINEAR, Q_LIN, R_LIN)

    def one(y):
        return vj.filter(est, y, us, x0=X0_LIN, P0=P0_LIN)

    outs = jax.jit(jax.vmap(one))(jnp.asarray(ys2))
    for i in range(2):
        out = jax.tree.map(lambda a: np.asarray(a[i]), outs)
        m, P, ll, nis = _numpy_kf(ys2[i], us)
        np.testing.assert_allclose(out.states, m, rtol=0, atol=1e-9)
        np.testing.assert_allclose(out.covariances, P, rtol=0, atol=1e-9)
        np.testing.assert_allclose(out.loglik, ll, rtol=0, atol=1e-9)
        np.testing.assert_allclose(out.nis, nis, rtol=0, atol=1e-9)
        np.testing.assert_array_equal(out.n_obs, np.isfinite(ys2[i]).sum(axis=1))
        assert out.params.shape == (T, 0) and out.params_cov.shape == (T, 0, 0)


def test_all_missing_step_is_pure_prediction():
    est = ukf(LINEAR, Q_LIN, R_LIN, sqrt=True)
    s = est.init(X0_LIN, P0_LIN)
    u = np.array([0.3, -0.1])
    _, out = jax.jit(est.step)(s, jnp.full(2, jnp.nan), u)
    np.testing.assert_allclose(out.mean, A @ X0_LIN + B @ u, atol=1e-12)
    np.testing.assert_allclose(out.cov, A @ P0_LIN @ A.T + Q_LIN, atol=1e-12)
    assert float(out.loglik) == 0.0 and float(out.nis) == 0.0 and int(out.n_obs) == 0


def test_masked_update_partial_equals_reduced_update():
    rng = np.random.default_rng(3)
    M = rng.normal(size=(3, 3))
    P = M @ M.T + np.eye(3)
    N = rng.normal(size=(3, 3))
    S = N @ N.T + np.eye(3)
    C = rng.normal(size=(3, 3))
    x, yh = rng.normal(size=3), rng.normal(size=3)
    y = np.array([0.3, np.nan, -1.0])
    r = masked_update(*map(jnp.asarray, (x, P, y, yh, S, C)))
    o = np.array([0, 2])
    So, Co = S[np.ix_(o, o)], C[:, o]
    K = Co @ np.linalg.inv(So)
    e = y[o] - yh[o]
    np.testing.assert_allclose(r.x, x + K @ e, atol=1e-12)
    np.testing.assert_allclose(r.P, P - K @ So @ K.T, atol=1e-12)
    ll = -0.5 * (e @ np.linalg.solve(So, e) + np.linalg.slogdet(So)[1] + 2 * np.log(2 * np.pi))
    np.testing.assert_allclose(r.loglik, ll, atol=1e-12)
    assert int(r.n_obs) == 2


# ---- a nonlinear model against filterpy -----------------------------------------------------
BIKE = KinematicBicycle(dt=0.1)
BEACON = (20.0, 10.0)  # python floats: a float32 run must stay float32


def _h_nonlin(x, u, th):
    dist = jnp.hypot(x[0] - BEACON[0], x[1] - BEACON[1])
    return jnp.stack([dist, x[2] + 0.1 * jnp.sin(x[3]), x[3] ** 2 / 10.0])


def _f_nonlin(x, u, th):
    return BIKE.transition(x, u, th)


NONLIN = Model(
    transition=_f_nonlin,
    observe=_h_nonlin,
    dt=0.1,
    state_names=BIKE.state_names,
    input_names=BIKE.input_names,
    param_names=BIKE.param_names,
    output_names=("range", "psi_s", "v2"),
    theta=np.asarray(BIKE.theta),
)
Q_NL = np.diag([0.02, 0.02, 0.005, 0.05])
R_NL = np.array([[0.25, 0.01, 0.0], [0.01, 0.01, 0.0], [0.0, 0.0, 0.4]])
X0_NL = np.array([0.0, 0.0, 0.1, 8.0])
P0_NL = np.diag([1.0, 1.0, 0.05, 1.0])

_f_np = jax.jit(_f_nonlin)
_h_np = jax.jit(_h_nonlin)
_TH = NONLIN.theta


def _nonlin_data(seed=1):
    rng = np.random.default_rng(seed)
    t = np.arange(T) * 0.1
    us = np.stack([0.5 * np.sin(0.5 * t), 0.15 * np.sin(0.8 * t)], axis=1)
    x = X0_NL.copy()
    ys = []
    for k in range(T):
        x = np.asarray(_f_np(x, us[k], _TH)) + rng.multivariate_normal(np.zeros(4), Q_NL)
        ys.append(np.asarray(_h_np(x, us[k], _TH)) + rng.multivariate_normal(np.zeros(3), R_NL))
    return np.array(ys), us


def _fx(x, dt, u):
    return np.asarray(_f_np(x, u, _TH))


def _hx(x):
    return np.asarray(_h_np(x, np.zeros(2), _TH))


def _filterpy_ukf(ys, us, alpha, beta, kappa):
    pts = MerweScaledSigmaPoints(4, alpha=alpha, beta=beta, kappa=kappa)
    f = UnscentedKalmanFilter(dim_x=4, dim_z=3, dt=0.1, hx=_hx, fx=_fx, points=pts)
    f.x, f.P, f.Q, f.R = X0_NL.copy(), P0_NL.copy(), Q_NL.copy(), R_NL.copy()
    out = []
    for y, u in zip(ys, us):
        f.predict(u=u)  # filterpy 2.0 redraws sigmas_f from (x-, P-) here, as Algorithm 2
        f.update(y)
        out.append((f.x.copy(), f.P.copy(), f.log_likelihood))
    return out


def _filterpy_ckf(ys, us):
    f = CubatureKalmanFilter(dim_x=4, dim_z=3, dt=0.1, hx=_hx, fx=lambda x, dt, u: _fx(x, dt, u))
    f.x, f.P, f.Q, f.R = X0_NL.copy()[:, None], P0_NL.copy(), Q_NL.copy(), R_NL.copy()
    out = []
    for y, u in zip(ys, us):
        f.predict(fx_args=(u,))
        # filterpy's CKF reuses the propagated points in update(); redraw them from (x-, P-) with
        # filterpy's own rule, so that Q enters S and Pxz as in the UKF (Algorithm 2).
        f.sigmas_f = spherical_radial_sigmas(f.x, f.P)
        f.update(y[:, None])  # column vectors, as filterpy's CKF keeps x
        out.append((f.x.ravel().copy(), f.P.copy(), f.log_likelihood))
    return out


def _compare(out, ref, tol=1e-8):
    m = np.array([r[0] for r in ref])
    P = np.array([r[1] for r in ref])
    ll = np.array([r[2] for r in ref])
    np.testing.assert_allclose(np.asarray(out.states), m, rtol=tol, atol=tol)
    np.testing.assert_allclose(np.asarray(out.covariances), P, rtol=tol, atol=tol)
    np.testing.assert_allclose(np.asarray(out.loglik), ll, rtol=tol, atol=tol)


NONLIN_FILTERS = {
    "ekf": lambda: ekf(NONLIN, Q_NL, R_NL),
    "ukf": lambda: ukf(NONLIN, Q_NL, R_NL),
    "ukf_negw0": lambda: ukf(NONLIN, Q_NL, R_NL, points=SigmaPoints(alpha=0.5, beta=2.0,
                                                                    kappa=-1.0)),
    "sr_ukf_negw0": lambda: ukf(NONLIN, Q_NL, R_NL, points=SigmaPoints(alpha=0.5, beta=2.0,
                                                                       kappa=-1.0), sqrt=True),
    "ckf": lambda: ckf(NONLIN, Q_NL, R_NL),
    "sr_ckf": lambda: ckf(NONLIN, Q_NL, R_NL, sqrt=True),
}


@functools.lru_cache(maxsize=None)
def _nonlin_run(name, dtype="float64"):
    """One filter on the nonlinear data set, run once per session (compiling dominates)."""
    ys, us = _nonlin_data()
    d = np.dtype(dtype)
    args = (a.astype(d) for a in (ys, us, X0_NL, P0_NL))
    return _scan(NONLIN_FILTERS[name](), *args)[1]


@pytest.mark.parametrize("name", ["ukf", "ukf_negw0", "sr_ukf_negw0"])
def test_ukf_matches_filterpy(name):
    abk = (0.5, 2.0, -1.0) if name.endswith("negw0") else (1.0, 2.0, 0.0)
    _compare(_nonlin_run(name), _filterpy_ukf(*_nonlin_data(), *abk))


@pytest.mark.parametrize("name", ["ckf", "sr_ckf"])
def test_ckf_matches_filterpy(name):
    _compare(_nonlin_run(name), _filterpy_ckf(*_nonlin_data()))


def test_ekf_matches_numpy_ekf_with_finite_difference_jacobians():
    ys, us = _nonlin_data()
    out = _nonlin_run("ekf")

    def jac(fn, x, eps=1e-6):
        cols = [(fn(x + eps * e) - fn(x - eps * e)) / (2 * eps) for e in np.eye(4)]
        return np.stack(cols, axis=1)

    x, P = X0_NL.copy(), P0_NL.copy()
    for k in range(T):
        F = jac(lambda z: _fx(z, 0.1, us[k]), x)
        x = _fx(x, 0.1, us[k])
        P = F @ P @ F.T + Q_NL
        Hk = jac(_hx, x)
        S = Hk @ P @ Hk.T + R_NL
        K = P @ Hk.T @ np.linalg.inv(S)
        x = x + K @ (ys[k] - _hx(x))
        P = P - K @ S @ K.T
        np.testing.assert_allclose(out.states[k], x, rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(out.covariances[k], P, rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("name", ["ekf", "ukf", "sr_ukf", "ckf"])
def test_noise_free_state_q_with_zero_variance_equals_kalman_filter(name):
    """Q may be positive semi-definite: a state without process noise (issue: zero entries
    where meaningful). The filters still equal the exact Kalman filter with that Q."""
    Q0 = np.diag(np.diag(Q_LIN) * np.array([1.0, 0.0, 1.0, 0.0]))
    est = {"ekf": ekf, "ukf": ukf, "ckf": ckf,
           "sr_ukf": lambda m, q, r: ukf(m, q, r, sqrt=True)}[name](LINEAR, Q0, R_LIN)
    ys, us = _linear_data()
    out = vj.filter(est, ys, us, x0=X0_LIN, P0=P0_LIN)
    m, P, ll, _ = _numpy_kf(ys, us, Q=Q0)
    np.testing.assert_allclose(out.states, m, rtol=0, atol=1e-9)
    np.testing.assert_allclose(out.covariances, P, rtol=0, atol=1e-9)
    np.testing.assert_allclose(out.loglik, ll, rtol=0, atol=1e-9)


# ---- float32 --------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["ekf", "ckf", "sr_ukf_negw0"])
def test_float32_agrees_with_float64(name):
    """Stated tolerance, over the 50 steps: the float32 mean stays within 5e-4 standard
    deviations of the float64 mean, the standard deviations agree to 1e-4 relative and the
    log-likelihoods to 1e-3 (measured: about 1e-5, 1e-5, 3e-5)."""
    o64, o32 = _nonlin_run(name), _nonlin_run(name, "float32")
    assert o32.states.dtype == jnp.float32 and o32.covariances.dtype == jnp.float32
    assert o32.loglik.dtype == jnp.float32
    sd64 = np.sqrt(np.diagonal(np.asarray(o64.covariances), axis1=1, axis2=2))
    sd32 = np.sqrt(np.diagonal(np.asarray(o32.covariances, dtype=float), axis1=1, axis2=2))
    assert np.max(np.abs(np.asarray(o32.states, dtype=float) - np.asarray(o64.states)) / sd64) < 5e-4
    assert np.max(np.abs(sd32 / sd64 - 1)) < 1e-4
    np.testing.assert_allclose(np.asarray(o32.loglik, dtype=float), o64.loglik, rtol=0, atol=1e-3)


# ---- sigma rules and square-root helpers ----------------------------------------------------
@pytest.mark.parametrize("abk", [(1.0, 2.0, 0.0), (1e-3, 2.0, 0.0), (0.5, 1.0, 3.0)])
def test_unscented_rule_matches_merwe_points(abk):
    n = 5
    rng = np.random.default_rng(0)
    M = rng.normal(size=(n, n))
    P, x = M @ M.T + 0.1 * np.eye(n), rng.normal(size=n)
    rule = unscented_rule(n, *abk)
    ref = MerweScaledSigmaPoints(n, *abk)
    np.testing.assert_allclose(rule.wm, ref.Wm, rtol=1e-12)
    np.testing.assert_allclose(rule.wc, ref.Wc, rtol=1e-12)
    pts = sigma_points(jnp.asarray(x), jnp.linalg.cholesky(jnp.asarray(P)), rule)
    np.testing.assert_allclose(pts, ref.sigma_points(x, P), rtol=1e-10, atol=1e-10)


def test_cubature_rule_matches_filterpy():
    n = 4
    rng = np.random.default_rng(1)
    M = rng.normal(size=(n, n))
    P, x = M @ M.T + 0.1 * np.eye(n), rng.normal(size=n)
    rule = cubature_rule(n)
    assert rule.m == 2 * n and np.allclose(rule.wm, 1 / (2 * n))
    pts = sigma_points(jnp.asarray(x), jnp.linalg.cholesky(jnp.asarray(P)), rule)
    np.testing.assert_allclose(pts, spherical_radial_sigmas(x, P), rtol=1e-10, atol=1e-10)


def test_triangularize_and_chol_update():
    rng = np.random.default_rng(2)
    Aa = rng.normal(size=(4, 9))
    L = triangularize(jnp.asarray(Aa))
    np.testing.assert_allclose(L, np.linalg.cholesky(Aa @ Aa.T), atol=1e-12)
    v = 0.5 * rng.normal(size=4)
    P = Aa @ Aa.T
    up, down = chol_update(L, jnp.asarray(v)), chol_update(L, jnp.asarray(v), downdate=True)
    np.testing.assert_allclose(up, np.linalg.cholesky(P + np.outer(v, v)), atol=1e-12)
    np.testing.assert_allclose(down, np.linalg.cholesky(P - np.outer(v, v)), atol=1e-12)


# ---- batching and gradients -------------------------------------------------------------------
def _random_spd(rng, batch, n):
    G = rng.normal(size=batch + (n, n))
    return G @ np.swapaxes(G, -1, -2) + 0.1 * np.eye(n)


@pytest.mark.parametrize("n", [1, 2, 3, 5, 8, 9, 12])
def test_small_cholesky_and_solve_match_numpy(n):
    """Unrolled for n <= 8, jnp.linalg beyond: both equal numpy's Cholesky and solve."""
    rng = np.random.default_rng(n)
    A = _random_spd(rng, (6,), n)
    L_np = np.linalg.cholesky(A)
    b, Bk = rng.normal(size=(6, n)), rng.normal(size=(6, n, 3))
    L = np.asarray(cholesky(jnp.asarray(A)))  # leading batch axis
    Lv = np.asarray(jax.vmap(cholesky)(jnp.asarray(A)))  # vmapped
    np.testing.assert_allclose(L, L_np, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(Lv, L_np, rtol=1e-12, atol=1e-12)
    assert np.all(np.triu(L, 1) == 0.0)
    x_np = np.linalg.solve(L_np, b[..., None])[..., 0]
    X_np = np.linalg.solve(L_np, Bk)
    np.testing.assert_allclose(solve_lower(jnp.asarray(L), jnp.asarray(b)), x_np, rtol=1e-10)
    np.testing.assert_allclose(
        jax.vmap(solve_lower)(jnp.asarray(L), jnp.asarray(Bk)), X_np, rtol=1e-10, atol=1e-12
    )
    # Like jnp.linalg.cholesky: the input is symmetrised, and a matrix that is not PD gives NaNs.
    skew = np.triu(rng.normal(size=(n, n)), 1) * 1e-3
    np.testing.assert_allclose(
        cholesky(jnp.asarray(A[0] + skew - skew.T)), L_np[0], rtol=1e-12, atol=1e-12
    )
    bad = A[0].copy()
    bad[-1, -1] = -1.0
    L_bad = np.asarray(cholesky(jnp.asarray(bad)))
    assert np.all(np.isnan(np.tril(L_bad)[-1])) and not np.all(np.isfinite(L_bad))
    if n <= 8:  # the unrolled factor is NaN throughout
        assert np.all(np.isnan(L_bad))


def test_vmap_over_runs_and_grad_of_loglik():
    """Batched over runs with vmap, and d loglik / d log(R scale) against finite differences
    of the numpy Kalman filter (R is built inside the differentiated function)."""
    ys, us = _linear_data()
    ys2 = np.stack([ys, _missing_pattern(_linear_data(seed=5)[0])])

    def total_loglik(log_r, ys):
        est = ekf(LINEAR, Q_LIN, R_LIN * jnp.exp(log_r))  # traced R: shape check only
        return vj.filter(est, ys, jnp.asarray(us), x0=X0_LIN, P0=P0_LIN).loglik.sum()

    batched = jax.jit(jax.vmap(jax.value_and_grad(total_loglik), in_axes=(None, 0)))
    lls, grads = batched(0.0, jnp.asarray(ys2))
    for i in range(2):

        def ll_np(log_r):
            return _numpy_kf(ys2[i], us, R=R_LIN * np.exp(log_r))[2].sum()

        np.testing.assert_allclose(lls[i], ll_np(0.0), atol=1e-9)
        np.testing.assert_allclose(grads[i], (ll_np(1e-5) - ll_np(-1e-5)) / 2e-5, rtol=1e-6)


# ---- bad input --------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "kwargs, arg",
    [
        (dict(Q=np.eye(3), R=R_LIN), "Q"),
        (dict(Q=-np.eye(4), R=R_LIN), "Q"),
        (dict(Q=np.diag([1.0, 1.0, -1e-3, 1.0]), R=R_LIN), "Q"),
        (dict(Q=Q_LIN + np.triu(np.ones((4, 4)), 1) * 1e-3, R=R_LIN), "Q"),
        (dict(Q=Q_LIN, R=np.array([0.1, np.nan])), "R"),
        (dict(Q=Q_LIN, R=np.array([[0.1, 0.2], [0.2, 0.1]])), "R"),
        (dict(Q=Q_LIN, R=np.ones(3)), "R"),
    ],
)
@pytest.mark.parametrize("builder", [ekf, ukf, ckf, lambda m, Q, R: ukf(m, Q, R, sqrt=True)])
def test_bad_noise_raises(builder, kwargs, arg):
    with pytest.raises(ValueError, match=rf"^{arg}:"):
        builder(LINEAR, **kwargs)


def test_bad_prior_and_tuning_raise():
    est = ukf(LINEAR, Q_LIN, R_LIN)
    with pytest.raises(ValueError, match="^x0:"):
        est.init(np.zeros(3), P0_LIN)
    with pytest.raises(ValueError, match="^P0:"):
        est.init(X0_LIN, np.eye(3))
    with pytest.raises(ValueError, match="^P0:"):
        est.init(X0_LIN, -P0_LIN)
    with pytest.raises(ValueError, match="^P0:"):
        est.init(X0_LIN, np.array([1.0, 1.0, -1.0, 1.0]))
    with pytest.raises(ValueError, match="^theta0:"):
        est.init(X0_LIN, P0_LIN, theta0=np.zeros(2))
    with pytest.raises(ValueError, match="^x0:"):  # the shape check also holds under jit
        jax.jit(lambda x: est.init(x, P0_LIN))(jnp.zeros(5))
    with pytest.raises(ValueError, match="^alpha:"):
        ukf(LINEAR, Q_LIN, R_LIN, points=SigmaPoints(alpha=0.0))
    with pytest.raises(ValueError, match="^kappa:"):
        ukf(LINEAR, Q_LIN, R_LIN, points=SigmaPoints(kappa=-4.0))
    with pytest.raises(ValueError, match=r"^P0\[1\]:"):
        validate_prior(est, np.zeros((2, 4)), np.stack([P0_LIN, -P0_LIN]))
    with pytest.raises(ValueError, match="^x0:"):
        validate_prior(est, np.zeros((2, 3)), P0_LIN)
    validate_prior(est, np.zeros((2, 4)), np.stack([P0_LIN, P0_LIN]))
    validate_prior(4, X0_LIN, np.diag(P0_LIN))


# ---- the many-runs form (runs-last batch, else vmap) equals the step run by run ------------------


@pytest.mark.parametrize("name, per_run", [("ekf", False), ("ukf", True), ("ckf", False)])
def test_many_runs_form_equals_the_step_run_by_run(name, per_run):
    from _contract import assert_batch_equals_step

    build = {"ekf": ekf, "ukf": ukf, "ckf": ckf}[name]
    runs, steps = 3, 8
    ys = np.stack([_linear_data(seed=s)[0][:steps] for s in range(runs)])
    ys[1, 2, 0] = np.nan  # one component missing
    ys[2, 4] = np.nan  # all missing
    us = _linear_data()[1][:steps]
    if per_run:
        us = us[None] * np.linspace(0.9, 1.1, runs)[:, None, None]
    x0 = X0_LIN + 0.1 * np.arange(runs)[:, None]
    est = build(LINEAR, Q_LIN, R_LIN)
    assert est.batch is not None  # a small model with constant noise has a runs-last step
    assert assert_batch_equals_step(est, ys, us, x0, P0_LIN) == "batch"
    # without it, run vmaps the step: that equals the step run by run as well
    assert assert_batch_equals_step(est._replace(runtime=est.runtime._replace(batch=None)), ys, us, x0, P0_LIN) == "vmap"


def test_many_runs_form_with_each_runs_theta0():
    """On a nonlinear model, each run with its own theta0 (the batch form then reads theta from
    the state) and its own inputs."""
    from _contract import assert_batch_equals_step

    runs, steps = 3, 6
    ys = np.stack([_nonlin_data(seed=s)[0][:steps] for s in range(runs)])
    us = _nonlin_data()[1][:steps][None] * np.linspace(0.9, 1.1, runs)[:, None, None]
    theta0 = np.asarray(NONLIN.theta) * np.linspace(0.9, 1.1, runs)[:, None]
    x0 = np.tile(X0_NL, (runs, 1))
    est = ukf(NONLIN, Q_NL, R_NL)  # the EKF's per-run theta: tests/filters/test_runs_last.py
    form = assert_batch_equals_step(est, ys, us, x0, P0_NL, theta0=theta0)
    assert form == ("batch" if est.batch is not None else "vmap")


@pytest.mark.parametrize("rule", [vj.filters.sigma.unscented_rule(3, 0.5, 2.0, 1.0),
                                  vj.filters.sigma.cubature_rule(3)],
                         ids=["unscented", "cubature"])
def test_sigma_moments_entry_by_entry_equal_the_matrix_forms(rule):
    """The entry-by-entry predict and measure (vehjax.filters.sigma.step_moments_entries, what
    the one-run UKF/CKF of a small model and the runs-last step run) give the matrix forms'
    moments (sigma.predict, sigma.measure) for a nonlinear transition and observation, a
    random covariance and a rule with a negative centre weight, to 1e-13."""
    rng = np.random.default_rng(5)
    A = rng.normal(size=(3, 3))
    x, P = rng.normal(size=3), A @ A.T + 0.2 * np.eye(3)
    Q, R = np.diag([0.1, 0.2, 0.05]), np.array([[0.3, 0.1], [0.1, 0.4]])

    def f(v):
        return jnp.stack([jnp.sin(v[0]) + v[1] * v[2], jnp.arctan(v[1]), v[2] + 0.1 * v[0] ** 2])

    def h(v):
        return jnp.stack([v[0] * v[1], jnp.cos(v[2])])

    def images(fn):
        return lambda pts: [list(fn(jnp.stack(p))) for p in pts]

    ent = lambda M: [[M[i, j] for j in range(M.shape[1])] for i in range(M.shape[0])]  # noqa: E731
    m = vj.filters.sigma.step_moments_entries(list(jnp.asarray(x)), ent(jnp.asarray(P)),
                                              images(f), images(h), ent(jnp.asarray(Q)),
                                              ent(jnp.asarray(R)), rule)
    xp, Pp = vj.filters.sigma.predict(rule, jnp.asarray(x), jnp.asarray(P), f, jnp.asarray(Q))
    me = vj.filters.sigma.measure(rule, xp, Pp, h, jnp.asarray(R))
    arr = lambda v: np.array(v, dtype=float)  # noqa: E731
    for got, want in ((m.xp, xp), (m.Pp, Pp), (m.yh, me.y_hat), (m.S, me.S), (m.C, me.C)):
        np.testing.assert_allclose(arr(got), np.asarray(want), rtol=1e-13, atol=1e-15)
    assert np.array_equal(arr(m.Pp), arr(m.Pp).T) and np.array_equal(arr(m.S), arr(m.S).T)
