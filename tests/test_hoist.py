"""vehjax._hoist.split: the early/late partition of a model function computes what it does."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import vehjax as vj
from vehjax._hoist import split

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
