"""vehjax.studies.limit_drive: the two-track truth at the friction limit and its simulated drives.

References nobody here wrote: scipy's DOP853 for the integration, scipy's brentq for the
magic formula's peak slip; the rest checks the drives against the issue's targets (issue 47,
item 5: peaks at 1.2-1.5 g, a known peak friction coefficient, understeer at the limit).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.optimize import brentq

import vehjax  # noqa: F401  (float64)
from vehjax.studies import limit_drive as ld

G = 9.81


#: one lap and a bit (laps of 51-53 s repeat in the default 200 s drive; test_default_drives)
DURATION = 60.0


@pytest.fixture(scope="module")
def drives():
    return {v: ld.limit_drive(v, duration=DURATION) for v in ("A", "B")}


@pytest.mark.parametrize("shape, curvature", [(1.45, -0.8), (1.35, -0.4), (1.6, 0.5), (1.2, -2.0)])
def test_wheel_force_peak_and_slope(shape, curvature):
    c, mu, fz = 9.0e4, 1.4, 4000.0
    b = c / (shape * mu * fz)
    x_ref = brentq(lambda x: (1 - curvature) * x + curvature * np.arctan(x)
                   - np.tan(np.pi / (2 * shape)), 0.0, 100.0, xtol=1e-14)
    alpha, peak, slope_peak, slope_0, curve = _curve(shape, curvature, c, mu, fz)
    np.testing.assert_allclose(float(alpha), x_ref / b, rtol=1e-12)
    np.testing.assert_allclose(float(peak), mu * fz, rtol=1e-12)
    assert abs(float(slope_peak)) < 1e-6 * c
    np.testing.assert_allclose(float(slope_0), c, rtol=1e-12)
    assert float(jnp.abs(curve).max()) <= mu * fz * (1 + 1e-12)
    np.testing.assert_allclose(np.asarray(curve[::-1]), -np.asarray(curve), atol=1e-9)


@jax.jit
def _curve(shape, curvature, c, mu, fz):
    """peak slip, force there, slopes at the peak and at 0, the curve on [-1, 1] rad."""
    force = lambda a: ld.wheel_force(a, c, mu, fz, shape, curvature)  # noqa: E731
    alpha = ld.peak_slip(c, mu, fz, shape, curvature)
    grid = jnp.linspace(-1.0, 1.0, 4001)
    return alpha, force(alpha), jax.grad(force)(alpha), jax.grad(force)(0.0), force(grid)


def test_load_sensitive_stiffness_and_transfer():
    tr = ld.VARIANTS["A"][0]
    fz = ld.wheel_loads(tr, 0.8 * G)
    static = ld.wheel_loads(tr, 0.0)
    np.testing.assert_allclose(float(fz.sum()), tr.m * G, rtol=1e-12)   # transfer keeps the sum
    assert fz[1] > static[1] and fz[0] < static[0]                      # ay > 0 loads the right
    c = ld.wheel_stiffness(tr, fz)
    np.testing.assert_allclose(np.asarray(ld.wheel_stiffness(tr, static)),
                               [tr.cf / 2, tr.cf / 2, tr.cr / 2, tr.cr / 2], rtol=1e-12)
    assert c[0] + c[1] < tr.cf and c[2] + c[3] < tr.cr                  # transfer lowers it


@pytest.mark.parametrize("variant", ["A", "B"])
def test_truth_peak_mu(drives, variant):
    d = drives[variant]
    assert d.mu == min(d.axle_mu)
    for ay in (0.0, 0.5 * G, np.abs(d.ay).max()):
        front, rear = ld.axle_peak_mu(d.truth, ay)
        assert abs(front / d.truth.mu - 1) < 0.01 and abs(rear / d.truth.mu - 1) < 0.01
        assert front <= d.truth.mu and rear <= d.truth.mu


def _check_peaks(d):
    a = np.abs(d.ay) / G
    assert 1.2 <= a.max() <= 1.5
    assert (a > 1.0).mean() < 0.2
    assert np.median(a) < 0.8
    vx = d.true_inputs[:, 1]
    assert 15.0 <= vx.min() and vx.max() <= 35.5
    assert (d.ay > G).any() and (d.ay < -G).any()       # corners both ways


@pytest.mark.parametrize("variant", ["A", "B"])
def test_peaks_and_time_above_1g(drives, variant):
    _check_peaks(drives[variant])


@pytest.mark.slow
@pytest.mark.parametrize("variant", ["A", "B"])
def test_default_drives(variant):
    d = ld.limit_drive(variant)
    assert len(d.t) == 20000
    _check_peaks(d)
    front, rear = d.axle_mu
    assert abs(front / d.truth.mu - 1) < 0.01 and abs(rear / d.truth.mu - 1) < 0.01


@pytest.mark.parametrize("variant", ["A", "B"])
def test_understeers_at_the_limit(drives, variant):
    d = drives[variant]
    k = int(np.argmax(np.abs(d.ay)))
    ay, forces = ld.solve_ay(d.truth, jnp.asarray(d.states[k]), jnp.asarray(d.true_inputs[k]))
    fz = np.asarray(ld.wheel_loads(d.truth, ay))
    front, rear = ld.axle_peak_mu(d.truth, ay)
    use_front = abs(float(forces[0] + forces[1])) / (front * (fz[0] + fz[1]))
    use_rear = abs(float(forces[2] + forces[3])) / (rear * (fz[2] + fz[3]))
    assert use_rear < use_front < 1.0
    assert use_front > 0.95                            # the drive does reach the limit
    assert np.abs(d.sideslip).max() < np.deg2rad(6.0)  # and does not spin


def test_load_loop_and_driver_converge(drives):
    d = drives["A"]
    states, inputs = jnp.asarray(d.states), jnp.asarray(d.true_inputs)
    residual = ld.lateral_acceleration(d.truth, states, inputs, jnp.asarray(d.ay), passes=1) - d.ay
    assert float(jnp.abs(residual).max()) < 1e-6
    vx = inputs[:, 1]
    target = ld.lap_targets("A", d.t)[1]
    z = ld.steady_state(d.truth, jnp.asarray(target), vx)
    res = jax.vmap(lambda z, a, v: ld.steady_residual(d.truth, z, a, v))(z, jnp.asarray(target), vx)
    assert float(jnp.abs(res).max()) < 1e-8


def test_rollout_matches_dop853(drives):
    """The drive's states over 2 s around its largest |ay| (RK4 at 1 ms with the warm-started
    load loop) against DOP853 (rtol 1e-11) from the same start on the converged derivative, the
    same linearly interpolated inputs."""
    d = drives["A"]
    k0 = int(np.argmax(np.abs(d.ay))) - 100
    u = d.true_inputs[k0:k0 + 201]
    x0 = d.states[k0]
    ours = d.states[k0:k0 + 201]
    rhs = jax.jit(lambda x, u: ld.derivative(d.truth, x, u))
    ref, x = [x0], x0
    for k in range(200):
        def f(s, x, k=k):
            w = s / 0.01
            return np.asarray(rhs(jnp.asarray(x), jnp.asarray((1 - w) * u[k] + w * u[k + 1])))
        x = solve_ivp(f, (0.0, 0.01), x, method="DOP853", rtol=1e-11, atol=1e-12).y[:, -1]
        ref.append(x)
    err = np.abs(ours - np.asarray(ref)).max(axis=0)
    assert err[0] < 1e-6 and err[1] < 1e-6, err   # m/s, rad/s


def test_noise_and_fields(drives):
    d = drives["A"]
    n = len(d.t)
    assert d.inputs.shape == (n, 2) and d.measurements.shape == (n, 2)
    assert d.states.shape == (n, 2) and d.sideslip.shape == (n,) and d.ay.shape == (n,)
    np.testing.assert_allclose(d.t[1] - d.t[0], 0.01)
    assert d.body == {"m": 1650.0, "iz": 2900.0, "lf": 1.15, "lr": 1.55}
    resid = d.measurements - np.stack([d.ay, d.states[:, 1]], axis=1)
    np.testing.assert_allclose(resid.std(axis=0), [d.noise_std["ay"], d.noise_std["r"]], rtol=0.05)
    steer = d.inputs[:, 0] - d.true_inputs[:, 0]   # sensor noise and the unmodelled disturbance
    total = np.hypot(d.noise_std["delta"], d.noise_std["steer_disturbance"])
    np.testing.assert_allclose(steer.std(), total, rtol=0.25)
    np.testing.assert_allclose(d.sideslip, np.arctan(d.states[:, 0] / d.true_inputs[:, 1]))


def test_deterministic(drives):
    again = ld.limit_drive("A", duration=DURATION)
    for a, b in zip(again, drives["A"]):
        if isinstance(a, np.ndarray):
            np.testing.assert_array_equal(a, b)
    other = ld.limit_drive("A", duration=DURATION, seed=1)
    assert not np.array_equal(other.measurements, again.measurements)
    np.testing.assert_array_equal(other.t, again.t)


def test_bad_arguments():
    with pytest.raises(ValueError, match="variant"):
        ld.limit_drive("C")
    with pytest.raises(ValueError, match="noise"):
        ld.limit_drive(noise={"yaw": 0.1})
    with pytest.raises(ValueError, match="duration"):
        ld.limit_drive(duration=-1.0)
    with pytest.raises(ValueError, match="noise"):
        ld.limit_drive(noise={"ay": -0.1})
