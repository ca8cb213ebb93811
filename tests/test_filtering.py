"""vehjax.filter: one run, pure and traceable; every builder agrees with vehjax.run; gradients of
the log-likelihood against central finite differences, also with missing measurements."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import vehjax as vj
from vehjax import filters as F

from _contract import DRAW_RTOL

T, RUNS = 40, 3


def _f(x, u, th):
    return jnp.stack([x[0] + 0.1 * x[1], x[1] + 0.1 * (-th[0] * jnp.sin(x[0]) - 0.3 * x[1] + u[0])])


def _h(x, u, th):
    return jnp.stack([x[0], jnp.arctan(x[1]) + 0.1 * x[0] ** 2])


MODEL = vj.models.Model(_f, _h, dt=0.1, state_names=("a", "w"), param_names=("k",),
                        input_names=("u",), output_names=("ya", "yw"), theta=[2.0])
Q = np.diag([1e-3, 4e-3])
R = np.diag([0.02, 0.05])
X0 = np.array([0.3, 0.0])
P0 = np.diag([0.05, 0.05])


def _data(seed=0, T=T, runs=RUNS):
    rng = np.random.default_rng(seed)
    us = np.sin(0.3 * np.arange(T))[:, None]
    ys = np.empty((runs, T, 2))
    for r in range(runs):
        x = X0 + rng.normal(size=2) * np.sqrt(np.diag(P0))
        for t in range(T):
            x = np.asarray(_f(x, us[t], MODEL.theta)) + rng.normal(size=2) * np.sqrt(np.diag(Q))
            ys[r, t] = np.asarray(_h(x, us[t], MODEL.theta)) + rng.normal(size=2) * np.sqrt(np.diag(R))
    return ys, us


PARAM = dict(Q_theta=[1e-4], estimate=("k",))
BUILDERS = {
    "ekf": lambda: F.ekf(MODEL, Q, R),
    "ukf": lambda: F.ukf(MODEL, Q, R),
    "ckf": lambda: F.ckf(MODEL, Q, R),
    "sr_ukf": lambda: F.ukf(MODEL, Q, R, sqrt=True),
    "sr_ckf": lambda: F.ckf(MODEL, Q, R, sqrt=True),
    "ackf": lambda: F.ackf(MODEL, Q, R),
    "bootstrap_pf": lambda: F.bootstrap_pf(MODEL, Q, R, n_particles=64),
    "dual_ekf": lambda: F.dual_ekf(MODEL, Q, R, **PARAM),
    "dual_ukf": lambda: F.dual_ukf(MODEL, Q, R, **PARAM),
    "joint_ekf": lambda: F.joint_ekf(MODEL, Q, R, **PARAM),
    "joint_ukf": lambda: F.joint_ukf(MODEL, Q, R, **PARAM),
    "liu_west_ukf": lambda: F.liu_west_ukf(MODEL, Q, R, n_particles=32, estimate="k",
                                           theta_low=[1.0], theta_high=[3.0]),
}


@pytest.mark.parametrize("name", [
    # Liu-West: the slowest compile here; its run/filter agreement also in
    # tests/filters/test_liu_west.py
    pytest.param(n, marks=pytest.mark.slow) if n == "liu_west_ukf" else n for n in BUILDERS])
def test_filter_and_run_agree_for_every_builder(name):
    est = BUILDERS[name]()
    ys, us = _data()
    ys[1, 5:9, 0] = np.nan  # some missing components
    prior = {}
    if est.param_names and est.param_prior is None:
        prior = dict(theta0=np.array([1.6]), P_theta0=np.array([[0.2]]))
    key = jax.random.key(7) if est.needs_key else None
    out = vj.run(est, ys, us, x0=X0, P0=P0, key=key, return_covariances=True, progress=False,
                 **prior)
    keys = jax.random.split(key, RUNS) if key is not None else [None] * RUNS
    for r in range(RUNS):
        one = vj.filter(est, ys[r], us, x0=X0, P0=P0, key=keys[r], **prior)
        # two programs: a filter that draws random numbers agrees to its float32 draws'
        # rounding (tests/_contract.py), the others to float64 rounding
        rtol = DRAW_RTOL if est.needs_key else 1e-9
        tol = dict(rtol=rtol, atol=1e-12)
        np.testing.assert_allclose(one.states, out.states[r], **tol)
        # an entry near zero (an off-diagonal covariance) carries the error of the largest
        cov_atol = rtol * float(np.max(np.abs(out.covariances[r]))) if est.needs_key else 1e-12
        np.testing.assert_allclose(one.covariances, out.covariances[r], rtol=rtol, atol=cov_atol)
        np.testing.assert_allclose(one.params, out.params[r], **tol)
        np.testing.assert_allclose(one.params_cov, out.params_cov[r], **tol)
        np.testing.assert_allclose(float(one.loglik.sum()), out.loglik[r], rtol=rtol)
        np.testing.assert_allclose(one.nis, out.nis[r], **tol)
        np.testing.assert_array_equal(one.n_obs, out.n_obs[r])
        assert bool(one.diverged) == bool(out.diverged[r]) and int(one.diverged_at) == out.diverged_at[r]
    assert np.asarray(out.n_obs)[1, 5:9].tolist() == [1] * 4


def test_filter_jits_and_vmaps():
    est = F.ukf(MODEL, Q, R)
    ys, us = _data()
    batched = jax.jit(jax.vmap(lambda y: vj.filter(est, y, us, x0=X0, P0=P0)))(jnp.asarray(ys))
    assert batched.states.shape == (RUNS, T, 2) and batched.loglik.shape == (RUNS, T)
    single = vj.filter(est, ys[2], us, x0=X0, P0=P0)
    np.testing.assert_allclose(batched.states[2], single.states, rtol=1e-12)
    assert isinstance(single.state, F.GaussianState)


def _ukf_loglik(r_diag, ys, us):
    est = F.ukf(MODEL, Q, jnp.diag(r_diag))  # built inside: R traced
    return vj.filter(est, ys, us, x0=X0, P0=P0).loglik.sum()


@pytest.mark.parametrize("missing", [0.0, 0.3])
def test_grad_of_ukf_loglik_wrt_R_matches_central_differences(missing):
    ys, us = _data(seed=3, runs=1)
    ys = ys[0]
    if missing:
        mask = np.random.default_rng(1).random(ys.shape) < missing
        ys = np.where(mask, np.nan, ys)
        assert 0.2 < mask.mean() < 0.4
    r0 = np.diag(R).copy()
    grad = np.asarray(jax.jit(jax.grad(_ukf_loglik))(jnp.asarray(r0), ys, us))
    assert np.all(np.isfinite(grad))
    ll = jax.jit(_ukf_loglik)
    for i in range(2):
        e = np.zeros(2)
        e[i] = 1e-6 * r0[i]
        fd = (float(ll(r0 + e, ys, us)) - float(ll(r0 - e, ys, us))) / (2 * e[i])
        assert abs(grad[i] - fd) <= 1e-5 * abs(fd), (i, grad[i], fd)


@pytest.mark.parametrize("build", [F.ekf, F.ckf, lambda m, q, r: F.ukf(m, q, r, sqrt=True)],
                         ids=["ekf", "ckf", "sr_ukf"])
def test_grads_wrt_Q_theta_and_x0_are_finite_with_missing_data(build):
    ys, us = _data(seed=4, runs=1)
    ys = ys[0].copy()
    ys[::3, 1] = np.nan

    def loglik(q_diag, k, x0):
        est = build(MODEL, jnp.diag(q_diag), R)
        res = vj.filter(est, ys, us, x0=x0, P0=P0, theta0=jnp.stack([k]))
        return res.loglik.sum()

    g = jax.jit(jax.grad(loglik, argnums=(0, 1, 2)))(jnp.diag(Q), 2.0, jnp.asarray(X0))
    for leaf in g:
        assert np.all(np.isfinite(np.asarray(leaf)))
    # and d/dk against central differences
    ll = jax.jit(loglik)
    fd = (float(ll(jnp.diag(Q), 2.0 + 1e-6, X0)) - float(ll(jnp.diag(Q), 2.0 - 1e-6, X0))) / 2e-6
    assert abs(float(g[1]) - fd) <= 1e-5 * abs(fd) + 1e-6


def test_filter_checks_shapes():
    est = F.ukf(MODEL, Q, R)
    ys, us = _data(runs=1)
    with pytest.raises(ValueError, match="^measurements:"):
        vj.filter(est, ys, us, x0=X0, P0=P0)  # (1, T, ny): that is a study
    with pytest.raises(ValueError, match="^measurements:"):
        vj.filter(est, ys[0, :, :1], us, x0=X0, P0=P0)
    with pytest.raises(ValueError, match="^inputs:"):
        vj.filter(est, ys[0], us[:-1], x0=X0, P0=P0)
    with pytest.raises(ValueError, match="^inputs:"):
        vj.filter(est, ys[0], None, x0=X0, P0=P0)
    with pytest.raises(ValueError, match="^x0:"):
        vj.filter(est, ys[0], us, x0=X0[:1], P0=P0)
    with pytest.raises(ValueError, match="^key:"):
        vj.filter(BUILDERS["bootstrap_pf"](), ys[0], us, x0=X0, P0=P0)
    with pytest.raises(ValueError, match="^P_theta0:"):
        vj.filter(BUILDERS["dual_ekf"](), ys[0], us, x0=X0, P0=P0)


def test_liu_west_needs_no_theta0():
    est = BUILDERS["liu_west_ukf"]()
    ys, us = _data()
    out = vj.run(est, ys, us, x0=X0, P0=P0, key=jax.random.key(0), progress=False)
    assert out.params.shape == (RUNS, T, 1) and np.all(np.isfinite(out.params))
    assert np.all((out.params > 1.0) & (out.params < 3.0))


@pytest.mark.slow  # a dual EKF and a simulation compiled for a shape check: `pytest -m slow` (README)
def test_dual_filter_without_theta0_reports_its_parameters():
    """theta0 omitted (a dual filter starts from the model's nominal values): params has the
    estimated parameters' width, not (T, 0), and starts at the nominal values."""
    from vehjax.filters import dual_ekf

    m = vj.models.KinematicBicycle(dt=0.05)
    est = dual_ekf(m, np.full(4, 1e-3), np.full(4, 1e-2), Q_theta=np.full(2, 1e-6), estimate=("lf", "lr"))
    sim = vj.simulate(m, vj.scenarios.sine_steer(m, speed=5.0, duration=2.0), runs=1,
                      meas_std=0.1, key=jax.random.key(0))
    r = vj.filter(est, sim.measurements[0], sim.inputs, x0=np.asarray(sim.states[0, 0]),
                  P0=np.full(4, 0.1), P_theta0=np.eye(2) * 0.01)
    assert r.params.shape == (40, 2) and r.params_cov.shape == (40, 2, 2)
    lf, lr = (float(m.theta[i]) for i in m.param_index(("lf", "lr")))
    np.testing.assert_allclose(r.params[0], [lf, lr], atol=1e-3)
