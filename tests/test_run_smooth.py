"""vehjax.run(..., smooth=...): a whole study smoothed with run's chunking, blocking and
divergence flags, equal to the textbook RTS smoother (numpy, written here) run by run."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import vehjax as vj
from vehjax import execution

DT = 0.1
F = np.array([[1.0, DT], [0.0, 0.95]])
B = np.array([[0.0], [DT]])
H = np.array([[1.0, 0.0], [0.0, 1.0]])
Q = np.array([[1e-3, 2e-4], [2e-4, 4e-3]])
R = np.diag([0.05, 0.02])
X0 = np.array([0.2, -0.1])
P0 = np.diag([0.3, 0.2])

MODEL = vj.models.Model(lambda x, u, th: jnp.asarray(F) @ x + jnp.asarray(B) @ u,
                        lambda x, u, th: jnp.asarray(H) @ x, dt=DT, state_names=("p", "v"),
                        input_names=("a",), output_names=("p", "v"))


def rts(ys, us, x0=None):
    """Kalman filter (predict with u_t, update with the observed part of y_t) from x0 (default
    X0) then the Rauch-Tung-Striebel recursion: smoothed means, covariances and
    Cov(x_t, x_t+1 | y)."""
    T = len(ys)
    mf, Pf, mp, Pp = [], [], [], []
    m, P = (X0 if x0 is None else np.asarray(x0)).copy(), P0.copy()
    for t in range(T):
        m, P = F @ m + B @ us[t], F @ P @ F.T + Q
        mp.append(m), Pp.append(P)
        o = ~np.isnan(ys[t])
        if o.any():
            Ho = H[o]
            S = Ho @ P @ Ho.T + R[np.ix_(o, o)]
            K = P @ Ho.T @ np.linalg.inv(S)
            m = m + K @ (ys[t][o] - Ho @ m)
            P = P - K @ S @ K.T
        mf.append(m), Pf.append(P)
    ms, Ps, cross = [mf[-1]], [Pf[-1]], []
    for t in range(T - 2, -1, -1):
        G = Pf[t] @ F.T @ np.linalg.inv(Pp[t + 1])
        ms.insert(0, mf[t] + G @ (ms[0] - mp[t + 1]))
        cross.insert(0, G @ Ps[0])
        Ps.insert(0, Pf[t] + G @ (Ps[0] - Pp[t + 1]) @ G.T)
    return np.array(ms), np.array(Ps), np.array(cross)


def _data(runs=5, steps=15, seed=0):
    rng = np.random.default_rng(seed)
    us = np.sin(0.3 * np.arange(steps))[:, None]
    ys = np.empty((runs, steps, 2))
    for r in range(runs):
        x = X0 + rng.normal(size=2) * np.sqrt(np.diag(P0))
        for t in range(steps):
            x = F @ x + B @ us[t] + rng.multivariate_normal(np.zeros(2), Q)
            ys[r, t] = H @ x + rng.normal(size=2) * np.sqrt(np.diag(R))
    if runs > 2:
        ys[2, 3, 0] = ys[2, 7] = np.nan  # missing components and a whole missing step
    return ys, us


def test_smoothed_study_equals_the_textbook_rts_run_by_run():
    ys, us = _data()
    for est in (vj.filters.ekf(MODEL, Q, R), vj.filters.ukf(MODEL, Q, R)):
        # in chunks of 2 and, inside them, blocks (the CPU rule forced small)
        strat = execution.for_platform("cpu")._replace(block_numbers=1)
        out = vj.run(est, ys, us, x0=X0, P0=P0, smooth=True, return_covariances=True,
                     execution=vj.Execution(chunk_size=2, strategy=strat))
        filt = vj.run(est, ys, us, x0=X0, P0=P0)
        assert out.cross_covariances.shape == (5, 14, 2, 2) and "smoothed" in out.name
        for r in range(5):
            ms, Ps, cross = rts(ys[r], us)
            np.testing.assert_allclose(out.states[r], ms, rtol=1e-9, atol=1e-11)
            np.testing.assert_allclose(out.covariances[r], Ps, rtol=1e-9, atol=1e-11)
            np.testing.assert_allclose(out.cross_covariances[r], cross, rtol=1e-9, atol=1e-11)
        np.testing.assert_allclose(out.loglik, filt.loglik, rtol=1e-10)
        np.testing.assert_array_equal(out.n_obs, filt.n_obs)
        assert not out.diverged.any()
        one = vj.smooth(est, ys[2], us, x0=X0, P0=P0)
        np.testing.assert_allclose(out.states[2], one.states, rtol=1e-10, atol=1e-12)


def test_a_diverging_run_is_flagged_and_the_others_are_untouched():
    ys, us = _data()
    bad = ys.copy()
    bad[3, 5:] = 1e200  # the filter's covariance stays finite, its mean and loglik do not
    est = vj.filters.ekf(MODEL, Q, R)
    out = vj.run(est, bad, us, x0=X0, P0=P0, smooth="rts")
    good = vj.run(est, ys, us, x0=X0, P0=P0, smooth=True)
    assert out.diverged.tolist() == [False, False, False, True, False]
    keep = [0, 1, 2, 4]
    np.testing.assert_array_equal(out.states[keep], good.states[keep])
    assert np.isfinite(out.states).all()


def test_bad_smooth_is_refused_naming_it():
    ys, us = _data(runs=2, steps=5)
    est = vj.filters.ekf(MODEL, Q, R)
    for smooth in ("bogus", 3, "ipls"):  # ipls needs a sigma-point filter
        with pytest.raises(ValueError, match="smooth"):
            vj.run(est, ys, us, x0=X0, P0=P0, smooth=smooth)
    pf = vj.filters.bootstrap_pf(MODEL, Q, R, n_particles=16)
    with pytest.raises(ValueError, match="smooth"):
        vj.run(pf, ys, us, x0=X0, P0=P0, smooth=True, key=jax.random.key(0))


#: a pendulum-like model: the iterated smoothers' passes move its linearisation
NONLINEAR = vj.models.Model(
    lambda x, u, th: jnp.stack([x[0] + DT * x[1], 0.95 * x[1] - DT * jnp.sin(x[0]) + DT * u[0]]),
    lambda x, u, th: jnp.stack([jnp.sin(x[0]), x[1]]), dt=DT, state_names=("p", "v"),
    input_names=("a",), output_names=("p", "v"))


def test_run_smooths_with_a_methods_record_as_vehjax_smooth_does():
    """``run(smooth=)`` takes vehjax.smooth's method records with their options: per run the
    same numbers as ``vehjax.smooth(method=<the record>)``; a name is its record's defaults."""
    from vehjax.smoothers import IEKS, IPLS, RTS

    ys, us = _data(runs=3, steps=12)
    ekf, ukf = vj.filters.ekf(NONLINEAR, Q, R), vj.filters.ukf(NONLINEAR, Q, R)
    kw = dict(x0=X0, P0=P0, return_covariances=True)
    for est, rec in ((ekf, IEKS(max_iter=1)),               # one pass: short of the fixed point
                     (ekf, IEKS(tol=1e-12, parallel="doubling")),
                     (ukf, IPLS(max_iter=2, parallel=True)),
                     (ekf, RTS(parallel="doubling"))):
        out = vj.run(est, ys, us, smooth=rec, **kw)
        assert out.name == f"{est.name} ({rec.name} smoothed)"
        for r in range(3):
            one = vj.smooth(est, ys[r], us, x0=X0, P0=P0, method=rec)
            for got, want in ((out.states[r], one.states), (out.covariances[r], one.covariances),
                              (out.cross_covariances[r], one.cross_covariances),
                              (out.loglik[r], one.loglik.sum())):
                np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
    # the options are honoured: one pass is not the default's converged smoother
    one_pass = vj.run(ekf, ys, us, smooth=IEKS(max_iter=1), **kw)
    default = vj.run(ekf, ys, us, smooth="ieks", **kw)
    assert np.max(np.abs(one_pass.states - default.states)) > 1e-6
    compiled = vj.compile_run(ekf, ys, us, smooth=IEKS(max_iter=1), **kw)()  # its signature
    np.testing.assert_array_equal(compiled.states, one_pass.states)
    for name, cls in (("rts", RTS), ("ieks", IEKS)):
        by_name, by_record = (vj.run(ekf, ys, us, smooth=m, **kw) for m in (name, cls()))
        for field in ("states", "covariances", "cross_covariances", "loglik", "diverged"):
            np.testing.assert_array_equal(getattr(by_name, field), getattr(by_record, field))
        assert by_name.name == by_record.name
    np.testing.assert_array_equal(vj.run(ekf, ys, us, smooth=True, **kw).states,
                                  vj.run(ekf, ys, us, smooth=RTS(), **kw).states)


def test_run_refuses_the_particle_smoothers_and_a_start_naming_smooth():
    from vehjax.smoothers import IEKS, IPLS, RTS, AncestorPaths, FFBSi, RejectionSampling

    ys, us = _data(runs=2, steps=5)
    est = vj.filters.ekf(MODEL, Q, R)
    pf = vj.filters.bootstrap_pf(MODEL, Q, R, n_particles=16)
    for rec in (FFBSi(), RejectionSampling(max_tries=3), AncestorPaths(n_trajectories=5),
                "ffbsi"):
        name = type(vj.smoothers.methods.record(rec)).__name__
        for e, key in ((est, None), (pf, jax.random.key(0))):
            with pytest.raises(ValueError, match=f"^smooth: {name} is a particle smoother.*"
                                                 f"vehjax.smooth"):
                vj.run(e, ys, us, x0=X0, P0=P0, key=key, smooth=rec)
    with pytest.raises(ValueError, match="^smooth: method: 'ipls' iterates sigma-point"):
        vj.run(est, ys, us, x0=X0, P0=P0, smooth=IPLS())
    with pytest.raises(ValueError, match="^smooth.initial: .*vehjax.smooth"):
        vj.run(est, ys, us, x0=X0, P0=P0, smooth=IEKS(initial=np.zeros((5, 2))))
    with pytest.raises(ValueError, match="^smooth: expected"):
        vj.run(est, ys, us, x0=X0, P0=P0, smooth=RTS)  # the class, not a record


def test_runs_last_smoothing_equals_the_vmapped_one_with_per_run_inputs():
    """The runs-last forward and backward pass of ``run(smooth=True)`` (CPU strategy, filters
    with a runs-last form) against the vmapped ``smooth_one_run`` (runs_last off) and the numpy
    RTS, with inputs, x0 and P0 per run and NaN components."""
    ys, us = _data(runs=3, steps=12, seed=4)
    rng = np.random.default_rng(5)
    us_r = us[None] + 0.1 * rng.normal(size=(3,) + us.shape)
    x0s = X0 + 0.05 * rng.normal(size=(3, 2))
    est = vj.filters.ckf(MODEL, Q, R)
    assert est.batch is not None
    cpu = execution.for_platform("cpu")
    kw = dict(x0=x0s, P0=np.broadcast_to(P0, (3, 2, 2)), smooth=True, return_covariances=True)
    fast = vj.run(est, ys, us_r, execution=vj.Execution(strategy=cpu), **kw)
    slow = vj.run(est, ys, us_r, execution=vj.Execution(strategy=cpu._replace(runs_last=False)), **kw)
    for name in ("states", "covariances", "cross_covariances", "loglik"):
        np.testing.assert_allclose(getattr(fast, name), getattr(slow, name), rtol=1e-12,
                                   atol=1e-14)
    np.testing.assert_array_equal(fast.diverged, slow.diverged)
    assert not fast.diverged.any()
    for r in range(3):
        ms, Ps, cross = rts(ys[r], us_r[r], x0s[r])
        np.testing.assert_allclose(fast.states[r], ms, rtol=1e-9, atol=1e-11)
        np.testing.assert_allclose(fast.covariances[r], Ps, rtol=1e-9, atol=1e-11)
        np.testing.assert_allclose(fast.cross_covariances[r], cross, rtol=1e-9, atol=1e-11)


def test_runs_last_divergence_test_equals_the_per_run_one():
    """smoothing._good_runs_last (entry by entry, runs last) against the per-run rule written
    with numpy: finite means and cross-covariances, finite positive definite covariances (one
    run's covariance indefinite, one run's mean NaN, one run's cross-covariance inf)."""
    from vehjax.smoothing import _good_runs_last

    rng = np.random.default_rng(7)
    T, n, R = 4, 3, 6
    A = rng.normal(size=(T, R, n, n))
    P = A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(n)
    P[2, 1] = np.diag([1.0, -0.5, 2.0])  # indefinite
    M, cross = rng.normal(size=(T, R, n)), rng.normal(size=(T - 1, R, n, n))
    M[0, 3, 1] = np.nan
    cross[1, 4, 0, 2] = np.inf
    def last(a):
        return jnp.moveaxis(jnp.asarray(a), 1, -1)

    got = jax.jit(_good_runs_last)(last(M), last(P), last(cross))

    def pd(S):
        return bool(np.all(np.linalg.eigvalsh(S) > 0))

    want = [bool(np.isfinite(M[:, r]).all() and np.isfinite(cross[:, r]).all()
                 and all(pd(P[t, r]) for t in range(T))) for r in range(R)]
    assert want == [True, False, True, False, False, True]
    assert np.asarray(got).tolist() == want
