"""Kinematic bicycle, 3-DOF dual-track model and the user-model wrapper."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import vehjax as vj
from vehjax.models import Dynamic3DOF, KinematicBicycle, Model


def kinematic_rhs(x, u, th):
    """Dutta et al. eq. 1-5, written out plainly."""
    _, _, psi, v = x
    a, delta = u
    lf, lr = th
    beta = np.arctan(lr / (lf + lr) * np.tan(delta))
    return np.array([v * np.cos(psi + beta), v * np.sin(psi + beta), v / lr * np.sin(beta), a])


def dynamic_rhs(x, u, th):
    """Dutta et al. eq. 6-10 (typos read as in the model's docstring), written out plainly."""
    vx, vy, r = x
    sfl, sfr, srl, srr, d = u
    m, cx, cy, a, b, J, ca = th
    Fxfl, Fxfr, Fxrl, Fxrr = cx * sfl, cx * sfr, cx * srl, cx * srr
    af = d - np.arctan((vy + a * r) / vx)
    ar = -np.arctan((vy - b * r) / vx)
    Fyfl = Fyfr = cy * af
    Fyrl = Fyrr = cy * ar
    dvx = vy * r + 1 / m * ((Fxfl + Fxfr) * np.cos(d) - (Fyfl + Fyfr) * np.sin(d) + Fxrl + Fxrr - ca * vx**2)
    dvy = -vx * r + 1 / m * ((Fxfl + Fxfr) * np.sin(d) + (Fyfl + Fyfr) * np.cos(d) + Fyrl + Fyrr)
    dr = 1 / J * (a * ((Fxfl + Fxfr) * np.sin(d) + (Fyfl + Fyfr) * np.cos(d)) - b * (Fyrl + Fyrr))
    return np.array([dvx, dvy, dr])


def test_kinematic_derivative_matches_paper():
    rng = np.random.default_rng(0)
    model = KinematicBicycle()
    for _ in range(20):
        x = rng.normal(size=4) * [10, 10, 1, 5] + [0, 0, 0, 15]
        u = rng.normal(size=2) * [1, 0.2]
        th = rng.uniform(1.0, 2.0, size=2)
        np.testing.assert_allclose(model.derivative(jnp.array(x), jnp.array(u), jnp.array(th)),
                                   kinematic_rhs(x, u, th), rtol=1e-12, atol=1e-12)


def test_dynamic_derivative_matches_paper():
    rng = np.random.default_rng(1)
    model = Dynamic3DOF()
    for _ in range(20):
        x = np.array([rng.uniform(5, 30), rng.normal() * 0.5, rng.normal() * 0.3])
        u = np.concatenate([rng.normal(size=4) * 0.01, rng.normal(size=1) * 0.1])
        th = np.asarray(model.theta) * rng.uniform(0.8, 1.2, size=7)
        np.testing.assert_allclose(model.derivative(jnp.array(x), jnp.array(u), jnp.array(th)),
                                   dynamic_rhs(x, u, th), rtol=1e-11, atol=1e-12)


def test_dynamic_matlab_outputs_give_lateral_acceleration():
    model = Dynamic3DOF(outputs="matlab")
    assert model.output_names == ("vx", "ay", "r")
    x = jnp.array([20.0, 0.3, 0.1])
    u = jnp.array([0.001, 0.001, 0.0, 0.0, 0.03])
    dvy = dynamic_rhs(np.asarray(x), np.asarray(u), np.asarray(model.theta))[1]
    y = model.observe(x, u, model.theta)
    np.testing.assert_allclose(y[1], dvy + 20.0 * 0.1, rtol=1e-12)


def _drive(model, delta, n_steps, x0):
    def step(x, _):
        accel = 2.0 * (20.0 - model.speed(x))  # hold 20 m/s
        u = model.drive_input(x, delta, accel, 20.0, model.theta)
        return model.transition(x, u, model.theta), x

    return jax.lax.scan(step, x0, None, length=n_steps)[1]


def test_straight_driving_gives_no_yaw():
    model = Dynamic3DOF()
    xs = _drive(model, 0.0, 500, model.initial_state(20.0))
    assert np.max(np.abs(xs[:, 1:])) == 0.0
    kin = KinematicBicycle()
    xk = _drive(kin, 0.0, 500, kin.initial_state(20.0))
    assert np.max(np.abs(xk[:, 1:3])) == 0.0


def test_mirrored_steering_mirrors_response():
    model = Dynamic3DOF()
    x0 = model.initial_state(20.0)
    left = _drive(model, 0.04, 400, x0)
    right = _drive(model, -0.04, 400, x0)
    np.testing.assert_allclose(left[:, 0], right[:, 0], rtol=1e-13)
    np.testing.assert_allclose(left[:, 1:], -right[:, 1:], rtol=1e-12, atol=1e-15)
    assert np.max(np.abs(left[:, 2])) > 0.05


@pytest.mark.parametrize("lf,lr", [(1.5, 1.5), (1.2, 1.8), (1.7, 1.3)])
def test_steady_cornering_matches_understeer_gradient(lf, lr):
    """Linear single-track theory: r = vx delta / (L + K vx^2), K = m (lr Cr - lf Cf) / (L Cf Cr)."""
    model = Dynamic3DOF().with_theta(lf=lf, lr=lr)
    m, cy = float(model.theta[0]), float(model.theta[2])
    L, Cf, Cr = lf + lr, 2 * cy, 2 * cy  # axle cornering stiffness: two tyres per axle
    K = m * (lr * Cr - lf * Cf) / (L * Cf * Cr)
    delta = 0.005  # small, so arctan(z) ~ z and cos(delta) ~ 1
    xs = _drive(model, delta, 3000, model.initial_state(20.0))
    vx, r = float(xs[-1, 0]), float(xs[-1, 2])
    assert abs(float(xs[-1, 2] - xs[-100, 2])) < 1e-6 * r  # settled
    np.testing.assert_allclose(r, vx * delta / (L + K * vx**2), rtol=5e-3)


def test_rk4_and_euler_agree_for_small_steps():
    fine = Dynamic3DOF(dt=0.0005, integrator="euler")
    coarse = Dynamic3DOF(dt=0.01, integrator="rk4")
    x0 = coarse.initial_state(20.0)
    u = jnp.array([0.001, 0.001, 0.0, 0.0, 0.03])
    x_rk4 = jax.lax.fori_loop(0, 100, lambda i, x: coarse.transition(x, u, coarse.theta), x0)
    x_eul = jax.lax.fori_loop(0, 2000, lambda i, x: fine.transition(x, u, fine.theta), x0)
    np.testing.assert_allclose(x_rk4, x_eul, rtol=2e-3, atol=2e-4)


def test_models_jit_and_vmap():
    model = Dynamic3DOF()
    xs = jnp.tile(model.initial_state(20.0), (5, 1))
    u = jnp.array([0.001, 0.001, 0.0, 0.0, 0.03])
    out = jax.jit(jax.vmap(lambda x: model.transition(x, u, model.theta)))(xs)
    assert out.shape == (5, 3) and out.dtype == jnp.float64


def test_user_model_wrapper():
    model = Model(transition=lambda x, u, th: th[0] * x + u, observe=lambda x, u, th: x[:1], dt=0.1,
                  state_names=("p", "v"), param_names=("a",), input_names=("u1", "u2"), theta=[0.5],
                  units={"p": "m"})
    assert model.output_names == ("y0",) and model.state_units == ("m", "-")
    np.testing.assert_allclose(model.transition(jnp.ones(2), jnp.ones(2), model.theta), [1.5, 1.5])
    assert model.observe(jnp.ones(2), jnp.ones(2), model.theta).shape == (1,)


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(dt=0.0), "dt"),
        (dict(dt=-1.0), "dt"),
        (dict(dt=float("nan")), "dt"),
        (dict(state_names="xy"), "state_names"),
        (dict(state_names=("x", "x")), "state_names"),
        (dict(theta=[1.0, 2.0]), "theta"),
        (dict(transition=3), "transition"),
    ],
)
def test_user_model_bad_input(kwargs, match):
    base = dict(transition=lambda x, u, th: x, observe=lambda x, u, th: x, dt=0.1,
                state_names=("x",), param_names=("a",), theta=[1.0])
    base.update(kwargs)
    with pytest.raises(ValueError, match=match):
        Model(**base)


def test_builtin_model_bad_input():
    with pytest.raises(ValueError, match="dt"):
        Dynamic3DOF(dt=0)
    with pytest.raises(ValueError, match="integrator"):
        Dynamic3DOF(integrator="heun")
    with pytest.raises(ValueError, match="outputs"):
        Dynamic3DOF(outputs="all")
    with pytest.raises(ValueError, match="theta"):
        Dynamic3DOF(theta=[1.0, 2.0])
    with pytest.raises(ValueError, match="unknown parameter"):
        Dynamic3DOF().with_theta(mass=1.0)


def test_registry_lists_every_model_with_units():
    for cls in vj.models.REGISTRY.values():
        m = cls()
        assert len(m.state_units) == m.nx and len(m.param_units) == m.n_params
        assert len(m.input_units) == m.nu and len(m.output_units) == m.ny
        assert cls.__name__ in m.describe()


def test_integrate_substeps_are_steps_of_dt_over_substeps():
    """integrate(..., substeps=k) = k steps of dt / k: eager and written out (traced), bit for
    bit, the derivative one call whose trace every stage of every sub-step shares; rolled
    into a loop (the CPU's strategy) to rounding."""
    from vehjax import execution
    from vehjax.models.base import integrate
    model = vj.models.SingleTrack(tyres="brush")
    x, u, th = jnp.array([0.4, 0.2]), jnp.array([0.05, 18.0]), jnp.asarray(model.theta)
    cpu = execution.for_platform("cpu")
    assert cpu.rolled_substeps and not execution.for_platform("gpu").rolled_substeps
    for integrator, stages in (("rk4", 4), ("euler", 1)):
        def two_steps(x, u, th):
            for _ in range(2):
                x = integrate(model.derivative, x, u, th, 0.005, integrator)
            return x

        def substeps(x, u, th):
            return integrate(model.derivative, x, u, th, 0.01, integrator, substeps=2)

        ref = two_steps(x, u, th)
        np.testing.assert_array_equal(substeps(x, u, th), ref)
        with execution.using(cpu._replace(rolled_substeps=False)):
            np.testing.assert_array_equal(jax.jit(substeps)(x, u, th), ref)
            calls = [e for e in jax.make_jaxpr(substeps)(x, u, th).jaxpr.eqns
                     if e.primitive.name in ("jit", "pjit")]
        assert len(calls) == 2 * stages
        assert len({id(e.params["jaxpr"].jaxpr) for e in calls}) == 1
        with execution.using(cpu):  # a new function: JAX keeps a function's trace
            rolled = lambda x, u, th: substeps(x, u, th)  # noqa: E731
            eqns = jax.make_jaxpr(rolled)(x, u, th).jaxpr.eqns
            np.testing.assert_allclose(jax.jit(rolled)(x, u, th), ref, rtol=1e-14)
        assert [e.primitive.name for e in eqns if e.primitive.name in ("scan", "while")]
        assert not [e for e in eqns if e.primitive.name in ("jit", "pjit")]
