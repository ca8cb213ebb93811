"""vehjax.run's runs-last EKF and UKF/CKF steps (vehjax.filters.runs_last) against the vmapped
per-run step they replace: the same study both ways agrees to rounding, field by field."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import vehjax as vj
from vehjax.filters import ckf, ekf, ukf

R_RUNS, T = 6, 60


def _vmapped(est):
    """The same estimator with a plain step function: run vmaps it over runs."""
    return est._replace(runtime=est.runtime._replace(batch=None))


def _assert_same(a, b, rtol):
    for f in ("states", "covariances", "loglik", "nis"):
        np.testing.assert_allclose(getattr(a, f), getattr(b, f), rtol=rtol, atol=rtol, err_msg=f)
    for f in ("n_obs", "diverged", "diverged_at"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f), err_msg=f)


@pytest.fixture(scope="module")
def study():
    model = vj.models.Dynamic3DOF(dt=0.01)
    scn = vj.scenarios.sine_steer(model, speed=20.0, duration=T * model.dt)
    Q, R = np.diag([0.05, 0.05, 0.01]) ** 2, np.diag([0.2, 0.2, 0.05]) ** 2
    sim = vj.simulate(model, scn, runs=R_RUNS, key=jax.random.key(3),
                      process_std=np.sqrt(np.diag(Q)), meas_std=np.sqrt(np.diag(R)))
    ys = np.array(sim.measurements)
    ys[1, 10:20, 0] = np.nan  # one component missing
    ys[2, 30:35] = np.nan  # all missing
    x0 = np.tile(np.asarray(scn.x0) + [0.5, 0.1, 0.02], (R_RUNS, 1))
    P0 = np.diag([1.0, 0.2, 0.05]) ** 2
    return model, Q, R, ys, np.asarray(sim.inputs), x0, P0


# the cubature filter shares the unscented one's sigma-point path: `pytest -m slow`
# (the EKF's runs-last form against its step also in tests/filters/test_gaussian.py's many-runs
# test)
@pytest.mark.parametrize("build", [ukf, pytest.param(ckf, marks=pytest.mark.slow),
                                   pytest.param(ekf, marks=pytest.mark.slow)],
                         ids=["ukf", "ckf", "ekf"])
def test_runs_last_equals_vmapped_step(study, build):
    model, Q, R, ys, us, x0, P0 = study
    est = build(model, Q, R)
    assert est.batch is not None
    us_runs = np.tile(us, (R_RUNS, 1, 1)) * np.linspace(0.9, 1.1, R_RUNS)[:, None, None]
    for inputs in (us, us_runs):  # shared and per-run inputs
        kw = dict(x0=x0, P0=P0, return_covariances=True, progress=False)
        fast = vj.run(est, ys, inputs, **kw)
        ref = vj.run(_vmapped(est), ys, inputs, **kw)
        _assert_same(fast, ref, 1e-9)
        assert fast.n_obs[2, 30:35].tolist() == [0] * 5 and fast.n_obs[1, 15] == 2
        assert not fast.diverged.any()


@pytest.mark.parametrize("build", [ukf, ekf], ids=["ukf", "ekf"])
def test_runs_last_diverging_run_is_frozen_others_untouched(build):
    dt = 0.1
    model = vj.models.Model(  # NaN once the input goes negative
        transition=lambda x, u, th: jnp.stack([x[0] + dt * x[1], x[1] + dt * jnp.sqrt(u[0])]),
        observe=lambda x, u, th: x[:1], dt=dt, state_names=("p", "v"), input_names=("a",),
        output_names=("y",),
    )
    runs, steps = 4, 20
    us = np.ones((runs, steps, 1))
    us[1, 5:] = -1.0
    ys = np.cumsum(np.ones((runs, steps, 1)) * 0.1, axis=1)
    est = build(model, np.eye(2) * 1e-3, [1e-2])
    assert est.batch is not None
    kw = dict(x0=[0.0, 1.0], P0=np.eye(2), return_covariances=True, progress=False)
    fast = vj.run(est, ys, us, **kw)
    _assert_same(fast, vj.run(_vmapped(est), ys, us, **kw), 1e-12)
    assert fast.diverged.tolist() == [False, True, False, False] and fast.diverged_at[1] == 5
    np.testing.assert_array_equal(fast.states[1, 5:], np.broadcast_to(fast.states[1, 4],
                                                                       (steps - 5, 2)))
    assert np.isnan(fast.nis[1, 5:]).all() and (fast.n_obs[1, 5:] == 0).all()
    np.testing.assert_allclose(fast.states[[0, 2, 3]], vj.run(est, ys[[0, 2, 3]], us[[0, 2, 3]],
                                                              **kw).states, rtol=1e-12)


# one filter each by default (the other: `pytest -m slow`)
@pytest.mark.parametrize("build", [ukf, pytest.param(ekf, marks=pytest.mark.slow)],
                         ids=["ukf", "ekf"])
def test_runs_last_chunked_equals_one_chunk(study, build):
    model, Q, R, ys, us, x0, P0 = study
    est = build(model, Q, R)
    kw = dict(x0=x0, P0=P0, return_covariances=True, progress=False)
    one = vj.run(est, ys, us, **kw)
    # 6 runs: a full and a padded chunk
    chunked = vj.run(est, ys, us, execution=vj.Execution(chunk_size=4), **kw)
    _assert_same(chunked, one, 1e-12)


@pytest.mark.parametrize("build", [ukf, pytest.param(ekf, marks=pytest.mark.slow)],
                         ids=["ukf", "ekf"])
def test_runs_last_float32(study, build):
    model, Q, R, ys, us, x0, P0 = study
    est = build(model, Q, R)
    kw = dict(x0=x0[:4].astype(np.float32), P0=P0.astype(np.float32), progress=False,
              return_covariances=True)
    fast = vj.run(est, ys[:4].astype(np.float32), us.astype(np.float32), **kw)
    ref = vj.run(_vmapped(est), ys[:4].astype(np.float32), us.astype(np.float32), **kw)
    assert fast.states.dtype == np.float32
    _assert_same(fast, ref, 2e-4)


def test_only_small_models_and_constant_noise_get_a_runs_last_step():
    small = ukf(vj.models.Dynamic3DOF(dt=0.01), np.eye(3) * 1e-3, np.eye(3) * 1e-2)
    assert small.batch is not None
    small_model = vj.models.Dynamic3DOF(dt=0.01)
    sqrt = ukf(small_model, np.eye(3) * 1e-3, np.eye(3) * 1e-2, sqrt=True)
    assert sqrt.batch is None
    # a builder called with traced noise (tuning Q, R by gradients) keeps the vmapped step
    seen = {}

    def build(q):
        est = ukf(small_model, q, np.eye(3) * 1e-2)
        seen["runs_last"] = est.batch
        return q.sum()

    jax.jit(build)(jnp.eye(3) * 1e-3)
    assert seen["runs_last"] is None


# both with `pytest -m slow`: a third output layout through the runs-last forms (their
# equality with the step on the default outputs runs by default)
@pytest.mark.parametrize("build", [pytest.param(ukf, marks=pytest.mark.slow),
                                   pytest.param(ekf, marks=pytest.mark.slow)],
                         ids=["ukf", "ekf"])
def test_runs_last_input_dependent_outputs(study, build):
    """The 'matlab' outputs (vx, ay, r) make observe depend on the input as well (and the
    EKF's measurement Jacobian has entries that vary besides its constant ones)."""
    _, Q, R, ys, us, x0, P0 = study
    model = vj.models.Dynamic3DOF(dt=0.01, outputs="matlab")
    est = build(model, Q, R)
    us_runs = np.tile(us, (R_RUNS, 1, 1)) * np.linspace(0.9, 1.1, R_RUNS)[:, None, None]
    for inputs in (us, us_runs):
        kw = dict(x0=x0, P0=P0, return_covariances=True, progress=False)
        _assert_same(vj.run(est, ys, inputs, **kw), vj.run(_vmapped(est), ys, inputs, **kw), 1e-9)


@pytest.mark.parametrize("build, per_run_inputs", [
    pytest.param(ukf, False, marks=pytest.mark.slow),
    pytest.param(ukf, True, marks=pytest.mark.slow), (ekf, True)],
                         ids=["ukf-shared", "ukf-per-run", "ekf-per-run"])
def test_runs_last_step_reads_theta_from_state_unless_constant(study, per_run_inputs, build):
    """With ``default_theta=False`` the batch step uses each run's theta from the state; with
    True it uses model.theta as a constant. Same result when the state holds model.theta,
    different when it does not."""
    model, Q, R, ys, us, x0, P0 = study
    est = build(model, Q, R)
    n = 4
    theta = np.tile(np.asarray(model.theta), (n, 1)) * np.linspace(0.8, 1.2, n)[:, None]
    u = np.tile(us[:3][..., None], (1, 1, n)) if per_run_inputs else us[:3]  # (T, nu[, R])
    y = np.moveaxis(ys[:n, :3], 0, -1)  # (T, ny, R)

    def first_steps(th, default_theta):
        batch = est.batch(per_run_inputs, jnp.float64, default_theta)
        state = vj.filters.gaussian.GaussianState(
            jnp.asarray(x0[:n].T), jnp.broadcast_to(jnp.asarray(P0)[..., None], (3, 3, n)),
            jnp.asarray(th.T))
        prepared = jax.jit(batch.prepare)(jnp.asarray(u))
        step = jax.jit(batch.step)  # one compile, not every operation on its own
        for t in range(3):
            state, out = step(state, jnp.asarray(y[t]), jax.tree.map(lambda a: a[t], prepared))
        return np.asarray(state.x)

    nominal = np.tile(np.asarray(model.theta), (n, 1))
    np.testing.assert_allclose(first_steps(nominal, False), first_steps(nominal, True), rtol=1e-12)
    per_run = first_steps(theta, False)
    # each run's own theta, through the per-run (vmapped) step
    one_step = jax.jit(est.step)
    for r in range(n):
        s = est.init(x0[r], P0, theta[r])
        for t in range(3):
            s, _ = one_step(s, ys[r, t], u[t, :, r] if per_run_inputs else u[t])
        np.testing.assert_allclose(per_run[:, r], s.x, rtol=1e-12)
    assert np.max(np.abs(per_run - first_steps(theta, True))) > 1e-6


def test_ekf_measurement_jacobian_constants_are_the_jacobian():
    """The entries of dh/dx the runs-last EKF folds as constants are exactly those that are the
    same at random states, inputs and parameters, with those values; the others vary."""
    from vehjax.filters.runs_last import _jacobian_constants

    model = vj.models.Dynamic3DOF(dt=0.01, outputs="matlab")  # vx, ay (nonlinear), r
    h = model.observe
    consts = _jacobian_constants(h, 3, len(model.input_names), len(model.param_names),
                                 np.float64, None)
    rng = np.random.default_rng(0)
    jac = jax.jit(jax.jacfwd(h))
    J = np.stack([np.asarray(jac(jnp.asarray([15.0, 0.0, 0.0]) + rng.normal(size=3),
                                 jnp.asarray(rng.normal(size=len(model.input_names)) * 0.1),
                                 jnp.asarray(model.theta) * rng.uniform(0.8, 1.2)))
                  for _ in range(20)])
    assert consts[0] == [1.0, 0.0, 0.0] and consts[2] == [0.0, 0.0, 1.0]
    for i in range(3):
        for j in range(3):
            if consts[i][j] is None:
                assert np.ptp(J[:, i, j]) > 1e-9, (i, j)
            else:
                np.testing.assert_array_equal(J[:, i, j], consts[i][j])


def test_entrywise_algebra_equals_numpy():
    """The shared entry-by-entry algebra (vehjax.lib.entrywise) against numpy on (R,)
    entries with structural zeros and ones mixed in: products, Cholesky factors on an observed
    block, back substitution, the barrier (values unchanged), entries/stack round trip."""
    from vehjax.lib import entrywise as ew
    from vehjax.lib.linalg import forward_entries

    rng = np.random.default_rng(0)
    R = 3
    A = rng.normal(size=(3, 4, R))
    Bm = rng.normal(size=(4, 2, R))
    Ae = ew.entries(jnp.asarray(A))
    Ae[0][1], Ae[2][3], Ae[1][0] = 0.0, 1.0, 2.5  # structural constants
    A[0, 1], A[2, 3], A[1, 0] = 0.0, 1.0, 2.5
    got = ew.stack(ew.matmul(Ae, ew.entries(jnp.asarray(Bm))), jnp.zeros(R))
    np.testing.assert_allclose(got, np.einsum("ikr,kjr->ijr", A, Bm), rtol=1e-13)
    x = rng.normal(size=(4, R))
    got = ew.stack(ew.matvec(Ae, ew.entries(jnp.asarray(x))), jnp.zeros(R))
    np.testing.assert_allclose(got, np.einsum("ikr,kr->ir", A, x), rtol=1e-13)
    assert ew.dot([0.0, 0.0], [jnp.ones(R), 2.0]) == 0.0
    # Cholesky on the observed block, identity elsewhere; back substitution L^-T b
    M = rng.normal(size=(4, 4, R))
    S = np.einsum("ikr,jkr->ijr", M, M) + 4 * np.eye(4)[:, :, None]
    obs = [jnp.asarray([True, True, False]), True, jnp.asarray([True, False, True]), True]
    L = ew.chol_masked(ew.entries(jnp.asarray(S)), obs)
    L = [[L[i][j] if j <= i else 0.0 for j in range(4)] for i in range(4)]  # upper: None
    b = rng.normal(size=(4, R))
    back = ew.stack(ew.backward_entries(L, ew.entries(jnp.asarray(b))), jnp.zeros(R))
    fwd = ew.stack(forward_entries(L, ew.entries(jnp.asarray(b))), jnp.zeros(R))
    for r in range(R):
        o = np.array([bool(np.asarray(v)[r]) if np.ndim(v) else v for v in obs])
        Sr = np.where(np.outer(o, o), S[:, :, r], np.eye(4))
        Lr = np.linalg.cholesky(Sr)
        np.testing.assert_allclose(ew.stack(L, jnp.zeros(R))[:, :, r], Lr, rtol=1e-12,
                                   atol=1e-14)
        np.testing.assert_allclose(back[:, r], np.linalg.solve(Lr.T, b[:, r]), rtol=1e-11)
        np.testing.assert_allclose(fwd[:, r], np.linalg.solve(Lr, b[:, r]), rtol=1e-11)
    kept = jax.jit(lambda a: ew.barrier((a, 3.0)))(jnp.asarray(b))
    np.testing.assert_array_equal(kept[0], b)
    assert kept[1] == 3.0
