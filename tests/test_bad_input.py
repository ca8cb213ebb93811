"""Bad input gets a clear ValueError naming the argument, or a flagged run with the other runs
unchanged; never a silent wrong result. Every case of the issue, more of our own, and a
property-based part (hypothesis) that draws shapes and values for run and simulate."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import vehjax as vj
from vehjax import filters as F

# the 2-state linear model of the Model docstring, with one input and two outputs
A = np.array([[1.0, 0.1], [0.0, 0.95]])


def _f(x, u, th):
    return jnp.asarray(A) @ x + jnp.stack([0.0, 0.1 * u[0]])


def _h(x, u, th):
    return x


MODEL = vj.models.Model(_f, _h, dt=0.1, state_names=("p", "v"), input_names=("u",),
                        output_names=("yp", "yv"), param_names=("a",), theta=[1.0])
Q, R = np.diag([1e-3, 1e-3]), np.diag([0.05, 0.05])
X0, P0 = np.zeros(2), np.eye(2) * 0.1
RUNS, T = 3, 30


def _data(seed=0, runs=RUNS, T=T):
    rng = np.random.default_rng(seed)
    us = rng.normal(size=(T, 1))
    ys = np.empty((runs, T, 2))
    for r in range(runs):
        x = X0.copy()
        for t in range(T):
            x = A @ x + np.array([0.0, 0.1 * us[t, 0]]) + rng.normal(size=2) * 0.03
            ys[r, t] = x + rng.normal(size=2) * np.sqrt(0.05)
    return ys, us


YS, US = _data()
FAMILIES = {
    "ekf": lambda: F.ekf(MODEL, Q, R),
    "ukf": lambda: F.ukf(MODEL, Q, R),
    "sr_ukf": lambda: F.ukf(MODEL, Q, R, sqrt=True),
    "ackf": lambda: F.ackf(MODEL, Q, R),
    "pf": lambda: F.bootstrap_pf(MODEL, Q, R, n_particles=50),
    "dual_ekf": lambda: F.dual_ekf(MODEL, Q, R, Q_theta=[1e-4], estimate="a"),
    "liu_west": lambda: F.liu_west_ukf(MODEL, Q, R, n_particles=20, estimate="a",
                                       theta_low=[0.5], theta_high=[1.5]),
}


def _kw(est):
    kw = dict(x0=X0, P0=P0, progress=False)
    if est.needs_key:
        kw["key"] = jax.random.key(0)
    if est.param_names and est.param_prior is None:
        kw.update(theta0=[1.0], P_theta0=[[0.1]])
    return kw


# ---- the cases --------------------------------------------------------------------------

@pytest.mark.parametrize("family", list(FAMILIES))
@pytest.mark.parametrize("width", [1, 3])
def test_measurement_width_must_match_the_model_outputs(family, width):
    est = FAMILIES[family]()
    ys = np.concatenate([YS, YS[..., :1]], axis=-1)[..., :width]
    with pytest.raises(ValueError, match="^measurements:.*2 columns"):
        vj.run(est, ys, US, **_kw(est))


@pytest.mark.parametrize("family", ["ekf", "ukf", "sr_ukf", "pf"])
def test_input_width_must_match_the_model_inputs(family):
    est = FAMILIES[family]()
    with pytest.raises(ValueError, match="^inputs:.*1 columns"):
        vj.run(est, YS, np.concatenate([US, US], axis=1), **_kw(est))
    with pytest.raises(ValueError, match="^inputs:.*required"):
        vj.run(est, YS, None, **_kw(est))


def test_model_functions_must_return_the_declared_shapes():
    with pytest.raises(ValueError, match="^observe:.*2 outputs"):
        vj.models.Model(_f, lambda x, u, th: x[:1], dt=0.1, state_names=("p", "v"),
                        input_names=("u",), output_names=("yp", "yv"))
    with pytest.raises(ValueError, match="^transition:.*2 states"):
        vj.models.Model(lambda x, u, th: x[:1], _h, dt=0.1, state_names=("p", "v"),
                        input_names=("u",))
    with pytest.raises(ValueError, match="^transition:.*failed"):
        vj.models.Model(lambda x, u, th: jnp.ones((3, 3)) @ x, _h, dt=0.1, state_names=("p", "v"),
                        input_names=("u",))


@pytest.mark.parametrize("family", ["ekf", "ukf", "sr_ukf", "ackf", "dual_ekf", "pf"])
def test_absurdly_scaled_run_is_flagged_others_unchanged(family):
    est = FAMILIES[family]()
    base = vj.run(est, YS, US, **_kw(est))
    bad = YS.copy()
    bad[1] *= 1e200
    out = vj.run(est, bad, US, **_kw(est))
    assert out.diverged.tolist() == [False, True, False]
    for r in (0, 2):
        np.testing.assert_allclose(out.states[r], base.states[r], rtol=1e-12)
        np.testing.assert_allclose(out.loglik[r], base.loglik[r], rtol=1e-12)
    # whatever is not flagged is finite
    assert np.isfinite(out.loglik).all() and np.isfinite(out.states).all()


def test_scaled_by_1e6_is_finite_or_flagged():
    for family in ("ekf", "ukf", "pf"):
        est = FAMILIES[family]()
        out = vj.run(est, YS * 1e6, US, **_kw(est))
        ok = np.isfinite(out.loglik) & np.isfinite(out.nis).all(axis=1)
        assert np.all(ok | out.diverged), family


def test_inf_measurements_one_rule():
    """One rule for +-inf measurements: refused by run and by filter (ValueError naming
    measurements and the first bad index); under a trace, where values are unknown, a filter
    treats +-inf as missing, like NaN, in every family."""
    bad = YS.copy()
    bad[0, 4, 1] = np.inf
    for family in ("ekf", "pf"):
        est = FAMILIES[family]()
        with pytest.raises(ValueError, match=r"^measurements:.*inf.*\(0, 4, 1\)"):
            vj.run(est, bad, US, **_kw(est))
        key = jax.random.key(1) if est.needs_key else None
        y_inf, y_nan = bad[0].copy(), bad[0].copy()
        y_inf[7, 0] = -np.inf
        y_nan[4, 1] = y_nan[7, 0] = np.nan
        with pytest.raises(ValueError, match=r"^measurements:.*inf.*\(4, 1\)"):
            vj.filter(est, y_inf, US, x0=X0, P0=P0, key=key)
        traced = jax.jit(lambda y: vj.filter(est, y, US, x0=X0, P0=P0, key=key))
        a, b = traced(y_inf), traced(y_nan)
        np.testing.assert_array_equal(a.states, b.states)
        assert int(a.n_obs[4]) == 1 and int(a.n_obs[7]) == 1


def test_pf_needs_two_particles():
    for n in (1, 0):
        with pytest.raises(ValueError, match="^n_particles:"):
            F.bootstrap_pf(MODEL, Q, R, n_particles=n)


def test_pf_with_r_far_below_the_noise_reinitialises_and_keeps_going():
    est = F.bootstrap_pf(MODEL, Q, R * 1e-10, n_particles=100)
    out = vj.run(est, YS, US, **_kw(est))
    assert out.diverged.all()  # flagged: its weights collapsed
    # not frozen: the estimates keep following the data after the flag
    for r in range(RUNS):
        t0 = out.diverged_at[r]
        assert np.ptp(out.states[r, t0:, 0]) > 0.05
        assert np.isfinite(out.states[r]).all()


def test_large_particle_study_is_chunked_by_what_the_filter_holds():
    from vehjax.runner.plan import plan as _plan

    m = vj.models.Dynamic3DOF()
    est = F.bootstrap_pf(m, np.eye(3) * 1e-3, np.eye(3) * 1e-2, n_particles=5000)
    ys = np.zeros((2000, 200, 3))
    plan = _plan(est, ys, np.zeros((200, m.nu)), np.array([20.0, 0, 0]), np.eye(3), None, None,
                 jax.random.key(0), False, None, None, None)
    assert plan.n_chunks >= 4  # so a progress bar shows and memory stays bounded
    ukf_plan = _plan(F.ukf(m, np.eye(3) * 1e-3, np.eye(3) * 1e-2), ys[:100], np.zeros((200, m.nu)),
                     np.array([20.0, 0, 0]), np.eye(3), None, None, None, False, None, None, None)
    assert ukf_plan.n_chunks == 1


def test_simulate_key_and_model_dt():
    scn = vj.scenarios.double_lane_change(vj.models.KinematicBicycle())
    with pytest.raises(ValueError, match="^key:"):
        vj.simulate(vj.models.KinematicBicycle(), scn, runs=2, key=0)
    for dt in (True, 0.0, -1.0, float("nan"), "fast"):
        with pytest.raises(ValueError, match="^dt:"):
            vj.models.Model(_f, _h, dt=dt, state_names=("p", "v"), input_names=("u",))


def test_ekf_with_a_very_wide_prior_does_not_diverge():
    """The EKF's Joseph-form update stays positive definite with P0 = 1e16 I, as the square-root
    UKF does. (The plain UKF's P- - K S K^T cancels to rounding noise at such a prior on this
    model and the run is flagged; its docstring says to use sqrt=True there.)"""
    for family in ("ekf", "sr_ukf"):
        est = FAMILIES[family]()
        out = vj.run(est, YS, US, x0=X0, P0=np.eye(2) * 1e16, progress=False)
        assert not out.diverged.any(), family


def test_covariance_arguments_one_rule_and_q_zero():
    """Every covariance argument takes (n, n) or (n,) variances; Q may have zero variances."""
    est = F.ukf(MODEL, np.array([1e-3, 0.0]), R)  # a noise-free first state
    a = vj.run(est, YS, US, x0=X0, P0=np.diag(P0), progress=False)
    b = vj.run(est, YS, US, x0=X0, P0=P0, progress=False)
    np.testing.assert_array_equal(a.states, b.states)
    assert not a.diverged.any()
    with pytest.raises(ValueError, match="^P0:"):
        vj.run(est, YS, US, x0=X0, P0=np.array([0.1, -0.1]), progress=False)
    with pytest.raises(ValueError, match="^R:"):
        F.ukf(MODEL, Q, np.array([0.05, 0.0]))  # the innovation covariance would be singular


# ---- more of our own ----------------------------------------------------------------------------

EST = FAMILIES["ukf"]()


@pytest.mark.parametrize(
    "kwargs, arg",
    [
        (dict(x0=np.array([np.nan, 0.0])), "x0"),
        (dict(x0=np.zeros(3)), "x0"),
        (dict(x0=np.zeros((2, 2))), "x0"),
        (dict(P0=np.array([[1.0, 0.5], [0.0, 1.0]])), "P0"),
        (dict(P0=np.array([[1.0, np.nan], [np.nan, 1.0]])), "P0"),
        (dict(P0=-np.eye(2)), "P0"),
        (dict(P0=np.eye(3)), "P0"),
        (dict(theta0=[1.0, 2.0]), "theta0"),  # the model has one parameter
        (dict(execution=dict(chunk_size=0)), "execution.chunk_size"),
        (dict(execution=dict(chunk_size=2.5)), "execution.chunk_size"),
        (dict(progress="yes"), "progress"),
        (dict(return_covariances="no"), "return_covariances"),
        (dict(execution=dict(devices=[1, 2])), "execution.devices"),
        (dict(key=0), "key"),
    ],
)
def test_run_arguments(kwargs, arg):
    kw = dict(x0=X0, P0=P0, progress=False)
    kw.update(kwargs)
    with pytest.raises(ValueError, match=f"^{arg}:"):
        if "execution" in kw:  # the record's fields check themselves when it is made
            kw["execution"] = vj.Execution(**kw["execution"])
        vj.run(EST, YS, US, **kw)


@pytest.mark.parametrize(
    "ys, us, arg",
    [
        (YS[0], US, "measurements"),  # 2-D: one run is (1, T, ny)
        (YS[:, :0], US[:0], "measurements"),  # no steps
        (YS.astype(bool), US, "measurements"),
        (np.array([["a", "b"]]), US, "measurements"),
        (YS, US[:-1], "inputs"),
        (YS, np.where(US > 0, np.nan, US), "inputs"),
        (YS, US[:, 0], "inputs"),
    ],
)
def test_run_data_shapes_and_values(ys, us, arg):
    with pytest.raises(ValueError, match=f"^{arg}:"):
        vj.run(EST, ys, us, x0=X0, P0=P0, progress=False)


def test_not_an_estimator_and_missing_parameter_priors():
    with pytest.raises(ValueError, match="^estimator:"):
        vj.run(F.ukf, YS, US, x0=X0, P0=P0)
    dual = FAMILIES["dual_ekf"]()
    with pytest.raises(ValueError, match="^P_theta0: required"):  # as vj.filter says
        vj.run(dual, YS, US, x0=X0, P0=P0)
    with pytest.raises(ValueError, match="^P_theta0: required"):
        vj.filter(dual, YS[0], US, x0=X0, P0=P0)
    with pytest.raises(ValueError, match="^theta0:"):
        vj.run(dual, YS, US, x0=X0, P0=P0, theta0=[1.0, 2.0], P_theta0=[[0.1]])
    with pytest.raises(ValueError, match="^key:"):
        vj.run(FAMILIES["pf"](), YS, US, x0=X0, P0=P0)


@pytest.mark.parametrize(
    "build, arg",
    [
        (lambda: F.ukf(MODEL, np.eye(3), R), "Q"),
        (lambda: F.ukf(MODEL, -np.eye(2), R), "Q"),
        (lambda: F.ekf(MODEL, Q, np.ones((2, 3))), "R"),
        (lambda: F.ukf(MODEL, Q, R, points=F.SigmaPoints(alpha=0.0)), "alpha"),
        (lambda: F.bootstrap_pf(MODEL, Q, R, n_particles=2.5), "n_particles"),
        (lambda: F.bootstrap_pf(MODEL, Q, R, resampling=F.Resampling(ess_threshold=float("nan"))),
         "ess_threshold"),
        (lambda: F.bootstrap_pf(MODEL, Q, R, resampling=F.Resampling(scheme="best")),
         "scheme"),
        (lambda: F.bootstrap_pf(MODEL, Q, R, resampling="best"), "resampling"),
        (lambda: F.ackf(MODEL, Q, R, forgetting=0.0), "forgetting"),
        (lambda: F.ackf(MODEL, Q, R, adapt=("P",)), "adapt"),
        (lambda: F.dual_ukf(MODEL, Q, R, Q_theta=[1e-4], estimate="b"), "estimate"),
        (lambda: F.dual_ukf(MODEL, Q, R, Q_theta=[1e-4], estimate="a", theta_decay=1.5),
         "theta_decay"),
        (lambda: F.liu_west_ukf(MODEL, Q, R, estimate="a", theta_low=[2.0], theta_high=[1.0]),
         "theta_low"),
        (lambda: F.ukf(object(), Q, R), "model"),
    ],
)
def test_builder_arguments(build, arg):
    with pytest.raises(ValueError, match=f"^{arg}"):
        build()


@pytest.mark.parametrize(
    "kwargs, arg",
    [
        (dict(state_names=()), "state_names"),
        (dict(state_names=("p", "p")), "state_names"),
        (dict(state_names="pv"), "state_names"),
        (dict(output_names=("a", "a")), "output_names"),
        (dict(theta=[1.0, 2.0], param_names=("a",)), "theta"),
        (dict(transition="f"), "transition"),
    ],
)
def test_model_arguments(kwargs, arg):
    kw = dict(transition=_f, observe=_h, dt=0.1, state_names=("p", "v"), input_names=("u",))
    kw.update(kwargs)
    with pytest.raises(ValueError, match=f"^{arg}:"):
        vj.models.Model(**kw)


def test_simulate_arguments():
    m = vj.models.KinematicBicycle()
    scn = vj.scenarios.double_lane_change(m)
    for kwargs, arg in [(dict(runs=0), "runs"), (dict(runs=True), "runs"),
                        (dict(meas_std=-1.0), "meas_std"), (dict(process_std=[1.0] * 9), "process_std")]:
        kw = dict(runs=2, key=jax.random.key(0))
        kw.update(kwargs)
        with pytest.raises(ValueError, match=f"^{arg}:"):
            vj.simulate(m, scn, **kw)
    with pytest.raises(ValueError, match="^model:"):
        vj.scenarios.double_lane_change(MODEL)


def test_tiny_and_huge_scales_are_finite_or_flagged():
    for scale in (1e-150, 1e150):
        model = vj.models.Model(_f, _h, dt=0.1, state_names=("p", "v"), input_names=("u",),
                                output_names=("yp", "yv"))
        est = F.ekf(model, Q * scale**2, R * scale**2)
        out = vj.run(est, YS * scale, US * scale, x0=X0, P0=P0 * scale**2, progress=False)
        good = ~out.diverged
        assert np.isfinite(out.states[good]).all() and np.isfinite(out.loglik[good]).all()


# ---- property-based -------------------------------------------------------------------------

_VALUES = st.sampled_from([0.0, 1.0, -3.5, 1e8, -1e-8, np.nan, np.inf, 1e300])


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(runs=st.integers(0, 3), steps=st.integers(0, 4), ny=st.integers(0, 3),
       nu=st.integers(0, 2), u_shared=st.booleans(), value=_VALUES, where=st.integers(0, 5),
       x0_len=st.integers(1, 3), p0_kind=st.sampled_from(["matrix", "vars", "bad", "batched"]))
def test_run_raises_only_value_errors(runs, steps, ny, nu, u_shared, value, where, x0_len,
                                      p0_kind):
    rng = np.random.default_rng(where)
    ys = rng.normal(size=(runs, steps, ny))
    us = rng.normal(size=(steps, nu) if u_shared else (runs, steps, nu))
    if ys.size:
        ys.flat[where % ys.size] = value
    if us.size and where % 2:
        us.flat[where % us.size] = value
    x0 = np.zeros(x0_len)
    P0_ = {"matrix": np.eye(2), "vars": np.ones(2), "bad": np.ones((2, 3)),
           "batched": np.stack([np.eye(2)] * max(runs, 1))}[p0_kind]
    try:
        out = vj.run(EST, ys, us, x0=x0, P0=P0_, progress=False)
    except ValueError:
        return
    assert out.states.shape == (runs, steps, 2)
    good = ~out.diverged
    assert np.isfinite(out.states[good]).all()


@settings(max_examples=10, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(runs=st.one_of(st.integers(-1, 3), st.just(2.0), st.just(True)),
       meas=st.one_of(st.sampled_from([0.0, 0.1, -1.0, np.nan, np.inf]),
                      st.lists(st.floats(-1, 1), min_size=0, max_size=4)),
       proc=st.one_of(st.none(), st.sampled_from([0.0, 0.01, np.nan]),
                      st.lists(st.floats(0, 1), min_size=0, max_size=4)),
       key_kind=st.sampled_from(["key", "int", "none", "str"]))
def test_simulate_raises_only_value_errors(runs, meas, proc, key_kind):
    m = vj.models.KinematicBicycle()
    scn = vj.scenarios.step_steer(m, duration=0.2)
    key = {"key": jax.random.key(1), "int": 3, "none": None, "str": "k"}[key_kind]
    try:
        sim = vj.simulate(m, scn, runs=runs, key=key, meas_std=meas, process_std=proc)
    except ValueError:
        return
    assert np.isfinite(sim.states).all() and sim.states.shape[0] == runs
