"""Vectorisable sin, cos, tan, arctan and arctan2 for writing fast vehicle models.

XLA on CPU evaluates ``jnp.sin``, ``jnp.cos``, ``jnp.tan``, ``jnp.arctan`` and ``jnp.arctan2``
by one scalar library call per element (15-25 ns in float64, against about 1 ns for a multiply)
and cannot fuse them into the vectorised loops it builds for the arithmetic around them. A
model evaluated at every sigma point, particle and Runge-Kutta stage spends most of its time
there. The functions here compute the same values with arithmetic and ``where`` only (Cephes'
range reductions and polynomials), so XLA vectorises them; vehjax's built-in models use them.

Accuracy, against numpy (libm) in float64:

* ``arctan``: within 1 ulp over all arguments; ``arctan2``: within 2 ulp in every quadrant,
  numpy's signed zeros and quadrants (both arguments zero gives 0 or +-pi).
* ``sin``, ``cos``: within 2 ulp, ``tan`` within 3 ulp, for ``|x| < 1e8`` rad (far beyond any
  angle a vehicle model sees); next to a zero of the function the error is absolute, below
  1e-18 * max(1, |x|). Inf and NaN give NaN.
* float32 arguments stay float32 (within 2 float32 eps); integers are computed as float.

Derivatives are those of the true functions (``jax.custom_jvp``: cos, -sin, 1 + tan^2,
1 / (1 + x^2); arctan2's by composition), so ``jax.jacfwd``/``jax.grad`` of a model written
with them match those of the ``jnp`` version to rounding.

When to use them: in a model's ``transition``/``observe`` that runs on CPU, for float32 or
float64 angles. Write ``from vehjax.math import sin, cos, arctan2`` in place of the ``jnp``
ones. On GPU, or for complex, float16 or bfloat16 arguments, ``jnp``'s are as good or the only
choice. A model already written with ``jnp`` functions can be converted without editing it by
:func:`vehjax.substitute.fast_elementary`, which replaces these five functions in its trace.

Example::

    import jax.numpy as jnp
    from vehjax.math import arctan2, cos, sin

    def f(x, u, theta):
        alpha = u[1] - arctan2(x[1] + theta[0] * x[2], x[0])
        return x + 0.01 * jnp.stack([cos(u[1]) * u[0], sin(u[1]) * u[0], alpha])
"""

from __future__ import annotations

from .elementary import arctan, arctan2, cos, sin, tan

__all__ = ["sin", "cos", "tan", "arctan", "arctan2"]
