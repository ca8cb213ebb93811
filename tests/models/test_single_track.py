"""vehjax.models.SingleTrack and SingleTrackLag against references written here: scipy's solve_ivp
of the continuous equations (with and without the tyre lag), the linear bicycle's steady-state
cornering (understeer gradient), the tyre curves' small-slip slopes and limits, the rigid-body
formula of an accelerometer away from the CoG (r' by finite differences of the reference
trajectory)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import vehjax  # noqa: F401  (float64)
from vehjax.models import REGISTRY, SingleTrack, SingleTrackLag
from vehjax.models.single_track import axle_loads
from vehjax.models.single_track import brush_axle as _brush_axle
from vehjax.models.single_track import magic_formula_axle as _magic_formula_axle

G = 9.81


# -- the continuous equations, written out again from the textbook ------------------------------
def _mf(alpha, c, mu, fz, shape):
    d = mu * fz
    b = c / (shape * d)
    return d * np.sin(shape * np.arctan(b * alpha))


def _fiala(alpha, c, mu, fz):
    t = np.tan(alpha)
    t_sl = 3 * mu * fz / c
    if abs(t) >= t_sl:
        return mu * fz * np.sign(t)
    return c * t - c**2 / (3 * mu * fz) * abs(t) * t + c**3 / (27 * (mu * fz) ** 2) * t**3


def _forces(tyres, theta):
    """(Ff, Fr, cos(delta) or 1) on the tyre curve at the slips of (vy, r)."""
    m, iz, lf, lr, cf, cr = theta[:6]
    fzf, fzr = m * G * lr / (lf + lr), m * G * lf / (lf + lr)

    def forces(x, delta, vx):
        vy, r = x
        if tyres == "linear":
            return cf * (delta - (vy + lf * r) / vx), cr * (lr * r - vy) / vx, 1.0
        af = delta - np.arctan((vy + lf * r) / vx)
        ar = -np.arctan((vy - lr * r) / vx)
        if tyres == "pacejka":
            return _mf(af, cf, theta[6], fzf, theta[7]), _mf(ar, cr, theta[6], fzr, theta[8]), \
                np.cos(delta)
        return _fiala(af, cf, theta[6], fzf), _fiala(ar, cr, theta[6], fzr), np.cos(delta)

    return forces


def _rhs(tyres, theta):
    m, iz, lf, lr = theta[:4]
    forces = _forces(tyres, theta)

    def rhs(x, delta, vx):
        ff, fr, c = forces(x, delta, vx)
        fy, mz = ff * c + fr, lf * ff * c - lr * fr
        return np.array([fy / m - vx * x[1], mz / iz]), fy / m

    return rhs


def _lag_rhs(tyres, theta):
    """The tyre-lag equations: Ff' = vx / sigma_f (F_f(alpha_f) - Ff), the same for the rear,
    the body's balance with the lagged forces. theta ends with (sigma_f, sigma_r)."""
    m, iz, lf, lr = theta[:4]
    sf, sr = theta[-2:]
    forces = _forces(tyres, theta)

    def rhs(z, delta, vx):
        ffs, frs, c = forces(z[:2], delta, vx)
        fy, mz = z[2] * c + z[3], lf * z[2] * c - lr * z[3]
        return np.array([fy / m - vx * z[1], mz / iz, vx / sf * (ffs - z[2]),
                         vx / sr * (frs - z[3])]), fy / m

    return rhs


def _reference_rollout(tyres, theta, u, dt, x0, rhs=None, eps=1e-4):
    """Zero-order-hold inputs, solve_ivp (DOP853, tight tolerances) from sample to sample:
    states, ay at the CoG, and r' at each sample's end by a second-order backward difference of
    the dense solution over ``eps`` seconds (inside the interval, where the input is held)."""
    rhs = _rhs(tyres, theta) if rhs is None else rhs
    xs, ays, rdots, x = [], [], [], np.array(x0, float)
    for delta, vx in u:
        sol = solve_ivp(lambda t, z: rhs(z, delta, vx)[0], (0.0, dt), x, method="DOP853",
                        rtol=1e-12, atol=1e-13, dense_output=True)
        x = sol.y[:, -1]
        r1, r2 = sol.sol(dt - eps)[1], sol.sol(dt - 2 * eps)[1]
        xs.append(x)
        ays.append(rhs(x, delta, vx)[1])
        rdots.append((3 * x[1] - 4 * r1 + r2) / (2 * eps))
    return np.array(xs), np.array(ays), np.array(rdots)


def _model_rollout(model, u, x0):
    th = model.theta

    def body(x, uk):
        x1 = model.transition(x, uk, th)
        return x1, (x1, model.observe(x1, uk, th))

    _, (xs, ys) = jax.jit(lambda x, uu: jax.lax.scan(body, x, uu))(jnp.asarray(x0), jnp.asarray(u))
    return np.asarray(xs), np.asarray(ys)


def _inputs(T, dt, amp, vx0):
    t = dt * np.arange(T)
    delta = amp * np.sin(2 * np.pi * 0.7 * t) * np.minimum(t / 0.3, 1.0)
    vx = vx0 + 2.0 * np.sin(2 * np.pi * 0.2 * t)
    return np.stack([delta, vx], axis=1)


@pytest.mark.parametrize("tyres, amp", [("linear", 0.03), ("pacejka", 0.12), ("brush", 0.12)])
def test_rollout_matches_solve_ivp(tyres, amp):
    model = SingleTrack(dt=0.01, tyres=tyres)
    u = _inputs(120, 0.01, amp, 15.0)
    x_ref, ay_ref, _ = _reference_rollout(tyres, np.asarray(model.theta), u, 0.01, [0.0, 0.0])
    xs, ys = _model_rollout(model, u, [0.0, 0.0])
    if tyres != "linear":
        # the manoeuvre reaches the saturating part of the curve (front slip beyond 4 deg)
        af = u[:, 0] - np.arctan((x_ref[:, 0] + 1.2 * x_ref[:, 1]) / u[:, 1])
        assert np.max(np.abs(af)) > np.radians(4.0)
    scale = np.max(np.abs(x_ref), axis=0)
    np.testing.assert_allclose(xs, x_ref, rtol=0, atol=1e-6 * scale.max())
    np.testing.assert_allclose(ys[:, 1], x_ref[:, 1], rtol=0, atol=1e-6 * scale[1])
    np.testing.assert_allclose(ys[:, 0], ay_ref, rtol=0, atol=1e-6 * np.max(np.abs(ay_ref)))


@pytest.mark.parametrize("vx", [8.0, 25.0])
def test_linear_steady_state_is_the_understeer_formula(vx):
    model = SingleTrack(dt=0.01)
    m, iz, lf, lr, cf, cr = np.asarray(model.theta)
    L = lf + lr
    K = m * (lr * cr - lf * cf) / (L * cf * cr)            # understeer gradient [rad s^2/m]
    assert K > 0 and model.understeer_gradient() == pytest.approx(K, rel=1e-14)
    delta = 0.01
    u = np.tile([delta, vx], (1500, 1))                    # 15 s: transients die out
    xs, ys = _model_rollout(model, u, [0.0, 0.0])
    r_ss = vx * delta / (L + K * vx**2)
    # vy from the rear axle's force balance: Fr = m ay lf / L, alpha_r = (lr r - vy) / vx
    vy_ss = lr * r_ss - vx * (m * vx * r_ss * lf / L) / cr
    assert xs[-1, 1] == pytest.approx(r_ss, rel=1e-9)
    assert xs[-1, 0] == pytest.approx(vy_ss, rel=1e-9)
    assert ys[-1, 0] == pytest.approx(vx * r_ss, rel=1e-9)  # ay = vx r in steady state


def test_saturating_curves_slope_and_limits():
    c, mu, fz = 1.2e5, 0.9, 7000.0
    for f in (jax.jit(lambda a: _magic_formula_axle(a, c, mu, fz, 1.3)),
              jax.jit(lambda a: _brush_axle(a, c, mu, fz))):
        slope = jax.jit(jax.grad(f))(0.0)
        assert float(slope) == pytest.approx(c, rel=1e-12)   # small-slip slope = linear stiffness
        small = 1e-4
        assert float(f(small)) == pytest.approx(c * small, rel=1e-3)
        assert float(f(-0.05)) == pytest.approx(-float(f(0.05)), rel=1e-14)   # odd
    # magic formula: peak D = mu Fz at B alpha = tan(pi / (2 C)); large slip D sin(C pi / 2)
    shape = 1.3
    magic_formula_axle = jax.jit(_magic_formula_axle)
    brush_axle = jax.jit(_brush_axle)
    b = c / (shape * mu * fz)
    a_peak = np.tan(np.pi / (2 * shape)) / b
    assert float(magic_formula_axle(a_peak, c, mu, fz, shape)) == pytest.approx(mu * fz, rel=1e-12)
    assert float(magic_formula_axle(1e6, c, mu, fz, shape)) == pytest.approx(
        mu * fz * np.sin(shape * np.pi / 2), rel=1e-5)
    # brush: full sliding at tan(alpha) = 3 mu Fz / c, with the force mu Fz, continuous
    a_sl = np.arctan(3 * mu * fz / c)
    for a in (a_sl * 0.999, a_sl, a_sl * 1.5, 0.6):
        assert float(brush_axle(a, c, mu, fz)) == pytest.approx(_fiala(a, c, mu, fz), rel=1e-9)
    assert float(brush_axle(a_sl * 1.5, c, mu, fz)) == pytest.approx(mu * fz, rel=1e-14)
    assert float(brush_axle(a_sl * 0.999, c, mu, fz)) == pytest.approx(mu * fz, rel=1e-6)
    # gradients are finite everywhere, including the sliding branch
    g = jax.jit(jax.vmap(jax.grad(lambda a: _brush_axle(a, c, mu, fz))))(jnp.linspace(-0.5, 0.5, 11))
    assert np.all(np.isfinite(np.asarray(g)))


def test_axle_loads():
    fzf, fzr = axle_loads(1500.0, 1.2, 1.5)
    assert float(fzf + fzr) == pytest.approx(1500 * G)
    assert float(fzf * 1.2) == pytest.approx(float(fzr * 1.5))   # moment balance about the CoG


def test_saturating_models_agree_with_linear_at_small_slip():
    # derivative and outputs at random small-slip points (vy, r, delta, vx), slips below 2 amp.
    # The magic formula departs from its tangent at third order in the slip (relative deviation
    # (B alpha)^2 (1 + C^2) / 6, B = 11.3 /rad on the nominal front axle: 2.3e-4 at 2e-3 rad),
    # the brush model at second (c |alpha| / (3 mu Fz) = 4.9 |alpha|: 1e-3 at 2e-4 rad)
    rng = np.random.default_rng(1)
    for tyres, amp in (("pacejka", 1e-3), ("brush", 1e-4)):
        pts = rng.uniform(-1, 1, (64, 3)) * amp * np.array([10.0, 1.0, 1.0])  # vy/vx, r, delta
        vx = rng.uniform(5, 30, 64)
        x = np.stack([pts[:, 0] * vx / 10, pts[:, 1]], 1)
        u = np.stack([pts[:, 2], vx], 1)
        out = []
        for model in (SingleTrack(tyres="linear"), SingleTrack(tyres=tyres)):
            f = jax.jit(jax.vmap(lambda xx, uu: jnp.concatenate(
                [model.derivative(xx, uu, model.theta), model.observe(xx, uu, model.theta)])))
            out.append(np.asarray(f(x, u)))
        rel = np.max(np.abs(out[1] - out[0]), axis=0) / np.max(np.abs(out[0]), axis=0)
        assert np.all(rel < 2e-3), (tyres, rel)


def test_names_units_registry_and_bad_input():
    model = SingleTrack()
    assert model.state_names == ("vy", "r") and model.input_names == ("delta", "vx")
    assert model.output_names == ("ay", "r") and model.output_units == ("m/s^2", "rad/s")
    assert model.param_names == ("m", "iz", "lf", "lr", "cf", "cr")
    assert SingleTrack(tyres="pacejka").param_names[6:] == ("mu", "shape_f", "shape_r")
    assert SingleTrack(tyres="brush").param_names[6:] == ("mu",)
    assert REGISTRY["SingleTrack"] is SingleTrack
    assert "cf = 120000 [N/rad]" in model.describe()
    assert float(model.with_theta(cf=9e4).theta[4]) == 9e4
    with pytest.raises(ValueError, match="tyres"):
        SingleTrack(tyres="magic")
    with pytest.raises(ValueError, match="substeps"):
        SingleTrack(substeps=0)
    with pytest.raises(ValueError, match="theta"):
        SingleTrack(tyres="pacejka", theta=[1500.0, 2700.0, 1.2, 1.5, 1e5, 1e5])
    with pytest.raises(ValueError, match="dt"):
        SingleTrack(dt=0.0)


# -- tyre lag ----------------------------------------------------------------------------------
@pytest.mark.parametrize("tyres, amp", [("linear", 0.03), ("pacejka", 0.12), ("brush", 0.12)])
def test_lag_rollout_matches_solve_ivp(tyres, amp):
    # 2 s of a steering sine at 20 m/s, sigma_f = 0.5 m, sigma_r = 0.4 m (time constants 25 and
    # 20 ms), from a state off the curve (forces not yet built)
    model = SingleTrackLag(dt=0.01, tyres=tyres).with_theta(sigma_r=0.4)
    u = _inputs(200, 0.01, amp, 20.0)
    x0 = [0.05, 0.02, 500.0, -300.0]
    x_ref, ay_ref, _ = _reference_rollout(tyres, np.asarray(model.theta), u, 0.01, x0,
                                          rhs=_lag_rhs(tyres, np.asarray(model.theta)))
    xs, ys = _model_rollout(model, u, x0)
    if tyres != "linear":
        af = u[:, 0] - np.arctan((x_ref[:, 0] + 1.2 * x_ref[:, 1]) / u[:, 1])
        assert np.max(np.abs(af)) > np.radians(4.0)
    scale = np.max(np.abs(x_ref), axis=0)
    np.testing.assert_allclose(xs / scale, x_ref / scale, rtol=0, atol=1e-6)
    np.testing.assert_allclose(ys[:, 0], ay_ref, rtol=0, atol=1e-6 * np.max(np.abs(ay_ref)))
    # the lag is visible: the forces are off the curve by more than the tolerance
    forces = _forces(tyres, np.asarray(model.theta))
    ff_ss = np.array([forces(x[:2], d, v)[0] for x, (d, v) in zip(x_ref, u)])
    assert np.max(np.abs(ff_ss - x_ref[:, 2])) > 0.05 * scale[2]


def test_lag_tends_to_single_track_as_sigma_goes_to_zero():
    # the forces' lag behind the curve is about tau F' with tau = sigma / vx: the gap to
    # SingleTrack halves with sigma
    # (RK4 at 0.5 ms: |lambda h| = vx h / sigma = 0.5 at 0.02 m)
    u = _inputs(3000, 0.0005, 0.08, 20.0)
    ref, _ = _model_rollout(SingleTrack(dt=0.0005, tyres="pacejka", substeps=1), u, [0.0, 0.0])
    gaps = []
    for sigma in (0.04, 0.02):
        lag = SingleTrackLag(dt=0.0005, tyres="pacejka").with_theta(sigma_f=sigma,
                                                                    sigma_r=sigma)
        xs, _ = _model_rollout(lag, u, np.zeros(4))
        gaps.append(np.max(np.abs(xs[:, :2] - ref), axis=0) / np.max(np.abs(ref), axis=0))
        forces = _forces("pacejka", np.asarray(lag.theta))
        ff_ss = np.array([forces(x[:2], d, v)[0] for x, (d, v) in zip(xs, u)])
        assert np.max(np.abs(ff_ss - xs[:, 2])) < 0.02 * np.max(np.abs(ff_ss))
    assert np.all(gaps[1] < 0.01)
    np.testing.assert_allclose(gaps[0] / gaps[1], 2.0, rtol=0.1)


@pytest.mark.parametrize("tyres", ["linear", "brush"])
def test_lag_steady_state_is_single_tracks(tyres):
    u = np.tile([0.03, 20.0], (1000, 1))                    # 10 s: transients die out
    xs, ys = _model_rollout(SingleTrack(tyres=tyres), u, [0.0, 0.0])
    lag = SingleTrackLag(tyres=tyres)
    xl, yl = _model_rollout(lag, u, np.zeros(4))
    np.testing.assert_allclose(xl[-1, :2], xs[-1], rtol=1e-9)
    np.testing.assert_allclose(yl[-1], ys[-1], rtol=1e-9)
    ff, fr, _ = _forces(tyres, np.asarray(lag.theta))(xl[-1, :2], 0.03, 20.0)
    np.testing.assert_allclose(xl[-1, 2:], [ff, fr], rtol=1e-9)
    np.testing.assert_allclose(np.asarray(lag.steady_forces(xs[-1], jnp.asarray(u[-1]))),
                               xl[-1], rtol=1e-9)


def test_lag_substeps_keep_rk4_stable():
    # eigenvalues of the linear lagged model's Jacobian (finite differences of the numpy
    # equations) at sigma = 0.2 m: |lambda h| with the default RK4 step of 2.5 ms
    assert SingleTrackLag(dt=0.01).substeps == 4 and SingleTrackLag(dt=0.005).substeps == 2
    assert SingleTrackLag(dt=0.01, substeps=7).substeps == 7
    theta = np.asarray(SingleTrackLag().with_theta(sigma_f=0.2, sigma_r=0.2).theta)
    rhs = _lag_rhs("linear", theta)
    worst = 0.0
    for vx in (3.0, 10.0, 20.0, 40.0):
        z0, e = np.zeros(4), np.array([1e-6, 1e-6, 1.0, 1.0])
        jac = np.stack([(rhs(z0 + e[j] * np.eye(4)[j], 0.0, vx)[0]
                         - rhs(z0 - e[j] * np.eye(4)[j], 0.0, vx)[0]) / (2 * e[j])
                        for j in range(4)], axis=1)
        lam = np.linalg.eigvals(jac)
        assert np.all(lam.real < 0)
        worst = max(worst, np.max(np.abs(lam)) * 0.0025)
    assert 0.3 < worst < 0.6                                # far inside RK4's 2.78


def test_lag_names_domains_and_nested_model():
    lag = SingleTrackLag(tyres="brush", lever_arm=True, references=("beta",))
    assert lag.state_names == ("vy", "r", "Ff", "Fr")
    assert lag.state_units == ("m/s", "rad/s", "N", "N")
    assert lag.param_names == ("m", "iz", "lf", "lr", "cf", "cr", "mu", "sigma_f", "sigma_r",
                               "xa", "ya")
    assert lag.output_names == ("ay", "r", "beta")
    np.testing.assert_array_equal(lag.state_envelope(), [300.0, 20.0, 1e6, 1e6])
    np.testing.assert_array_equal(np.asarray(lag.initial_state(20.0)), np.zeros(4))
    assert REGISTRY["SingleTrackLag"] is SingleTrackLag
    lag = lag.with_theta(sigma_f=0.7, cf=1e5, xa=0.8)
    nested = lag.nested_model()
    assert isinstance(nested, SingleTrackLag) and nested.tyres == "linear"
    assert nested.state_names == lag.state_names and nested.output_names == lag.output_names
    assert nested.substeps == lag.substeps and nested.dt == lag.dt
    assert nested.param_names == ("m", "iz", "lf", "lr", "cf", "cr", "sigma_f", "sigma_r",
                                  "xa", "ya")
    for n in nested.param_names:
        assert float(nested.theta[nested.param_names.index(n)]) == float(
            lag.theta[lag.param_names.index(n)])
    assert nested.nested_model() is None
    assert lag.data_floors(np.array([[9.81 * 0.8, 0.0, 0.0]] * 40), None)["mu"] == \
        pytest.approx(0.8)
    for bad in (0.01, 0.0, 10.0, -0.5):
        with pytest.raises(ValueError, match="sigma_f"):
            SingleTrackLag().with_theta(sigma_f=bad)
    with pytest.raises(ValueError, match="sigma_r"):
        SingleTrackLag(theta=list(np.asarray(SingleTrackLag().theta)[:7]) + [20.0])
    with pytest.raises(ValueError, match="substeps"):
        SingleTrackLag(substeps=0)


def test_lag_drives_a_scenario():
    lag = SingleTrackLag(tyres="pacejka")
    scn = vehjax.scenarios.double_lane_change(lag, speed=20.0)
    sim = vehjax.simulate(lag, scn, runs=1, key=jax.random.key(0))
    assert not bool(np.any(sim.diverged))
    assert np.max(np.abs(np.asarray(sim.states)[..., 2])) > 1e3     # the forces were built


# -- the accelerometer's lever arm and reference outputs ----------------------------------------
@pytest.mark.parametrize("lagged", [False, True])
def test_lever_arm_is_the_rigid_body_formula(lagged):
    cls = SingleTrackLag if lagged else SingleTrack
    model = cls(tyres="pacejka", lever_arm=True).with_theta(xa=1.1, ya=-0.3)
    th = np.asarray(model.theta)
    u = _inputs(120, 0.01, 0.1, 15.0)
    x0 = np.zeros(model.nx)
    rhs = _lag_rhs("pacejka", th[:-2]) if lagged else _rhs("pacejka", th[:-2])
    x_ref, ay_ref, rdot = _reference_rollout("pacejka", th, u, 0.01, x0, rhs=rhs)
    _, ys = _model_rollout(model, u, x0)
    ay_s = ay_ref + 1.1 * rdot + 0.3 * x_ref[:, 1] ** 2
    assert np.max(np.abs(ay_s - ay_ref)) > 0.1 * np.max(np.abs(ay_ref))   # the arm matters
    np.testing.assert_allclose(ys[:, 0], ay_s, rtol=0, atol=1e-6 * np.max(np.abs(ay_s)))
    assert model.param_names[-2:] == ("xa", "ya") and model.param_units[-2:] == ("m", "m")
    for bad in (5.0, -6.0):
        with pytest.raises(ValueError, match="xa"):
            model.with_theta(xa=bad)
    nested = model.nested_model()
    assert nested.param_names[-2:] == ("xa", "ya") and float(nested.theta[-2]) == 1.1


def test_reference_outputs():
    model = SingleTrack(tyres="pacejka", references=("vy", "beta"))
    assert model.output_names == ("ay", "r", "vy", "beta")
    assert model.output_units == ("m/s^2", "rad/s", "m/s", "rad")
    assert SingleTrack(references=("beta",)).output_names == ("ay", "r", "beta")
    assert model.param_names == SingleTrack(tyres="pacejka").param_names
    nested = model.nested_model()
    assert nested.output_names == model.output_names and nested.tyres == "linear"
    x, u = jnp.array([0.4, 0.1]), jnp.array([0.05, 12.0])
    y = np.asarray(model.observe(x, u, model.theta))
    y0 = np.asarray(SingleTrack(tyres="pacejka").observe(x, u, model.theta))
    np.testing.assert_array_equal(y[:2], y0)
    assert y[2] == 0.4 and y[3] == pytest.approx(np.arctan2(0.4, 12.0), rel=1e-15)
    with pytest.raises(ValueError, match="references"):
        SingleTrack(references=("vx",))
    with pytest.raises(ValueError, match="references"):
        SingleTrack(references=("vy", "vy"))
    with pytest.raises(ValueError, match="lever_arm"):
        SingleTrack(lever_arm="yes")


@pytest.mark.parametrize("cls", [SingleTrack, SingleTrackLag])
def test_nan_reference_column_is_skipped_by_the_filter(cls):
    # the filter of a reference-observing model on data whose reference column is NaN is the
    # filter of the model without it: the same states and log-likelihood
    plain = cls(tyres="brush", substeps=2)
    ref = cls(tyres="brush", substeps=2, references=("vy", "beta"))
    u = _inputs(150, 0.01, 0.08, 15.0)
    x0 = np.zeros(plain.nx)
    _, ys = _model_rollout(plain, u, x0)
    ys = ys + np.random.default_rng(0).normal(0, [0.3, 0.005], ys.shape)
    ys_ref = np.concatenate([ys, np.full((len(ys), 2), np.nan)], axis=1)
    Q = np.diag([1e-4, 1e-5, 1e4, 1e4][:plain.nx])
    P0 = np.diag([1e-2, 1e-3, 1e6, 1e6][:plain.nx])
    a = vehjax.filter(vehjax.filters.ekf(plain, Q, np.diag([0.09, 2.5e-5])), ys, u, x0=x0, P0=P0)
    b = vehjax.filter(vehjax.filters.ekf(ref, Q, np.diag([0.09, 2.5e-5, 0.01, 1e-4])), ys_ref,
                      u, x0=x0, P0=P0)
    assert np.all(np.isfinite(np.asarray(b.loglik)))
    np.testing.assert_allclose(np.asarray(b.loglik), np.asarray(a.loglik), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(b.states), np.asarray(a.states), rtol=1e-12,
                               atol=1e-12)
    # with the reference present the filter uses it: a different likelihood
    ys_ok = np.concatenate([ys, np.zeros((len(ys), 2))], axis=1)
    c = vehjax.filter(vehjax.filters.ekf(ref, Q, np.diag([0.09, 2.5e-5, 0.01, 1e-4])), ys_ok,
                      u, x0=x0, P0=P0)
    assert abs(float(np.sum(c.loglik)) - float(np.sum(a.loglik))) > 1.0


@pytest.mark.slow
def test_fit_of_a_lagged_reference_model_goes_through_the_nested_start():
    # vehjax.tune.fit's staged start fits the nested (lagged linear, same states and outputs)
    # model first with the same Q0 and R0 (a minute on 2 cores)
    m = SingleTrackLag(tyres="brush", references=("vy",))
    scn = vehjax.scenarios.double_lane_change(m, speed=20.0)
    sim = vehjax.simulate(m, scn, runs=1, key=jax.random.key(0), meas_std=[0.3, 0.005, 0.05])
    us = np.asarray(sim.inputs)
    res = vehjax.tune.fit(vehjax.filters.ekf, m.with_theta(cf=1.0e5),
                          np.diag([1e-4, 1e-5, 1e4, 1e4]), np.diag([0.09, 2.5e-5, 0.0025]),
                          np.asarray(sim.measurements[0]), us[0] if us.ndim == 3 else us,
                          x0=np.zeros(4), P0=np.diag([1e-2, 1e-3, 1e6, 1e6]), params=("cf",))
    assert res.nested is not None and "cf" in res.nested.values
    assert res.values["cf"] == pytest.approx(1.2e5, rel=0.02)
    assert res.values["R[vy,vy]"] == pytest.approx(0.05**2, rel=0.2)
