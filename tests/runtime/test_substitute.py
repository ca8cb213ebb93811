"""vehjax.runtime.substitute.fast_elementary: a user's model written with jnp.sin/cos/arctan2 runs with
vehjax's vectorisable elementary functions, to their ulp bounds, derivatives included."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import lax

import vehjax as vj
from vehjax.runtime.hoist import split
from vehjax.runtime.substitute import fast_elementary

SD = jax.ShapeDtypeStruct
SUBSTITUTED = {"sin", "cos", "tan", "atan", "atan2"}
EPS = np.finfo(np.float64).eps


def _prims(jaxpr):
    """Names of all primitives in a jaxpr, nested jaxprs included."""
    jaxpr = getattr(jaxpr, "jaxpr", jaxpr)
    names = []
    for eqn in jaxpr.eqns:
        names.append(eqn.primitive.name)
        for sub in jax.extend.core.jaxprs_in_params(eqn.params):
            names += _prims(sub)
    return names


def _ulps(got, ref):
    got, ref = np.asarray(got, np.float64), np.asarray(ref, np.float64)
    return np.abs(got - ref) / np.spacing(np.maximum(np.abs(ref), np.finfo(float).tiny))


# -- a user's 3-DOF dual-track model, the equations of vehjax.models.Dynamic3DOF in jnp -------

def _forces(x, u, th):
    vx, vy, r = x[0], x[1], x[2]
    s_fl, s_fr, s_rl, s_rr, delta = u[0], u[1], u[2], u[3], u[4]
    m, cx, cy, lf, lr, iz, ca = (th[i] for i in range(7))
    alpha_f = delta - jnp.arctan2(vy + lf * r, vx)
    alpha_r = -jnp.arctan2(vy - lr * r, vx)
    fx_front = cx * s_fl + cx * s_fr
    fx_rear = cx * s_rl + cx * s_rr
    fy_front = 2.0 * (cy * alpha_f)
    fy_rear = 2.0 * (cy * alpha_r)
    c, s = jnp.cos(delta), jnp.sin(delta)
    fx = fx_front * c - fy_front * s + fx_rear - ca * vx**2
    fy = fx_front * s + fy_front * c + fy_rear
    mz = lf * (fx_front * s + fy_front * c) - lr * fy_rear
    return fx, fy, mz


def _derivative(x, u, th):
    vx, vy, r = x[0], x[1], x[2]
    fx, fy, mz = _forces(x, u, th)
    return jnp.stack([vy * r + fx / th[0], -vx * r + fy / th[0], mz / th[5]])


def user_f(x, u, th):
    return vj.models.integrate(_derivative, x, u, th, 0.01, "rk4")


def user_h(x, u, th):
    return jnp.stack([x[0], _forces(x, u, th)[1] / th[0], x[2]])


def user_fh(x, u, th):
    return user_f(x, u, th), user_h(x, u, th)


BUILTIN = vj.models.Dynamic3DOF(dt=0.01, outputs="matlab")
THETA = jnp.asarray(BUILTIN.theta)


def _points(n=64, seed=0):
    rng = np.random.default_rng(seed)
    x = np.stack([rng.uniform(5.0, 35.0, n), rng.normal(0.0, 0.5, n), rng.normal(0.0, 0.3, n)], 1)
    u = np.concatenate([rng.normal(0.0, 0.02, (n, 4)), rng.normal(0.0, 0.1, (n, 1))], 1)
    return jnp.asarray(x), jnp.asarray(u)


def test_user_model_matches_original_and_builtin():
    X, U = _points()
    batch = lambda fn: jax.jit(jax.vmap(fn, in_axes=(0, 0, None)))  # noqa: E731
    got = batch(fast_elementary(user_fh))(X, U, THETA)
    want = batch(user_fh)(X, U, THETA)
    ref = batch(lambda x, u, th: (BUILTIN.transition(x, u, th), BUILTIN.observe(x, u, th)))(X, U, THETA)
    for g, w, r in zip(got, want, ref):
        g, w, r = np.asarray(g), np.asarray(w), np.asarray(r)
        scale = np.max(np.abs(w), axis=0)  # per component: ay and r pass through zero
        assert np.all(np.abs(g - w) <= 64 * EPS * scale)
        # vs the built-in model, which uses the same elementary functions: rounding only
        assert np.all(np.abs(g - r) <= 8 * EPS * scale)
    # the rewritten model holds none of XLA's transcendental primitives
    names = _prims(jax.make_jaxpr(fast_elementary(user_f))(X[0], U[0], THETA))
    assert not SUBSTITUTED & set(names) and "custom_jvp_call" in names
    assert {"atan2", "sin", "cos"} <= set(_prims(jax.make_jaxpr(user_f)(X[0], U[0], THETA)))


def test_each_function_within_its_ulp_bound():
    rng = np.random.default_rng(1)
    x = np.concatenate([rng.normal(size=4000) * s for s in (1e-3, 0.7, 3.0, 1e3)])
    y = rng.normal(size=x.size) * np.exp(2 * rng.normal(size=x.size))

    def fn(x, y):
        return jnp.sin(x), jnp.cos(x), jnp.tan(x), jnp.arctan(x), jnp.arctan2(y, x)

    got = jax.jit(fast_elementary(fn))(x, y)
    refs = (np.sin(x), np.cos(x), np.tan(x), np.arctan(x), np.arctan2(y, x))
    for g, r, bound in zip(got, refs, (2, 2, 3, 1, 2)):
        away = np.abs(r) > 1e-3  # next to a zero the error is absolute (test_elementary)
        assert np.max(_ulps(g, r)[away]) <= bound
        assert np.max(np.abs(np.asarray(g) - r)[~away]) < 1e-18 * 1e3
    # float32 stays float32, within 2 eps
    got32 = fast_elementary(fn)(x.astype(np.float32), y.astype(np.float32))
    for g, r in zip(got32, (np.sin, np.cos, np.tan, np.arctan)):
        assert g.dtype == jnp.float32
        want = r(x.astype(np.float32).astype(np.float64))
        ok = np.abs(want) < 1e3  # tan's poles
        assert np.max(np.abs(np.asarray(g, np.float64) - want)[ok] / np.maximum(1, np.abs(want[ok]))) \
            <= 4 * np.finfo(np.float32).eps


def test_jacobians_agree_with_jax():
    X, U = _points(8, seed=2)
    jac = lambda fn: jax.jit(jax.vmap(jax.jacfwd(fn, argnums=(0, 2)), in_axes=(0, 0, None)))  # noqa: E731
    got, want = jac(fast_elementary(user_fh))(X, U, THETA), jac(user_fh)(X, U, THETA)
    for g, w in zip(jax.tree.leaves(got), jax.tree.leaves(want)):  # d(f, h)/d(x, theta)
        g, w = np.asarray(g), np.asarray(w)
        np.testing.assert_allclose(g, w, rtol=1e-12, atol=1e-12 * np.max(np.abs(w)))


def test_eager_jit_vmap_and_tracer_arguments_agree():
    X, U = _points(6, seed=3)
    fast = fast_elementary(user_h)
    eager = np.stack([np.asarray(fast(x, u, THETA)) for x, u in zip(X, U)])  # compiled once
    jitted = np.asarray(jax.jit(jax.vmap(fast, in_axes=(0, 0, None)))(X, U, THETA))
    # closed over a traced input and parameters, as the filters' point functions are
    closure = jax.jit(lambda X, u, th: jax.vmap(lambda x: fast(x, u, th))(X))
    # compiled per point and compiled over the batch: rounding apart (XLA's fusion may
    # contract a multiply and an add)
    np.testing.assert_allclose(jitted, eager, rtol=4 * EPS, atol=4 * EPS)
    np.testing.assert_allclose(closure(X, U[0], THETA)[0], eager[0], rtol=4 * EPS, atol=4 * EPS)
    # an eager transformation (tracer arguments, op by op) of a small function
    small = fast_elementary(lambda v, d: jnp.cos(d) * v[0] - jnp.arctan2(v[1], v[0]))
    np.testing.assert_allclose(jax.grad(small, argnums=1)(X[0], U[0, 4]),
                               -jnp.sin(U[0, 4]) * X[0, 0], rtol=4 * EPS)
    # one wrapper per function: the cache is shared
    assert fast_elementary(user_h) is fast and fast_elementary(fast) is fast


def test_cond_scan_and_while_bodies_are_rewritten():
    def fn(x):
        y = lax.cond(x[0] > 0, lambda v: jnp.sin(v) + 1.0, lambda v: jnp.cos(v), x)
        y, ys = lax.scan(lambda c, a: (c * jnp.cos(a) + jnp.arctan(c), jnp.sin(c)), y, x)
        y = lax.fori_loop(0, 3, lambda i, c: c + 0.1 * jnp.tan(c), y)  # a scan: static bounds
        z = lax.while_loop(lambda c: c[0] < 2.0, lambda c: c + 0.5 + jnp.sin(c) ** 2, y)
        return y + ys.sum(0), jax.jit(jnp.arctan2)(z, y + 2.0)

    fast = fast_elementary(fn)
    names = _prims(jax.make_jaxpr(fast)(jnp.ones(3)))
    assert not SUBSTITUTED & set(names)
    assert {"cond", "scan", "while"} <= set(names)
    xs = jnp.array([[0.3, -0.2, 1.1], [-0.4, 0.8, 0.05]])
    for g, w in zip(jax.jit(jax.vmap(fast))(xs), jax.jit(jax.vmap(fn))(xs)):
        np.testing.assert_allclose(g, w, rtol=32 * EPS, atol=32 * EPS)

    # derivatives through cond and scan (not the while loop: no reverse mode there)
    def g(x):
        return fn(x)[0].sum()

    np.testing.assert_allclose(jax.jit(jax.grad(fast_elementary(g)))(xs[0]),
                               jax.jit(jax.grad(g))(xs[0]), rtol=1e-12)
    np.testing.assert_allclose(jax.jit(jax.jacfwd(fast))(xs[1])[1], jax.jit(jax.jacfwd(fn))(xs[1])[1],
                               rtol=1e-12, atol=1e-14)


def test_public_elementary_module_exports_the_five_functions():
    import vehjax.lib.elementary as el

    assert set(el.__all__) == {"sin", "cos", "tan", "arctan", "arctan2"}
    assert all(callable(getattr(el, n)) for n in el.__all__)


def test_non_float_operands_and_other_dtypes_untouched():
    def fn(k, z, h, x):
        return k * 3 + 1, jnp.sin(z), jnp.cos(h), jnp.sin(x)

    k = jnp.arange(5)
    z = jnp.linspace(0, 1, 5) * (1 + 1j)
    h = jnp.linspace(0, 1, 5).astype(jnp.float16)
    x = jnp.linspace(0, 1, 5)
    fast = fast_elementary(fn)
    got, want = fast(k, z, h, x), fn(k, z, h, x)
    for g, w in zip(got[:3], want[:3]):  # integers, complex, float16: XLA's, bit for bit
        assert g.dtype == w.dtype
        np.testing.assert_array_equal(g, w)
    names = _prims(jax.make_jaxpr(fast)(k, z, h, x))
    assert names.count("sin") == 1 and names.count("cos") == 1  # complex sin, float16 cos
    # a function of integers alone (nothing to substitute) is called as it is
    ints = fast_elementary(lambda a, b: (a * b) // 3)
    np.testing.assert_array_equal(ints(k, k + 2), (k * (k + 2)) // 3)


def test_functions_without_transcendentals_or_with_effects_unchanged():
    def poly(x, u):
        return x * x + u * jnp.exp(x)

    x, u = jnp.linspace(-1, 1, 7), jnp.float64(0.3)
    fast = fast_elementary(poly)
    np.testing.assert_array_equal(fast(x, u), poly(x, u))
    assert str(jax.make_jaxpr(fast)(x, u)) == str(jax.make_jaxpr(poly)(x, u))

    seen = []

    def noisy(x):
        jax.debug.callback(lambda v: seen.append(float(v)), x[0])
        return jnp.sin(x)

    got = fast_elementary(noisy)(x)
    np.testing.assert_array_equal(got, noisy(x))  # XLA's sin: the function as it is
    assert len(seen) == 2
    assert "sin" in _prims(jax.make_jaxpr(fast_elementary(noisy))(x))
    # weakly typed Python scalars keep their weak type
    out = fast_elementary(lambda a: jnp.sin(a) * 2)(0.5)
    assert jax.typeof(out).weak_type and float(out) == pytest.approx(2 * np.sin(0.5), rel=4 * EPS)


def test_hoisting_still_finds_the_steering_trigonometry():
    args = (SD((3,), jnp.float64), SD((5,), jnp.float64), SD((7,), jnp.float64))
    sp = split(fast_elementary(user_f), args, late=(True, False, False))
    assert sp.n_residuals > 0
    early = jax.make_jaxpr(sp.early)(args[1], args[2]).jaxpr
    calls = {e.params["call_jaxpr"].jaxpr.debug_info.func_name
             for e in early.eqns if e.primitive.name == "custom_jvp_call"}
    assert {"sin", "cos"} <= calls  # sin and cos of the steering angle, once per input
    X, U = _points(4, seed=4)
    def both(x, u, th):
        return sp.late(x, *sp.early(u, th)), fast_elementary(user_f)(x, u, th)

    got, want = jax.jit(jax.vmap(both, in_axes=(0, 0, None)))(X, U, THETA)
    np.testing.assert_allclose(got, want, rtol=4 * EPS, atol=4 * EPS)
    # a user's model from the wrapped functions (Model's shape checks call them eagerly)
    model = vj.models.Model(transition=fast_elementary(user_f), observe=lambda x, u, th: x, dt=0.01,
                            state_names=("vx", "vy", "r"), param_names=BUILTIN.param_names,
                            input_names=BUILTIN.input_names, theta=BUILTIN.theta)
    assert model.transition(X[0], U[0], THETA).shape == (3,)


def test_per_point_filter_steps_use_the_functions_as_written():
    """A user Model with fast_math: the runs-last EKF/UKF and the particle filters get the
    substitutes, the per-run steps (vmapped over runs, short vectors where the substitutes were
    measured slower) the functions as written, with the same estimates to rounding."""
    from vehjax.filters._model import per_point

    names = ("vx", "vy", "r")
    kw = dict(dt=0.01, state_names=names, output_names=("vx", "ay", "r"),
              param_names=BUILTIN.param_names, input_names=BUILTIN.input_names,
              theta=np.asarray(BUILTIN.theta))
    fast = vj.models.Model(user_f, user_h, fast_math=True, **kw)
    plain = vj.models.Model(user_f, user_h, fast_math=False, **kw)
    X, U = _points(4)
    f_fast, _ = per_point(fast)
    assert {"atan2", "sin", "cos"} <= set(_prims(jax.make_jaxpr(f_fast)(X[0], U[0], THETA)))
    assert not SUBSTITUTED & set(_prims(jax.make_jaxpr(fast.transition)(X[0], U[0], THETA)))
    Q, R = np.diag([0.05, 0.05, 0.01]) ** 2, np.diag([0.2, 0.3, 0.05]) ** 2
    ys = np.asarray(jax.vmap(lambda x, u: user_h(x, u, THETA))(X, U))[None].repeat(2, 0)
    kw_run = dict(x0=np.asarray(X[0]), P0=np.diag([1.0, 0.2, 0.05]) ** 2, progress=False)
    ekf_fast, ekf_plain = vj.filters.ekf(fast, Q, R), vj.filters.ekf(plain, Q, R)
    a = vj.run(ekf_fast._replace(runtime=ekf_fast.runtime._replace(batch=None)), ys, np.asarray(U), **kw_run)
    b = vj.run(ekf_plain._replace(runtime=ekf_plain.runtime._replace(batch=None)), ys, np.asarray(U), **kw_run)
    np.testing.assert_array_equal(a.states, b.states)  # the very same computation
    c = vj.run(ekf_fast, ys, np.asarray(U), **kw_run)  # runs-last: the substitutes
    np.testing.assert_allclose(c.states, b.states, rtol=1e-12)
