"""Vectorisable sin, cos, tan, arctan and arctan2 for the vehicle models and the filters.

XLA on CPU evaluates ``jnp.sin``, ``cos``, ``tan``, ``arctan`` and ``arctan2`` in float64 by a
scalar library call per element, 15-25 ns against about 1 ns for a multiply or a division (which
it vectorises). Slip angles and the tyre formula are computed for every wheel, Runge-Kutta stage,
sigma point and particle, so these calls were most of a particle filter's model time. The
versions here use only arithmetic and ``where``, so XLA vectorises them; they agree with numpy
to 1-2 ulp (sin, cos, tan for |x| < 1e8 rad, far beyond any angle a vehicle model sees).

arctan (Moshier's Cephes ``atan``): reduce |x| to [0, tan(pi/8)] with
atan(x) = pi/2 - atan(1/x) above tan(3 pi/8) and pi/4 + atan((x - 1)/(x + 1)) above 0.66, then
a degree 4/5 rational function in x^2; the low-order bits of pi/2 and pi/4 are added back
separately. The derivative is defined exactly as 1/(1 + x^2) (``custom_jvp``), so Jacobians
by ``jax.jacfwd`` are those of the true arctan; arctan2's likewise as (x dy - y dx) / (x^2 + y^2)
(a tenth of the operations of differentiating its quadrant folding).

sin, cos (Cephes ``sin``/``cos``): x = j pi/4 + r with j even and |r| <= pi/4, the product j pi/4
subtracted in three parts (Cody-Waite) so r keeps its bits for |x| up to about 1e8, then degree-6
polynomials in r^2 for sin r and cos r and the octant's sign and swap. Derivatives are defined as
cos and -sin.

In your own model, on CPU, for float32 or float64 angles::

    from vehjax.lib.elementary import arctan2, cos, sin

float32 arguments stay float32, integers are computed as float; on GPU, or for complex, float16
or bfloat16 arguments, ``jnp``'s are as good or the only choice. A model already written with
``jnp`` converts without editing through :func:`vehjax.runtime.substitute.fast_elementary`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

_T3P8 = 2.41421356237309504880  # tan(3 pi / 8)
_MOREBITS = 6.123233995736765886130e-17  # pi/2 - float64(pi/2)
# Cephes atan.c: atan(x) = x + x z P(z) / Q(z), z = x^2, |x| <= 0.66 after reduction.
_P = (-8.750608600031904122785e-1, -1.615753718733365076637e1, -7.500855792314704667340e1,
      -1.228866684490136173410e2, -6.485021904942025371773e1)
_Q = (2.485846490142306297962e1, 1.650270098316988542046e2, 4.328810604912902668951e2,
      4.853903996359136964868e2, 1.945506571482613964425e2)


__all__ = ["sin", "cos", "tan", "arctan", "arctan2"]


def _horner(z, coeffs, monic: bool):
    acc = jnp.ones_like(z) if monic else jnp.full_like(z, coeffs[0])
    for c in coeffs if monic else coeffs[1:]:
        acc = acc * z + c
    return acc


@jax.custom_jvp
def arctan(x):
    """Elementwise arctan of a float array, rad in (-pi/2, pi/2)."""
    x = jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(float)
    a = jnp.abs(x)
    big = a > _T3P8
    mid = (a > 0.66) & ~big
    # Arguments of the reduced branches, made safe where the branch is not taken (no inf/NaN).
    a_big = jnp.where(big, a, 1.0)
    r = jnp.where(big, -1.0 / a_big, jnp.where(mid, (a - 1.0) / (a + 1.0), a))
    base = jnp.where(big, np.pi / 2, jnp.where(mid, np.pi / 4, 0.0))
    extra = jnp.where(big, _MOREBITS, jnp.where(mid, 0.5 * _MOREBITS, 0.0))
    z = r * r
    p = z * _horner(z, _P, monic=False) / _horner(z, _Q, monic=True)
    y = base + (r * p + r + extra)
    y = jnp.where(jnp.isnan(x), x, y)
    return jnp.where(x < 0, -y, y).astype(x.dtype)


@arctan.defjvp
def _arctan_jvp(primals, tangents):
    (x,), (tx,) = primals, tangents
    return arctan(x), tx / (1.0 + jnp.asarray(x) ** 2)


@jax.custom_jvp
def arctan2(y, x):
    """Elementwise arctan2(y, x), rad in [-pi, pi], with numpy's quadrants and signed zeros
    handled as ``jnp.arctan2`` does for finite arguments (both zero gives 0 or +-pi). The
    derivative is that of the true arctan2, (x dy - y dx) / (x^2 + y^2) (``custom_jvp``)."""
    y, x = jnp.asarray(y), jnp.asarray(x)
    dtype = jnp.result_type(y.dtype, x.dtype, float)
    y, x = y.astype(dtype), x.astype(dtype)
    ay, ax = jnp.abs(y), jnp.abs(x)
    # atan(num / den) with num <= den, reduced as arctan's (its tan(3 pi / 8) branch cannot
    # occur): above 0.66, pi/4 + atan((num - den) / (num + den)), one division either way
    swap = ay > ax
    num = jnp.where(swap, ax, ay)
    den = jnp.where(swap, ay, ax)
    mid = num > 0.66 * den
    r = jnp.where(mid, num - den, num) / jnp.where(mid, num + den, jnp.where(den == 0, 1.0, den))
    z = r * r
    p = z * _horner(z, _P, monic=False) / _horner(z, _Q, monic=True)
    t = jnp.where(mid, np.pi / 4, 0.0) + (r * p + r + jnp.where(mid, 0.5 * _MOREBITS, 0.0))
    t = jnp.where(swap, np.pi / 2 - t, t)
    t = jnp.where(jnp.signbit(x), np.pi - t, t)
    return jnp.where(jnp.signbit(y), -t, t)


@arctan2.defjvp
def _arctan2_jvp(primals, tangents):
    (y, x), (ty, tx) = primals, tangents
    out = arctan2(y, x)
    y, x = jnp.asarray(y, out.dtype), jnp.asarray(x, out.dtype)
    return out, (x * ty - y * tx) / (x * x + y * y)


# pi/4 in three parts whose products with the octant index j are exact (Cephes sin.c, sinf.c).
_DP = {
    8: (7.85398125648498535156e-1, 3.77489470793079817668e-8, 2.69515142907905952645e-15),
    4: (0.78515625, 2.4187564849853515625e-4, 3.77489497744594108e-8),
}
_SIN = (1.58962301576546568060e-10, -2.50507477628578072866e-8, 2.75573136213857245213e-6,
        -1.98412698295895385996e-4, 8.33333333332211858878e-3, -1.66666666666666307295e-1)
_COS = (-1.13585365213876817300e-11, 2.08757008419747316778e-9, -2.75573141792967388112e-7,
        2.48015872888517045348e-5, -1.38888888888730564116e-3, 4.16666666666665929218e-2)


def _float(x):
    x = jnp.asarray(x)
    return x if jnp.issubdtype(x.dtype, jnp.floating) else x.astype(float)


def _reduce(x):
    """|x| = j pi/4 + r: (r, j mod 8 as float with j even) for the octant logic."""
    a = jnp.abs(x)
    dp1, dp2, dp3 = _DP[8 if x.dtype.itemsize >= 8 else 4]
    j = jnp.floor(a * (4.0 / np.pi))
    # j mod 2 and j mod 8 by floor, exact for integer-valued j: XLA on CPU calls fmod per element
    j = j + (j - 2.0 * jnp.floor(0.5 * j))  # round up to even: r in [-pi/4, pi/4]
    r = ((a - j * dp1) - j * dp2) - j * dp3
    return r, j - 8.0 * jnp.floor(0.125 * j)


def _sin_cos_poly(r):
    z = r * r
    s = r + r * z * _horner(z, _SIN, monic=False)
    c = 1.0 - 0.5 * z + z * z * _horner(z, _COS, monic=False)
    return s, c


def _sincos(x):
    x = _float(x)
    r, q = _reduce(x)  # q in {0, 2, 4, 6}: multiples of pi/2 in |x|
    s, c = _sin_cos_poly(r)
    swap = (q == 2.0) | (q == 6.0)
    sin_a = jnp.where(swap, c, s) * jnp.where(q >= 4.0, -1.0, 1.0)
    cos_a = jnp.where(swap, s, c) * jnp.where((q == 2.0) | (q == 4.0), -1.0, 1.0)
    sin_x = jnp.where(x < 0, -sin_a, sin_a)
    # sin(-x) = -sin(x), cos(-x) = cos(x); inf and NaN give NaN through the arithmetic.
    return sin_x.astype(x.dtype), cos_a.astype(x.dtype)


@jax.custom_jvp
def sin(x):
    """Elementwise sine of a float array (rad)."""
    return _sincos(x)[0]


@jax.custom_jvp
def cos(x):
    """Elementwise cosine of a float array (rad)."""
    return _sincos(x)[1]


@sin.defjvp
def _sin_jvp(primals, tangents):
    (x,), (tx,) = primals, tangents
    s, c = _sincos(x)
    return s, tx * c


@cos.defjvp
def _cos_jvp(primals, tangents):
    (x,), (tx,) = primals, tangents
    s, c = _sincos(x)
    return c, -tx * s


@jax.custom_jvp
def tan(x):
    """Elementwise tangent of a float array (rad), sin/cos of one reduction."""
    s, c = _sincos(x)
    return s / c


@tan.defjvp
def _tan_jvp(primals, tangents):
    (x,), (tx,) = primals, tangents
    s, c = _sincos(x)
    t = s / c
    return t, tx * (1.0 + t * t)
