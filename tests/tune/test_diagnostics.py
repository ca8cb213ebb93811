"""vehjax.tune.diagnostics and vehjax.tune.innovations: the score tests of the parameters a fit
held fixed and the per-output innovation checks.

References nobody here wrote: an exact Kalman filter's log-likelihood in numpy (a scalar linear
model) with central differences, a refit by scipy.optimize, vehjax.filter's own NIS, and the
truth of a simulated drive.
"""

import math
import warnings

import jax
import numpy as np
import pytest
from scipy.optimize import minimize

import vehjax
from vehjax.models import Model, SingleTrack
from vehjax.tune import diagnostics, innovations
from vehjax.tune.likelihood import prepare

A, B, QV, RV, T = 0.9, 0.5, 0.01, 0.04, 400


def _scalar_model(b):
    return Model(transition=lambda x, u, th: th[0] * x + th[1] * u,
                 observe=lambda x, u, th: x, dt=0.1, state_names=("x",),
                 param_names=("a", "b", "c"), input_names=("u",), output_names=("y",),
                 theta=[A, b, 1.0])


def _scalar_data(seed):
    rng = np.random.default_rng(seed)
    t = np.arange(T)
    u = np.sin(2 * np.pi * t / 40.0) + 0.5 * rng.standard_normal(T)
    x, ys = 0.0, []
    for k in range(T):
        x = A * x + B * u[k] + math.sqrt(QV) * rng.standard_normal()
        ys.append(x + math.sqrt(RV) * rng.standard_normal())
    return np.array(ys)[:, None], u[:, None]


def _np_loglik(z, ys, us, log_b=True):
    """Exact Kalman-filter log-likelihood of the scalar model in the fit's coordinates
    z = (log std Q, log std R, log a, log b) (b itself with ``log_b=False``); x0 = 0, P0 = 1."""
    Q, R, a = math.exp(2 * z[0]), math.exp(2 * z[1]), math.exp(z[2])
    b = math.exp(z[3]) if log_b else z[3]
    x, P, ll = 0.0, 1.0, 0.0
    for y, u in zip(ys[:, 0], us[:, 0]):
        x, P = a * x + b * u, a * a * P + Q
        S = P + R
        e = y - x
        ll -= 0.5 * (math.log(2 * math.pi * S) + e * e / S)
        K = P / S
        x, P = x + K * e, (1 - K) * P
    return ll


def _np_derivatives(z, ys, us, h=1e-4, log_b=True):
    n = len(z)
    E = np.eye(n) * h
    ll = lambda v: _np_loglik(v, ys, us, log_b)  # noqa: E731
    g = np.array([(ll(z + E[i]) - ll(z - E[i])) / (2 * h) for i in range(n)])
    H = np.empty((n, n))
    for i in range(n):
        for j in range(n):
            H[i, j] = (ll(z + E[i] + E[j]) - ll(z + E[i] - E[j]) - ll(z - E[i] + E[j])
                       + ll(z - E[i] - E[j])) / (4 * h * h)
    return g, H


def _scalar_fit(b_held, seed=0):
    ys, us = _scalar_data(seed)
    model = _scalar_model(b_held)
    args = (vehjax.filters.ekf, model, np.array([0.02]), np.array([0.02]), ys, us)
    kw = dict(x0=np.zeros(1), P0=np.ones(1), params=vehjax.tune.Fitted(("a",), noise=("Q", "R")))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = vehjax.tune.fit_from_theta(*args, **kw, options=vehjax.tune.Options(progress=False))
    obj, setup = prepare(*args, x0=kw["x0"], P0=kw["P0"], params=("a",))
    return res, obj, setup, ys, us, [str(w.message) for w in caught]


#: b held 3 % above the truth (0.5) and 4 % above the data's optimum (0.493): LM ~ 7
B_OFF = 0.515


@pytest.fixture(scope="module")
def slightly_off():
    return _scalar_fit(B_OFF)


def test_score_and_information_match_numpy_differences(slightly_off):
    res, obj, setup, ys, us, _ = slightly_off
    names, score, info, opg, _, _ = diagnostics.augmented_information(res, setup, obj.data,
                                                                      None, ("b",))
    assert names == ("Q[x,x]", "R[y,y]", "a", "b")
    z = np.array([0.5 * math.log(res.Q[0, 0]), 0.5 * math.log(res.R[0, 0]),
                  math.log(res.params["a"]), math.log(B_OFF)])
    g, H = _np_derivatives(z, ys, us)
    assert abs(g[3]) > 10  # b is off: a large score, the fitted ones ~0
    np.testing.assert_allclose(score, g, rtol=1e-5, atol=1e-3)
    np.testing.assert_allclose(info, -H, rtol=1e-4, atol=1e-2 * np.max(np.abs(H)) * 1e-3)
    # the test in b itself (the tested parameter's physical coordinate) from numpy's block
    zb = np.concatenate([z[:3], [B_OFF]])
    gb, Hb = _np_derivatives(zb, ys, us, h=1e-5, log_b=False)
    inv = np.linalg.inv(-Hb)
    t = res.score_tests["b"]
    assert t.statistic == pytest.approx(gb[3] ** 2 * inv[3, 3], rel=1e-4)
    assert t.score == pytest.approx(gb[3], rel=1e-5)
    assert t.one_step == pytest.approx(B_OFF + gb[3] * inv[3, 3], rel=1e-5)
    # the outer product of the per-step scores: positive definite, near the information
    assert np.all(np.linalg.eigvalsh(opg) > 0)
    np.testing.assert_allclose(np.diag(opg), np.diag(info), rtol=0.5)
    assert t.gain == pytest.approx(t.statistic / 2, rel=1e-12)
    assert t.p_value == pytest.approx(math.erfc(math.sqrt(t.statistic / 2)), rel=1e-9)
    assert t.value == B_OFF


def test_predicted_gain_and_one_step_agree_with_a_refit(slightly_off):
    res, _, _, ys, us, _ = slightly_off
    z = np.array([0.5 * math.log(res.Q[0, 0]), 0.5 * math.log(res.R[0, 0]),
                  math.log(res.params["a"]), math.log(B_OFF)])
    ref = minimize(lambda v: -_np_loglik(v, ys, us), z, method="BFGS",
                   options={"gtol": 1e-8})
    gain = -ref.fun - _np_loglik(z, ys, us)
    assert res.loglik == pytest.approx(_np_loglik(z, ys, us), abs=1e-6)
    t = res.score_tests["b"]
    assert gain > 2
    # agreement to first order in the distance: 17 % here (25 % at 0.52, 44 % at 0.53)
    assert t.gain == pytest.approx(gain, rel=0.2)
    b_opt = math.exp(ref.x[3])
    assert abs(t.one_step - b_opt) < 0.3 * abs(B_OFF - b_opt)


def test_an_unused_parameter_gets_nan_and_p_above_the_threshold_is_not_reported(slightly_off):
    res, *_, caught = slightly_off
    c = res.score_tests["c"]
    assert math.isnan(c.statistic) and math.isnan(c.p_value) and c.value == 1.0
    assert set(res.score_tests) == {"b", "c"}
    assert 1e-3 < res.score_tests["b"].p_value < 0.05  # significant, not contradicted
    assert "data reject" not in res.summary() and not any("held fixed" in m for m in caught)
    assert set(res.innovations) == {"y"}


def test_far_off_value_is_rejected_with_tiny_p():
    res, *_, caught = _scalar_fit(1.0)
    t = res.score_tests["b"]
    assert t.p_value < 1e-12 and diagnostics.rejected(t)
    assert t.one_step < 0.8  # towards the truth 0.5
    assert "b = 1 [-] (held fixed): the data reject it" in res.summary()
    assert any("b = 1 [-] (held fixed)" in m for m in caught)


def test_true_value_is_not_rejected():
    ps = []
    for seed in (1, 2, 3):
        res, *_ = _scalar_fit(B, seed)
        ps.append(res.score_tests["b"].p_value)
        assert "data reject" not in res.summary()
    assert min(ps) > 1e-3, ps


@pytest.mark.slow
def test_true_value_p_values_are_roughly_uniform():
    """Monte Carlo: at the true b the score test's p-value is about uniform (LM ~ chi2_1)."""
    ps = np.array([_scalar_fit(B, seed)[0].score_tests["b"].p_value for seed in range(10, 50)])
    assert 0.02 <= np.mean(ps < 0.1) <= 0.25
    assert 0.3 <= np.mean(ps < 0.5) <= 0.7


def test_lm_statistic_is_nan_for_singular_information():
    assert all(math.isnan(v) for v in diagnostics.lm_statistic(2.0, np.zeros((2, 2))))
    assert all(math.isnan(v) for v in diagnostics.lm_statistic(
        2.0, np.array([[1.0, 1.0], [1.0, 1.0]])))
    lm, step = diagnostics.lm_statistic(2.0, np.array([[4.0, 1.0], [1.0, 2.0]]))
    inv = np.linalg.inv(np.array([[4.0, 1.0], [1.0, 2.0]]))
    assert lm == pytest.approx(4.0 * inv[1, 1]) and step == pytest.approx(2.0 * inv[1, 1])


# --- innovations --------------------------------------------------------------------------

def _drive(model_truth, T=300, seed=0, q=(1e-3, 1e-4)):
    rng = np.random.default_rng(seed)
    t = np.arange(T) * model_truth.dt
    delta = 0.03 * np.sin(2 * np.pi * 0.5 * t) + 0.02 * np.sin(2 * np.pi * 1.3 * t)
    us = np.stack([delta, np.full(T, 20.0)], 1)
    f = jax.jit(lambda x, u: model_truth.transition(x, u, model_truth.theta))
    h = jax.jit(lambda x, u: model_truth.observe(x, u, model_truth.theta))
    x, ys = np.zeros(2), []
    for k in range(T):
        x = np.asarray(f(x, us[k])) + rng.normal(0, q)
        ys.append(np.asarray(h(x, us[k])) + rng.normal(0, [0.3, 0.005]))
    return np.array(ys), us


@pytest.mark.parametrize("input_noise", [None, {"delta": 0.002}])
def test_recomputed_ekf_nis_equals_the_filters(input_noise):
    m = SingleTrack()
    ys, us = _drive(m.with_theta(iz=6000.0))
    ys[10, 0] = np.nan
    ys[20, 1] = np.nan
    Q, R, P0 = np.diag([1e-6, 1e-8]), np.diag([0.09, 2.5e-5]), np.eye(2) * 0.1
    est = vehjax.filters.ekf(m, Q, R, input_noise=input_noise)
    out = vehjax.filter(est, ys, us, x0=np.zeros(2), P0=P0)
    Lu = vehjax.filters.input_noise.input_factor(input_noise, m.input_names)
    e, S = innovations.innovations(m, Q, R, ys[None], us, np.asarray(out.states)[None],
                                   np.asarray(out.covariances)[None], np.zeros(2), P0, Lu)
    e, S = e[0], S[0]
    full = np.all(np.isfinite(ys), axis=1)
    nis = np.einsum("ti,ti->t", e, np.linalg.solve(S, e[..., None])[..., 0])
    np.testing.assert_allclose(nis[full], np.asarray(out.nis)[full], rtol=1e-9, atol=1e-12)
    # one component missing: the NIS of the other alone
    assert np.isnan(e[10, 0]) and e[10, 1] ** 2 / S[10, 1, 1] == pytest.approx(
        float(out.nis[10]), rel=1e-9)
    checks = vehjax.tune.check_innovations(m, Q, R, ys, us, out, x0=np.zeros(2), P0=P0,
                                           input_noise=input_noise)
    assert checks["ay"].n == 299 and checks["r"].n == 299 and checks["ay"].lags == 20
    assert checks["r"].nis_mean > 2  # iz is wrong and Q small: the filter is overconfident


def test_check_innovations_on_a_study_and_bad_input():
    m = SingleTrack()
    ys = np.stack([_drive(m, 200, s)[0] for s in (0, 1)])
    us = _drive(m, 200)[1]
    Q, R = np.diag([1e-6, 1e-8]), np.diag([0.09, 2.5e-5])
    est = vehjax.filters.ekf(m, np.diag([1e-6, 1e-8]), R)
    out = vehjax.run(est, ys, us, x0=np.zeros(2), P0=np.eye(2), return_covariances=True,
                     progress=False)
    checks = vehjax.tune.check_innovations(m, Q, R, ys, us, out, x0=np.zeros(2), P0=np.eye(2))
    assert checks["ay"].n == 400 and set(checks) == {"ay", "r"}
    one = vehjax.filter(est, ys[0], us, x0=np.zeros(2), P0=np.eye(2), return_covariances=False)
    with pytest.raises(ValueError, match="^states"):
        vehjax.tune.check_innovations(m, Q, R, ys[0], us, one, x0=np.zeros(2), P0=np.eye(2))
    with pytest.raises(ValueError, match="^states"):
        vehjax.tune.check_innovations(m, Q, R, ys[0], us, np.zeros((5, 2)), np.zeros((5, 2, 2)),
                                      x0=np.zeros(2), P0=np.eye(2))
    with pytest.raises(ValueError, match="^covariances"):
        vehjax.tune.check_innovations(m, Q, R, ys, us, out.states, x0=np.zeros(2), P0=np.eye(2))
    with pytest.raises(ValueError, match="^lags"):
        vehjax.tune.check_innovations(m, Q, R, ys, us, out, x0=np.zeros(2), P0=np.eye(2),
                                      lags=0)
    with pytest.raises(ValueError, match="^R"):
        vehjax.tune.check_innovations(m, Q, -R, ys, us, out, x0=np.zeros(2), P0=np.eye(2))
    with pytest.raises(ValueError, match="^input_noise"):
        vehjax.tune.check_innovations(m, Q, R, ys, us, out, x0=np.zeros(2), P0=np.eye(2),
                                      input_noise={"steer": 0.01})


# --- the car --------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def car_drive():
    """10 s of a sinusoidal steering drive of a car whose yaw inertia is 2.5 x the spec's."""
    return _drive(SingleTrack().with_theta(iz=2.5 * 2700.0), T=1000, q=(1e-3, 1e-4))


def _car_fit(drive, iz_held, release=False):
    ys, us = drive
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = vehjax.tune.fit(vehjax.filters.ekf, SingleTrack().with_theta(iz=iz_held),
                              np.diag([1e-6, 1e-8]), np.diag([0.05, 1e-5]), ys, us,
                              x0=np.zeros(2), P0=np.eye(2) * 0.1,
                              params=vehjax.tune.Fitted(("cf", "cr"), noise=("R",)),
                              options=vehjax.tune.Options(progress=False),
                              start=vehjax.tune.Start(release=release))
    return res, [str(w.message) for w in caught]


def test_single_track_names_the_wrong_yaw_inertia(car_drive):
    res, caught = _car_fit(car_drive, 2700.0)  # held as given (release=False)
    assert res.params["cf"] < 0.5 * 1.2e5  # the fitted stiffnesses absorb the wrong iz
    assert "iz = 2700 [kg m^2] (held fixed): the data reject it" in res.summary()
    assert any("iz = 2700" in m for m in caught)
    t = res.score_tests["iz"]
    assert t.gain > 100 and t.p_value < 1e-16
    assert abs(t.one_step - 6750.0) < 0.25 * (6750.0 - 2700.0)  # most of the way to the truth
    # the mean NIS is in band (the fitted R absorbed it) but the yaw rate's innovations are
    # coloured
    assert 0.8 < res.innovations["r"].nis_mean < 1.2
    assert innovations.coloured(res.innovations["r"])
    assert "innovations of r are coloured: lag-1 autocorrelation 0.3" in res.summary()


def test_single_track_at_the_true_yaw_inertia_is_not_contradicted(car_drive):
    res, _ = _car_fit(car_drive, 2.5 * 2700.0)
    assert res.params["cf"] == pytest.approx(1.2e5, rel=0.05)
    assert not any(diagnostics.rejected(t) for t in res.score_tests.values())
    assert "data reject" not in res.summary() and "coloured" not in res.summary()


def test_fit_releases_the_wrong_yaw_inertia_under_its_data_sheet_prior(car_drive):
    """The default fit (release=True) fits the rejected iz under SingleTrack's 30 % prior: the
    stiffnesses come back to the truth, and the report says what was released."""
    res, caught = _car_fit(car_drive, 2700.0, release=True)
    assert set(res.released) == {"iz"} and res.released["iz"].value == 2700.0
    assert res.priors["iz"] == SingleTrack().with_theta(iz=2700.0).spec_priors()["iz"]
    assert res.params["iz"] == pytest.approx(6750.0, rel=0.1)
    assert res.params["cf"] == pytest.approx(1.2e5, rel=0.1)
    assert res.pulls["iz"] == pytest.approx(np.log(res.params["iz"] / 2700.0) / 0.3)
    text = "iz = 2700 [kg m^2] was given, and the data reject it"
    assert text in res.summary() and any(text in m for m in caught)
    # the superseded first fit's warnings are not raised ("fit it too, or correct it")
    assert not any("iz = 2700 [kg m^2] (held fixed)" in m for m in caught)
    assert "iz" not in res.score_tests  # fitted now
