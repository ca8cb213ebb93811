"""vehjax.run against plain numpy Kalman recursions, run by run and step by step."""

import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import vehjax  # noqa: F401  (float64)
from vehjax import execution
from vehjax.execution import Execution
from vehjax.filters.base import Dims, Estimator, ParamSpec, Runtime, StepOutput
from vehjax.run import RunResult, compile_run, run
from vehjax.runner import plan as plan_mod
from vehjax.runtime import eager

DT = 0.1
F = np.array([[1.0, DT], [0.0, 1.0]])
B = np.array([[0.5 * DT**2], [DT]])
H = np.array([[1.0, 0.0], [0.3, 1.0]])
Q = np.array([[0.02, 0.005], [0.005, 0.03]])
RN = np.array([[0.5, 0.1], [0.1, 0.2]])
R_RUNS, T = 3, 40
X0 = np.array([0.5, -1.0])
P0 = np.array([[2.0, 0.3], [0.3, 1.0]])


def kalman_estimator(F, B, H, Q, Rn, name="kf", param_view=False, needs_key=False):
    """Exact linear Kalman filter following the Estimator contract, NaN-masked update.

    Missing components get a zero row in H, a zero innovation and a unit, uncorrelated noise
    variance, which leaves the observed components' update exact. With ``param_view`` the first
    state is also reported as the (single) estimated parameter.
    """
    F, B, H, Q, Rn = map(jnp.asarray, (F, B, H, Q, Rn))
    nx, ny = F.shape[0], H.shape[0]

    def init(x0, P0, theta0, P_theta0, key):
        return (x0, P0)

    def step(state, y, u):
        x, P = state
        x = F @ x + B @ u
        P = F @ P @ F.T + Q
        obs = ~jnp.isnan(y)
        Hm = jnp.where(obs[:, None], H, 0.0)
        Rm = jnp.where(obs[:, None] & obs[None, :], Rn, jnp.eye(ny))
        v = jnp.where(obs, y - H @ x, 0.0)
        S = Hm @ P @ Hm.T + Rm
        L = jnp.linalg.cholesky(S)
        K = jax.scipy.linalg.cho_solve((L, True), Hm @ P).T
        x = x + K @ v
        A = jnp.eye(nx) - K @ Hm
        P = A @ P @ A.T + K @ Rm @ K.T
        P = 0.5 * (P + P.T)
        z = jax.scipy.linalg.solve_triangular(L, v, lower=True)
        nis = z @ z
        n = jnp.sum(obs)
        ll = -0.5 * (nis + 2.0 * jnp.sum(jnp.log(jnp.diag(L))) + n * jnp.log(2.0 * jnp.pi))
        if param_view:
            params, pcov = x[:1], P[:1, :1]
        else:
            params, pcov = jnp.zeros(0), jnp.zeros((0, 0))
        return (x, P), StepOutput(x, P, ll, nis, n, params, pcov)

    return Estimator(init, step, Dims(nx), name, ParamSpec(("a",) if param_view else ()),
                     Runtime(needs_key=needs_key))


def numpy_kf(ys, us, x0, P0):
    """One run, plainly: predict with u_t, update with the observed components of y_t."""
    x, P = np.array(x0, float), np.array(P0, float)
    means, covs, lls, niss, nobs = [], [], [], [], []
    for y, u in zip(ys, us):
        x = F @ x + B @ u
        P = F @ P @ F.T + Q
        o = ~np.isnan(y)
        ll = nis = 0.0
        if o.any():
            Ho, Ro = H[o], RN[np.ix_(o, o)]
            v = y[o] - Ho @ x
            S = Ho @ P @ Ho.T + Ro
            K = P @ Ho.T @ np.linalg.inv(S)
            x = x + K @ v
            P = (np.eye(2) - K @ Ho) @ P
            nis = float(v @ np.linalg.solve(S, v))
            ll = -0.5 * (nis + np.log(np.linalg.det(S)) + o.sum() * np.log(2 * np.pi))
        means.append(x)
        covs.append(P)
        lls.append(ll)
        niss.append(nis)
        nobs.append(o.sum())
    return np.array(means), np.array(covs), np.sum(lls), np.array(niss), np.array(nobs)


EST = kalman_estimator(F, B, H, Q, RN)


def _data(R=R_RUNS, seed=0):
    rng = np.random.default_rng(seed)
    us = rng.normal(size=(R, T, 1))
    ys = rng.normal(size=(R, T, 2)) + np.linspace(0, 3, T)[None, :, None]
    ys[0, 5, 1] = np.nan  # partial
    ys[1, 7] = np.nan  # full
    ys[2, 10:13, 0] = np.nan
    return ys, us


def _assert_close(a: RunResult, b: RunResult, rtol=1e-12):
    for f in RunResult._fields:
        if f in ("name", "param_names"):
            continue
        x, y = getattr(a, f), getattr(b, f)
        if x is None or y is None:
            assert x is None and y is None, f
        else:
            assert x.shape == y.shape, f
            np.testing.assert_allclose(x, y, rtol=rtol, atol=1e-12, err_msg=f)


def test_matches_numpy_kalman_filter_run_by_run():
    ys, us = _data()
    out = run(EST, ys, us, x0=X0, P0=P0, return_covariances=True)
    assert out.states.shape == (R_RUNS, T, 2) and out.covariances.shape == (R_RUNS, T, 2, 2)
    assert out.params.shape == (R_RUNS, T, 0) and out.params_cov.shape == (R_RUNS, T, 0, 0)
    assert out.name == "kf"
    for r in range(R_RUNS):
        m, C, ll, nis, nobs = numpy_kf(ys[r], us[r], X0, P0)
        np.testing.assert_allclose(out.states[r], m, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(out.covariances[r], C, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(out.loglik[r], ll, rtol=1e-10)
        np.testing.assert_allclose(out.nis[r], nis, rtol=1e-10, atol=1e-12)
        np.testing.assert_array_equal(out.n_obs[r], nobs)
    assert out.n_obs[0, 5] == 1 and out.n_obs[1, 7] == 0 and out.nis[1, 7] == 0.0
    assert not out.diverged.any() and (out.diverged_at == -1).all()


def test_shared_and_per_run_arguments_agree():
    ys, us = _data()
    x0s = X0 + np.arange(R_RUNS)[:, None] * np.array([1.0, -0.5])
    P0s = P0 * (1.0 + np.arange(R_RUNS))[:, None, None]
    tiled_us = np.broadcast_to(us[0], us.shape)
    kw = dict(return_covariances=True)
    per_run = run(EST, ys, tiled_us, x0=np.tile(X0, (R_RUNS, 1)), P0=np.tile(P0, (R_RUNS, 1, 1)), **kw)
    shared = run(EST, ys, us[0], x0=X0, P0=P0, **kw)
    _assert_close(per_run, shared)
    distinct = run(EST, ys, tiled_us, x0=x0s, P0=P0s, **kw)
    for r in range(R_RUNS):
        m, C, *_ = numpy_kf(ys[r], us[0], x0s[r], P0s[r])
        np.testing.assert_allclose(distinct.states[r], m, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(distinct.covariances[r], C, rtol=1e-10, atol=1e-12)


def test_covariances_only_when_asked():
    ys, us = _data()
    out = run(EST, ys, us, x0=X0, P0=P0)
    assert out.covariances is None and out.params_cov is None
    full = run(EST, ys, us, x0=X0, P0=P0, return_covariances=True)
    np.testing.assert_array_equal(out.states, full.states)


def test_all_missing_run_is_open_loop_prediction():
    ys, us = _data()
    ys[1] = np.nan
    out = run(EST, ys, us, x0=X0, P0=P0, return_covariances=True)
    x, P, pred, covs = X0.copy(), P0.copy(), [], []
    for u in us[1]:
        x, P = F @ x + B @ u, F @ P @ F.T + Q
        pred.append(x)
        covs.append(P)
    np.testing.assert_allclose(out.states[1], np.array(pred), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(out.covariances[1], np.array(covs), rtol=1e-12, atol=1e-12)
    assert (out.n_obs[1] == 0).all() and out.loglik[1] == 0.0 and (out.nis[1] == 0.0).all()
    assert not out.diverged.any()


def test_diverging_run_is_flagged_and_frozen_others_untouched():
    ys, us = _data()
    bad = ys.copy()
    bad[1, 12, 0] = 1e300  # the update sends this run's mean to inf/NaN
    out = run(EST, bad, us, x0=X0, P0=P0, return_covariances=True)
    np.testing.assert_array_equal(out.diverged, [False, True, False])
    np.testing.assert_array_equal(out.diverged_at, [-1, 12, -1])
    # run 1 holds its last good estimate; nis/n_obs/loglik stop at the divergence
    held = np.broadcast_to(out.states[1, 11], (T - 12, 2))
    np.testing.assert_array_equal(out.states[1, 12:], held)
    held_cov = np.broadcast_to(out.covariances[1, 11], (T - 12, 2, 2))
    np.testing.assert_array_equal(out.covariances[1, 12:], held_cov)
    assert np.isnan(out.nis[1, 12:]).all() and (out.n_obs[1, 12:] == 0).all()
    m, _, ll_before, _, _ = numpy_kf(bad[1, :12], us[1, :12], X0, P0)
    np.testing.assert_allclose(out.states[1, :12], m, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(out.loglik[1], ll_before, rtol=1e-10)
    assert np.isfinite(out.states).all() and np.isfinite(out.loglik).all()
    # the other runs are bit for bit what the same study without the bad data gives
    clean = run(EST, ys, us, x0=X0, P0=P0, return_covariances=True)
    for f in ("states", "covariances", "loglik", "nis", "n_obs"):
        np.testing.assert_array_equal(getattr(out, f)[[0, 2]], getattr(clean, f)[[0, 2]])


def _corrupting(est, threshold=50.0):
    """Returns a covariance that is not positive definite whenever |y_0| > threshold."""

    def step(state, y, u):
        new, out = est.step(state, y, u)
        flip = jnp.abs(y[0]) > threshold
        return new, out._replace(cov=jnp.where(flip, -out.cov, out.cov))

    return est._replace(step=step, name="corrupting", runtime=est.runtime._replace(batch=None))


def test_non_positive_definite_covariance_flags_divergence():
    ys, us = _data()
    ys[0, 0, 0] = 100.0  # at the first step: holds the prior
    ys[2, 20, 0] = -100.0
    out = run(_corrupting(EST), ys, us, x0=X0, P0=P0, return_covariances=True)
    np.testing.assert_array_equal(out.diverged, [True, False, True])
    np.testing.assert_array_equal(out.diverged_at, [0, -1, 20])
    np.testing.assert_array_equal(out.states[0], np.broadcast_to(X0, (T, 2)))
    np.testing.assert_array_equal(out.covariances[0], np.broadcast_to(P0, (T, 2, 2)))
    assert out.loglik[0] == 0.0
    np.testing.assert_array_equal(out.states[2, 20:], np.broadcast_to(out.states[2, 19], (T - 20, 2)))
    m, *_ = numpy_kf(ys[1], us[1], X0, P0)
    np.testing.assert_allclose(out.states[1], m, rtol=1e-10, atol=1e-12)


def test_chunked_equals_unchunked_and_progress(capsys):
    ys, us = _data(R=7, seed=3)
    whole = run(EST, ys, us, x0=X0, P0=P0, return_covariances=True)
    assert capsys.readouterr().err == ""  # one chunk: no bar by default
    for chunk in (3, 100):
        part = run(EST, ys, us, x0=X0, P0=P0, return_covariances=True,
                   execution=Execution(chunk_size=chunk))
        _assert_close(part, whole)
    err = capsys.readouterr().err
    assert "chunk 3/3" in err and "7/7 runs" in err and ", ," not in err
    run(EST, ys, us, x0=X0, P0=P0, return_covariances=True,
        execution=Execution(chunk_size=3), progress=False)
    assert capsys.readouterr().err == ""


def test_runs_in_blocks_equal_runs_side_by_side():
    """A chunk's runs go through in blocks of the strategy's ``block_numbers`` carried numbers
    (the CPU rule, for filters with a large state, e.g. particles): the same results as all
    runs vmapped at once (the GPU rule), per-run keys included, also when the block does not
    divide the chunk."""
    est = _key_reporting_estimator()
    ys, us = _data(R=10, seed=6)
    key = jax.random.key(3)
    side_by_side = execution.for_platform("cpu")._replace(block_numbers=None)
    whole = run(est, ys, us, x0=X0, P0=P0, key=key, execution=Execution(strategy=side_by_side))
    kf = run(EST, ys, us, x0=X0, P0=P0, return_covariances=True)
    tiny = execution.for_platform("cpu")._replace(block_numbers=1)  # blocks of 4 runs
    plan = plan_mod.plan(EST, ys, us, X0, P0, None, None, None, False, None,
                         Execution(strategy=tiny))
    assert plan.block == 4 < plan.chunk == 10
    assert plan_mod.plan(EST, ys, us, X0, P0, None, None, None, False, None,
                         Execution(strategy="gpu")).block is None
    blocked = run(est, ys, us, x0=X0, P0=P0, key=key, execution=Execution(strategy=tiny))
    np.testing.assert_array_equal(blocked.states, whole.states)
    _assert_close(run(EST, ys, us, x0=X0, P0=P0, return_covariances=True,
                      execution=Execution(strategy=tiny)), kf)


def test_blocks_are_balanced():
    """Runs go in as few blocks as the block size allows, as even as they can be: 20 runs at
    a block of 19 are two blocks of 10 (not 19 and 1 padded to 19: 38 runs computed)."""
    balanced = plan_mod.balanced_blocks
    assert balanced(20, 19) == (2, 10)
    assert balanced(10, 4) == (3, 4)
    assert balanced(100, 4) == (25, 4)
    assert balanced(7, 7) == (1, 7)
    for runs in range(1, 40):
        for block in range(1, 12):
            n, size = balanced(runs, block)
            assert size <= block and n == -(-runs // block)  # as few blocks as allowed
            assert 0 <= n * size - runs < n  # padded by less than one run a block


def test_compile_run_times_compilation_apart():
    ys, us = _data(R=7, seed=4)
    kw = dict(x0=X0, P0=P0, return_covariances=True,
              execution=Execution(chunk_size=3), progress=False)
    prepared = compile_run(EST, ys, us, **kw)
    assert prepared.compile_seconds > 0 and prepared.chunk_size == 3 and prepared.n_chunks == 3
    a, b = prepared(), prepared()
    for r in range(7):
        np.testing.assert_allclose(a.states[r], numpy_kf(ys[r], us[r], X0, P0)[0], rtol=1e-10, atol=1e-12)
    _assert_close(a, b, rtol=0)


def test_compiler_options_reach_xla_and_keep_the_results():
    """compiler_options compile the study with those XLA options (run and compile_run): at LLVM
    level 1 the results are the exact Kalman recursions' still; an option XLA does not know is
    a ValueError naming the argument."""
    ys, us = _data(R=3, seed=9)
    opts = {"xla_backend_optimization_level": 1}
    out = run(EST, ys, us, x0=X0, P0=P0, execution=Execution(compiler_options=opts))
    prepared = compile_run(EST, ys, us, x0=X0, P0=P0, execution=Execution(compiler_options=opts))
    for res in (out, prepared()):
        for r in range(3):
            np.testing.assert_allclose(res.states[r], numpy_kf(ys[r], us[r], X0, P0)[0],
                                       rtol=1e-10, atol=1e-12)
    with pytest.raises(ValueError, match="compiler_options.*xla_no_such_option"):
        run(EST, ys, us, x0=X0, P0=P0,
            execution=Execution(compiler_options={"xla_no_such_option": 1}))
    # the compiled study is reused by the next call with the same estimator, options, shapes
    n = len(eager.CACHE)
    again = run(EST, ys + 1.0, us, x0=X0, P0=P0, execution=Execution(compiler_options=opts))
    assert len(eager.CACHE) == n
    np.testing.assert_allclose(again.states[1], numpy_kf(ys[1] + 1.0, us[1], X0, P0)[0],
                               rtol=1e-10, atol=1e-12)
    run(EST, ys[:2], us[:2], x0=X0, P0=P0,
        execution=Execution(compiler_options=opts))  # other shapes: anew
    assert len(eager.CACHE) == min(n + 1, eager.CACHE_SIZE)
    # the strategy's options (by the estimator's workload) under the caller's, name by name
    cpu = execution.for_platform("cpu")
    assert execution.compiler_options(cpu, "small_dense") == {"xla_cpu_use_fusion_emitters": False}
    assert execution.compiler_options(cpu, "particles") is None
    assert execution.compiler_options(cpu, "small_dense", {"xla_cpu_use_fusion_emitters": True,
                                                           "xla_backend_optimization_level": 2}
                                      ) == {"xla_cpu_use_fusion_emitters": True,
                                            "xla_backend_optimization_level": 2}
    res = run(EST._replace(runtime=EST.runtime._replace(workload="small_dense")), ys, us, x0=X0, P0=P0)
    np.testing.assert_allclose(res.states, out.states, rtol=1e-10, atol=1e-12)


def _key_reporting_estimator():
    """Needs a key: carries it in its state and reports the key's two uint32 words as its mean."""

    def init(x0, P0, theta0, P_theta0, key):
        return key

    def step(key, y, u):
        mean = jax.random.key_data(key).astype(jnp.float64)
        zero = jnp.zeros(())
        no_params = (jnp.zeros(0), jnp.zeros((0, 0)))
        return key, StepOutput(mean, jnp.eye(2), zero, zero, jnp.array(0), *no_params)

    return Estimator(init, step, Dims(2), "keyed", runtime=Runtime(needs_key=True))


def test_keys_are_split_per_run_independent_of_chunking():
    est = _key_reporting_estimator()
    ys, us = _data(R=5, seed=5)
    key = jax.random.key(7)
    with pytest.raises(ValueError, match="key"):
        run(est, ys, us, x0=X0, P0=P0)
    out = run(est, ys, us, x0=X0, P0=P0, key=key)
    expected = np.asarray(jax.random.key_data(jax.random.split(key, 5)), float)
    np.testing.assert_array_equal(out.states, np.broadcast_to(expected[:, None], (5, T, 2)))
    assert len({tuple(k) for k in expected}) == 5
    chunked = run(est, ys, us, x0=X0, P0=P0, key=key,
                  execution=Execution(chunk_size=3), progress=False)
    np.testing.assert_array_equal(chunked.states, out.states)


def test_parameter_outputs_and_theta_checks():
    est = kalman_estimator(F, B, H, Q, RN, name="kf-param", param_view=True)
    ys, us = _data()
    with pytest.raises(ValueError, match="theta0"):
        run(est, ys, us, x0=X0, P0=P0)
    with pytest.raises(ValueError, match="theta0"):
        run(EST, ys, us, x0=X0, P0=P0, theta0=[1.0], P_theta0=[[1.0]])
    with pytest.raises(ValueError, match="P_theta0"):
        run(est, ys, us, x0=X0, P0=P0, theta0=[1.0], P_theta0=[[-1.0]])
    with pytest.raises(ValueError, match="theta0"):
        run(est, ys, us, x0=X0, P0=P0, theta0=[1.0, 2.0], P_theta0=[[1.0]])
    bad = ys.copy()
    bad[0, 0, 0] = 1e300  # diverges at the first step: holds theta0, P_theta0
    bad[2, 30, 0] = 1e300
    out = run(est, bad, us, x0=X0, P0=P0, theta0=[9.0], P_theta0=[[3.0]], return_covariances=True)
    assert (out.params[0] == 9.0).all() and (out.params_cov[0] == 3.0).all()
    assert out.params.shape == (R_RUNS, T, 1) and out.params_cov.shape == (R_RUNS, T, 1, 1)
    np.testing.assert_array_equal(out.params[1:, :, 0], out.states[1:, :, 0])
    np.testing.assert_array_equal(out.params_cov[1:, :, 0, 0], out.covariances[1:, :, 0, 0])
    np.testing.assert_array_equal(out.diverged_at, [0, -1, 30])
    np.testing.assert_array_equal(out.params[2, 30:, 0], out.params[2, 29, 0])


def _exploding():
    """An estimator that fails loudly if anything traces or calls it."""

    def boom(*args):
        raise RuntimeError("traced before validation")

    return Estimator(boom, boom, Dims(2), "boom")


@pytest.mark.parametrize(
    "change, arg",
    [
        (dict(measurements=np.zeros((T, 2))), "measurements"),
        (dict(measurements=np.zeros((2, 0, 2))), "measurements"),
        (dict(measurements=np.zeros((2, T, 2), complex)), "measurements"),
        (dict(inputs=np.zeros((T + 1, 1))), "inputs"),
        (dict(inputs=np.zeros((3, T, 1))), "inputs"),
        (dict(inputs=np.zeros(T)), "inputs"),
        (dict(inputs=np.full((T, 1), np.nan)), "inputs"),
        (dict(x0=np.zeros(3)), "x0"),
        (dict(x0=np.zeros((3, 2))), "x0"),
        (dict(x0=np.array([np.nan, 0.0])), "x0"),
        (dict(P0=np.eye(3)), "P0"),
        (dict(P0=np.diag([1.0, -1.0])), "P0"),
        (dict(P0=np.array([[1.0, 0.5], [0.0, 1.0]])), "P0"),
        (dict(P0=np.stack([np.eye(2), np.diag([1.0, 0.0])])), "P0"),
        (dict(execution=dict(chunk_size=0)), "chunk_size"),
        (dict(execution=dict(chunk_size=2.5)), "chunk_size"),
        (dict(key="seed"), "key"),
        (dict(execution=dict(devices="cpu")), "devices"),
        (dict(progress="yes"), "progress"),
        (dict(return_covariances="yes"), "return_covariances"),
        (dict(theta0=[1.0]), "theta0"),
        (dict(estimator="ukf"), "estimator"),
        (dict(execution=dict(compiler_options=[("xla_backend_optimization_level", 1)])), "compiler_options"),
        (dict(execution=dict(compiler_options={"xla_backend_optimization_level": [1]})), "compiler_options"),
    ],
)
def test_bad_input_raises_before_tracing(change, arg):
    kwargs = dict(estimator=_exploding(), measurements=np.zeros((2, T, 2)), inputs=np.zeros((T, 1)),
                  x0=np.zeros(2), P0=np.eye(2))
    kwargs.update(change)
    est, ys, us = kwargs.pop("estimator"), kwargs.pop("measurements"), kwargs.pop("inputs")
    with pytest.raises(ValueError, match=arg):
        if "execution" in kwargs:  # the record's fields check themselves, before any tracing
            kwargs["execution"] = Execution(**kwargs["execution"])
        run(est, ys, us, **kwargs)


def test_estimator_output_shape_is_checked():
    def step(state, y, u):
        new, out = EST.step(state, y, u)
        return new, out._replace(mean=out.mean[:1])

    ys, us = _data()
    with pytest.raises(ValueError, match="StepOutput.mean"):
        run(EST._replace(step=step, runtime=EST.runtime._replace(batch=None)), ys, us, x0=X0, P0=P0)


_SHARDED = textwrap.dedent(
    """
    import os, sys
    os.environ["XLA_FLAGS"] = "--xla_force_host_platform_device_count=2"
    sys.path.insert(0, {tests!r})
    import jax, numpy as np
    import test_run as t
    from vehjax.execution import Execution
    from vehjax.run import compile_run, run
    assert len(jax.devices()) == 2, jax.devices()
    ys, us = t._data(R=5, seed=9)
    ys[3, 8, 1] = 1e300
    kw = dict(x0=t.X0, P0=t.P0, return_covariances=True)
    one = run(t.EST, ys, us, execution=Execution(devices=False), **kw)
    two = run(t.EST, ys, us, **kw)  # one chunk of 6: 5 runs padded over 2 devices
    assert one.diverged.tolist() == [False, False, False, True, False]
    t._assert_close(two, one)
    prepared = compile_run(t.EST, ys, us, execution=Execution(chunk_size=1), **kw)
    assert (prepared.chunk_size, prepared.n_chunks) == (2, 3)  # rounded up to the device count
    t._assert_close(prepared(progress=False), one)
    # the runs-last UKF step (vehjax.filters.runs_last) sharded the same way
    import vehjax as vj
    model = vj.models.Dynamic3DOF(dt=0.01)
    scn = vj.scenarios.sine_steer(model, speed=20.0, duration=0.2)
    sim = vj.simulate(model, scn, runs=5, key=jax.random.key(0), meas_std=[0.2, 0.2, 0.05])
    est = vj.filters.ukf(model, [1e-3, 1e-3, 1e-4], [0.04, 0.04, 0.0025])
    assert est.batch is not None
    kw = dict(x0=scn.x0, P0=np.eye(3) * 0.1, return_covariances=True, progress=False)
    one = run(est, sim.measurements, sim.inputs, execution=Execution(devices=False), **kw)
    two = run(est, sim.measurements, sim.inputs, **kw)
    np.testing.assert_allclose(two.states, one.states, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(two.covariances, one.covariances, rtol=1e-12, atol=1e-15)
    print("sharded ok")
    """
)


@pytest.mark.slow  # two fresh processes compiling the study: `pytest -m slow` (README)
def test_sharded_over_two_devices_equals_one_device():
    code = _SHARDED.format(tests=os.path.dirname(__file__))
    env = dict(os.environ)
    env.pop("XLA_FLAGS", None)
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "sharded ok" in res.stdout


# ----------------------------------------------------------------------------------------------
# What a notebook user sees and exports


def test_repr_summary_and_exports(tmp_path):
    xr = pytest.importorskip("xarray")
    from vehjax.models import Model

    ys, us = _data()
    est = kalman_estimator(F, B, H, Q, RN, name="kf", param_view=True)
    out = run(est, ys, us, x0=X0, P0=P0, theta0=np.zeros(1), P_theta0=np.eye(1),
              return_covariances=True)
    text = repr(out)
    assert text.startswith("RunResult(kf: 3 runs x 40 steps, 2 states, parameters (a), 0 diverged")
    ll_step = np.mean(out.loglik / (out.n_obs > 0).sum(axis=1))
    assert f"{ll_step:.4g}" in text

    model = Model(transition=lambda x, u, th: F @ x + B @ u, observe=lambda x, u, th: H @ x,
                  theta=np.array([1.0]), dt=DT, state_names=("pos", "vel"), param_names=("a",),
                  input_names=("acc",), output_names=("y1", "y2"),
                  units={"pos": "m", "vel": "m/s", "a": "m"})
    truth = out.states + np.array([0.1, -0.2])  # a known error per state
    lines = out.summary(truth, model).splitlines()
    assert lines[1].split() == ["RMSE", "over", "3", "runs:"]
    assert lines[2].split() == ["pos", "0.1", "m"] and lines[3].split() == ["vel", "0.2", "m/s"]

    path = out.to_npz(tmp_path / "study", model)
    with np.load(path) as f:
        np.testing.assert_array_equal(f["states"], out.states)
        np.testing.assert_array_equal(f["diverged_at"], out.diverged_at)
        import json
        labels = json.loads(str(f["labels"]))
    assert labels == {"state_names": ["pos", "vel"], "state_units": ["m", "m/s"],
                      "param_names": ["a"], "param_units": ["m"], "name": "kf"}

    ds = out.to_xarray(model)
    assert dict(ds.sizes) == {"run": 3, "time": 40, "state": 2, "param": 1, "state2": 2,
                              "param2": 1}
    np.testing.assert_allclose(ds["time"].values, np.arange(40) * DT)
    np.testing.assert_array_equal(ds["states"].sel(state="vel").values, out.states[..., 1])
    assert ds["states"].attrs["units"] == ["m", "m/s"] and ds.attrs["filter"] == "kf"
    assert isinstance(ds, xr.Dataset)


def test_summary_names_diverged_runs_and_leaves_them_out_of_the_rmse():
    ys, us = _data()
    ys[1, 20:] = 1e200  # run 1 overflows
    out = run(EST, ys, us, x0=X0, P0=P0)
    assert out.diverged.tolist() == [False, True, False]
    text = out.summary(np.zeros(2))
    assert "1 diverged" in text and "diverged runs: [1]" in text and "RMSE over 2 runs" in text
    assert "x0" in text and "nan" not in text.lower()


def test_compiled_study_takes_no_data_positionally():
    """A compiled study runs with its own data: new measurements given positionally are refused
    with a message that says how to run new data, not taken for ``progress`` (issue 46)."""
    ys, us = _data(R=5, seed=4)
    prepared = compile_run(EST, ys, us, x0=X0, P0=P0, progress=False)
    with pytest.raises(TypeError, match="compile_run.*or vehjax.run.*keyword-only"):
        prepared(ys + 1.0)
    with pytest.raises(ValueError, match="^progress"):
        prepared(progress="yes")
