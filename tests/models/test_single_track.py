"""vehjax.models.SingleTrack against references written here: scipy's solve_ivp of the continuous
equations, the linear bicycle's steady-state cornering (understeer gradient), the tyre curves'
small-slip slopes and limits."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import vehjax  # noqa: F401  (float64)
from vehjax.models import REGISTRY, SingleTrack
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


def _rhs(tyres, theta):
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

    def rhs(x, delta, vx):
        ff, fr, c = forces(x, delta, vx)
        fy, mz = ff * c + fr, lf * ff * c - lr * fr
        return np.array([fy / m - vx * x[1], mz / iz]), fy / m

    return rhs


def _reference_rollout(tyres, theta, u, dt, x0):
    """Zero-order-hold inputs, solve_ivp (DOP853, tight tolerances) from sample to sample."""
    rhs = _rhs(tyres, theta)
    xs, ays, x = [], [], np.array(x0, float)
    for delta, vx in u:
        sol = solve_ivp(lambda t, z: rhs(z, delta, vx)[0], (0.0, dt), x, method="DOP853",
                        rtol=1e-11, atol=1e-13)
        x = sol.y[:, -1]
        xs.append(x)
        ays.append(rhs(x, delta, vx)[1])
    return np.array(xs), np.array(ays)


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
    x_ref, ay_ref = _reference_rollout(tyres, np.asarray(model.theta), u, 0.01, [0.0, 0.0])
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
