"""SingleTrackBank (Berntorp & Di Cairano 2018, eq. 1-10) against plain numpy / scipy references."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

import vehjax  # noqa: F401  (float64)
from vehjax.models.bank import G, SingleTrackBank, virtual_yaw_rate

from _bank_ref import continuous_matrices

MODEL = SingleTrackBank(dt=0.01)
TH = np.asarray(MODEL.theta)


def _ref_derivative(x, u, th):
    """Eq. 1-3 as printed, with eq. 2a's bank term read as - m g phi."""
    vy, r, phi, phid, phidd = x
    vx, delta = u
    m, iz, lf, lr, cf, cr = th
    af = delta - (vy + lf * r) / vx
    ar = (lr * r - vy) / vx
    vy_dot = (-m * vx * r + cf * af + cr * ar - m * G * phi) / m
    r_dot = (lf * cf * af - lr * cr * ar) / iz
    return np.array([vy_dot, r_dot, phid, phidd, 0.0])


def _simulate(model, x0, u, steps, theta=None):
    theta = model.theta if theta is None else theta
    u = jnp.asarray(u, dtype=float)

    def body(x, _):
        x = model.transition(x, u, theta)
        return x, x

    return jax.jit(lambda x: jax.lax.scan(body, x, None, length=steps))(jnp.asarray(x0, float))


def _random_points(n, seed):
    rng = np.random.default_rng(seed)
    xs = rng.normal(size=(n, 5)) * np.array([1.0, 0.3, 0.1, 0.05, 0.01])
    us = np.column_stack([rng.uniform(5.0, 35.0, n), rng.normal(0.0, 0.05, n)])
    ths = TH * rng.uniform(0.7, 1.3, size=(n, 6))
    return xs, us, ths


def test_derivative_matches_equations_2_and_3():
    xs, us, ths = _random_points(20, 0)
    got = jax.vmap(MODEL.derivative)(jnp.asarray(xs), jnp.asarray(us), jnp.asarray(ths))
    ref = np.stack([_ref_derivative(x, u, th) for x, u, th in zip(xs, us, ths)])
    assert got.dtype == jnp.float64
    np.testing.assert_allclose(np.asarray(got), ref, rtol=1e-12, atol=1e-12)


def test_transition_matches_exact_zoh_discretisation():
    # For x' = A x + b delta with delta held, one RK4 step is exactly the degree-4 Taylor
    # polynomial of exp(M dt), M = [[A, b], [0, 0]] (to rounding), and differs from scipy's exact
    # exp(M dt) by O((|lambda| dt)^5 / 5!), ~2e-6 here (|lambda| up to ~20 1/s at 10 m/s).
    xs, us, _ = _random_points(6, 1)
    us[:, 0] = np.linspace(10.0, 30.0, len(us))
    dt = MODEL.dt
    for x, u in zip(xs, us):
        a, b = continuous_matrices(u[0], TH)
        big = np.zeros((6, 6))
        big[:5, :5], big[:5, 5] = a, b
        taylor = sum(
            np.linalg.matrix_power(big * dt, k) / np.prod(np.arange(1, k + 1)) for k in range(5)
        )
        exact = scipy.linalg.expm(big * dt)
        xu = np.append(x, u[1])
        got = np.asarray(MODEL.transition(jnp.asarray(x), jnp.asarray(u), MODEL.theta))
        np.testing.assert_allclose(got, (taylor @ xu)[:5], rtol=1e-12, atol=1e-15)
        ref = (exact @ xu)[:5]
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-5 * (1 + np.abs(ref).max()))
        gain = np.asarray(MODEL.steering_noise_gain(jnp.asarray(x), jnp.asarray(u), MODEL.theta))
        np.testing.assert_allclose(gain, taylor[:5, 5], rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(gain, exact[:5, 5], rtol=1e-4, atol=1e-12)
        # the bank block is eq. 3's A_phi (as corrected), to rounding
        np.testing.assert_allclose(
            exact[2:5, 2:5], [[1, dt, dt**2 / 2], [0, 1, dt], [0, 0, 1]], rtol=0, atol=1e-15
        )
        np.testing.assert_allclose(got[2:], exact[2:5, 2:5] @ x[2:], rtol=1e-13, atol=1e-16)


def test_straight_on_flat_road_stays_straight():
    _, xs = _simulate(MODEL, np.zeros(5), [20.0, 0.0], 500)
    assert np.all(np.asarray(xs) == 0.0)
    y = MODEL.observe(xs[-1], jnp.array([20.0, 0.0]), MODEL.theta)
    assert np.all(np.asarray(y) == 0.0)


def test_mirrored_steering_and_bank_give_mirrored_response():
    rng = np.random.default_rng(2)
    x0 = rng.normal(size=5) * np.array([0.5, 0.1, 0.05, 0.01, 0.001])
    u = np.array([15.0, 0.03])
    mirror_u = np.array([15.0, -0.03])
    _, xs = _simulate(MODEL, x0, u, 200)
    _, xm = _simulate(MODEL, -x0, mirror_u, 200)
    np.testing.assert_allclose(np.asarray(xm), -np.asarray(xs), rtol=1e-12, atol=1e-15)
    y = MODEL.observe(xs[-1], jnp.asarray(u), MODEL.theta)
    ym = MODEL.observe(xm[-1], jnp.asarray(mirror_u), MODEL.theta)
    np.testing.assert_allclose(np.asarray(ym), -np.asarray(y), rtol=1e-12, atol=1e-15)
    assert abs(float(y[1])) > 1e-3  # the response is not trivially zero


@pytest.mark.parametrize("vx", [10.0, 30.0])
def test_steady_state_cornering_matches_understeer_gradient(vx):
    m, _, lf, lr, cf, cr = TH
    wheelbase = lf + lr
    delta = 0.02
    _, xs = _simulate(MODEL, np.zeros(5), [vx, delta], 1500)
    vy_ss, r_ss = np.asarray(xs[-1, :2])
    # textbook steady state (Gillespie, Rajamani): delta = L r / vx + K_us vx r with per-axle
    # stiffnesses, and the rear slip angle carries Fyr = lf / L m vx r.
    k_us = m * (lr * cr - lf * cf) / (wheelbase * cf * cr)
    r_ref = vx * delta / (wheelbase + k_us * vx**2)
    vy_ref = lr * r_ref - lf * m * vx**2 * r_ref / (wheelbase * cr)
    assert k_us > 0  # the nominal car understeers
    np.testing.assert_allclose(r_ss, r_ref, rtol=1e-9)
    np.testing.assert_allclose(vy_ss, vy_ref, rtol=1e-9, atol=1e-12)
    ay = float(MODEL.observe(xs[-1], jnp.array([vx, delta]), MODEL.theta)[0])
    np.testing.assert_allclose(ay, vx * r_ref, rtol=1e-9)  # flat road: ay = vx r


def test_constant_bank_makes_car_drift_down_slope():
    phi = 0.05  # left side higher, so down-slope is to the car's right (negative y)
    vx = 20.0
    u = jnp.array([vx, 0.0])
    x0 = np.array([0.0, 0.0, phi, 0.0, 0.0])
    d0 = np.asarray(MODEL.derivative(jnp.asarray(x0), u, MODEL.theta))
    np.testing.assert_allclose(d0[0], -G * phi, rtol=1e-14)  # pure gravity at rest in y
    _, xs = _simulate(MODEL, x0, u, 1500)
    xs = np.asarray(xs)
    assert np.all(xs[:, 0] < 0.0)  # lateral velocity down the slope from the first step on
    assert np.all(xs[:, 2] == phi)
    # steady state from the 2x2 linear system of eq. 2 solved in numpy
    a, _ = continuous_matrices(vx, TH)
    ss = np.linalg.solve(a[:2, :2], -a[:2, 2] * phi)
    np.testing.assert_allclose(xs[-1, :2], ss, rtol=1e-9)
    assert ss[1] < 0.0  # the understeering nominal car also yaws down the slope
    # the accelerometer reads the tyre forces: gravity's share g phi on top of vx r
    ay = float(MODEL.observe(jnp.asarray(xs[-1]), u, MODEL.theta)[0])
    np.testing.assert_allclose(ay, vx * ss[1] + G * phi, rtol=1e-9)


def test_bank_states_follow_exact_polynomial():
    phi0, phid0, phidd0 = 0.01, -0.004, 0.0015
    steps = 1000
    _, xs = _simulate(MODEL, [0.3, 0.02, phi0, phid0, phidd0], [25.0, 0.01], steps)
    t = MODEL.dt * np.arange(1, steps + 1)
    xs = np.asarray(xs)
    np.testing.assert_allclose(xs[:, 2], phi0 + phid0 * t + phidd0 * t**2 / 2, rtol=0, atol=1e-13)
    np.testing.assert_allclose(xs[:, 3], phid0 + phidd0 * t, rtol=0, atol=1e-14)
    assert np.all(xs[:, 4] == phidd0)
    # explicit Euler drops the T^2/2 term: it must not agree to that accuracy
    euler = SingleTrackBank(dt=0.01, integrator="euler")
    _, xe = _simulate(euler, [0.3, 0.02, phi0, phid0, phidd0], [25.0, 0.01], steps)
    assert np.max(np.abs(np.asarray(xe)[:, 2] - (phi0 + phid0 * t + phidd0 * t**2 / 2))) > 1e-5


@pytest.mark.parametrize("integrator", ["rk4", "euler"])
def test_noise_gains_are_derivatives_wrt_steering(integrator):
    model = SingleTrackBank(dt=0.02, integrator=integrator)
    xs, us, ths = _random_points(5, 3)
    h = 1e-3
    for x, u, th in zip(xs, us, ths):
        x, th = jnp.asarray(x), jnp.asarray(th)
        up, um = jnp.asarray(u + [0.0, h]), jnp.asarray(u - [0.0, h])
        f = lambda uu: np.asarray(model.transition(x, uu, th))  # noqa: E731
        fd = (f(up) - f(um)) / (2 * h)
        g = np.asarray(model.steering_noise_gain(x, jnp.asarray(u), th))
        np.testing.assert_allclose(g, fd, rtol=1e-7, atol=1e-10)
        assert g.shape == (5,) and np.all(g[2:] == 0.0) and g[0] > 0 and g[1] > 0
        # affine in delta: a finite offset w shifts the next state by exactly w g (eq. 6)
        w = 0.01
        shifted = model.transition(x, jnp.asarray(u + [0.0, w]), th)
        np.testing.assert_allclose(
            np.asarray(shifted), np.asarray(model.transition(x, jnp.asarray(u), th)) + w * g,
            rtol=1e-12, atol=1e-14,
        )
        hy = lambda uu: np.asarray(model.observe(x, uu, th))  # noqa: E731
        fd_y = (hy(up) - hy(um)) / (2 * h)
        d = np.asarray(model.measurement_noise_gain(x, jnp.asarray(u), th))
        np.testing.assert_allclose(d, [th[4] / th[0], 0, 0, 0, 0], rtol=1e-14, atol=0)
        np.testing.assert_allclose(d, fd_y, rtol=1e-8, atol=1e-12)


def test_bank_noise_gain_is_exact_jerk_discretisation():
    # Van Loan: exp([[A_z, b], [0, 0]] T) with a chain of three integrators driven by jerk b
    dt = 0.025
    big = np.zeros((4, 4))
    big[0, 1] = big[1, 2] = big[2, 3] = 1.0
    ref = scipy.linalg.expm(big * dt)[:3, 3]
    got = np.asarray(SingleTrackBank(dt=dt).bank_noise_gain())
    np.testing.assert_allclose(got[2:], ref, rtol=1e-13)
    assert np.all(got[:2] == 0.0)


def test_names_shapes_and_batching():
    assert MODEL.state_names == ("vy", "r", "phi", "phi_dot", "phi_ddot")
    assert MODEL.input_names == ("vx", "delta")
    assert MODEL.param_names == ("m", "iz", "lf", "lr", "cf", "cr")
    assert MODEL.output_names == ("ay", "r", "roll_rate", "phi", "r_virt")
    assert len(MODEL.output_units) == 5 and len(MODEL.state_units) == 5
    assert MODEL.theta.shape == (6,) and MODEL.theta.dtype == jnp.float64
    xs, us, ths = _random_points(4, 4)
    fx = jax.jit(jax.vmap(MODEL.transition))(jnp.asarray(xs), jnp.asarray(us), jnp.asarray(ths))
    fy = jax.jit(jax.vmap(MODEL.observe))(jnp.asarray(xs), jnp.asarray(us), jnp.asarray(ths))
    assert fx.shape == (4, 5) and fy.shape == (4, 5) and fy.dtype == jnp.float64
    np.testing.assert_array_equal(np.asarray(fy[:, 1]), xs[:, 1])  # r
    np.testing.assert_array_equal(np.asarray(fy[:, 4]), xs[:, 1])  # r_virt
    np.testing.assert_array_equal(np.asarray(fy[:, 2]), xs[:, 3])  # roll rate = bank rate
    np.testing.assert_array_equal(np.asarray(fy[:, 3]), xs[:, 2])  # bank angle


def test_driver_interface():
    x = jnp.array([0.2, 0.1, 0.0, 0.0, 0.0])
    assert MODEL.speed(x) is None and MODEL.pose(x) is None
    u = jax.jit(lambda d, s: MODEL.drive_input(x, d, 1.0, s, MODEL.theta))(0.05, 22.0)
    np.testing.assert_array_equal(np.asarray(u), [22.0, 0.05])
    vx, vy, r = MODEL.body_velocity(x, u, MODEL.theta)
    assert (float(vx), float(vy), float(r)) == (22.0, 0.2, 0.1)
    np.testing.assert_array_equal(np.asarray(MODEL.initial_state(20.0)), np.zeros(5))


def test_virtual_yaw_rate_recovers_rigid_body_yaw_rate():
    # free-rolling rear wheels of a car turning at r with rear-axle speed v: v +/- r l_T / 2
    r, v, track, radius = 0.3, 15.0, 1.55, 0.31
    w_rl = (v - r * track / 2) / radius
    w_rr = (v + r * track / 2) / radius
    np.testing.assert_allclose(float(virtual_yaw_rate(w_rl, w_rr, radius, track)), r, rtol=1e-14)
    batched = virtual_yaw_rate(jnp.full(3, w_rl), jnp.full(3, w_rr), radius, track)
    np.testing.assert_allclose(np.asarray(batched), r, rtol=1e-14)
    jitted = jax.jit(virtual_yaw_rate)(w_rl, w_rr, radius, track)
    np.testing.assert_allclose(float(jitted), r, rtol=1e-14)
    with pytest.raises(ValueError, match="track"):
        virtual_yaw_rate(w_rl, w_rr, radius, 0.0)
    with pytest.raises(ValueError, match="wheel_radius"):
        virtual_yaw_rate(w_rl, w_rr, -0.3, track)


def test_bad_construction_raises():
    with pytest.raises(ValueError, match="theta"):
        SingleTrackBank(theta=[1500.0, 2700.0])
    with pytest.raises(ValueError, match="dt"):
        SingleTrackBank(dt=0.0)
    with pytest.raises(ValueError, match="integrator"):
        SingleTrackBank(integrator="rk45")
