"""vehjax.runtime.hoist.split: the early/late partition of a model function computes what it does."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import vehjax as vj
from vehjax.runtime.hoist import split

SD = jax.ShapeDtypeStruct


def _args(nx, nu, n_params, dtype=jnp.float64):
    return SD((nx,), dtype), SD((nu,), dtype), SD((n_params,), dtype)


@pytest.mark.parametrize("model", [vj.models.Dynamic3DOF(dt=0.01, outputs="matlab"),
                                   vj.models.KinematicBicycle(dt=0.01)], ids=lambda m: type(m).__name__)
def test_split_model_equals_model(model):
    rng = np.random.default_rng(0)
    x = jnp.asarray(model.initial_state(15.0)) + 0.1 * rng.standard_normal(model.nx)
    u = jnp.asarray(0.02 * rng.standard_normal(model.nu))
    theta = jnp.asarray(model.theta)
    for fn in (model.transition, model.observe):
        sp = split(fn, _args(model.nx, model.nu, model.n_params), late=(True, False, False))
        res = sp.early(u, theta)
        assert len(res) == sp.n_residuals
        np.testing.assert_array_equal(sp.late(x, *res), fn(x, u, theta))
    # the steering trigonometry and slip forces of the 3-DOF transition are computed early
    sp = split(model.transition, _args(model.nx, model.nu, model.n_params), (True, False, False))
    assert sp.n_residuals > 0


def test_split_vmaps_late_over_points_with_shared_residuals():
    def fn(x, u, theta):
        c = jnp.cos(u[0]) * theta[0]
        return jnp.stack([x[0] * c + x[1], u[1] * 2.0, jnp.sin(x[1] * u[0])])

    sp = split(fn, _args(2, 2, 1), late=(True, False, False))
    u, th = jnp.array([0.3, -1.5]), jnp.array([2.0])
    X = jnp.asarray(np.random.default_rng(1).standard_normal((2, 9)))
    got = jax.vmap(sp.late, in_axes=(1,) + (None,) * sp.n_residuals, out_axes=1)(X, *sp.early(u, th))
    want = jax.vmap(fn, in_axes=(1, None, None), out_axes=1)(X, u, th)
    np.testing.assert_array_equal(got, want)


def test_split_keeps_functions_with_effects_whole():
    seen = []

    def fn(x, u):
        jax.debug.callback(lambda v: seen.append(float(v)), u[0])
        return x * jnp.cos(u[0])

    sp = split(fn, (SD((2,), jnp.float64), SD((1,), jnp.float64)), late=(True, False))
    res = sp.early(jnp.array([0.5]))
    assert sp.n_residuals == 1 and res[0].shape == (1,)  # the input itself, nothing computed
    np.testing.assert_allclose(sp.late(jnp.ones(2), *res), np.cos(0.5) * np.ones(2))
    assert seen == [0.5]


def test_split_rejects_wrong_number_of_flags():
    with pytest.raises(ValueError, match="late"):
        split(lambda x, u: x + u, (SD((2,), jnp.float64), SD((2,), jnp.float64)), late=(True,))


# -- dependence: which output entries are constants of the function --------------------------

from vehjax.runtime.hoist import dependence  # noqa: E402


def test_dependence_follows_entries_through_moves_and_elementwise_ops():
    def fn(x, u):
        a = jnp.stack([x[0] * u[1], 2.0 + u[0] * 0.0, jnp.sin(x[1]) + x[0] - x[0]])  # 0 * u: 2.0
        b = jnp.concatenate([a[:1], jnp.array([3.0, 0.0]), jnp.cos(u[1:2])])
        c = jnp.zeros(4).at[1].add(x[1]).at[3].set(7.0)  # scatters at fixed indices
        return {"a": a, "b": b, "c": c, "k": jnp.ones((2, 2)) * 5.0, "s": jnp.sum(x) + 1.0}

    d = dependence(fn, (jnp.ones(2), jnp.ones(2)))
    np.testing.assert_array_equal(d["a"], [True, False, True])  # x - x still "depends"
    np.testing.assert_array_equal(d["b"], [True, False, False, True])
    np.testing.assert_array_equal(d["c"], [False, True, False, False])
    np.testing.assert_array_equal(d["k"], np.zeros((2, 2), bool))
    assert d["s"].shape == () and bool(d["s"])


def test_dependence_is_conservative_for_reductions_and_products():
    def fn(x):
        M = jnp.diag(x) @ jnp.eye(2)  # a matrix product: every entry depends
        return M, jnp.cumsum(jnp.array([1.0, 0.0]) * x[0])

    M, c = dependence(fn, (jnp.ones(2),))
    assert M.all() and c.all()


@pytest.mark.parametrize("model", [
    vj.models.SingleTrackBank(dt=0.01),
    # the other two models: about 20 s of compiling each on 2 cores (`pytest -m slow`)
    pytest.param(vj.models.Dynamic3DOF(dt=0.01), marks=pytest.mark.slow),
    pytest.param(vj.models.KinematicBicycle(dt=0.01), marks=pytest.mark.slow)],
                         ids=lambda m: type(m).__name__)
def test_entries_found_constant_are_the_same_at_random_points(model):
    """Sound on the built-in models: every Jacobian entry of transition and observe that
    ``dependence`` calls constant takes that one value at 20 random states and inputs; and the
    structural zeros and ones of SingleTrackBank's bank dynamics are found."""
    theta = jnp.asarray(model.theta)

    def jac(x, u):
        return (jax.jacfwd(model.transition)(x, u, theta), jax.jacfwd(model.observe)(x, u, theta),
                jax.jacfwd(model.transition, argnums=1)(x, u, theta))

    x0, u0 = jnp.asarray(model.initial_state(15.0)), jnp.full(model.nu, 0.01)
    deps = dependence(jac, (x0, u0))
    rng = np.random.default_rng(3)
    X = x0 + 0.3 * rng.standard_normal((20, model.nx)) * (1.0 + np.abs(np.asarray(x0)))
    U = np.asarray(u0) + 0.1 * rng.standard_normal((20, model.nu))
    vals = jax.vmap(jac)(jnp.asarray(X), jnp.asarray(U))
    n_const = 0
    for d, v in zip(deps, vals):
        v = np.asarray(v)
        const = ~np.asarray(d)
        n_const += int(const.sum())
        np.testing.assert_array_equal(np.broadcast_to(v[0], v.shape)[:, const], v[:, const])
    assert n_const > 0
    if isinstance(model, vj.models.SingleTrackBank):
        A = ~np.asarray(deps[0])[2:, 2:]  # d(phi, phi_dot, phi_ddot)' / d(phi, phi_dot, phi_ddot)
        assert A.all()


def test_numpy_evaluation_of_equations_equals_the_primitives():
    """``dependence`` evaluates common primitives in numpy (hoist._apply); each such equation of
    a function using them gives what binding the primitive gives, dtype and shape included."""
    from vehjax.runtime import hoist

    def fn(x, i):
        a = jnp.stack([x[0] * x[1] - x[2] / x[1], -x[0], jnp.abs(x[2]) + jnp.floor(x[1])])
        b = jnp.concatenate([a, jnp.sin(x) * jnp.cos(x), jnp.arctan2(x, a) + jnp.tanh(x)])
        c = jnp.where(b > 0.1, b ** 3, jnp.maximum(b, -x[0]) + jnp.sqrt(jnp.exp(x[1])))
        m = jnp.broadcast_to(c[:3, None], (3, 2)).T.reshape(6)
        k = (jax.lax.bitcast_convert_type(x[0], jnp.int64) >> 3) + i
        return m[1:4], (c >= 0) & (c != 0.5) | ~(c < -1.0), k.astype(jnp.float64), \
            jnp.log(jnp.abs(c) + 1.0), jnp.arange(4) * 2.0, x.astype(jnp.float32)

    args = (np.array([0.7, -1.3, 2.1]), np.int64(5))
    closed = jax.make_jaxpr(fn)(*args)
    env = dict(zip(closed.jaxpr.invars, args))
    env.update(zip(closed.jaxpr.constvars, closed.consts))
    n_numpy = 0
    for eqn in closed.jaxpr.eqns:
        vals = [v.val if isinstance(v, jax.extend.core.Literal) else env[v] for v in eqn.invars]
        got = hoist._apply(eqn, vals)
        ref = eqn.primitive.bind(*vals, **eqn.params)
        ref = list(ref) if eqn.primitive.multiple_results else [ref]
        for g, r in zip(got, ref):
            assert np.shape(g) == np.shape(r) and np.asarray(g).dtype == np.asarray(r).dtype, eqn
            np.testing.assert_allclose(np.asarray(g, float), np.asarray(r, float), rtol=1e-14,
                                       err_msg=str(eqn))
        n_numpy += all(isinstance(g, np.ndarray) for g in got) and eqn.primitive.name in (
            hoist._NUMPY)
        env.update(zip(eqn.outvars, got))
    assert n_numpy >= 20


def test_inline_calls_writes_nested_calls_in_place_and_split_sees_through_them():
    from jax.extend.core import jaxpr_as_fun

    from vehjax.runtime.hoist import inline_calls

    inner = jax.jit(lambda x, u: x * jnp.cos(u[0]) + u[1])
    outer = jax.jit(lambda x, u: inner(x, u) * 2.0)

    def fn(x, u, theta):
        return outer(x, u) + theta[0]

    closed = jax.make_jaxpr(fn)(*[jnp.ones(2), jnp.ones(2), jnp.ones(1)])
    flat = inline_calls(closed)
    assert not [e for e in flat.jaxpr.eqns if e.primitive.name in ("jit", "pjit")]
    args = (jnp.array([0.3, -1.2]), jnp.array([0.7, 2.0]), jnp.array([0.5]))
    np.testing.assert_array_equal(jaxpr_as_fun(flat)(*args)[0], fn(*args))
    # cos(u[0]) is inside the calls and needs no state: split computes it early
    sp = split(fn, _args(2, 2, 1), late=(True, False, False))
    late_prims = {e.primitive.name for e in jax.make_jaxpr(sp.late)(
        *[jnp.ones(2)] + list(sp.early(jnp.ones(2), jnp.ones(1)))).jaxpr.eqns}
    assert "cos" not in late_prims and sp.n_residuals > 0
    np.testing.assert_array_equal(sp.late(args[0], *sp.early(args[1], args[2])), fn(*args))
