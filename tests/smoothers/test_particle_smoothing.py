"""Particle smoothing (vehjax.smoothers.particle) against references written here: the
Kalman filter and RTS smoother of a linear-Gaussian model from the textbook recursion in numpy,
and backward-sampling probabilities computed in numpy."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import vehjax as vj
from vehjax.smoothers import particle as ps

from _contract import DRAW_RTOL

# x' = A x + B u + w, y = H x + v: position and velocity, position measured
A = np.array([[1.0, 0.1], [0.0, 0.9]])
B = np.array([[0.0], [0.1]])
H = np.array([[1.0, 0.0]])
Q = np.array([[0.02, 0.005], [0.005, 0.05]])
R = np.array([[0.1]])
X0 = np.array([0.5, -0.2])
P0 = np.diag([0.5, 0.3])
T = 20
NAN_STEPS = (4, 11)  # measurements missing there


def _model():
    f = lambda x, u, th: jnp.asarray(A) @ x + jnp.asarray(B) @ u  # noqa: E731
    h = lambda x, u, th: jnp.asarray(H) @ x  # noqa: E731
    return vj.models.Model(transition=f, observe=h, dt=0.1, state_names=("p", "v"),
                           input_names=("u",), output_names=("y",), param_names=())


def _data(T=T, seed=3):
    """One run simulated in numpy (its own generator), with NAN_STEPS missing."""
    rng = np.random.default_rng(seed)
    us = rng.normal(size=(T, 1))
    x = rng.multivariate_normal(X0, P0)
    ys = np.empty((T, 1))
    for t in range(T):
        x = A @ x + B @ us[t] + rng.multivariate_normal(np.zeros(2), Q)
        ys[t] = H @ x + rng.multivariate_normal(np.zeros(1), R)
    ys[[s for s in NAN_STEPS if s < T]] = np.nan
    return ys, us


def kalman_rts(ys, us):
    """Textbook Kalman filter (step t: predict with u_t, update with y_t, NaN skipped) and RTS
    smoother. Returns smoothed means (T, nx), covariances (T, nx, nx) and lag-one covariances
    P_{t,t+1|T} = G_t P_{t+1|T} (T-1, nx, nx)."""
    n = len(ys)
    x, P = X0.copy(), P0.copy()
    xp, Pp, xf, Pf = [], [], [], []
    for t in range(n):
        x, P = A @ x + B @ us[t], A @ P @ A.T + Q
        xp.append(x), Pp.append(P)
        obs = np.isfinite(ys[t])
        if obs.any():
            Ho = H[obs]
            S = Ho @ P @ Ho.T + R[np.ix_(obs, obs)]
            K = np.linalg.solve(S, Ho @ P).T
            x, P = x + K @ (ys[t][obs] - Ho @ x), P - K @ S @ K.T
        xf.append(x), Pf.append(P)
    xs, Ps, C = [None] * n, [None] * n, [None] * (n - 1)
    xs[-1], Ps[-1] = xf[-1], Pf[-1]
    for t in range(n - 2, -1, -1):
        G = np.linalg.solve(Pp[t + 1], A @ Pf[t]).T  # P_t|t A^T P_t+1|t^-1
        xs[t] = xf[t] + G @ (xs[t + 1] - xp[t + 1])
        Ps[t] = Pf[t] + G @ (Ps[t + 1] - Pp[t + 1]) @ G.T
        C[t] = G @ Ps[t + 1]
    return np.array(xs), np.array(Ps), np.array(C)


@functools.lru_cache(maxsize=None)
def _smoothed(n, reps=8):
    """FFBSi and rejection smoothing of one data set with N = M = n, over `reps` keys (the same
    key gives both methods the same filter run)."""
    ys, us = _data()
    est = vj.filters.bootstrap_pf(_model(), Q, R, n_particles=n)

    def both(key):
        kw = dict(x0=X0, P0=P0, key=key, n_trajectories=n)
        return (ps.smooth(est, ys, us, method="ffbsi", **kw),
                ps.smooth(est, ys, us, method="rejection", max_tries=4, **kw))

    keys = jax.random.split(jax.random.key(11), reps)
    return jax.jit(jax.vmap(both))(keys)


def _z_rms(est, ref):
    """RMS over entries of (replicate mean - ref) / (its standard error from the replicates'
    spread); about 1 (a t-distribution with reps - 1 dof per entry) when est is unbiased."""
    est = np.asarray(est)
    se = est.std(axis=0, ddof=1) / np.sqrt(est.shape[0])
    return float(np.sqrt(np.mean(((est.mean(axis=0) - ref) / se) ** 2)))


@pytest.mark.slow  # a convergence study at two particle counts: `pytest -m slow` (README)
def test_ffbsi_means_converge_to_the_rts_smoother():
    """FFBSi's smoothed means (with two missing measurements) against the numpy RTS: the
    replicates' mean is within Monte-Carlo error of the RTS (z-scores from the replicates'
    spread, RMS < 2 where ~1.2 is expected for 8 replicates), and the error shrinks with
    N = M from 50 to 400 close to 1/sqrt(N) (expected ratio sqrt(8) = 2.8; asserted > 1.8)."""
    ys, us = _data()
    m, P, _ = kalman_rts(ys, us)
    sd = np.sqrt(np.diagonal(P, axis1=1, axis2=2))
    rms = {}
    for n in (50, 400):
        ff, _ = _smoothed(n)
        assert ff.states.shape == (8, T, 2) and ff.trajectories.shape == (8, n, T, 2)
        assert not np.any(ff.diverged)
        rms[n] = float(np.sqrt(np.mean(((np.asarray(ff.states) - m) / sd) ** 2)))
        assert _z_rms(ff.states, m) < 2.0, n
    assert rms[50] / rms[400] > 1.8, rms
    # in units of the smoothed std, 400 independent draws would give 0.05
    assert rms[400] < 0.25, rms


@pytest.mark.slow  # a Monte-Carlo study: `pytest -m slow` (README)
def test_ffbsi_covariance_and_lag_one_covariance_match_the_rts():
    """The trajectories' covariances and lag-one covariances Cov(x_t, x_t+1 | y) against the
    RTS's P_t|T and G_t P_t+1|T, within Monte-Carlo error (z RMS < 2, as above); and a
    lag-one covariance of the wrong lag (P_t+1|T itself) is rejected by the same test."""
    ys, us = _data()
    _, P, C = kalman_rts(ys, us)
    ff, _ = _smoothed(400)
    assert ff.cross_covariances.shape == (8, T - 1, 2, 2)
    assert _z_rms(ff.covariances, P) < 2.0
    assert _z_rms(ff.cross_covariances, C) < 2.0
    assert _z_rms(ff.cross_covariances, P[1:]) > 4.0
    # the reported moments are those of the trajectories
    traj = np.asarray(ff.trajectories[0])
    d = traj - traj.mean(axis=0)
    np.testing.assert_allclose(ff.cross_covariances[0, 3], d[:, 3].T @ d[:, 4] / 399, rtol=1e-10)


@pytest.mark.slow  # two particle-smoother compiles compared in distribution: `pytest -m slow` (README)
def test_rejection_sampling_agrees_with_ffbsi():
    """Same filter runs (same keys), backward draws by rejection with 4 tries and the exact
    fallback: means and covariances agree with FFBSi's within Monte-Carlo error (z of the
    paired differences, RMS < 2), and both proposals and fallbacks were used. At the last
    time both take the same draw from the final filter weights."""
    for n in (50, 400):
        ff, rj = _smoothed(n)
        np.testing.assert_array_equal(ff.loglik, rj.loglik)
        np.testing.assert_array_equal(ff.trajectories[:, :, -1], rj.trajectories[:, :, -1])
        diff = np.asarray(rj.states - ff.states)[:, :-1]
        assert _z_rms(diff, 0.0) < 2.0, n
        dcov = np.asarray(rj.covariances - ff.covariances)[:, :-1]
        assert _z_rms(dcov, 0.0) < 2.0, n
        fb = np.asarray(rj.fallbacks)
        assert fb[:, -1].sum() == 0 and np.all(ff.fallbacks == 0)
        assert 0 < fb.sum() < 0.9 * fb[:, :-1].size * n, n


def _backward_probs(lw, fx, xn, L):
    """numpy: p_i proportional to W_i N(xn; fx_i, L L^T)."""
    Qm = L @ L.T
    d = xn[:, None] - fx
    q = np.einsum("in,ij,jn->n", d, np.linalg.inv(Qm), d)
    p = np.exp(lw - 0.5 * q - np.max(lw - 0.5 * q))
    return p / p.sum()


@pytest.mark.parametrize("method", ["ffbsi", "rejection"])
def test_one_backward_step_draws_from_the_backward_kernel(method):
    """One backward step with 20000 trajectories at the same next state: the frequencies of the
    drawn indices pass a chi-square test (p > 0.001) against W_i N(x'; f(x_i), Q) computed in
    numpy; the rejection sampler also with a fallback for some trajectories."""
    rng = np.random.default_rng(5)
    n, m = 6, 20000
    L = np.linalg.cholesky(Q)
    fx = rng.normal(scale=0.2, size=(2, n))
    lw = np.log(rng.dirichlet(np.ones(n)))
    xn = np.array([0.05, -0.1])
    p = _backward_probs(lw, fx, xn, L)
    key = jax.random.key(2)
    xm = np.repeat(xn[:, None], m, axis=1)
    if method == "ffbsi":
        idx = jax.jit(lambda: ps.ffbsi_indices(key, lw, ps.transition_logdens(L, fx, xm)))()
    else:
        Li = np.linalg.inv(L)
        idx, fb = jax.jit(lambda: ps.rejection_indices(key, lw, Li @ xm, Li @ fx, 2))()
        assert 0 < int(fb) < m
    counts = np.bincount(np.asarray(idx), minlength=n)
    chi2 = float(np.sum((counts - m * p) ** 2 / (m * p)))
    assert chi2 < 20.5, (counts, m * p)  # chi-square 5 dof, 0.999 quantile


def test_transition_logdens_is_the_gaussian_log_density_up_to_its_constant():
    rng = np.random.default_rng(1)
    L = np.linalg.cholesky(Q)
    fx, xn = rng.normal(size=(2, 4)), rng.normal(size=(2, 3))
    got = np.asarray(ps.transition_logdens(L, fx, xn))
    from scipy.stats import multivariate_normal
    const = -0.5 * np.log(np.linalg.det(2 * np.pi * Q))
    want = np.array([[multivariate_normal(fx[:, i], Q).logpdf(xn[:, j]) - const
                      for i in range(4)] for j in range(3)])
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)


def test_ancestor_tracing_is_degenerate_as_documented():
    """Resampling at every step (T = 40, N = M = 100): the traced genealogies coalesce, the
    number of distinct particles never grows backwards in time (an exact property of ancestor
    tracing) and is at most 10 of 100 at t = 0 (FFBSi's trajectories, measured on the same
    data with 4 keys, pass through 32-97 there); the traced paths are genealogies: x_t+1 - A x_t - B u_t+1 is the
    filter's process noise, of Mahalanobis size about 1 per state under Q (a wrong pairing
    gives the filter's spread, several times larger); the log-likelihood is vehjax.filter's
    with the same key (to its float32 draws' rounding)."""
    ys, us = _data(T=40)
    n = 100
    est = vj.filters.bootstrap_pf(_model(), Q, R, n_particles=n,
                                  resampling=vj.filters.Resampling(ess_threshold=1.0))
    an = jax.jit(lambda: ps.smooth(est, ys, us, x0=X0, P0=P0, key=jax.random.key(4),
                                   method="ancestor", n_trajectories=n))()
    nu = np.asarray(an.n_unique)
    assert np.all(np.diff(nu) >= 0), nu
    assert nu[0] <= 10 and nu[-1] > 40, nu
    traj = np.asarray(an.trajectories)
    w = traj[:, 1:] - traj[:, :-1] @ A.T - (us[1:] @ B.T)[None]
    maha = np.einsum("mti,ij,mtj->mt", w, np.linalg.inv(Q), w) / 2
    assert maha.mean() < 1.5, maha.mean()
    wrong = traj[:, 1:] - traj[::-1, :-1] @ A.T - (us[1:] @ B.T)[None]
    assert np.einsum("mti,ij,mtj->mt", wrong, np.linalg.inv(Q), wrong).mean() / 2 > 3.0
    fr = vj.filter(est, ys, us, x0=X0, P0=P0, key=jax.random.key(4))
    # two programs drawing the same float32 normals: equal to their rounding (_contract.py)
    np.testing.assert_allclose(an.loglik, fr.loglik, rtol=DRAW_RTOL, atol=1e-12)
    assert not an.diverged and np.all(np.isfinite(an.states))


def test_a_diverging_run_is_flagged_and_does_not_poison_the_batch():
    """Two runs smoothed under one vmap, the second with a measurement 10^4 off (every
    particle's likelihood underflows, the filter re-initialises): that run is flagged and finite,
    and the first run's smoothing is the same, bit for bit, as when its neighbour is a clean
    copy of it (one compiled program, called twice)."""
    ys, us = _data()
    bad = ys.copy()
    bad[8] = 1e4
    est = vj.filters.bootstrap_pf(_model(), Q, R, n_particles=50)
    key = jax.random.key(11)
    both = jax.jit(jax.vmap(lambda y: ps.smooth(est, y, us, x0=X0, P0=P0, key=key,
                                                n_trajectories=50)))
    out, ref = both(np.stack([ys, bad])), both(np.stack([ys, ys]))
    np.testing.assert_array_equal(out.diverged, [False, True])
    np.testing.assert_array_equal(ref.diverged, [False, False])
    assert np.all(np.isfinite(out.trajectories)) and np.all(np.isfinite(out.loglik))
    assert np.sum(out.loglik[1]) < np.sum(ref.loglik[1]) - 100.0  # the 10^4 measurement seen
    np.testing.assert_array_equal(out.states[0], ref.states[0])
    np.testing.assert_array_equal(out.trajectories[0], ref.trajectories[0])
    np.testing.assert_array_equal(out.loglik[0], ref.loglik[0])


def test_float32_priors_smooth_in_float32():
    ys, us = _data(T=4)
    est = vj.filters.bootstrap_pf(_model(), Q, R, n_particles=16)
    out = jax.jit(lambda: ps.smooth(est, ys.astype(np.float32), us.astype(np.float32),
                                    x0=X0.astype(np.float32), P0=P0.astype(np.float32),
                                    key=jax.random.key(0), method="rejection",
                                    n_trajectories=8))()
    assert out.trajectories.dtype == jnp.float32 and out.covariances.dtype == jnp.float32
    assert out.trajectories.shape == (8, 4, 2) and np.all(np.isfinite(out.trajectories))


def test_bad_input_names_the_argument():
    ys, us = _data(T=5)
    pf = vj.filters.bootstrap_pf(_model(), Q, R, n_particles=10)
    kw = dict(x0=X0, P0=P0, key=jax.random.key(0))
    with pytest.raises(ValueError, match="n_trajectories"):
        ps.smooth(pf, ys, us, n_trajectories=0, **kw)
    with pytest.raises(ValueError, match="method"):
        ps.smooth(pf, ys, us, method="forward-backward", **kw)
    with pytest.raises(ValueError, match="max_tries"):
        ps.smooth(pf, ys, us, method="rejection", max_tries=0, **kw)
    with pytest.raises(ValueError, match="estimator"):
        ps.smooth(vj.filters.ukf(_model(), Q, R), ys, us, **kw)
    with pytest.raises(ValueError, match="estimator"):
        ps.smooth("bootstrap_pf", ys, us, **kw)
    noisy_input = vj.filters.bootstrap_pf(_model(), Q, R, n_particles=10, input_noise={"u": 0.1})
    with pytest.raises(ValueError, match="estimator.*input"):
        ps.smooth(noisy_input, ys, us, **kw)
    singular = vj.filters.bootstrap_pf(_model(), np.diag([0.0, 0.05]), R, n_particles=10)
    with pytest.raises(ValueError, match="estimator.*semi-definite"):
        ps.smooth(singular, ys, us, **kw)
    with pytest.raises(ValueError, match="measurements"):
        ps.smooth(pf, ys[:, 0], us, **kw)
    with pytest.raises(ValueError, match="inputs"):
        ps.smooth(pf, ys, us[:3], **kw)
    with pytest.raises(ValueError, match="x0"):
        ps.smooth(pf, ys, us, x0=np.zeros(3), P0=P0, key=jax.random.key(0))
    with pytest.raises(ValueError, match="key"):
        ps.smooth(pf, ys, us, x0=X0, P0=P0, key=None)
