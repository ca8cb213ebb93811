"""vehjax.runtime.prng: the unrolled Threefry-2x32 is JAX's hash bit for bit; its normals and
uniforms have the distributions they claim."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.extend.random import threefry_2x32

from vehjax.runtime import prng


@pytest.mark.parametrize("seed", [0, 1, 2**31 + 7])
def test_threefry_equals_jax(seed):
    key = prng.raw_key(jax.random.key(seed))
    counts = jnp.asarray(np.random.default_rng(seed).integers(0, 2**32, 64, dtype=np.uint32))
    ref = threefry_2x32(key, counts)
    y0, y1 = prng.threefry2x32(key, counts[:32], counts[32:])
    np.testing.assert_array_equal(np.concatenate([y0, y1]), ref)


def test_split_hashes_four_counters_and_gives_distinct_keys():
    key = prng.raw_key(jax.random.key(42))
    nxt, sub = prng.split(key)
    ref = threefry_2x32(key, jnp.arange(4, dtype=jnp.uint32))
    np.testing.assert_array_equal(np.concatenate([nxt, sub]), ref)
    assert len({tuple(np.asarray(k).tolist()) for k in (key, nxt, sub)}) == 3


def test_normal_rows_are_independent_standard_normals():
    stats = pytest.importorskip("scipy.stats")
    key = prng.raw_key(jax.random.key(5))
    rows = np.asarray(jnp.stack(prng.std_normal_rows(key, 3, 200_000, jnp.float64)))
    assert rows.shape == (3, 200_000) and rows.dtype == np.float64
    np.testing.assert_allclose(rows.mean(axis=1), 0.0, atol=4 / np.sqrt(200_000))
    np.testing.assert_allclose(np.corrcoef(rows), np.eye(3), atol=0.01)
    for r in rows:
        assert stats.kstest(r, "norm").pvalue > 1e-3
    assert np.abs(rows).max() <= np.sqrt(-2 * np.log(2.0**-24)) + 1e-6
    # another stream of the same key gives other numbers
    other = np.asarray(prng.std_normal_rows(key, 1, 200_000, jnp.float64, stream=2)[0])
    assert abs(np.corrcoef(other, rows[0])[0, 1]) < 0.01


@pytest.mark.parametrize("dtype, bits", [(jnp.float64, 32), (jnp.float32, 24)])
def test_uniforms_on_their_grid(dtype, bits):
    key = prng.raw_key(jax.random.key(9))
    u = np.asarray(prng.uniforms(key, 100_000, dtype))
    assert u.dtype == dtype and u.min() >= 0.0 and u.max() < 1.0
    np.testing.assert_array_equal(u * 2.0**bits, np.floor(u * 2.0**bits))
    assert abs(u.mean() - 0.5) < 4 * np.sqrt(1 / 12 / u.size)
    np.testing.assert_allclose(np.histogram(u, bins=10, range=(0, 1))[0] / u.size, 0.1, atol=0.005)


def test_unit_circle_is_sin_cos_of_the_angle_the_bits_give():
    w = np.random.default_rng(0).integers(0, 2**32, 100_000, dtype=np.uint32)
    w = np.concatenate([w, np.array([0, 2**30, 2**31, 3 * 2**30, 2**32 - 1], np.uint32)])
    cos_a, sin_a = prng._unit_circle(jnp.asarray(w))
    angle = 2 * np.pi * (w >> 8).astype(np.float64) / 2.0**24
    assert cos_a.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(cos_a), np.cos(angle), rtol=0, atol=3e-7)
    np.testing.assert_allclose(np.asarray(sin_a), np.sin(angle), rtol=0, atol=3e-7)
