"""vehjax.tune.fit's start from the data and its comparison with the nested model
(:mod:`vehjax.tune.staged`), on drives whose truth is known.

References nobody here wrote: scipy's bounded optimiser (L-BFGS-B) on the exact likelihood of a
short drive, the physics of the friction limit (|ay| <= mu g), and the simulated limit drives'
truth (:mod:`vehjax.studies.limit_drive`: a two-track car with load transfer, not a fitted model).
"""

import functools
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import minimize

import vehjax
from vehjax.models import SingleTrack
from vehjax.models.single_track import G, peak_lateral_acceleration
from vehjax.tune import staged

#: the EKF with the starting value of the input noise that noise "input" fits
EKF_DELTA = functools.partial(vehjax.filters.ekf, input_noise={"delta": 0.002})


@pytest.fixture(scope="module")
def drives():
    """One lap and a bit of each limit drive (the laps repeat)."""
    return {v: vehjax.studies.limit_drive.limit_drive(v, duration=60.0) for v in ("A", "B")}


def test_peak_lateral_acceleration_averages_the_noise_out_and_skips_nan():
    dt = 0.01
    t = np.arange(6000) * dt
    ay = 12.0 * np.sin(2 * np.pi * 0.05 * t)
    rng = np.random.default_rng(0)
    noisy = ay + 0.3 * rng.standard_normal(t.size)
    noisy[::7] = np.nan
    peak = peak_lateral_acceleration(noisy, dt)
    # the raw maximum overshoots by more than one noise std; the 0.2 s average by a fraction
    assert np.nanmax(np.abs(noisy)) > 12.0 + 0.5
    assert abs(peak - 12.0) < 0.15
    # the average over 0.2 s of a 0.05 Hz sine loses (2 pi 0.05 0.1)^2 / 6 ~ 1.6e-4 of its peak
    assert peak_lateral_acceleration(ay, dt) == pytest.approx(12.0, rel=2e-4)
    assert peak_lateral_acceleration(np.full(10, np.nan), dt) == 0.0
    # runs: the peak over all of them
    assert peak_lateral_acceleration(np.stack([ay, 0.5 * ay]), dt) == pytest.approx(
        peak_lateral_acceleration(ay, dt))


@pytest.mark.parametrize("variant", ["A", "B"])
def test_the_friction_floor_lies_just_below_the_truths_peak(drives, variant):
    """mu >= peak |ay| / g: on a drive to 96 % of the limit the floor is within 10 % of the
    truth's peak friction coefficient and not above it; the linear tyres have none."""
    d = drives[variant]
    floor = SingleTrack(tyres="brush").data_floors(d.measurements, d.inputs)["mu"]
    assert floor == SingleTrack(tyres="pacejka").data_floors(d.measurements, d.inputs)["mu"]
    true_peak = np.max(np.abs(d.ay)) / G
    assert abs(floor - true_peak) < 0.02            # the noise adds little to the peak
    assert 0.9 * d.mu < floor < d.mu
    assert SingleTrack().data_floors(d.measurements, d.inputs) == {}


def test_start_values_from_the_floor_within_the_domain_and_the_bounds():
    model = SingleTrack(tyres="brush")
    floors = {"mu": 1.4}
    first = staged.start_values(model, floors, ("cf", "mu"))
    assert first == {"mu": pytest.approx(staged.FLOOR_MARGIN * 1.4)}
    second = staged.start_values(model, floors, ("mu",), second=True)
    assert second["mu"] == pytest.approx(np.sqrt(staged.FLOOR_MARGIN * 1.4 * 3.0))  # domain (0, 3)
    # user bounds narrow the domain; a start is kept 5 % of the width inside it
    assert staged.start_values(model, floors, ("mu",), {"mu": (0.5, 1.2)}) == {
        "mu": pytest.approx(1.2 - 0.05 * 0.7)}
    # only fitted parameters are moved
    assert staged.start_values(model, floors, ("cf",)) == {}


def test_the_saturating_tyres_nest_the_linear_ones():
    brush = SingleTrack(tyres="brush", theta=(1650.0, 2900.0, 1.15, 1.55, 1.1e5, 1.3e5, 1.2))
    lin = brush.nested_model()
    assert lin.tyres == "linear" and lin.param_names == brush.param_names[:6]
    np.testing.assert_array_equal(np.asarray(lin.theta), np.asarray(brush.theta)[:6])
    assert (lin.dt, lin.substeps, lin.integrator) == (brush.dt, brush.substeps, brush.integrator)
    assert lin.nested_model() is None
    # at a large friction coefficient and small slips the two agree to the brush curve's
    # curvature term c |t| / (3 mu Fz), about 1.5e-3 at these slips (rear 1e-3 rad)
    x, u = np.array([0.05, 0.02]), np.array([0.004, 20.0])
    far = brush.with_theta(mu=2.99)
    np.testing.assert_allclose(np.asarray(far.observe(x, u, far.theta)),
                               np.asarray(lin.observe(x, u, lin.theta)), rtol=4e-3)
    near, u = brush.with_theta(mu=0.3), np.array([0.08, 20.0])   # front slip 0.043 rad
    assert abs(float(near.observe(x, u, near.theta)[0] - lin.observe(x, u, lin.theta)[0])) > 1.0


def _neg_loglik(model, names, ys, us, R, x0, P0):
    """-log-likelihood of the EKF at the model's parameters ``names`` = values, jitted."""
    idx = np.asarray(model.param_index(names))

    @jax.jit
    def f(values):
        m = eqx.tree_at(lambda m: m.theta, model, model.theta.at[idx].set(values))
        est = vehjax.filters.ekf(m, np.zeros((2, 2)), R, input_noise={"delta": 0.003})
        return -vehjax.filter(est, ys, us, x0=x0, P0=P0).loglik.sum()

    return f


def test_the_fit_lands_at_scipys_bounded_optimum_on_a_short_drive(drives):
    """tune.fit's default path (nested linear fit, start from the data, scoring, Newton
    polish) and scipy's L-BFGS-B on the same exact EKF likelihood, in the physical
    parameters within the model's domains, reach the same optimum."""
    d = drives["B"]
    ys, us = d.measurements[1500:3000], d.inputs[1500:3000]   # a corner near the limit
    x0, P0 = np.zeros(2), np.array([0.1, 0.01])
    R = np.array([0.25**2, np.deg2rad(0.3) ** 2])
    model = SingleTrack(tyres="brush", theta=tuple(d.body.values()) + (1.2e5, 1.4e5, 1.0))
    names = ("cf", "cr", "mu")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = vehjax.tune.fit(functools.partial(vehjax.filters.ekf,
                                                input_noise={"delta": 0.003}),
                              model, np.zeros((2, 2)), R, ys, us, x0=x0, P0=P0,
                              params=vehjax.tune.Fitted(names, noise=()),
                              options=vehjax.tune.Options(progress=False))
    f = _neg_loglik(model, names, ys, us, R, x0, P0)
    scale = np.array([1e5, 1e5, 1.0])
    start = np.array([1.2e5, 1.4e5, 1.5])
    # the exact gradient of the same likelihood (JAX's reverse mode through vehjax.filter):
    # with scipy's finite differences (step 1e-8) the gradient's rounding noise is above gtol
    # and the line search ends ABNORMAL on some CPUs, after reaching the optimum
    fg = jax.jit(jax.value_and_grad(lambda v: f(v * scale)))

    def value_grad(v):
        val, g = fg(jnp.asarray(v))
        return float(val), np.asarray(g, dtype=float)

    ref = minimize(value_grad, start / scale, jac=True, method="L-BFGS-B",
                   bounds=[(1e-3, None), (1e-3, None), (1e-3, 3.0 - 1e-9)],
                   options={"ftol": 1e-15, "gtol": 1e-10, "maxiter": 500})
    assert ref.success, ref.message
    fitted = np.array([res.params[k] for k in names])
    np.testing.assert_allclose(fitted, ref.x * scale, rtol=1e-5)  # measured: 7.8e-10
    assert res.loglik >= -ref.fun - 1e-6


@pytest.mark.slow
def test_work_side_by_side_changes_the_time_not_the_result(drives):
    """The default path on two host threads (the saturating model's program compiled while the
    nested model is fitted, the Hessian's gradients evaluated side by side) and on one reach
    the same result: the same program evaluated at the same points (measured: equal bits)."""
    d = drives["A"]
    model = SingleTrack(tyres="brush", theta=tuple(d.body.values()) + (1.2e5, 1.4e5, 1.0))
    out = {}
    for side in (1, 2):
        with vehjax.execution.using(vehjax.execution.current()._replace(side_by_side=side)), \
                warnings.catch_warnings():
            warnings.simplefilter("ignore")
            out[side] = vehjax.tune.fit(EKF_DELTA, model, np.zeros((2, 2)),
                                        np.array([0.1, 1e-4]), d.measurements[1500:3000],
                                        d.inputs[1500:3000], x0=np.zeros(2),
                                        P0=np.array([0.1, 0.01]),
                                        params=vehjax.tune.Fitted(("cf", "cr", "mu"),
                                                                  noise=("R", "input")),
                                        options=vehjax.tune.Options(progress=False))
    one, two = out[1], out[2]
    assert one.evaluations == two.evaluations and one.nested.loglik == two.nested.loglik
    np.testing.assert_allclose(two.loglik, one.loglik, rtol=1e-12)
    for k in one.values:
        np.testing.assert_allclose(two.values[k], one.values[k], rtol=1e-10)
        np.testing.assert_allclose(two.std_errors[k], one.std_errors[k], rtol=1e-8)


@pytest.mark.slow  # two full fits from the trap, about 2.5 minutes of one core
def test_a_fit_held_in_the_trap_is_reported_with_both_likelihoods(drives):
    """The trap, deliberately: the brush tyres with mu held at most 1.0 (a user's bounds) on a
    drive that reached 1.35 g. The model cannot produce what was measured: the report says mu
    is below the least value the data allow, not that it is undetermined, and
    that the likelihood is below the nested linear model's, with both values."""
    d = drives["A"]
    model = SingleTrack(tyres="brush", theta=tuple(d.body.values()) + (1.2e5, 1.4e5, 0.9))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = vehjax.tune.fit(EKF_DELTA, model, np.zeros((2, 2)), np.array([0.1, 1e-4]),
                              d.measurements[:3000], d.inputs[:3000], x0=np.zeros(2),
                              P0=np.array([0.1, 0.01]),
                              params=vehjax.tune.Fitted(("cf", "cr", "mu"), noise=("R", "input"),
                                                        bounds={"mu": (0.5, 1.0)}),
                              start="theta",
                              options=vehjax.tune.Options(optimizer=vehjax.tune.Scoring(steps=20),
                                                          progress=False))  # the trap's report
    floor = model.data_floors(d.measurements[:3000], d.inputs[:3000])["mu"]
    assert floor > 1.3
    assert res.params["mu"] == pytest.approx(1.0, abs=1e-3)
    assert res.below_floor == {"mu": (pytest.approx(res.params["mu"]), floor)}
    assert "mu" not in res.undetermined
    assert res.below_nested and res.nested.loglik > res.loglik + staged.BELOW_NESTED
    text = " ".join(str(w.message) for w in caught)
    assert f"{res.loglik:.6g}" in text and f"{res.nested.loglik:.6g}" in text
    assert "least value the data allow" in text and "least value the data allow" in res.summary()


@pytest.fixture(scope="module")
def long_drives():
    """The 200 s drives (20,000 steps) to fit on, and another realisation of each to judge on."""
    ld = vehjax.studies.limit_drive.limit_drive
    return {v: (ld(v, seed=0), ld(v, seed=1)) for v in ("A", "B")}


def _fit_default(drive, tyres):
    params = {"linear": ("cf", "cr"), "brush": ("cf", "cr", "mu"),
              "pacejka": ("cf", "cr", "mu", "shape_f", "shape_r")}[tyres]
    nominal = np.asarray(SingleTrack(tyres=tyres).theta)
    model = SingleTrack(tyres=tyres, theta=tuple(drive.body.values()) + tuple(nominal[4:]))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = vehjax.tune.fit(EKF_DELTA, model, np.zeros((2, 2)), np.array([0.1, 1e-4]),
                              drive.measurements, drive.inputs, x0=np.zeros(2),
                              P0=np.array([0.1, 0.01]),
                              params=vehjax.tune.Fitted(params, noise=("R", "input")),
                              options=vehjax.tune.Options(progress=False))
    return res, [str(w.message) for w in caught]


def _sideslip_rms(res, drive):
    out = vehjax.filter(res.estimator, drive.measurements, drive.inputs, x0=np.zeros(2),
                        P0=np.array([0.1, 0.01]))
    beta = np.arctan(np.asarray(out.states)[:, 0] / drive.inputs[:, 1])
    return float(np.sqrt(np.mean((beta - drive.sideslip) ** 2)))


@pytest.mark.slow
@pytest.mark.parametrize("variant", ["A", "B"])
def test_saturating_fits_from_the_defaults_find_the_limit(long_drives, variant):
    """Issue 47's targets on the simulated limit drives (B held back from every choice in
    vehjax.tune.staged): from the models' nominal tyre values, tune.fit with its defaults
    fits mu within 5 % of the truth's peak, every parameter inside its domain, a likelihood
    above the nested linear model's, and a sideslip error on another realisation of the drive
    below the linear model's."""
    drive, held = long_drives[variant]
    linear, _ = _fit_default(drive, "linear")
    rms_linear = _sideslip_rms(linear, held)
    for tyres in ("brush", "pacejka"):
        res, msgs = _fit_default(drive, tyres)
        lo, hi = res.model.param_domains().bounds()
        theta = np.asarray(res.model.theta)
        assert np.all((theta > lo) & (theta < hi)), (tyres, theta)
        assert abs(res.params["mu"] / drive.mu - 1) < 0.05, (tyres, res.params["mu"], drive.mu)
        assert not res.below_nested and not res.below_floor, msgs
        assert res.loglik > res.nested.loglik
        assert res.nested.loglik == pytest.approx(linear.loglik, abs=0.1)
        assert _sideslip_rms(res, held) < rms_linear, tyres


def _no_stage_may_run(monkeypatch):
    """Every stage of the staged fit made to fail: a refusal must come before them."""
    def stage(*a, **k):
        raise AssertionError("a stage ran (something was traced) before the refusal")

    for name in ("_nested_stage", "fit_start", "compile_objective"):
        monkeypatch.setattr(staged, name, stage)


@pytest.mark.parametrize("start", ["data", "theta"])
@pytest.mark.parametrize("kw, words", [
    (dict(bounds={"mu": (3.5, 5.0)}), ["bounds", "mu", "(3.5, 5.0)", "domain (0, 3)"]),
    (dict(bounds={"cf": (-2.0, -1.0)}), ["bounds", "cf", "domain (0, inf)"]),
])
def test_the_staged_fit_refuses_what_its_last_stage_would_before_the_first(
        monkeypatch, start, kw, words):
    """Bounds wholly outside a parameter's domain and a learning rate for a line search are
    refused before the nested model's fit (which neither concerns), naming the argument."""
    _no_stage_may_run(monkeypatch)
    ys, us = np.zeros((50, 2)), np.tile([0.0, 20.0], (50, 1))
    with pytest.raises(ValueError) as err:
        vehjax.tune.fit(vehjax.filters.ekf, SingleTrack(tyres="brush"), np.eye(2), np.eye(2), ys,
                        us, x0=np.zeros(2), P0=np.eye(2),
                        params=vehjax.tune.Fitted(("cf", "mu"), **kw), start=start,
                        options=vehjax.tune.Options(progress=False))
    text = str(err.value)
    assert text.startswith(words[0] + ":")
    for w in words:
        assert w in text, (w, text)


@pytest.mark.parametrize("record", ["LBFGS", "Scoring"])
def test_a_learning_rate_is_no_option_of_a_line_search(record):
    """A learning rate for a line search (the default optimizer of a deterministic filter) is
    refused: the records of scoring and L-BFGS have none."""
    with pytest.raises(TypeError, match="learning_rate"):
        getattr(vehjax.tune, record)(learning_rate=0.1)


def test_a_learning_rate_is_left_to_a_particle_filter_whose_default_is_adam():
    from vehjax.tune import driver, likelihood

    model = SingleTrack()
    args = (model, np.eye(2), np.eye(2), vehjax.tune.Fitted(("cf",), ("Q", "R"), False))
    assert likelihood.draws_random_numbers(
        functools.partial(vehjax.filters.bootstrap_pf, n_particles=16), *args)
    assert not likelihood.draws_random_numbers(vehjax.filters.ekf, *args)
    driver.check_optimizer(vehjax.tune.Adam(learning_rate=0.1), stochastic=True)  # adam takes it
    assert driver.choose_optimizer(None, True, True) == vehjax.tune.Adam()
    with pytest.raises(ValueError, match="^optimizer: 'scoring' needs a deterministic"):
        driver.check_optimizer(vehjax.tune.Scoring(), stochastic=True)


def test_a_nested_variance_on_its_bound_starts_the_models_fit_at_the_given_value():
    """The nested fit's variances on their bound (zero) start the model's fit at the value the
    user gave, the others at the nested fit's; a full and a diagonal form alike."""
    on = {"R[ay,ay]": ("lower", 0.0, -3.1e3)}
    fitted = np.array([[1e-14, 0.0], [0.0, 3.8e-6]])
    out = staged._off_bounds(fitted, np.array([0.01, 4e-6]), "R", ("ay", "r"), on)
    np.testing.assert_array_equal(out, [[0.01, 0.0], [0.0, 3.8e-6]])
    out = staged._off_bounds(np.array([1e-14, 3.8e-6]), np.diag([0.01, 4e-6]), "R",
                             ("ay", "r"), on)
    np.testing.assert_array_equal(out, [0.01, 3.8e-6])
    assert staged._off_bounds(fitted, np.eye(2), "Q", ("vy", "r"), on) is not fitted


def test_the_nested_fits_warnings_say_they_are_the_nested_models():
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        warnings.warn("vehjax.tune: R[ay,ay] is on its lower bound 0")
        warnings.warn("a warning of another module")
    with pytest.warns(UserWarning) as out:
        staged._reissue(caught, "SingleTrack (m, iz)")
    assert [str(w.message) for w in out] == [
        "vehjax.tune (the nested SingleTrack (m, iz)'s fit): R[ay,ay] is on its lower bound 0",
        "vehjax.tune (the nested SingleTrack (m, iz)'s fit): a warning of another module"]


@pytest.mark.slow  # two fits of a 300-step drive, about a minute each
def test_a_variance_the_data_push_to_zero_is_on_its_bound_from_the_data_start():
    """Exact measurements of ay: R[ay,ay] goes to its bound 0 in the nested (linear) fit, from
    which the data start begins. It is reported on its bound, with the one-sided derivative, as
    the fit from the given values (start="theta", the second entry point) reports it, not as
    undetermined with an infinite standard error; the nested fit's warning is labelled so."""
    model = SingleTrack(tyres="brush", dt=0.02)
    scn = vehjax.scenarios.sine_steer(model, speed=15.0, amplitude=0.02, duration=6.0)
    sim = vehjax.simulate(model, scn, runs=1, key=jax.random.key(1),
                          process_std=[0.003, 0.003], meas_std=[0.0, 0.002])
    ys, us = np.asarray(sim.measurements[0]), np.asarray(sim.inputs)
    kw = dict(x0=np.zeros(2), P0=np.array([0.01, 0.001]), params=vehjax.tune.Fitted(noise=("R",)),
              options=vehjax.tune.Options(progress=False))
    out = {}
    for start in ("data", "theta"):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            out[start] = vehjax.tune.fit(vehjax.filters.ekf, model, np.full(2, 0.003**2),
                                         np.array([0.1**2, 0.002**2]), ys, us, start=start, **kw)
        texts = [str(w.message) for w in caught]
        assert any(t.startswith("vehjax.tune (the nested SingleTrack") and "R[ay,ay] is on its "
                   "lower bound 0" in t for t in texts), texts
        assert not any("do not determine" in t for t in texts), texts
    res, ref = out["data"], out["theta"]
    assert res.undetermined == () and set(res.on_bound) == {"R[ay,ay]"}
    side, bound, dlogl = res.on_bound["R[ay,ay]"]
    assert (side, bound) == ("lower", 0.0) and dlogl < 0
    np.testing.assert_allclose(dlogl, ref.on_bound["R[ay,ay]"][2], rtol=1e-3)
    assert res.R[0, 0] < 1e-9 and np.isfinite(res.std_errors["R[r,r]"])
    np.testing.assert_allclose(res.R[1, 1], ref.R[1, 1], rtol=1e-5)
    np.testing.assert_allclose(res.std_errors["R[r,r]"], ref.std_errors["R[r,r]"], rtol=1e-3)


def test_fit_from_theta_refuses_scoring_for_a_particle_filter_before_compiling(monkeypatch):
    from vehjax.tune import program

    def compiled(*a, **k):
        raise AssertionError("compiled before the refusal")

    monkeypatch.setattr(program, "compiled_loss", compiled)
    ys, us = np.zeros((50, 2)), np.tile([0.0, 20.0], (50, 1))
    with pytest.raises(ValueError, match="^optimizer: 'scoring' needs a deterministic"):
        vehjax.tune.fit_from_theta(functools.partial(vehjax.filters.bootstrap_pf,
                                                     n_particles=16), SingleTrack(), np.eye(2),
                                   np.eye(2), ys, us, x0=np.zeros(2), P0=np.eye(2),
                                   params=("cf",),
                                   options=vehjax.tune.Options(optimizer="scoring",
                                                               progress=False,
                                                               key=jax.random.key(0)))
