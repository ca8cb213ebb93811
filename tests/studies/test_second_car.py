"""vehjax.studies.second_car (issue 53): the truth's integration, the accelerometer's vibration, the spec
sheet, the runs; and benchmarks/textbook_observer.py against vehjax's EKF on the linear model."""

import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import vehjax
from vehjax.studies import second_car as sc

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import textbook_observer as tob  # noqa: E402

G = 9.81


@pytest.fixture(scope="module")
def runs():
    return {k: sc.second_car(k) for k in (1, 2, 3)}


@pytest.fixture(scope="module")
def short():
    return sc.second_car(1, duration=10.0)


def test_rollout_matches_dop853(short):
    """1 s of RK4 at 1 ms from the run's state at the first corner's peak against DOP853."""
    d = short
    k0 = int(np.argmax(np.abs(d.ay[:1200])))
    k1 = k0 + 200
    t = d.t[k0:k1 + 1]
    u = d.true_inputs[k0:k1 + 1]
    f = jax.jit(lambda x, v: sc.derivative(sc.TRUTH, x, v))

    def rhs(s, x):
        v = np.array([np.interp(s, t, u[:, 0]), np.interp(s, t, u[:, 1])])
        return np.asarray(f(jnp.asarray(x), jnp.asarray(v)))

    ref = solve_ivp(rhs, (t[0], t[-1]), d.full_states[k0], method="DOP853", t_eval=t,
                    rtol=1e-10, atol=1e-10).y.T
    got = d.full_states[k0:k1 + 1]
    assert abs(d.ay[k0]) > 0.8 * G  # the window holds a real corner
    np.testing.assert_allclose(got[:, :4], ref[:, :4], rtol=0, atol=1e-8)
    # forces [N] of up to 12,000: 1e-7 relative (DOP853 steps across the inputs' kinks)
    np.testing.assert_allclose(got[:, 4:], ref[:, 4:], rtol=1e-7, atol=1e-3)
    assert np.ptp(got[:, 0]) > 0.05 and np.ptp(got[:, 4:]) > 100.0  # the window moves


def test_steady_state_loads_equal_the_planar_truth():
    """With phi at its steady value and p = 0 the dynamic loads are limit_drive's (planar)."""
    ay = 9.0
    b = sc.TRUTH.body
    hs = b.h - sc.TRUTH.roll_height
    phi = b.m * hs * ay / (sc.TRUTH.roll_stiffness - b.m * G * hs)
    np.testing.assert_allclose(sc.wheel_loads(sc.TRUTH, phi, 0.0, ay),
                               vehjax.studies.limit_drive.wheel_loads(sc.planar(sc.TRUTH), ay),
                               rtol=1e-12)
    # a roll rate moves load through the dampers: the loads are dynamic
    assert not np.allclose(sc.wheel_loads(sc.TRUTH, phi, 0.2, ay),
                           sc.wheel_loads(sc.TRUTH, phi, 0.0, ay), rtol=1e-3)


def test_vibration_negative_lag_one_and_in_band(runs):
    d = runs[1]
    noise = d.measurements[:, 0] - d.ay
    lag1 = np.corrcoef(noise[:-1], noise[1:])[0, 1]
    assert -0.6 < lag1 < -0.3
    f = np.fft.rfftfreq(noise.size, d.dt)
    power = np.abs(np.fft.rfft(noise)) ** 2
    band = (f >= 40.0) & (f <= 100.0)
    assert power[band].sum() / power.sum() > 0.9
    assert np.std(d.vibration) == pytest.approx(sc.NOISE["vibration"], rel=1e-9)
    # the gyro's noise is white
    gyro = d.measurements[:, 1] - d.states[:, 1]
    assert abs(np.corrcoef(gyro[:-1], gyro[1:])[0, 1]) < 0.05


def test_spec_sheet_and_runs(runs):
    spec = runs[1].spec
    assert spec["iz"] * 2.5 == pytest.approx(sc.TRUTH.body.iz)
    assert sc.TRUTH.body.iz > 6000.0 and 1500.0 <= spec["m"] <= 1700.0
    assert 2.6 < spec["lf"] + spec["lr"] < 2.8 and spec["lf"] < spec["lr"]  # front-heavy (FWD)
    for d in runs.values():
        assert d.t.size == 17600 and d.dt == 0.005
        assert np.all(np.isfinite(d.full_states)) and np.all(d.inputs[:, 1] > 5.0)
    peaks = [np.abs(d.ay).max() / G for d in runs.values()]
    assert 1.15 < max(peaks) < 1.3 and min(peaks) > 1.0
    speeds = [d.inputs[:, 1].mean() for d in runs.values()]
    assert min(abs(a - b) for i, a in enumerate(speeds) for b in speeds[i + 1:]) > 2.0
    s1, s2 = runs[1].inputs[:, 0], runs[2].inputs[:, 0]
    assert abs(np.corrcoef(s1, s2)[0, 1]) < 0.5
    assert np.std(runs[1].sideslip) > np.deg2rad(0.3)   # the sideslip is worth estimating
    # the body rolls: about 3.9 deg/g at the peak (the docstring's steady roll gradient)
    d = runs[1]
    gradient = np.degrees(np.abs(d.full_states[:, 2]).max()) / (np.abs(d.ay).max() / G)
    assert 3.5 < gradient < 4.3


def test_bad_run_names_argument():
    with pytest.raises(ValueError, match="run"):
        sc.second_car(4)
    with pytest.raises(ValueError, match="run"):
        sc.second_car(True)
    with pytest.raises(ValueError, match="duration"):
        sc.second_car(1, duration=-1.0)


def test_textbook_observer_matches_vehjax_ekf(short):
    """The numpy recursion equals vehjax's EKF on the linear SingleTrack with the same values
    (the model is linear, so the EKF is the KF): validates both."""
    d, spec = short, short.spec
    nz = tob.TEXTBOOK_NOISE
    out = tob.textbook_observer(d.measurements, d.inputs, spec, d.dt)
    beta = np.arctan(out.states[:, 0] / d.inputs[:, 1])
    assert d.t.size == 2000 and np.all(np.isfinite(beta))
    assert np.sqrt(np.mean((beta - d.sideslip) ** 2)) < np.deg2rad(3.0)
    model = vehjax.models.SingleTrack(dt=d.dt, theta=tuple(spec[k] for k in
                                                            ("m", "iz", "lf", "lr", "cf", "cr")))
    est = vehjax.filters.ekf(model, np.square(nz["q"]), np.array([nz["ay"], nz["r"]]) ** 2,
                             input_noise={"delta": nz["delta"]})
    ref = vehjax.filter(est, d.measurements, d.inputs, x0=np.zeros(2), P0=np.array([0.1, 0.01]))
    np.testing.assert_allclose(out.states, np.asarray(ref.states), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(out.loglik, np.asarray(ref.loglik), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(out.nis, np.asarray(ref.nis), rtol=1e-8, atol=1e-10)
    # and it is not trivially equal: another iz gives another estimate
    other = tob.textbook_observer(d.measurements, d.inputs, {**spec, "iz": sc.TRUTH.body.iz}, d.dt)
    assert np.max(np.abs(other.states[:, 0] - out.states[:, 0])) > 1e-3


def test_discretise_against_series():
    """Phi and Gamma of RK4 converge to the exact zero-order hold (matrix exponential)."""
    A, B, _, _ = tob.linear_matrices(sc.spec_sheet(), 20.0)
    Phi, Gamma = tob.discretise(A, B, 0.005, 2)
    # exact ZOH by the augmented matrix exponential (Taylor series, small norm)
    M = np.zeros((3, 3))
    M[:2, :2], M[:2, 2] = A * 0.005, B * 0.005
    E, term = np.eye(3), np.eye(3)
    for k in range(1, 30):
        term = term @ M / k
        E = E + term
    np.testing.assert_allclose(Phi, E[:2, :2], atol=1e-7)
    np.testing.assert_allclose(Gamma, E[:2, 2], rtol=1e-6)
