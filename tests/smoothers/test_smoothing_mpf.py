"""The marginalized PF's smoother (vehjax.smoothers.marginalized) against references written
here: the Kalman filter and RTS smoother of the linear-Gaussian system in numpy (textbook
recursion), numpy pseudo-inverses and genealogies followed in a Python loop."""

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import vehjax as vj
from vehjax.filters.marginalized import NiW, marginalized_pf
from vehjax.smoothers import marginalized as ms

# x = (v, a): v' = 0.95 v + 0.1 a + 0.1 (u + w), a' = 0.05 v + 0.9 a + zeta; y = (v + e1, a + e2)
# with w ~ N(MU_W, SIG_W^2) the input error, e1 ~ N(B1, R1) the "sensor", e2 ~ N(0, R2) known
A = np.array([[0.95, 0.1], [0.05, 0.9]])
B = np.array([0.1, 0.0])
MU_W, SIG_W, SIG_Z = 0.3, 0.8, 0.05
B1, SD1, SD2 = 0.2, 0.1, 0.15
X0 = np.array([0.5, -0.2])
P0 = np.diag([0.2, 0.1])
T = 25
NAN_STEPS = (6, 13)


def _model():
    def f(x, u, th):
        return jnp.stack([0.95 * x[0] + 0.1 * x[1] + 0.1 * u[0], 0.05 * x[0] + 0.9 * x[1]])

    def h(x, u, th):
        return jnp.stack([x[0], x[1]])

    return vj.models.Model(transition=f, observe=h, dt=0.1, state_names=("v", "a"),
                           input_names=("u",), output_names=("y1", "y2"), param_names=())


def _data(seed=3):
    """One run simulated in numpy (its own generator); the sensor missing at NAN_STEPS."""
    rng = np.random.default_rng(seed)
    us = np.sin(0.3 * np.arange(T))[:, None]
    x = rng.multivariate_normal(X0, P0)
    ys = np.empty((T, 2))
    for t in range(T):
        w = MU_W + SIG_W * rng.normal()
        x = A @ x + B * (us[t, 0] + w) + np.array([0.0, SIG_Z * rng.normal()])
        ys[t] = x + np.array([B1 + SD1 * rng.normal(), SD2 * rng.normal()])
    ys[list(NAN_STEPS), 0] = np.nan
    return ys, us


def _rts_backward(F, xf, Pf, xp, Pp):
    """The textbook Rauch-Tung-Striebel backward pass for x_t+1 = F x_t + ...: smoothed means,
    covariances and lag-one covariances Cov(x_t, x_t+1) from the filtered (xf, Pf) and
    predicted (xp, Pp) moments, lists over t."""
    n = len(xf)
    xs, Ps, C = [None] * n, [None] * n, [None] * (n - 1)
    xs[-1], Ps[-1] = xf[-1], Pf[-1]
    for t in range(n - 2, -1, -1):
        G = np.linalg.solve(Pp[t + 1], F @ Pf[t]).T
        xs[t] = xf[t] + G @ (xs[t + 1] - xp[t + 1])
        Ps[t] = Pf[t] + G @ (Ps[t + 1] - Pp[t + 1]) @ G.T
        C[t] = G @ Ps[t + 1]
    return np.array(xs), np.array(Ps), np.array(C)


def kalman_rts(ys, us):
    """Textbook Kalman filter (predict with u_t, update with y_t, NaN skipped) and RTS smoother
    of the system with its noise known. Returns smoothed means (T, 2), covariances (T, 2, 2)
    and lag-one covariances G_t P_t+1|T (T - 1, 2, 2)."""
    Q = SIG_W**2 * np.outer(B, B) + np.diag([0.0, SIG_Z**2])
    R = np.diag([SD1**2, SD2**2])
    b = np.array([B1, 0.0])
    x, P = X0.copy(), P0.copy()
    xp, Pp, xf, Pf = [], [], [], []
    for t in range(len(ys)):
        x, P = A @ x + B * (us[t, 0] + MU_W), A @ P @ A.T + Q
        xp.append(x), Pp.append(P)
        o = np.isfinite(ys[t])
        S = P[np.ix_(o, o)] + R[np.ix_(o, o)]
        K = np.linalg.solve(S, P[o]).T
        x, P = x + K @ (ys[t][o] - b[o] - x[o]), P - K @ S @ K.T
        xf.append(x), Pf.append(P)
    return _rts_backward(A, xf, Pf, xp, Pp)


def _known_noise_mpf(n, **kw):
    """The MPF with its noise statistics made known (nu0 = 1e7, lambda = 1, gamma0 = 1e-9, the
    true means and stds as prior) and the linear state in each particle's Gaussian."""
    return marginalized_pf(_model(), n, noisy_input="u", sensors=("y1",), known_std={"y2": SD2},
                           linear_states=("a",), Q=SIG_Z ** 2,
                           kalman_states=kw.pop("kalman_states", "all"), **kw,
                           niw=NiW(std0={"u": SIG_W, "y1": SD1}, mean0={"u": MU_W, "y1": B1},
                                   forgetting=1.0, nu0=1e7, gamma0=1e-9))


@functools.lru_cache(maxsize=None)
def _smoothed(n, reps=8):
    ys, us = _data()
    est = _known_noise_mpf(n)

    def one(key):
        return vj.smooth(est, ys, us, x0=X0, P0=P0, key=key,
                         method=vj.smoothers.AncestorPaths(n_trajectories=n))

    keys = jax.random.split(jax.random.key(5), reps)
    return jax.jit(jax.vmap(one))(keys)


def _z_rms(est, ref):
    """RMS over entries of (replicate mean - ref) / (its standard error from the replicates'
    spread); about 1 when est is unbiased."""
    est = np.asarray(est)
    se = est.std(axis=0, ddof=1) / np.sqrt(est.shape[0])
    return float(np.sqrt(np.mean(((est.mean(axis=0) - ref) / se) ** 2)))


@pytest.mark.slow  # two MPF + smoother compiles, about 20 s of CPU each: `pytest -m slow`
def test_smoothed_states_converge_to_the_rts_smoother():
    """Noise known, the linear state in each particle's Gaussian: the smoothed means (two
    sensor readings missing) are within Monte-Carlo error of the numpy RTS (z of the 8
    replicates' mean, RMS < 2, as for the bootstrap PF's FFBSi) at N = M = 50 and 400
    (observed 1.91 and 0.88: at 50 the filter's O(1/N) bias shows), and the error shrinks with
    N close to 1/sqrt(N) (expected ratio sqrt(8) = 2.8, observed 3.1; asserted > 1.8). The
    covariances and lag-one covariances at N = 400 are within Monte-Carlo error of the RTS's
    (observed z 1.27, 1.24); at N = 50 the covariances are too small, the degeneracy of
    ancestor paths documented in the module (observed 0.52 of the RTS variance of v at t = 0,
    0.78 on average)."""
    ys, us = _data()
    m, P, C = kalman_rts(ys, us)
    sd = np.sqrt(np.diagonal(P, axis1=1, axis2=2))
    rms = {}
    for n in (50, 400):
        sm = _smoothed(n)
        assert sm.states.shape == (8, T, 2) and sm.path_states.shape == (8, n, T, 2)
        assert not np.any(sm.diverged)
        rms[n] = float(np.sqrt(np.mean(((np.asarray(sm.states) - m) / sd) ** 2)))
        assert _z_rms(sm.states, m) < 2.0, (n, _z_rms(sm.states, m))
    assert rms[50] / rms[400] > 1.8, rms
    # in units of the smoothed std, 400 independent draws would give 0.05
    assert rms[400] < 0.2, rms
    sm = _smoothed(400)
    assert _z_rms(sm.covariances, P) < 2.0
    assert _z_rms(sm.cross_covariances, C) < 2.0
    assert _z_rms(sm.cross_covariances, P[1:]) > 4.0  # the wrong lag is rejected
    var50 = np.asarray(_smoothed(50).covariances).mean(axis=0)[:, 0, 0] / P[:, 0, 0]
    assert var50.mean() < 0.9 and var50[0] < var50[-1], var50


def test_the_noise_statistics_stay_at_the_known_values():
    """With the statistics known the smoothed noise estimates are the prior's at every time."""
    sm = _smoothed(50)
    p = np.asarray(sm.params)
    np.testing.assert_allclose(p[..., 0], MU_W, rtol=1e-6)
    np.testing.assert_allclose(p[..., 1], SIG_W, rtol=1e-4)
    np.testing.assert_allclose(p[..., 2], B1, rtol=1e-6)
    np.testing.assert_allclose(p[..., 3], SD1, rtol=1e-4)


def test_paths_are_genealogies():
    """The number of distinct particles on the paths never grows backwards in time (ancestor
    tracing)."""
    nu = np.asarray(_smoothed(50).n_unique)
    assert np.all(np.diff(nu, axis=1) >= 0)


@pytest.mark.slow  # a second MPF compile (vehjax.filter's own program): `pytest -m slow`
def test_loglik_is_the_filters():
    """The smoother's log-likelihood is vehjax.filter's with the same key."""
    ys, us = _data()
    est = _known_noise_mpf(50)
    key = jax.random.split(jax.random.key(5), 8)[0]
    fr = vj.filter(est, ys, us, x0=X0, P0=P0, key=key)
    np.testing.assert_allclose(np.asarray(_smoothed(50).loglik[0]), np.asarray(fr.loglik),
                               rtol=1e-12)


def test_trace_ancestors_follows_the_genealogy():
    rng = np.random.default_rng(0)
    anc = rng.integers(0, 7, size=(6, 7))
    last = np.array([0, 3, 6, 6])
    got = np.asarray(ms.trace_ancestors(jnp.asarray(anc), jnp.asarray(last)))
    ref = np.empty((6, 4), int)
    ref[-1] = last
    for t in range(4, -1, -1):
        ref[t] = anc[t + 1][ref[t + 1]]
    np.testing.assert_array_equal(got, ref)


def test_psd_right_solve_is_the_pseudo_inverse_on_the_range():
    """For S positive definite, C S^-1; for S singular with C's rows in its range (C = P Phi^T,
    S = Phi P Phi^T), numpy's pinv and G S = C."""
    rng = np.random.default_rng(1)
    Mx = rng.normal(size=(4, 4))
    S = Mx @ Mx.T + np.eye(4)
    Cm = rng.normal(size=(3, 4))
    np.testing.assert_allclose(ms.psd_right_solve(Cm, S), np.linalg.solve(S, Cm.T).T, rtol=1e-10)
    L = rng.normal(size=(4, 2))
    P = L @ L.T  # rank 2
    Phi = rng.normal(size=(4, 4))
    Cs, Ss = P @ Phi.T, Phi @ P @ Phi.T
    G = np.asarray(ms.psd_right_solve(Cs, Ss))
    np.testing.assert_allclose(G, Cs @ np.linalg.pinv(Ss, rcond=1e-10, hermitian=True),
                               rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(G @ Ss, Cs, rtol=1e-8, atol=1e-10)


def test_bad_input_names_the_argument():
    ys, us = _data()
    kw = dict(x0=X0, P0=P0, key=jax.random.key(0))
    with pytest.raises(ValueError, match="n_trajectories"):
        ms.smooth(_known_noise_mpf(10), ys, us, n_trajectories=0, **kw)
    with pytest.raises(ValueError, match="method"):
        ms.smooth(_known_noise_mpf(10), ys, us, method="rejection", **kw)
    with pytest.raises(ValueError, match="method.*kalman_states='linear'"):
        ms.smooth(_known_noise_mpf(10), ys, us, method="ffbsi", **kw)  # "all": not offered
    lin10 = _known_noise_mpf(10, kalman_states="linear")
    for bad in (0, -3, 2.5, None):
        with pytest.raises(ValueError, match="n_trajectories"):
            ms.smooth(lin10, ys, us, method="ffbsi", n_trajectories=bad, **kw)
    with pytest.raises(ValueError, match="method"):
        vj.smooth(lin10, ys, us, method="FFBSi", **kw)
    lin = _known_noise_mpf(10, kalman_states="linear")  # smoothed since issue 29's item 2
    undeclared = lin._replace(backward=lin.backward._replace(
        rao_blackwell=lin.rao_blackwell._replace(linear=None)))
    with pytest.raises(ValueError, match="estimator.*kalman_states='linear'"):
        ms.smooth(undeclared, ys, us, **kw)
    with pytest.raises(ValueError, match="estimator"):
        ms.smooth(vj.filters.ukf(_model(), np.eye(2) * 0.01, np.eye(2) * 0.01), ys, us, **kw)
    with pytest.raises(ValueError, match="key"):
        ms.smooth(_known_noise_mpf(10), ys, us, x0=X0, P0=P0, key=None)


def _bank_drive(model, Tb, x0, seed):
    """Tb steps of SingleTrackBank at 20 m/s with a 0.5 Hz steering sine and a 0.3 deg steering
    offset from x0, measurements with 0.01 white noise: (U (Tb, 2), Y (Tb, 5))."""
    t = np.arange(Tb) * 0.01
    U = np.stack([np.full(Tb, 20.0), 0.02 * np.sin(2 * np.pi * 0.5 * t)], 1)
    th = jnp.asarray(model.theta)

    def body(x, u):
        xn = model.transition(x, u + jnp.array([0.0, math.radians(0.3)]), th)
        return xn, model.observe(xn, u, th)

    _, Y = jax.lax.scan(body, jnp.asarray(x0, float), jnp.asarray(U))
    return U, np.asarray(Y) + 0.01 * np.random.default_rng(seed).normal(size=(Tb, 5))


def _bank_mpf(model):
    """The paper's filter with Gaussian particle states on SingleTrackBank (16 particles) and
    its prior covariance."""
    est = marginalized_pf(model, 16, known_std={"phi": 0.01, "r_virt": 0.005},
                          Q=0.05 ** 2, kalman_states="all",
                          niw=NiW(std0={"delta": 0.01, "ay": 0.4, "r": 0.02, "roll_rate": 0.02}))
    return est, np.diag([0.1, 0.01, 1e-4, 1e-4, 1e-4])


@pytest.mark.slow  # the bank model's MPF and smoother compile for about a minute on 2 cores
def test_single_track_bank_smoke():
    """The paper's filter with Gaussian particle states on SingleTrackBank, 40 steps of
    simulated data: finite smoothed states and noise statistics of the right shapes, the
    filter's log-likelihood, no divergence."""
    model = vj.models.SingleTrackBank(dt=0.01)
    Tb = 40
    U, Y = _bank_drive(model, Tb, np.zeros(5), seed=0)
    est, P0b = _bank_mpf(model)
    key = jax.random.key(2)
    sm = jax.jit(lambda: vj.smooth(est, Y, U, x0=np.zeros(5), P0=P0b, key=key,
                                   method=vj.smoothers.AncestorPaths(n_trajectories=8)))()
    assert sm.states.shape == (Tb, 5) and sm.covariances.shape == (Tb, 5, 5)
    assert sm.params.shape == (Tb, 8) and sm.params_cov.shape == (Tb, 8, 8)
    assert not bool(sm.diverged)
    assert np.all(np.isfinite(sm.states)) and np.all(np.isfinite(sm.params))
    assert_psd(sm.covariances)


@pytest.mark.slow  # the bank model's MPF and smoother compile for about a minute on 2 cores
def test_single_track_bank_long_drive_smoothed_covariances_are_psd():
    """A drive-length run (6000 steps, a minute at 100 Hz) of the paper's filter with Gaussian
    particle states on SingleTrackBank, smoothed along 8 paths: every smoothed covariance
    symmetric and positive semi-definite to rounding (:func:`assert_psd`), the mixture's and
    each path's, and the lag-one covariances finite."""
    model = vj.models.SingleTrackBank(dt=0.01)
    Tb = 6000
    U, Y = _bank_drive(model, Tb, np.zeros(5), seed=1)
    est, P0b = _bank_mpf(model)
    sm = jax.jit(lambda: vj.smooth(est, Y, U, x0=np.zeros(5), P0=P0b, key=jax.random.key(5),
                                   method=vj.smoothers.AncestorPaths(n_trajectories=8)))()
    assert not bool(sm.diverged)
    assert_psd(sm.covariances)
    assert np.all(np.isfinite(sm.cross_covariances))


def assert_psd(covs):
    """Symmetric positive semi-definite to rounding: each (n, n) covariance's eigenvalues
    (numpy's eigvalsh) at or above -8 n eps of its largest. A smoothed covariance is PSD in
    exact arithmetic and singular where the exact answer is (a particle's sampled states start
    as a point, so at t = 0 every path's covariance has a zero block); eigvalsh of an exactly
    PSD matrix with a zero eigenvalue returns it within a few n eps of the largest, of either
    sign, so "> 0" cannot be asked there, and "- a few eps" can."""
    covs = np.asarray(covs)
    np.testing.assert_array_equal(covs, np.swapaxes(covs, -1, -2))
    lam = np.linalg.eigvalsh(covs)
    n = covs.shape[-1]
    floor = -8 * n * np.finfo(covs.dtype).eps * np.max(np.abs(lam), axis=-1)
    assert np.all(lam[..., 0] >= floor), (lam[..., 0].min(), floor.min())


# ----------------------------------------------------------------------------------------------
# kalman_states="linear" (the paper's Algorithm 1): each particle samples v, a Kalman filter of
# the linear state a. A second model with the linear state feeding the sampled one (AB), the
# offset driving it (GZ) and the measurements (DY):
# v' = 0.95 v + AB a + 0.1 (u + w), a' = 0.05 v + 0.9 a + GZ (u + w) + zeta,
# y = (v + CA a + e1, a + DY (u + w) + e2)
AB, GZ, CA, DY = 0.1, 0.05, 0.3, 0.2


def _model_lin(ab=AB):
    def f(x, u, th):
        return jnp.stack([0.95 * x[0] + ab * x[1] + 0.1 * u[0],
                          0.05 * x[0] + 0.9 * x[1] + GZ * u[0]])

    def h(x, u, th):
        return jnp.stack([x[0] + CA * x[1], x[1] + DY * u[0]])

    return vj.models.Model(transition=f, observe=h, dt=0.1, state_names=("v", "a"),
                           input_names=("u",), output_names=("y1", "y2"), param_names=())


LAM_LIN = 0.9


def _linear_mpf(n, ab=AB):
    """The paper's filter on _model_lin, noise statistics unknown and forgotten (lambda 0.9), so
    that the plug-in estimates move along a path."""
    return marginalized_pf(_model_lin(ab), n, noisy_input="u", sensors=("y1",),
                           known_std={"y2": SD2}, linear_states=("a",), Q=SIG_Z ** 2,
                           kalman_states="linear",
                           niw=NiW(std0={"u": 0.5, "y1": 0.2}, forgetting=LAM_LIN))


def _batch_path_reference(xs, m0, P0z, mu, lam_w, lam_e, nus, ys, us, ab=AB):
    """Exact Gaussian conditioning, in one batch, of the linear state a along a fixed path v_t
    (t = 0 .. T-1) of _model_lin, with the plug-in noise of each step t read from the path's
    statistics at t - 1 as the paper's filter uses them (eq. 20 forgetting, eq. 23 means):
    w_t ~ N(mu_w, sigma_w^2), e1 ~ N(b, R). Variables V = (a_0, w_1..w_T-1, zeta_1..zeta_T-1),
    prior a_0 ~ N(m0, P0z) (the path's filtered moments at 0); a_t = c_t + L_t V; observed:
    v_t - 0.95 v_t-1 - 0.1 u_t = AB a_t-1 + 0.1 w_t exactly, y1_t - v_t - b = CA a_t + e1 (when
    not NaN), y2_t - DY u_t = a_t + DY w_t + e2. Returns the filtered and the smoothed means
    (T,), variances (T,) and the smoothed Cov(a_t-1, a_t) (T - 1,)."""
    T = len(xs)
    n = 2 * T - 1
    mean = np.zeros(n)
    cov = np.zeros((n, n))
    mean[0], cov[0, 0] = m0, P0z
    c, L = np.zeros(T), np.zeros((T, n))
    L[0, 0] = 1.0
    rows, vals, noise, when = [], [], [], []
    d = 2
    for t in range(1, T):
        iw, iz = t, T - 1 + t
        nu_p = LAM_LIN * nus[t - 1]
        mean[iw] = mu[t - 1, 0]
        cov[iw, iw] = LAM_LIN * lam_w[t - 1] / (nu_p - d - 1)
        cov[iz, iz] = SIG_Z**2
        R1 = LAM_LIN * lam_e[t - 1, 0, 0] / (nu_p - d - 1)
        b1 = mu[t - 1, 1]
        c[t] = 0.05 * xs[t - 1] + 0.9 * c[t - 1] + GZ * us[t]
        L[t] = 0.9 * L[t - 1]
        L[t, iw] += GZ
        L[t, iz] += 1.0
        e_w = np.zeros(n)
        e_w[iw] = 1.0
        rows.append(ab * L[t - 1] + 0.1 * e_w)
        vals.append(xs[t] - 0.95 * xs[t - 1] - 0.1 * us[t] - ab * c[t - 1])
        noise.append(0.0), when.append(t)
        if np.isfinite(ys[t, 0]):
            rows.append(CA * L[t]), vals.append(ys[t, 0] - xs[t] - CA * c[t] - b1)
            noise.append(R1), when.append(t)
        rows.append(L[t] + DY * e_w), vals.append(ys[t, 1] - DY * us[t] - c[t])
        noise.append(SD2**2), when.append(t)
    H, r, Rn, when = np.array(rows), np.array(vals), np.diag(noise), np.array(when)

    def condition(k):  # on the observations up to time k
        o = when <= k
        Ho = H[o]
        S = Ho @ cov @ Ho.T + Rn[np.ix_(o, o)]
        K = np.linalg.solve(S, Ho @ cov).T
        return mean + K @ (r[o] - Ho @ mean), cov - K @ S @ K.T

    filt_m, filt_v = np.empty(T), np.empty(T)
    for k in range(T):
        mk, Ck = condition(k)
        filt_m[k], filt_v[k] = c[k] + L[k] @ mk, L[k] @ Ck @ L[k]
    mT, CT = condition(T)
    sm_m = c + L @ mT
    sm_v = np.einsum("ti,ij,tj->t", L, CT, L)
    sm_c = np.einsum("ti,ij,tj->t", L[:-1], CT, L[1:])
    return filt_m, filt_v, sm_m, sm_v, sm_c


def test_linear_path_rts_is_the_exact_conditional_given_the_path():
    """kalman_states="linear", one fixed path (made up here: sampled states, NiW statistics
    moving along it, two NaN sensor readings) with the filtered moments of the linear state
    from batch conditioning on the data up to each t: the path's RTS (ms.linear_path_rts, which
    recomputes each step's Kalman update with ms.linear_step_joint) equals batch Gaussian
    conditioning on all the data (numpy, above) to 1e-9: smoothed means and variances and the
    lag-one covariances (a wrong filtered moment in the recomputed step would show here)."""
    rb = _linear_mpf(4).rao_blackwell
    rng = np.random.default_rng(7)
    ys, us = _data(seed=11)
    xs = np.cumsum(0.3 * rng.normal(size=T))[:, None]
    mu = np.stack([0.3 + 0.1 * rng.normal(size=T), 0.2 + 0.05 * rng.normal(size=T)], 1)
    nus = 8.0 + np.arange(T) * 0.5
    lam_w = (0.5 + rng.uniform(size=T)) * 0.3 * nus
    lam_e = ((0.5 + rng.uniform(size=T)) * 0.02 * nus)[:, None, None]
    fm, fv, sm_m, sm_v, sm_c = _batch_path_reference(xs[:, 0], -0.1, 0.07, mu, lam_w, lam_e,
                                                    nus, ys, us[:, 0])
    theta = jnp.asarray(rb.theta, float)
    zs, Ps, cross = map(np.asarray, jax.jit(functools.partial(ms.linear_path_rts, rb, theta))(
        ys, us, nus, xs, fm[:, None], fv[:, None, None], mu, lam_w, lam_e))
    assert np.isnan(ys[NAN_STEPS[0], 0])
    np.testing.assert_allclose(zs[:, 0], sm_m, rtol=0, atol=1e-9)
    np.testing.assert_allclose(Ps[:, 0, 0], sm_v, rtol=0, atol=1e-9)
    np.testing.assert_allclose(cross[:, 0, 0], sm_c, rtol=0, atol=1e-9)
    # the smoothing did something: the smoothed differ from the filtered beyond 1e-9
    assert np.max(np.abs(sm_m[:-1] - fm[:-1])) > 1e-3
    assert np.all(sm_v[:-1] < fv[:-1])


@pytest.mark.slow  # the filter twice (its own scan and inside vj.smooth): about a minute on 2 cores
def test_linear_one_path_of_the_filter_is_the_exact_conditional():
    """The smoother with M = 1 on the paper's filter (kalman_states="linear", statistics unknown
    and forgotten, two sensor readings missing), its backward pass over a forward pass kept
    here: the one path's particles (``path_indices``) are those followed back through that
    pass's genealogy, its sampled states are theirs, with zero smoothed variance, and its linear
    state's smoothed means, variances and lag-one covariances equal batch Gaussian conditioning
    along that path (numpy, from the path's own statistics and filtered moments at t = 0) to
    1e-9."""
    ys, us = _data(seed=4)
    est = _linear_mpf(30)
    key = jax.random.key(3)
    # the forward pass once; the smoother's backward pass reads these very particles, so what
    # it followed is told by the indices it carries, not by matching floats across programs
    sts = jax.jit(lambda k: ms.forward(est, jnp.asarray(ys), jnp.asarray(us), jnp.asarray(X0),
                                       jnp.asarray(P0), None, k))(key)
    sm = jax.jit(lambda f, k: ms.backward(est, f, ys, us, key=k, n_trajectories=1))(sts, key)
    x = np.asarray(sts.x)[:, 0]  # (T, N)
    anc = np.asarray(sts.ancestors)
    path = np.asarray(sm.path_states)[0]
    # the path's particles as the smoother carries them: the genealogy followed here gives the
    # same indices, and the path's sampled states are those particles' (the same arrays)
    idx = np.empty(T, int)
    idx[-1] = np.asarray(sm.path_indices)[0, -1]
    for t in range(T - 1, 0, -1):
        idx[t - 1] = anc[t, idx[t]]
    np.testing.assert_array_equal(np.asarray(sm.path_indices)[0], idx)
    tt = np.arange(T)
    np.testing.assert_array_equal(path[:, 0], x[tt, idx])
    mu = np.asarray(sts.mu)[tt, :, idx]
    lam_w = np.asarray(sts.lam_w)[tt, idx]
    lam_e = np.asarray(sts.lam_e)[tt, :, :, idx]
    z0, P0z = np.asarray(sts.z)[0, 0, idx[0]], np.asarray(sts.P)[0, 0, 0, idx[0]]
    assert np.ptp(mu[:, 0]) > 1e-3  # the plug-in offset mean moves along the path
    _, _, sm_m, sm_v, sm_c = _batch_path_reference(
        x[tt, idx], z0, P0z, mu, lam_w, lam_e, np.asarray(sts.nu), ys, us[:, 0])
    np.testing.assert_allclose(path[:, 1], sm_m, rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.asarray(sm.states), path, rtol=0, atol=1e-12)
    cov = np.asarray(sm.covariances)
    np.testing.assert_allclose(cov[:, 1, 1], sm_v, rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.asarray(sm.cross_covariances)[:, 1, 1], sm_c, rtol=0,
                               atol=1e-9)
    assert np.all(cov[:, 0, :] == 0.0)


def _data_exact(seed=3):
    """One run of _model_lin without the linear state in v (AB = 0), noise as _data's: the
    "linear" filter with its noise known is then the exact Rao-Blackwellised filter (module
    docstring of the smoother)."""
    rng = np.random.default_rng(seed)
    us = np.sin(0.3 * np.arange(T))[:, None]
    x = rng.multivariate_normal(X0, P0)
    ys = np.empty((T, 2))
    for t in range(T):
        w = MU_W + SIG_W * rng.normal()
        u = us[t, 0] + w
        x = np.array([0.95 * x[0] + 0.1 * u, 0.05 * x[0] + 0.9 * x[1] + GZ * u
                      + SIG_Z * rng.normal()])
        ys[t] = [x[0] + CA * x[1] + B1 + SD1 * rng.normal(), x[1] + DY * u + SD2 * rng.normal()]
    ys[list(NAN_STEPS), 0] = np.nan
    return ys, us


def kalman_rts_exact(ys, us):
    """Textbook Kalman filter and RTS smoother of _model_lin with AB = 0 and its noise known,
    on the state (v, a, w_t) (w_t enters the transition and y2 alike). Returns smoothed means
    (T, 2), covariances (T, 2, 2) and lag-one covariances G_t P_t+1|T (T - 1, 2, 2) of
    (v, a)."""
    F = np.array([[0.95, 0.0, 0.0], [0.05, 0.9, 0.0], [0.0, 0.0, 0.0]])
    g = np.array([0.1, GZ, 1.0])
    Q = SIG_W**2 * np.outer(g, g) + np.diag([0.0, SIG_Z**2, 0.0])
    H = np.array([[1.0, CA, 0.0], [0.0, 1.0, DY]])
    R = np.diag([SD1**2, SD2**2])
    x, P = np.r_[X0, 0.0], np.zeros((3, 3))
    P[:2, :2] = P0
    xp, Pp, xf, Pf = [], [], [], []
    for t in range(len(ys)):
        x, P = F @ x + g * (us[t, 0] + MU_W) - np.r_[0.0, 0.0, us[t, 0]], F @ P @ F.T + Q
        xp.append(x), Pp.append(P)
        o = np.isfinite(ys[t])
        Ho = H[o]
        S = Ho @ P @ Ho.T + R[np.ix_(o, o)]
        K = np.linalg.solve(S, Ho @ P).T
        off = np.array([B1, DY * us[t, 0]])[o]
        x, P = x + K @ (ys[t][o] - off - Ho @ x), P - K @ S @ K.T
        xf.append(x), Pf.append(P)
    xs, Ps, C = _rts_backward(F, xf, Pf, xp, Pp)
    return xs[:, :2], Ps[:, :2, :2], C[:, :2, :2]


@functools.lru_cache(maxsize=None)
def _smoothed_linear(n, reps=8, method=None):
    ys, us = _data_exact()
    est = marginalized_pf(_model_lin(ab=0.0), n, noisy_input="u", sensors=("y1",),
                          known_std={"y2": SD2}, linear_states=("a",), Q=SIG_Z ** 2,
                          kalman_states="linear",
                          niw=NiW(std0={"u": SIG_W, "y1": SD1}, mean0={"u": MU_W, "y1": B1},
                                  forgetting=1.0, nu0=1e7, gamma0=1e-9))

    def one(key):
        return vj.smooth(est, ys, us, x0=X0, P0=P0, key=key,
                         method=vj.smoothers.methods.BY_NAME[method or "ancestor"](
                             n_trajectories=n))  # None: the marginalized PF's ancestor paths

    keys = jax.random.split(jax.random.key(5), reps)
    return jax.jit(jax.vmap(one))(keys)


@pytest.mark.slow  # two MPF + smoother compiles: `pytest -m slow`
def test_linear_smoothed_states_converge_to_the_rts_smoother():
    """kalman_states="linear" (the paper's filter), noise known, a model on which it is the
    exact Rao-Blackwellised filter (the linear state does not enter the sampled one; the offset
    drives both states and y2 directly): the smoothed means of both states (two sensor readings
    missing) are within Monte-Carlo error of the numpy RTS of the whole linear-Gaussian system
    (z of the 8 replicates' mean, RMS < 2) at N = M = 50 and 400, the error shrinks with N
    (expected ratio sqrt(8) = 2.8; asserted > 1.8), and at N = 400 the covariances are within
    Monte-Carlo error of the RTS's, the lag-one covariances too (the wrong lag rejected)."""
    ys, us = _data_exact()
    m, P, C = kalman_rts_exact(ys, us)
    sd = np.sqrt(np.diagonal(P, axis1=1, axis2=2))
    rms, zr = {}, {}
    for n in (50, 400):
        sm = _smoothed_linear(n)
        assert not np.any(sm.diverged)
        rms[n] = float(np.sqrt(np.mean(((np.asarray(sm.states) - m) / sd) ** 2)))
        zr[n] = _z_rms(sm.states, m)
    sm = _smoothed_linear(400)
    print("linear: z-RMS", zr, "error / sd", rms, "cov z", _z_rms(sm.covariances, P),
          "lag-one z", _z_rms(sm.cross_covariances, C), "wrong lag z",
          _z_rms(sm.cross_covariances, P[1:]))
    assert zr[50] < 2.0 and zr[400] < 2.0, zr
    assert rms[50] / rms[400] > 1.8, rms
    assert rms[400] < 0.2, rms
    assert _z_rms(sm.covariances, P) < 2.0
    assert _z_rms(sm.cross_covariances, C) < 2.0
    assert _z_rms(sm.cross_covariances, P[1:]) > 4.0


@pytest.mark.slow  # the bank model's MPF compiles for about a minute on 2 cores
def test_linear_step_joint_is_the_filters_kalman_step_on_single_track_bank():
    """The paper's filter (kalman_states="linear") on SingleTrackBank, 40 steps of simulated
    data with the bank angle phi a known-std output that is NaN at every step and a yaw-gyro
    reading missing at two steps: for every particle and step, ms.linear_step_joint from its
    parent's stored state (the genealogy) gives the filter's own Kalman mean and covariance of
    the bank at t in its z_t block (the sampled states have two components, the bank enters
    them off the steering direction, so this checks the projection on g, the used output rows,
    the known variances and the plug-in statistics as the filter has them), and a joint
    covariance that is positive semi-definite."""
    model = vj.models.SingleTrackBank(dt=0.01)
    Tb = 40
    U, Y = _bank_drive(model, Tb, np.array([0.0, 0.0, 0.02, 0.0, 0.0]), seed=1)
    names = list(model.output_names)
    Y[:, names.index("phi")] = np.nan
    Y[[9, 25], names.index("r")] = np.nan
    n = 16
    est = marginalized_pf(model, n, known_std={"phi": 0.01, "r_virt": 0.005},
                          Q=0.05 ** 2, kalman_states="linear",
                          niw=NiW(std0={"delta": 0.01, "ay": 0.4, "r": 0.02, "roll_rate": 0.02}))
    P0b = np.diag([0.1, 0.01, 1e-2, 1e-3, 1e-4]) ** 2
    fwd = jax.jit(lambda k: ms.forward(est, jnp.asarray(Y), jnp.asarray(U), jnp.zeros(5),
                                        jnp.asarray(P0b), None, k))(jax.random.key(4))
    rb = est.rao_blackwell
    theta = jnp.asarray(rb.theta, float)
    anc = np.asarray(fwd.ancestors)
    par = anc[1:]  # (T - 1, N): the parent of slot j at t, at t - 1

    def prev(a):  # (T, ..., N) -> (T - 1, N, ...) at the parents
        a = np.moveaxis(np.asarray(a), -1, 1)[:-1]
        return a[np.arange(Tb - 1)[:, None], par]

    def now(a):
        return np.moveaxis(np.asarray(a), -1, 1)[1:]

    joint = jax.jit(jax.vmap(jax.vmap(
        lambda *a: ms.linear_step_joint(rb, theta, *a),
        in_axes=(0, 0, 0, 0, 0, 0, None, 0, None, None)),
        in_axes=(0, 0, 0, 0, 0, 0, 0, 0, 0, 0)))
    mean, cov = map(np.asarray, joint(
        prev(fwd.x), prev(fwd.z), prev(fwd.P), prev(fwd.mu), prev(fwd.lam_w), prev(fwd.lam_e),
        np.asarray(fwd.nu)[:-1], now(fwd.x), Y[1:], U[1:]))
    z_f, P_f = now(fwd.z), now(fwd.P)  # (T - 1, N, 3), (T - 1, N, 3, 3)
    assert not bool(np.any(np.asarray(fwd.bad)))
    np.testing.assert_allclose(mean[..., 3:], z_f, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(cov[..., 3:, 3:], P_f, rtol=1e-8, atol=1e-14)
    # z_t-1 given the data up to t: the parent's filtered mean moves (the smoothing signal)
    assert np.max(np.abs(mean[..., :3] - prev(fwd.z))) > 0
    assert np.min(np.linalg.eigvalsh(cov)) > -1e-12 * np.max(np.abs(cov))


# ----------------------------------------------------------------------------------------------
# method="ffbsi" (kalman_states="linear"): Rao-Blackwellised backward simulation


def _joint_next_reference(vj_, aj, Pj, muw, bj, lw, le, gamma, nu, u, lam, ab=AB):
    """numpy: mean and covariance of (v_t+1, y1_t+1, y2_t+1) of _model_lin given one particle
    (v_j, a ~ N(a_j, P_j)) with w ~ N(mu_w, var_w), zeta ~ N(0, SIG_Z^2), e1 ~ N(b, R),
    e2 ~ N(0, SD2^2), the variances the moment-matched NiW predictive's after forgetting:
    (1 + gamma / lam) lam Lambda / (lam nu - d - 1), d = 2. Written from the model equations
    with the variables (a, w, zeta, e1, e2)."""
    c = (1.0 + gamma / lam) * lam / (lam * nu - 2 - 1)
    var = np.diag([Pj, c * lw, SIG_Z**2, c * le, SD2**2])
    mean_v = np.array([aj, muw, 0.0, bj, 0.0])
    # v' = 0.95 v + ab a + 0.1 (u + w); a' = 0.05 v + 0.9 a + GZ (u + w) + zeta
    v1 = np.array([ab, 0.1, 0.0, 0.0, 0.0]), 0.95 * vj_ + 0.1 * u
    a1 = np.array([0.9, GZ, 1.0, 0.0, 0.0]), 0.05 * vj_ + GZ * u
    y1 = v1[0] + CA * a1[0] + np.array([0, 0, 0, 1.0, 0]), v1[1] + CA * a1[1]
    y2 = a1[0] + DY * np.array([0, 1.0, 0, 0, 0]) + np.array([0, 0, 0, 0, 1.0]), a1[1] + DY * u
    H = np.stack([v1[0], y1[0], y2[0]])
    off = np.array([v1[1], y1[1], y2[1]])
    return off + H @ mean_v, H @ var @ H.T


def test_backward_density_is_the_gaussian_of_the_next_state_and_measurement():
    """ms.backward_logdens on made-up particles of the paper's filter on _model_lin (its linear
    state entering the sampled one, the offset entering y2 directly): for every (trajectory,
    particle) pair the log density of (v_t+1, y_t+1) from a numpy/scipy transcription of the
    model equations, up to one constant common to all pairs (2 pi's), also with y1 missing."""
    from scipy.stats import multivariate_normal

    rb = _linear_mpf(4).rao_blackwell
    rng = np.random.default_rng(2)
    n, m = 5, 3
    x = rng.normal(0.0, 0.3, (1, n))
    z = rng.normal(0.0, 0.2, (1, n))
    P = rng.uniform(0.01, 0.05, (1, 1, n))
    mu = np.stack([0.3 + 0.1 * rng.normal(size=n), 0.2 + 0.05 * rng.normal(size=n)])
    lw = rng.uniform(2.0, 4.0, n)
    le = rng.uniform(0.1, 0.3, (1, 1, n))
    gamma, nu, u = 0.2, 12.0, np.array([0.4])
    x_next = rng.normal(0.0, 0.3, (1, m))
    f = jax.jit(functools.partial(ms.backward_logdens, rb, jnp.asarray(rb.theta, float)))
    for y in (np.array([0.3, -0.1]), np.array([np.nan, -0.1])):
        got = np.asarray(f(x, z, P, mu, lw, le, gamma, nu, u, y, x_next))
        o = np.r_[True, np.isfinite(y)]
        ref = np.empty((m, n))
        for j in range(n):
            mean, cov = _joint_next_reference(x[0, j], z[0, j], P[0, 0, j], mu[0, j], mu[1, j],
                                              lw[j], le[0, 0, j], gamma, nu, u[0], LAM_LIN)
            for k in range(m):
                val = np.r_[x_next[0, k], y][o]
                ref[k, j] = multivariate_normal(mean[o], cov[np.ix_(o, o)]).logpdf(val)
        const = ref - got
        np.testing.assert_allclose(const, const[0, 0], rtol=0, atol=1e-6)
        assert np.ptp(got) > 1.0  # the pairs differ


@pytest.mark.slow  # the filter's forward pass and the re-run compile: about 30 s on 2 cores
def test_linear_path_forward_along_ancestral_paths_is_the_filter():
    """ms.linear_path_forward (the Kalman filter of the linear state and the NiW statistics
    re-run along a path, as FFBSi does for its stitched trajectories) along the filter's own
    ancestral paths (statistics unknown and forgotten, two sensor readings missing) gives the
    filter's stored means, covariances and statistics at every step (1e-12)."""
    ys, us = _data(seed=4)
    n = 30
    est = _linear_mpf(n)
    rb = est.rao_blackwell
    theta = jnp.asarray(rb.theta, float)
    fwd = jax.jit(lambda k: ms.forward(est, jnp.asarray(ys), jnp.asarray(us), jnp.asarray(X0),
                                        jnp.asarray(P0), None, k))(jax.random.key(3))
    idx = np.asarray(ms.trace_ancestors(fwd.ancestors, jnp.arange(n)))  # (T, n)
    tt = np.arange(T)[:, None]

    def take(a):  # (T, ..., N) -> (n, T, ...)
        return np.moveaxis(np.moveaxis(np.asarray(a), -1, 1)[tt, idx], 1, 0)

    xs, zs, Ps, mu, lw, le = map(take, (fwd.x, fwd.z, fwd.P, fwd.mu, fwd.lam_w, fwd.lam_e))
    assert len(np.unique(idx[0])) < n  # the paths share their beginnings
    out = jax.jit(jax.vmap(lambda x, *a: ms.linear_path_forward(
        rb, theta, jnp.asarray(ys), jnp.asarray(us), fwd.gamma, fwd.nu, x, *a)))(
        xs, zs[:, 0], Ps[:, 0], mu[:, 0], lw[:, 0], le[:, 0])
    assert np.ptp(mu[:, :, 0]) > 1e-3  # the plug-in offset mean moves
    for got, ref in zip(out, (zs, Ps, mu, lw, le)):
        np.testing.assert_allclose(np.asarray(got), ref, rtol=1e-12, atol=1e-12)


@pytest.mark.slow  # four MPF + smoother compiles, about a minute each on 2 cores
def test_ffbsi_converges_to_the_rts_smoother_and_spreads_early():
    """method="ffbsi" on the model where the paper's filter with known noise is the exact
    Rao-Blackwellised filter (as test_linear_smoothed_states_converge_to_the_rts_smoother):
    the smoothed means are within Monte-Carlo error of the numpy RTS (z of the 8 replicates'
    mean, RMS < 2) at N = M = 50 and 400, their error shrinks with N (expected sqrt(8) = 2.8,
    asserted > 1.8) and is below ancestor tracing's at both N, the covariances and the
    trajectories' lag-one covariances at N = 400 within Monte-Carlo error of the RTS's (the
    wrong lag rejected), and at t = 0 the trajectories pass through more particles than the
    ancestral paths, by slot and by value, with backward weights of ESS > 1 at every step.
    The backward weights ignore what the data after t + 1 say about the linear state (module
    docstring): on this model that is within the Monte-Carlo error here."""
    ys, us = _data_exact()
    m, P, C = kalman_rts_exact(ys, us)
    sd = np.sqrt(np.diagonal(P, axis1=1, axis2=2))
    err, zr = {}, {}
    for method in ("ffbsi", "ancestor"):
        for n in (50, 400):
            sm = _smoothed_linear(n, method=method)
            assert not np.any(sm.diverged)
            err[method, n] = float(np.sqrt(np.mean(((np.asarray(sm.states) - m) / sd) ** 2)))
            zr[method, n] = _z_rms(sm.states, m)
    print("error / sd", err, "z-RMS", zr)
    assert zr["ffbsi", 50] < 2.0 and zr["ffbsi", 400] < 2.0, zr
    assert err["ffbsi", 50] / err["ffbsi", 400] > 1.8, err
    assert err["ffbsi", 50] < err["ancestor", 50] and err["ffbsi", 400] < err["ancestor", 400]
    ff, an = _smoothed_linear(400, method="ffbsi"), _smoothed_linear(400, method="ancestor")
    assert _z_rms(ff.covariances, P) < 2.0
    assert _z_rms(ff.cross_covariances, C) < 2.0
    assert _z_rms(ff.cross_covariances, P[1:]) > 4.0
    for n in (50, 400):
        ff, an = _smoothed_linear(n, method="ffbsi"), _smoothed_linear(n, method="ancestor")
        assert np.all(np.asarray(ff.n_unique)[:, 0] > np.asarray(an.n_unique)[:, 0])
        assert np.mean(ff.n_distinct[:, 0]) > np.mean(an.n_distinct[:, 0])
        assert np.all(np.asarray(ff.backward_ess)[:, :-1] > 1.0)
        np.testing.assert_array_equal(np.asarray(an.backward_ess), 1.0)
        # the statistics re-run along the trajectories stay at the known values
        pr = np.asarray(ff.params)
        np.testing.assert_allclose(pr[..., 0], MU_W, rtol=1e-6)
        np.testing.assert_allclose(pr[..., 1], SIG_W, rtol=1e-4)
        np.testing.assert_allclose(pr[..., 2], B1, rtol=1e-6)
        np.testing.assert_allclose(pr[..., 3], SD1, rtol=1e-4)
