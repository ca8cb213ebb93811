"""Parallel-in-time Kalman filter / RTS smoother and the iterated smoothers (IEKS, IPLS).

References written here: a numpy Kalman filter and RTS smoother for a time-varying affine model,
and the maximum a posteriori trajectory of a nonlinear model by scipy.optimize.least_squares on
the whole negative log posterior."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import least_squares

import vehjax as vj
from vehjax.smoothers import linear, parallel

# ------------------------------------------------------------------------------------------------
# parallel = sequential on a time-varying affine model, with missing components


def _affine(T=10, n=3, ny=2, seed=0):
    rng = np.random.default_rng(seed)
    F = 0.5 * rng.normal(size=(T + 1, n, n))
    F[0] = 0
    c = rng.normal(size=(T + 1, n))

    def spd(k):
        A = rng.normal(size=(T + 1, k, k))
        return A @ A.transpose(0, 2, 1) + 0.5 * np.eye(k)

    Q, R = spd(n), spd(ny)
    H, d = rng.normal(size=(T + 1, ny, n)), rng.normal(size=(T + 1, ny))
    y = rng.normal(size=(T + 1, ny))
    y[0] = np.nan
    y[5, 1] = np.nan
    y[8] = np.nan
    y[10, 0] = np.nan
    return (F, c, Q, H, d, R), y


def _numpy_kf_rts(F, c, Q, H, d, R, y):
    """Textbook Kalman filter + RTS smoother, observed components only (t = 0 is the prior:
    F_0 = 0)."""
    n = F.shape[-1]
    m, P = np.zeros(n), np.eye(n)
    mf, Pf, ll = [], [], []
    for t in range(len(y)):
        mp, Pp = F[t] @ m + c[t], F[t] @ P @ F[t].T + Q[t]
        o = np.isfinite(y[t])
        Ho, do, Ro = H[t][o], d[t][o], R[t][np.ix_(o, o)]
        S = Ho @ Pp @ Ho.T + Ro
        e = y[t][o] - Ho @ mp - do
        K = Pp @ Ho.T @ np.linalg.inv(S)
        m, P = mp + K @ e, Pp - K @ S @ K.T
        ll.append(-0.5 * (e @ np.linalg.solve(S, e) + np.linalg.slogdet(S)[1]
                          + o.sum() * np.log(2 * np.pi)) if o.any() else 0.0)
        mf.append(m), Pf.append(P)
    ms, Ps, cross = [mf[-1]], [Pf[-1]], []
    for t in range(len(y) - 2, -1, -1):
        Pp = F[t + 1] @ Pf[t] @ F[t + 1].T + Q[t + 1]
        G = Pf[t] @ F[t + 1].T @ np.linalg.inv(Pp)
        cross.insert(0, G @ Ps[0])
        ms.insert(0, mf[t] + G @ (ms[0] - F[t + 1] @ mf[t] - c[t + 1]))
        Ps.insert(0, Pf[t] + G @ (Ps[0] - Pp) @ G.T)
    return np.array(mf), np.array(Pf), np.array(ll), np.array(ms), np.array(Ps), np.array(cross)


def test_parallel_and_sequential_kalman_equal_numpy_with_missing_components():
    """The associative-scan and recursive-doubling filters and smoothers and the sequential
    ones all equal the numpy textbook recursions to 1e-9, with single components and a whole
    step missing."""
    arrays, y = _affine()
    ref = _numpy_kf_rts(*arrays, y)
    model = linear.Affine(*map(jnp.asarray, arrays))
    for mod, kw in ((linear, {}), (parallel, {"scan": "associative"}),
                    (parallel, {"scan": "doubling"})):
        ms, Ps, ll = jax.jit(lambda m, y: mod.kalman_filter(m, y, **kw))(model, y)
        m_s, P_s, cross = jax.jit(lambda m, a, b: mod.rts_smoother(m, a, b, **kw))(model, ms, Ps)
        for got, want in zip((ms, Ps, ll, m_s, P_s, cross), ref):
            np.testing.assert_allclose(got, want, atol=1e-9)


# ------------------------------------------------------------------------------------------------
# iterated smoothers on a nonlinear model

DT = 0.1
QP = np.diag([1e-3, 1e-2])
RP = np.diag([0.02, 0.05])
M0 = np.array([1.0, 0.0])
PP0 = np.diag([0.2, 0.2])
TN = 8


def _f_np(x, u, g):
    return np.array([x[0] + DT * x[1], x[1] - DT * g * np.sin(x[0]) + DT * u[0]])


def _h_np(x):
    return np.array([np.sin(x[0]), x[0] * x[1]])


def _pendulum():
    def f(x, u, th):
        return jnp.array([x[0] + DT * x[1], x[1] - DT * th[0] * jnp.sin(x[0]) + DT * u[0]])

    return vj.models.Model(transition=f, observe=lambda x, u, th: jnp.array(
        [jnp.sin(x[0]), x[0] * x[1]]), dt=DT, state_names=("a", "w"), param_names=("g",),
        input_names=("u",), output_names=("s", "aw"), theta=np.array([9.81]))


@pytest.fixture(scope="module")
def pend():
    rng = np.random.default_rng(7)
    us = 0.5 * np.cos(np.arange(TN) * 0.3)[:, None]
    x = M0 + rng.normal(0, np.sqrt(np.diag(PP0)))
    ys = []
    for t in range(TN):
        x = _f_np(x, us[t], 9.81) + rng.normal(0, np.sqrt(np.diag(QP)))
        ys.append(_h_np(x) + rng.normal(0, np.sqrt(np.diag(RP))))
    ys = np.array(ys)
    ys[5, 1] = np.nan
    return _pendulum(), ys, us


def _map_trajectory(ys, us, g=9.81):
    """argmin over x_0..x_T of the negative log posterior (prior, transitions, observed
    measurements), as whitened least squares, by scipy."""
    wP, wQ, wR = (np.linalg.inv(np.linalg.cholesky(A)) for A in (PP0, QP, RP))

    def residuals(z):
        X = z.reshape(TN + 1, 2)
        r = [wP @ (X[0] - M0)]
        for t in range(TN):
            r.append(wQ @ (X[t + 1] - _f_np(X[t], us[t], g)))
            e = ys[t] - _h_np(X[t + 1])
            r.append(np.where(np.isfinite(e), wR @ np.where(np.isfinite(e), e, 0.0), 0.0))
        return np.concatenate(r)

    z0 = np.tile(M0, TN + 1)
    sol = least_squares(residuals, z0, xtol=1e-15, ftol=1e-15, gtol=1e-15)
    return sol.x.reshape(TN + 1, 2)[1:]


@pytest.mark.slow  # the parallel IEKS compile (its sequential form, and the parallel RTS, run by default)
def test_parallel_ieks_converges_to_scipy_map(pend):
    """The IEKS fixed point is the MAP trajectory (Gauss-Newton on the negative log posterior):
    the parallel-in-time passes reach scipy's minimiser and flag convergence, where the plain
    extended RTS is visibly off; a single pass with a tight tolerance is reported as not
    converged."""
    model, ys, us = pend
    est = vj.filters.ekf(model, QP, RP)
    ref = _map_trajectory(ys, us)
    sm = jax.jit(lambda y: vj.smooth(est, y, us, x0=M0, P0=PP0, method=vj.smoothers.IEKS(
        tol=1e-10, max_iter=40, parallel=True)))(ys)
    assert bool(sm.converged) and not bool(sm.diverged)
    assert 1 < int(sm.iterations) < 40
    np.testing.assert_allclose(sm.states, ref, atol=1e-7)
    rts = vj.smooth(est, ys, us, x0=M0, P0=PP0)
    assert np.abs(rts.states - ref).max() > 1e-4  # the plain extended RTS is not the MAP
    one = jax.jit(lambda y: vj.smooth(est, y, us, x0=M0, P0=PP0, method=vj.smoothers.IEKS(
        tol=1e-12, max_iter=1)))(ys)
    assert not bool(one.converged) and int(one.iterations) == 1


@pytest.mark.slow  # two IPLS compiles: `pytest -m slow` (README)
def test_ipls_fixed_point_from_two_starts(pend):
    """The IPLS (cubature points) reaches the same fixed point from the filter's own moments
    (sequential passes) and from a flat start at the prior mean (parallel passes by recursive
    doubling)."""
    model, ys, us = pend
    est = vj.filters.ckf(model, QP, RP)
    run = jax.jit(lambda y, init, par: vj.smooth(est, y, us, x0=M0, P0=PP0,
                                                 method=vj.smoothers.IPLS(
                                                     tol=1e-10, max_iter=60, initial=init,
                                                     parallel=par)), static_argnums=2)
    a = run(ys, None, False)
    b = run(ys, np.tile(M0, (TN, 1)), "doubling")
    for r in (a, b):
        assert bool(r.converged) and not bool(r.diverged)
    np.testing.assert_allclose(a.states, b.states, atol=1e-7)
    np.testing.assert_allclose(a.covariances, b.covariances, atol=1e-7)


def test_sequential_ieks_map_and_loglik_gradient_equals_finite_differences(pend):
    """The sequential IEKS at a parameter value reaches scipy's MAP for that value; d/dg of its
    log-likelihood at the fixed point (implicit differentiation, not unrolled) equals central
    finite differences of the same function."""
    model, ys, us = pend

    def sm(g):
        est = vj.filters.ekf(model, QP, RP)
        return vj.smooth(est, ys, us, x0=M0, P0=PP0, theta0=jnp.array([g]),
                         method=vj.smoothers.IEKS(tol=1e-12, max_iter=60))

    g0, h = 9.0, 1e-4
    # one program: the log-likelihood, its gradient and the smoothing (as auxiliary output)
    def ll(g):
        r = sm(g)
        return r.loglik.sum(), r

    vg = jax.jit(jax.value_and_grad(ll, has_aux=True))
    (_, mid), grad = vg(g0)
    assert bool(mid.converged)
    np.testing.assert_allclose(mid.states, _map_trajectory(ys, us, g0), atol=1e-7)
    fd = (vg(g0 + h)[0][0] - vg(g0 - h)[0][0]) / (2 * h)
    assert np.isfinite(grad)
    np.testing.assert_allclose(grad, fd, rtol=1e-5)
