"""Counter-based random numbers for the particle filters, cheap on CPU in float64 mode.

``jax.random`` on CPU hashes with Threefry-2x32 in a rolled loop (five passes of a
``fori_loop``), and in float64 mode ``jax.random.normal`` draws 64-bit uniforms and an inverse
error function: about 40 ns a number on one core. The filters here need thousands of normals
per run and step, and a resolution of 2^-24 is far below any particle filter's Monte-Carlo error,
so they hash with the same Threefry-2x32 (Salmon, Moraes, Dror & Shaw 2011, 20 rounds) written
out in straight-line code that XLA fuses into one vectorised loop, and turn 32-bit words into
float32 normals by Box-Muller. The hash is bit-for-bit ``jax.extend.random.threefry_2x32``
(tests/runtime/test_random.py checks it), so keys from ``jax.random`` plug in unchanged.

Keys are raw (2,) uint32 arrays. A step calls :func:`split` once and draws from the sub-key with
counters that it chooses so that no two draws of that step share one.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

_ROTATIONS = ((13, 15, 26, 6), (17, 29, 16, 24))
_PARITY = np.uint32(0x1BD11BDA)


def threefry2x32(key, x0, x1):
    """Threefry-2x32 with 20 rounds: the pair of uint32 words hashed from the counter pair
    (x0, x1) under ``key``.

    Args:
        key: (2,) uint32.
        x0, x1: uint32 arrays of one shape (or broadcastable): the counters.

    Returns:
        (y0, y1), uint32 arrays of the broadcast shape. ``threefry_2x32(key, concat([a, b]))``
        of ``jax.extend.random`` equals ``concat(threefry2x32(key, a, b))``.
    """
    ks = (key[0], key[1], key[0] ^ key[1] ^ _PARITY)
    x0 = x0 + ks[0]
    x1 = x1 + ks[1]
    for i in range(5):
        for r in _ROTATIONS[i % 2]:
            x0 = x0 + x1
            x1 = (x1 << np.uint32(r)) | (x1 >> np.uint32(32 - r))
            x1 = x1 ^ x0
        x0 = x0 + ks[(i + 1) % 3]
        x1 = x1 + ks[(i + 2) % 3] + np.uint32(i + 1)
    return x0, x1


def raw_key(key):
    """A (2,) uint32 Threefry key from any JAX PRNG key (typed, or legacy uint32[2])."""
    return jax.random.bits(key, (2,), jnp.uint32)


def split(key):
    """(next key, sub-key) from a raw key: the words ``threefry_2x32(key, arange(4))`` of
    ``jax.extend.random``, split in two halves."""
    return threefry2x32(key, np.array([0, 1], np.uint32), np.array([2, 3], np.uint32))


# Cephes sinf.c / cosf.c: float32 polynomials for sin t and cos t, |t| <= pi/4.
_SINF = (-1.9515295891e-4, 8.3321608736e-3, -1.6666654611e-1)
_COSF = (2.443315711809948e-5, -1.388731625493765e-3, 4.166664568298827e-2)


def _unit_circle(w):
    """(cos a, sin a), float32, for the angle a = 2 pi (w >> 8) / 2^24 of uint32 words ``w``.

    The top two bits pick the quadrant, the next 22 the angle phi = pi/4 + t in it, so the
    polynomials see |t| <= pi/4 only and no range reduction is needed.
    """
    q = w >> np.uint32(30)
    f = ((w >> np.uint32(8)) & np.uint32(0x3FFFFF)).astype(jnp.float32)
    t = (f * np.float32(2.0**-22) - np.float32(0.5)) * np.float32(math.pi / 2)
    z = t * t
    s = t + t * z * ((_SINF[0] * z + _SINF[1]) * z + _SINF[2])
    c = 1.0 - 0.5 * z + z * z * ((_COSF[0] * z + _COSF[1]) * z + _COSF[2])
    r2 = np.float32(math.sqrt(0.5))
    s_phi, c_phi = (s + c) * r2, (c - s) * r2  # sin, cos of pi/4 + t
    sin_a = jnp.where(q == 0, s_phi, jnp.where(q == 1, c_phi, jnp.where(q == 2, -s_phi, -c_phi)))
    cos_a = jnp.where(q == 0, c_phi, jnp.where(q == 1, -s_phi, jnp.where(q == 2, -c_phi, s_phi)))
    return cos_a, sin_a


def std_normal_rows(key, rows: int, n: int, dtype, stream: int = 0):
    """(rows, n) standard normals from one key.

    Box-Muller on pairs of float32 uniforms on a 2^-24 grid, u1 in (0, 1] and an angle in
    [0, 2 pi): the radius reaches 5.77 at most. Row pairs (2k, 2k + 1) share the hashes of
    counters (p, stream + k), p = 0..n-1, one row as the cosine and the other as the sine
    branch; an odd last row leaves its sines unused.

    Args:
        key: (2,) uint32 raw key.
        rows, n: how many rows, and normals per row.
        dtype: dtype of the results (the arithmetic is float32).
        stream: counter offset; draws of one key with different ``stream`` ranges, at least
            ceil(rows / 2) apart, are independent.
    """
    p = np.arange(n, dtype=np.uint32)
    out = []
    for k in range((rows + 1) // 2):
        w0, w1 = threefry2x32(key, p, np.uint32(stream + k))
        u1 = ((w0 >> 8).astype(jnp.float32) + 1.0) * np.float32(2.0**-24)
        r = jnp.sqrt(-2.0 * jnp.log(u1))
        cos_a, sin_a = _unit_circle(w1)
        out.append((r * cos_a).astype(dtype))
        if len(out) < rows:
            out.append((r * sin_a).astype(dtype))
    return jnp.stack(out)


def uniforms(key, n: int, dtype, stream: int = 0):
    """(n,) uniforms in [0, 1) exactly representable in ``dtype``, from counters (p, stream).

    32 random bits in float64, 24 in float32.
    """
    w0, _ = threefry2x32(key, np.arange(n, dtype=np.uint32), np.uint32(stream))
    keep = min(32, jnp.finfo(dtype).nmant + 1)
    return (w0 >> np.uint32(32 - keep)).astype(dtype) * jnp.asarray(2.0**-keep, dtype)
