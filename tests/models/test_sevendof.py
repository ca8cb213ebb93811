"""7-DOF model (Wang et al. 2016, eq. 1-20) against the paper's equations written out plainly."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import vehjax as vj
from vehjax.models.sevendof import _ETD_C, _ETD_TABLE, SevenDOF, _phi_functions

G = 9.81
EPS = 0.5  # m/s, the documented regularisation of the slip denominator
# Pacejka '89 example lateral set, typed in from the published table; camber 0.5 deg.
A = (1.65, -34.0, 1250.0, 3036.0, 12.8, 0.00501, -0.02103, 0.77394, 0.0022890, 0.013442,
     0.003709, 19.1656, 1.21356, 6.26206)
GAMMA = 0.5


def mf(X, B, C, D, E, Sh, Sv):
    x = X + Sh
    return D * np.sin(C * np.arctan(B * x - E * (B * x - np.arctan(B * x)))) + Sv


def fy_right(alpha_deg, fz):
    """Pacejka '89 lateral force, Fz in kN."""
    C = A[0]
    D = (A[1] * fz + A[2]) * fz
    B = A[3] * np.sin(2 * np.arctan(fz / A[4])) * (1 - A[5] * GAMMA) / (C * D)
    return mf(alpha_deg, B, C, D, A[6] * fz + A[7], A[8] * GAMMA + A[9] * fz + A[10],
              A[11] * fz * GAMMA + A[12] * fz + A[13])


def fx_tyre(slip_pct, fz):
    """Longitudinal law as documented: lateral C, D, E, Sh, Sv; BCD of the published b-set shape
    (130, 276, 0.0886) scaled to the lateral BCD at 3.16 kN."""
    k = (A[3] * np.sin(2 * np.arctan(3.16 / A[4])) * (1 - A[5] * GAMMA)
         / ((130.0 * 3.16**2 + 276.0 * 3.16) * np.exp(-0.0886 * 3.16)))
    C = A[0]
    D = (A[1] * fz + A[2]) * fz
    B = k * (130.0 * fz**2 + 276.0 * fz) * np.exp(-0.0886 * fz) / (C * D)
    return mf(slip_pct, B, C, D, A[6] * fz + A[7], A[8] * GAMMA + A[9] * fz + A[10],
              A[11] * fz * GAMMA + A[12] * fz + A[13])


def paper_rhs(x, inp, th, passes=200):
    """Eq. 1-14 in ISO axes (y left; left wheels at +t/2), Mz neglected; loads by plain
    fixed-point iteration of eq. 7-8 to convergence. Returns (xdot, derived, loads)."""
    U, V, R = x[:3]
    w = np.asarray(x[3:])
    d, T = inp[0], np.asarray(inp[1:])
    m, Iz, a, b, tf, tr, h, re, Iw = th
    l = a + b
    # eq. 9-10
    al = np.array([
        d - np.arctan((V + a * R) / (U - tf / 2 * R)),
        d - np.arctan((V + a * R) / (U + tf / 2 * R)),
        -np.arctan((V - b * R) / (U - tr / 2 * R)),
        -np.arctan((V - b * R) / (U + tr / 2 * R)),
    ])
    # eq. 12-14, wheel-centre velocity along the wheel heading
    uw = np.array([
        (U - tf / 2 * R) * np.cos(d) + (V + a * R) * np.sin(d),
        (U + tf / 2 * R) * np.cos(d) + (V + a * R) * np.sin(d),
        U - tr / 2 * R,
        U + tr / 2 * R,
    ])
    s = (re * w - uw) / np.sqrt(uw**2 + EPS**2)
    deg = np.degrees(al)

    def forces(fz):
        kn = fz / 1000.0
        Fx = np.array([fx_tyre(100 * s[i], kn[i]) for i in range(4)])
        Fy = np.array([-fy_right(-deg[0], kn[0]), fy_right(deg[1], kn[1]),
                       -fy_right(-deg[2], kn[2]), fy_right(deg[3], kn[3])])
        return Fx, Fy

    def accel(Fx, Fy):
        ax = (Fx[0] * np.cos(d) + Fx[1] * np.cos(d) + Fx[2] + Fx[3]
              - Fy[0] * np.sin(d) - Fy[1] * np.sin(d)) / m  # eq. 2
        ay = (Fx[0] * np.sin(d) + Fx[1] * np.sin(d) + Fy[0] * np.cos(d) + Fy[1] * np.cos(d)
              + Fy[2] + Fy[3]) / m  # eq. 4
        return ax, ay

    def loads(ax, ay):  # eq. 7-8; ay > 0 (to the left) loads the right wheels
        return np.array([
            (m * G / 2 - m * ay * h / tf) * b / l - 0.5 * m * ax * h / l,
            (m * G / 2 + m * ay * h / tf) * b / l - 0.5 * m * ax * h / l,
            (m * G / 2 - m * ay * h / tr) * a / l + 0.5 * m * ax * h / l,
            (m * G / 2 + m * ay * h / tr) * a / l + 0.5 * m * ax * h / l,
        ])

    ax = ay = 0.0
    for _ in range(passes):
        ax, ay = accel(*forces(loads(ax, ay)))
    fz = loads(ax, ay)
    Fx, Fy = forces(fz)
    ax, ay = accel(Fx, Fy)
    Fxp = Fx * np.cos(d) - Fy * np.sin(d)
    Fyp = Fy * np.cos(d) + Fx * np.sin(d)
    Gamma = (-tf / 2 * Fxp[0] + tf / 2 * Fxp[1] - tr / 2 * Fx[2] + tr / 2 * Fx[3]
             + a * Fyp[0] + a * Fyp[1] - b * Fy[2] - b * Fy[3])  # eq. 5, ISO signs
    xdot = np.concatenate([[ax + V * R, ay - U * R, Gamma / Iz], (T - re * Fx) / Iw])  # eq. 1-6
    derived = np.array([U, V, ax, ay, R, np.arctan(V / U), Gamma])  # eq. 18, beta by eq. 11
    return xdot, derived, fz


@pytest.fixture(scope="module")
def model():
    return MODEL


MODEL = SevenDOF()
# derivative, eq. 18 vector and loads in one compiled call, shared by the tests below
EVAL = jax.jit(lambda x, u, th: (MODEL.derivative(x, u, th), MODEL.derived(x, u, th),
                                 MODEL.wheel_loads(x, u, th)))


def _random_points(n, seed):
    rng = np.random.default_rng(seed)
    nominal = np.asarray(SevenDOF().theta)
    for _ in range(n):
        th = nominal * rng.uniform(0.9, 1.1, size=9)
        U = rng.uniform(10.0, 35.0)
        x = np.concatenate([[U, rng.normal() * 0.3, rng.uniform(-1, 1) * 6.0 / U],
                            U / th[7] * (1 + 0.004 * rng.normal(size=4))])
        inp = np.concatenate([[rng.uniform(-0.06, 0.06)], rng.normal(size=4) * 200.0])
        yield x, inp, th


def test_derivative_matches_paper_equations():
    for x, inp, th in _random_points(25, 0):
        xdot, derived, fz = paper_rhs(x, inp, th)
        assert np.all(fz > 500.0)  # away from the wheel-lift floor
        got_xdot, got_derived, got_fz = EVAL(jnp.asarray(x), jnp.asarray(inp), jnp.asarray(th))
        # The model resolves the load loop in a fixed number of Newton steps; their residual
        # (~1e-7 m/s^2, ~1e-4 N here) sets the tolerance.
        np.testing.assert_allclose(got_xdot, xdot, rtol=1e-6, atol=1e-5)
        np.testing.assert_allclose(got_derived, derived, rtol=1e-6, atol=1e-5)
        np.testing.assert_allclose(got_fz, fz, rtol=1e-6)


N_STEPS = 400  # 4 s; one length for every closed-loop run so the drive compiles once


@eqx.filter_jit
def _drive(model, x0, steer, speed, gain, accel):
    def step(x, d):
        a = gain * (speed - model.speed(x)) + accel
        u = model.drive_input(x, d, a, speed, model.theta)
        return model.transition(x, u, model.theta), x

    return jax.lax.scan(step, x0, steer)[1]


def drive(model, speed, steer=0.0, gain=2.0, accel=0.0):
    """States (N_STEPS, 7) from initial_state(speed) under a steer profile (scalar or (N_STEPS,)),
    with accel = gain (speed - u) + accel fed to drive_input (gain = accel = 0: zero torque)."""
    steer = jnp.broadcast_to(jnp.asarray(steer, dtype=jnp.float64), (N_STEPS,))
    f = lambda v: jnp.asarray(v, dtype=jnp.float64)  # arrays, not static Python floats
    return _drive(model, model.initial_state(speed), steer, f(speed), f(gain), f(accel))


def test_straight_driving_gives_no_yaw_and_no_lateral_velocity(model):
    xs = drive(model, 20.0)
    assert bool(jnp.all(jnp.isfinite(xs)))
    assert float(jnp.max(jnp.abs(xs[:, 1:3]))) < 1e-12
    np.testing.assert_allclose(xs[-1, 0], 20.0, atol=1e-3)
    # left and right wheels of an axle turn alike
    np.testing.assert_allclose(xs[:, 3], xs[:, 4], rtol=1e-12)
    np.testing.assert_allclose(xs[:, 5], xs[:, 6], rtol=1e-12)


def test_mirrored_steering_gives_mirrored_response(model):
    t = jnp.arange(N_STEPS) * model.dt
    steer = 0.04 * jnp.sin(2 * jnp.pi * 0.5 * t)
    a = drive(model, 22.0, steer)
    b = drive(model, 22.0, -steer)
    assert float(jnp.max(jnp.abs(a[:, 2]))) > 0.1  # a real manoeuvre
    np.testing.assert_allclose(b[:, 0], a[:, 0], rtol=1e-10)
    np.testing.assert_allclose(b[:, 1:3], -a[:, 1:3], rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(b[:, [4, 3, 6, 5]], a[:, 3:7], rtol=1e-10)  # left <-> right


def test_free_rolling_at_constant_speed_loses_speed_only_slowly(model):
    xs = drive(model, 20.0, gain=0.0)  # zero torque on every wheel
    assert float(jnp.max(jnp.abs(model.drive_input(xs[0], 0.0, 0.0, 20.0, model.theta)))) == 0.0
    assert bool(jnp.all(jnp.isfinite(xs)))
    # No rolling resistance or drag in the paper's model: 4 s of coasting barely change u.
    assert abs(float(xs[-1, 0]) - 20.0) < 1e-3
    # The wheels settle at the free-rolling slip of the tyre's zero-force offsets (< 0.2 %).
    slip = 0.36 * xs[-1, 3:] / xs[-1, 0] - 1.0
    assert float(jnp.max(jnp.abs(slip))) < 2e-3
    # ... and stay there: no wheel-spin oscillation left after the first steps.
    assert float(jnp.max(jnp.abs(xs[-1, 3:] - xs[-100, 3:]))) < 1e-6


def test_steady_cornering_matches_linear_single_track(model):
    """Small steer: yaw rate as the linear bicycle with the tyres' cornering stiffness predicts;
    left steer turns left (r > 0 in ISO axes) with the inner (left) wheels turning slower."""
    th = np.asarray(model.theta)
    m, a, b = th[0], th[2], th[3]
    l = a + b
    h = 1e-6

    def axle_stiffness(fz_kn):  # both tyres of an axle, slope at alpha = 0, per rad
        return 2 * (fy_right(h, fz_kn) - fy_right(-h, fz_kn)) / (2 * h) * 180 / np.pi

    cf = axle_stiffness(m * G / 2 * b / l / 1000)
    cr = axle_stiffness(m * G / 2 * a / l / 1000)
    kus = m * (b * cr - a * cf) / (l * cf * cr)
    for delta in (0.005, 0.01):
        xs = drive(model, 20.0, delta)
        U, r = float(xs[-1, 0]), float(xs[-1, 2])
        assert r > 0.0
        np.testing.assert_allclose(r, U * delta / (l + kus * U**2), rtol=5e-3)
        assert float(xs[-1, 3]) < float(xs[-1, 4]) and float(xs[-1, 5]) < float(xs[-1, 6])


def test_drive_input_gives_requested_acceleration(model):
    for accel in (1.0, -2.0):
        xs = drive(model, 20.0, gain=0.0, accel=accel)
        got = (float(xs[200, 0]) - float(xs[100, 0])) / (100 * model.dt)
        np.testing.assert_allclose(got, accel, rtol=1e-2)


def test_drive_input_splits_torque_by_static_axle_load(model):
    u = model.drive_input(model.initial_state(20.0), 0.03, 1.5, 20.0, model.theta)
    m, a, b, re, iw = (float(model.theta[i]) for i in (0, 2, 3, 7, 8))
    total = (m * re + 4 * iw / re) * 1.5
    np.testing.assert_allclose(u, [0.03, total * b / (a + b) / 2, total * b / (a + b) / 2,
                                   total * a / (a + b) / 2, total * a / (a + b) / 2], rtol=1e-12)


def test_initial_state_rolls_freely(model):
    x0 = model.initial_state(25.0)
    np.testing.assert_allclose(x0, [25.0, 0, 0] + [25.0 / 0.36] * 4, rtol=1e-12)
    assert model.speed(x0) == 25.0 and model.pose(x0) is None
    np.testing.assert_allclose(model.body_velocity(x0, jnp.zeros(5), model.theta), [25.0, 0, 0])


def test_output_sets():
    x = jnp.array([20.0, 0.3, 0.2, 55.0, 56.0, 55.2, 56.1])
    u = jnp.array([0.03, 50.0, 50.0, 20.0, 20.0])
    m20 = SevenDOF()
    m18 = SevenDOF(outputs="eq18")
    assert m20.output_names == ("r", "ay", "u")
    assert m20.output_units == ("rad/s", "m/s^2", "m/s")
    assert m18.output_names == ("u", "v", "ax", "ay", "r", "beta", "Gamma")
    assert m18.output_units == ("m/s", "m/s", "m/s^2", "m/s^2", "rad/s", "rad", "N m")
    assert m20.ny == 3 and m18.ny == 7
    obs = jax.jit(lambda x, u: (m18.observe(x, u, m18.theta), m20.observe(x, u, m20.theta)))
    y18, y20 = obs(x, u)
    d = EVAL(x, u, MODEL.theta)[1]
    assert y18.shape == (7,) and y20.shape == (3,)
    np.testing.assert_allclose(y18, d, rtol=1e-12)
    np.testing.assert_allclose(y20, d[jnp.array([4, 3, 0])], rtol=1e-12)
    ref = paper_rhs(np.asarray(x), np.asarray(u), np.asarray(m18.theta))[1]
    np.testing.assert_allclose(y18, ref, rtol=1e-6, atol=1e-5)


def test_names_units_and_nominal_parameters():
    model = SevenDOF()
    assert model.state_names == ("u", "v", "r", "omega_fl", "omega_fr", "omega_rl", "omega_rr")
    assert model.input_names == ("delta", "T_fl", "T_fr", "T_rl", "T_rr")
    assert model.param_names == ("m", "iz", "a", "b", "tf", "tr", "h", "re", "iw")
    assert len(model.param_units) == 9 and len(model.state_units) == 7
    # section 4 of the paper
    np.testing.assert_allclose(model.theta[:8], [1685, 2580, 1.16, 1.36, 1.54, 1.59, 0.436, 0.36])
    assert model.theta.dtype == jnp.float64
    assert model.substeps == 10 and SevenDOF(dt=0.0025).substeps == 3


def test_bad_arguments_raise_value_error():
    with pytest.raises(ValueError, match="outputs"):
        SevenDOF(outputs="eq19")
    with pytest.raises(ValueError, match="substeps"):
        SevenDOF(substeps=0)
    with pytest.raises(ValueError, match="substeps"):
        SevenDOF(substeps=2.5)
    with pytest.raises(ValueError, match="dt"):
        SevenDOF(dt=0.0)
    with pytest.raises(ValueError, match="theta"):
        SevenDOF(theta=np.ones(8))


@pytest.mark.slow  # two 7-DOF compiles (RK4 sub-steps and Euler): `pytest -m slow` (README)
def test_jit_vmap_jacobian_and_integrators(model):
    pts = list(_random_points(6, 1))
    X = jnp.asarray(np.stack([p[0] for p in pts]))
    U = jnp.asarray(np.stack([p[1] for p in pts]))
    TH = jnp.asarray(np.stack([p[2] for p in pts]))
    euler = SevenDOF(integrator="euler", substeps=1)
    step = jax.jit(lambda X, U, TH: (jax.vmap(model.transition)(X, U, TH),
                                     jax.vmap(euler.transition)(X, U, TH),
                                     jax.jacfwd(model.transition)(X[0], U[0], TH[0])))
    xn, xe, J = step(X, U, TH)  # one compile of the 7-DOF model, not two
    assert xn.shape == (6, 7) and xn.dtype == jnp.float64 and bool(jnp.all(jnp.isfinite(xn)))
    assert J.shape == (7, 7) and bool(jnp.all(jnp.isfinite(J)))
    # the sub-stepped, stage-looped RK4 is ten classic RK4 steps of dt / 10 ...
    f = lambda x: np.asarray(EVAL(jnp.asarray(x), U[0], TH[0])[0])
    h = model.dt / 10
    x = np.asarray(X[0])
    for _ in range(10):
        k1 = f(x)
        k2 = f(x + h / 2 * k1)
        k3 = f(x + h / 2 * k2)
        k4 = f(x + h * k3)
        x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    np.testing.assert_allclose(xn[0], x, rtol=1e-12, atol=1e-10)
    # ... and the Euler model one explicit step
    np.testing.assert_allclose(xe[1], X[1] + euler.dt * EVAL(X[1], U[1], TH[1])[0], rtol=1e-13)


def test_double_lane_change_scenario_runs(model):
    scn = vj.scenarios.double_lane_change(model, speed=20.0)
    assert scn.inputs.shape[1] == 5 and bool(jnp.all(jnp.isfinite(scn.inputs)))
    assert 3.0 < float(np.max(scn.path[:, 1])) < 4.0  # reaches the 3.5 m offset lane


# -- the ROS2 integrator ----------------------------------------------------------------------

DLC_SPEED = 80.0 / 3.6  # m/s, the ISO 3888-1 test speed (the wang2016 study's default)


@eqx.filter_jit
def _replay(model, x0, inputs):
    """States (T, 7) and eq. 18's derived vector (T, 7) with the inputs replayed open loop."""
    def step(x, u):
        xn = model.transition(x, u, model.theta)
        return xn, (xn, model.derived(xn, u, model.theta))

    return jax.lax.scan(step, x0, inputs)[1]


@pytest.fixture(scope="module")
def dlc_replays():
    """A 10 s double lane change at 80 km/h replayed by fine RK4 (0.25 ms, the reference) and
    by ROS2 with one and two steps per 10 ms."""
    scn = vj.scenarios.double_lane_change(MODEL, speed=DLC_SPEED, duration=10.0)
    ref = _replay(SevenDOF(substeps=40), scn.x0, scn.inputs)
    one = _replay(SevenDOF(integrator="ros2"), scn.x0, scn.inputs)
    two = _replay(SevenDOF(integrator="ros2", substeps=2), scn.x0, scn.inputs)
    return ref, one, two


def _max_err(a, b):
    return np.max(np.abs(np.asarray(a) - np.asarray(b)), axis=0)


@pytest.mark.slow  # an integrator accuracy study: fine-RK4 replays of a 10 s manoeuvre
def test_ros2_one_step_per_sample_tracks_fine_rk4_over_a_double_lane_change(dlc_replays):
    (x_ref, d_ref), (x1, d1), _ = dlc_replays
    assert float(np.max(np.abs(d_ref[:, 3]))) > 5.0  # a real manoeuvre: |ay| above 0.5 g
    ex, ed = _max_err(x1, x_ref), _max_err(d1, d_ref)
    # Worst error over the 1000 steps; the study's measurement noise (peak std) is 0.0047 m/s
    # in u, 0.58 m/s^2 in ay, 0.029 rad/s in r.
    assert ex[0] < 5e-3  # u [m/s]
    assert ex[1] < 1.5e-3  # v [m/s]
    assert ex[2] < 3e-4  # r [rad/s]
    assert np.all(ex[3:] < 0.02)  # wheel speeds [rad/s], of about 62
    assert ed[2] < 0.05 and ed[3] < 0.02  # ax, ay [m/s^2]
    assert ed[5] < 1e-4  # beta [rad]


@pytest.mark.slow  # an integrator accuracy study: fine-RK4 replays of a 10 s manoeuvre
def test_ros2_error_falls_with_the_step(dlc_replays):
    """Halving the step at least nearly halves the worst error of u, v, r and ay."""
    (x_ref, d_ref), (x1, d1), (x2, d2) = dlc_replays
    e1, e2 = _max_err(d1, d_ref), _max_err(d2, d_ref)
    for i in (0, 1, 3, 4):  # u, v, ay, r
        assert e2[i] < e1[i] / 1.8, (i, e1[i], e2[i])


@pytest.mark.slow  # the ROS2 integrator's wheel Jacobian compile: `pytest -m slow` (README)
def test_ros2_wheel_jacobian_rows_match_autodiff():
    """The wheel rows that ROS2 uses equal jacfwd of omega' with the loads frozen at their solved
    values; their diagonal (the stiff part) is within 10 % of the full Jacobian's, which also
    carries the loads' dependence on the wheel speeds (up to 7 % at these random states)."""
    m = SevenDOF(integrator="ros2")

    def omega_dot_frozen(x, u, th, fz):
        _, slip, _ = m._wheel_slips(x, u, th)
        fx = m._tyre_forces(jnp.zeros(4), slip, fz)[0]
        return (u[1:5] - th[7] * fx) / th[8]

    @jax.jit
    def evaluate(x, u, th):
        fz = m.wheel_loads(x, u, th)
        frozen = jax.jacfwd(omega_dot_frozen)(x, u, th, fz)  # (4, 7)
        full = jax.jacfwd(lambda x: m.derivative(x, u, th))(x)
        return frozen, full, m._derivative_and_wheel_jacobian(x, u, th)

    for x, inp, th in _random_points(5, 2):
        x, inp, th = jnp.asarray(x), jnp.asarray(inp), jnp.asarray(th)
        frozen, full, (xdot, j, g) = evaluate(x, inp, th)
        np.testing.assert_allclose(xdot, EVAL(x, inp, th)[0], rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(j, np.diag(np.asarray(frozen)[:, 3:]), rtol=1e-10)
        np.testing.assert_allclose(g, frozen[:, :3], rtol=1e-10, atol=1e-9)
        assert np.all(np.asarray(j) < -200.0)  # stiff: hundreds to thousands per second
        np.testing.assert_allclose(j, np.diag(np.asarray(full))[3:], rtol=0.1)


def test_ros2_construction():
    assert SevenDOF(integrator="ros2").substeps == 1
    assert SevenDOF(integrator="ros2", dt=0.02).substeps == 2
    assert SevenDOF(integrator="ros2").integrator == "ros2"
    with pytest.raises(ValueError, match="integrator"):
        SevenDOF(integrator="ros3")


# -- the ETDRK4 integrator --------------------------------------------------------------------

@pytest.fixture(scope="module")
def etd_replays(dlc_replays):
    """The double lane change of ``dlc_replays`` replayed by ETDRK4 with its default three
    sub-steps per 10 ms and with six (every sub-step halved)."""
    scn = vj.scenarios.double_lane_change(MODEL, speed=DLC_SPEED, duration=10.0)
    three = _replay(SevenDOF(integrator="etdrk4"), scn.x0, scn.inputs)
    six = _replay(SevenDOF(integrator="etdrk4", substeps=6), scn.x0, scn.inputs)
    return dlc_replays[0], three, six, dlc_replays[1]


def _dlc_errors(x, d, ref):
    """Largest errors over the drive of u, v, r, the wheel speeds (largest of four) and ay."""
    ex, ed = _max_err(x, ref[0]), _max_err(d, ref[1])
    return np.array([ex[0], ex[1], ex[2], np.max(ex[3:]), ed[3]])


@pytest.mark.slow  # an integrator accuracy study: fine-RK4 replays of a 10 s manoeuvre
def test_etdrk4_tracks_fine_rk4_over_a_double_lane_change(etd_replays):
    """The documented errors of the default ETDRK4 (u, v, r, wheels, ay), and three orders of
    magnitude or more below ROS2's (one step per 10 ms), computed here."""
    ref, (x3, d3), _, (x_ros, d_ros) = etd_replays
    e3 = _dlc_errors(x3, d3, ref)
    e_ros = _dlc_errors(x_ros, d_ros, ref)
    # measured: 9.8e-8, 3.2e-7, 1.4e-7, 4.0e-7, 3.0e-6 (module docstring)
    np.testing.assert_array_less(e3, [2e-7, 6e-7, 3e-7, 8e-7, 6e-6])
    np.testing.assert_array_less(e3, e_ros / 500.0)  # measured: 900 (r) to 33000 (u) times


@pytest.mark.slow  # an integrator accuracy study: fine-RK4 replays of a 10 s manoeuvre
def test_etdrk4_error_falls_with_the_step(etd_replays):
    """Halving every sub-step (3 -> 6 per 10 ms) cuts the worst errors by more than 8, the
    factor of the method's stiff order 3 (measured: 12-13)."""
    ref, (x3, d3), (x6, d6), _ = etd_replays
    e3, e6 = _dlc_errors(x3, d3, ref), _dlc_errors(x6, d6, ref)
    np.testing.assert_array_less(8.0 * e6, e3)


@pytest.mark.slow  # one ETDRK4 Jacobian compile, about 30 s on 2 cores: `pytest -m slow` (README)
def test_etdrk4_jacobian_is_finite_and_matches_central_differences():
    """jacfwd of the ETDRK4 transition (through the linear part formed at x, too) against
    central differences, at a state of the double lane change (0.6 g to the left) and at a
    random one. One compiled function gives the transition and its Jacobian, so that jacfwd is
    compiled once."""
    m = SevenDOF(integrator="etdrk4")
    pts = [(np.array([22.15, 0.27, -0.12, 61.75, 61.23, 61.76, 61.22]),
            np.array([-7e-4, 11.7, 11.7, 10.0, 10.0]), np.asarray(m.theta))]
    pts += list(_random_points(1, 3))
    steps = np.array([1e-5, 1e-6, 1e-6, 1e-5, 1e-5, 1e-5, 1e-5])

    @jax.jit
    def evaluate(x, u, th):
        f = lambda x: m.transition(x, u, th)
        return f(x), jax.jacfwd(f)(x)

    for x, u, th in pts:
        u, th = jnp.asarray(u), jnp.asarray(th)
        _, jac = evaluate(jnp.asarray(x), u, th)
        assert bool(jnp.all(jnp.isfinite(jac)))
        fd = np.stack([(np.asarray(evaluate(jnp.asarray(x + e), u, th)[0])
                        - np.asarray(evaluate(jnp.asarray(x - e), u, th)[0])) / (2.0 * e.sum())
                       for e in np.diag(steps)], axis=1)
        np.testing.assert_allclose(jac, fd, rtol=1e-5, atol=2e-6)


def test_phi_functions_match_their_series():
    """phi_0..phi_4 against their power series summed in exact rationals, across the switch
    between the two ways they are computed (|z| = 1) and far out on both sides."""
    from fractions import Fraction

    zs = [-40.0, -12.0, -3.0, -1.0000001, -0.9999999, -0.5, -1e-3, 0.0, 1e-3, 0.5, 0.9999999,
          1.0000001, 3.0]
    got = np.asarray(_phi_functions(jnp.asarray(zs), 4))
    for i, z in enumerate(zs):
        zf = Fraction(z)
        for k in range(5):
            if abs(z) > 5:  # the series converges too slowly there: use the closed form
                e = np.exp(z)
                want = (e - sum(z**n / math.factorial(n) for n in range(k))) / z**k
            else:
                want = float(sum(zf**n / math.factorial(n + k) for n in range(60)))
            np.testing.assert_allclose(got[k, i], want, rtol=2e-14, atol=1e-300)


def test_etdrk4_coefficients_meet_the_order_conditions():
    """Krogstad's coefficients as tabulated (a_ij, b_i as combinations of phi_k(c h L)): for
    scalar h L = z, the stiff order conditions up to order 3 (Hochbruck and Ostermann 2005)
    hold for every z, and at z = 0 the method is classical RK4."""
    c = np.asarray(_ETD_C)
    table = np.asarray(_ETD_TABLE)  # (row, source, k - 1, c index), c index 0: 1/2, 1: 1

    def coefficients(z):
        """a (4, 4), b (4,) and phi_k at (z/2, z). The table holds each row's weight of f(x),
        c_i phi_1(c_i z), and of D_j, j > 1, (a_ij, b_j); a_i1, b_1 take the rest."""
        phi = np.asarray(_phi_functions(jnp.asarray([z / 2.0, z]), 3))  # (k, c)
        rows = np.einsum("rskc,kc->rs", table, phi[1:])
        rows[:, 0] -= rows[:, 1:].sum(axis=1)
        a = np.zeros((4, 4))
        a[1:] = rows[:3]
        return a, rows[3], phi

    for z in (-20.0, -3.0, -0.5, 0.0, 0.7):
        a, b, phi = coefficients(z)
        phi1, phi2, phi3 = phi[1:4, 1]
        phi2_c = np.array([0.0, phi[2, 0], phi[2, 0], phi[2, 1]])  # phi_2(c_i z)
        phi1_c = np.array([1.0, phi[1, 0], phi[1, 0], phi[1, 1]])
        np.testing.assert_allclose(a.sum(axis=1), c * phi1_c, atol=1e-15)  # sum_j a_ij
        np.testing.assert_allclose(b.sum(), phi1, rtol=1e-13)
        np.testing.assert_allclose(b @ c, phi2, rtol=1e-13)
        np.testing.assert_allclose(b @ c**2 / 2.0, phi3, rtol=1e-13)
        psi = a @ c - c**2 * phi2_c
        np.testing.assert_allclose(b * psi, [0.0, b[1] * psi[1], -b[1] * psi[1], 0.0],
                                   atol=1e-15)  # sum_i b_i J psi_i = 0 for every J
    a, b, _ = coefficients(0.0)
    np.testing.assert_allclose(a, [[0, 0, 0, 0], [0.5, 0, 0, 0], [0, 0.5, 0, 0], [0, 0, 1, 0]],
                               atol=1e-15)
    np.testing.assert_allclose(b, [1 / 6, 1 / 3, 1 / 3, 1 / 6], rtol=1e-14)


def test_etdrk4_traces_the_derivative_twice_whatever_the_substeps():
    """The stage loop is a scan: one trace of the derivative in it and one of the linearisation
    before it, for any number of sub-steps (compile time)."""
    x = jnp.array([20.0, 0.3, 0.2, 55.0, 56.0, 55.2, 56.1])
    u = jnp.array([0.03, 50.0, 50.0, 20.0, 20.0])
    for substeps in (1, 6):
        m = SevenDOF(integrator="etdrk4", substeps=substeps)
        calls = []
        orig = SevenDOF._solve

        def counted(self, *args, **kwargs):
            calls.append(1)
            return orig(self, *args, **kwargs)

        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(SevenDOF, "_solve", counted)
            jax.make_jaxpr(lambda x: m.transition(x, u, m.theta))(x)
        assert len(calls) == 2, (substeps, len(calls))


def test_etdrk4_construction():
    assert SevenDOF(integrator="etdrk4").integrator == "etdrk4"
    assert SevenDOF(integrator="etdrk4").substeps == 3
    assert SevenDOF(integrator="etdrk4", dt=0.02).substeps == 6
    assert SevenDOF(integrator="etdrk4", dt=0.005).substeps == 2
    assert SevenDOF(integrator="etdrk4", substeps=5).substeps == 5
    with pytest.raises(ValueError, match="integrator"):
        SevenDOF(integrator="etd")
    with pytest.raises(ValueError, match="substeps"):
        SevenDOF(integrator="etdrk4", substeps=0)
