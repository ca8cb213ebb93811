"""The models' vectorisable sin, cos, tan, arctan, arctan2 against numpy's (libm), to the last bits."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from vehjax.lib.elementary import arctan, arctan2, cos, sin, tan


def _ulps(got, ref):
    return np.abs(got - ref) / np.spacing(np.maximum(np.abs(ref), np.finfo(float).tiny))


def test_arctan_within_one_ulp_over_all_scales():
    rng = np.random.default_rng(0)
    x = np.concatenate([rng.normal(size=20000) * s for s in (1e-9, 1e-3, 0.5, 1.0, 3.0, 1e3, 1e12)])
    edges = np.array([0.0, -0.0, 0.66, -0.66, 2.414213562373095, 1.0, np.inf, -np.inf, 1e300])
    x = np.concatenate([x, edges, np.nextafter(edges[:6], 5.0)])
    got = np.asarray(jax.jit(arctan)(x))
    assert np.max(_ulps(got, np.arctan(x))) <= 1.0
    assert np.isnan(np.asarray(arctan(jnp.array([np.nan])))).all()


def test_arctan2_matches_numpy_in_every_quadrant():
    rng = np.random.default_rng(1)
    y = rng.normal(size=50000) * np.exp(3 * rng.normal(size=50000))
    x = rng.normal(size=50000) * np.exp(3 * rng.normal(size=50000))
    got = np.asarray(jax.jit(arctan2)(y, x))
    assert np.max(_ulps(got, np.arctan2(y, x))) <= 2.0
    zeros_y = np.array([0.0, 0.0, -0.0, -0.0, 1.0, -1.0, 2.0, -2.0])
    zeros_x = np.array([0.0, -0.0, 0.0, -0.0, 0.0, -0.0, -1e-300, 1e-300])
    np.testing.assert_array_equal(np.asarray(arctan2(zeros_y, zeros_x)), np.arctan2(zeros_y, zeros_x))
    # the reduction's edges: |y| = |x|, ratios next to 0.66 and 1/0.66, tiny and huge ratios
    edge = np.array([1.0, 0.66, 0.66 * (1 + 1e-15), 0.66 * (1 - 1e-15), 1 / 0.66, 1e-300, 1e300])
    for sy in (1.0, -1.0):
        for sx in (1.0, -1.0):
            got = np.asarray(arctan2(sy * edge, sx * np.ones_like(edge)))
            assert np.max(_ulps(got, np.arctan2(sy * edge, sx))) <= 2.0
    assert np.isnan(np.asarray(arctan2(jnp.array([np.nan, 1.0]), jnp.array([1.0, np.nan])))).all()


def test_derivative_is_that_of_arctan():
    x = jnp.array([0.0, 0.3, -1.0, 2.5, 1e4])
    # every derivative below under jit: one compile each, not one per primitive op by op
    np.testing.assert_allclose(jax.jit(jax.vmap(jax.grad(arctan)))(x), 1 / (1 + x**2), rtol=1e-15)
    # arctan2: d/dy atan2(y, x) = x / (x^2 + y^2), d/dx = -y / (x^2 + y^2), as jnp.arctan2's,
    # in every quadrant, forward and reverse mode
    rng = np.random.default_rng(5)
    y, x = rng.normal(size=(2, 64)) * np.array([[1.0], [3.0]])
    for argnums in (0, 1):
        ref = jax.jit(jax.vmap(jax.grad(jnp.arctan2, argnums)))(y, x)
        for grad in (jax.grad, lambda f, a: (lambda *v: jax.jacfwd(f, a)(*v))):
            got = jax.jit(jax.vmap(grad(arctan2, argnums)))(y, x)
            np.testing.assert_allclose(got, ref, rtol=1e-14)
    g = jax.grad(arctan2)(0.7, -1.3)
    assert g == pytest.approx(-1.3 / (0.7**2 + 1.3**2), rel=1e-14)


def test_float32_stays_float32():
    x = np.linspace(-50, 50, 1001, dtype=np.float32)
    got = arctan(jnp.asarray(x))
    assert got.dtype == jnp.float32
    assert np.max(np.abs(np.asarray(got) - np.arctan(x))) <= 2 * np.finfo(np.float32).eps


@pytest.mark.parametrize("fast, ref, ulps", [(sin, np.sin, 2), (cos, np.cos, 2), (tan, np.tan, 3)])
def test_sin_cos_tan_within_a_few_ulps(fast, ref, ulps):
    rng = np.random.default_rng(2)
    x = np.concatenate([rng.normal(size=20000) * s for s in (1e-8, 1e-2, 0.7, 2.0, 10.0, 1e3, 1e6)])
    x = np.concatenate([x, np.arange(-8, 9) * np.pi / 4, [0.0, -0.0]])
    got, want = np.asarray(jax.jit(fast)(x)), ref(x)
    away = (np.abs(want) > 1e-3) & (np.abs(want) < 1e8)  # tan's poles: no digits to keep
    assert np.max(_ulps(got[away], want[away])) <= ulps
    # next to a zero of the function the error is absolute: the last bits of pi/4 carried
    near_zero = np.abs(want) <= 1e-3
    assert np.max(np.abs(got - want)[near_zero] / np.maximum(1.0, np.abs(x[near_zero]))) < 1e-18
    assert np.isnan(np.asarray(fast(jnp.array([np.inf, -np.inf, np.nan])))).all()


def test_sin_cos_tan_derivatives():
    x = jnp.array([-2.0, -0.3, 0.0, 0.4, 1.2, 7.0])
    np.testing.assert_allclose(jax.vmap(jax.grad(sin))(x), np.cos(x), rtol=1e-15, atol=1e-16)
    np.testing.assert_allclose(jax.vmap(jax.grad(cos))(x), -np.sin(x), rtol=1e-15, atol=1e-16)
    np.testing.assert_allclose(jax.vmap(jax.grad(tan))(x), 1 / np.cos(x) ** 2, rtol=1e-14)


def test_float32_sin_cos_for_the_particle_filters_box_muller():
    angle = np.linspace(0.0, 2 * np.pi, 100_001, dtype=np.float32)
    for fast, ref in ((sin, np.sin), (cos, np.cos)):
        got = fast(jnp.asarray(angle))
        assert got.dtype == jnp.float32
        want = ref(angle.astype(np.float64))
        assert np.max(np.abs(np.asarray(got, np.float64) - want)) <= 2 * np.finfo(np.float32).eps
