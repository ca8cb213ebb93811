"""Parameter transforms: maps between a bounded parameter and an unconstrained coordinate.

Every estimator that keeps a parameter theta inside its domain (low, high) works on an
unconstrained coordinate s instead: the parameter-estimating filters (``vehjax.filters.dual``,
``vehjax.filters.liu_west``), maximum-likelihood fitting (``vehjax.tune``) and the priors of
particle MCMC (``vehjax.calibrate``: Normal, LogNormal and Uniform are the maps none, lower
(low 0) and box with c = 1). ``low = -inf`` or ``high = +inf`` is an open end. The kind of map
follows from which ends are finite, with c > 0 the parameter's scale (its units)::

    none    theta = c s                          (-inf, inf)
    lower   theta = low + c exp(s)               (low, inf)
    upper   theta = high - c exp(s)              (-inf, high)
    box     theta = low + (high - low) sigmoid(s) (low, high)    (c unused)

Scalar maps of one kind: :func:`forward`, :func:`inverse`, :func:`derivative` and
:func:`log_derivative` (log |d theta / d s|, the log-Jacobian a density in s needs);
:class:`Transform` applies them to a vector of parameters.

A Gaussian N(s, P_s) in the unconstrained coordinate is reported in physical units by the delta
method: ``theta = g(s)``, ``P_theta = J P_s J^T`` with J = diag(dg/ds) evaluated at s; a
physical covariance C (a prior, a random-walk step) is brought in the other way,
``P_s = K^-1 C K^-T`` (:meth:`Transform.cov_to_physical`, :meth:`Transform.cov_to_unconstrained`).
K is J, except that for a bounded parameter |K_i| is no smaller than the standard deviation
sqrt(C_ii): |J_i| is about the distance to the nearer bound, and within one standard deviation
of a bound the linearisation means nothing (a physical step of std sigma at a distance d << sigma
would become a step of std sigma / d in s, e.g. an estimate 1e-4 from its bound thrown orders of
magnitude away by one random-walk step). With the floor the variance of s is at most 1 there
(for the log maps: a factor of about e^(+-2) at 95 %, which is the scale of a normal of std sigma
truncated at the bound); away from the bounds (sigma < d) it is the delta method.

Numerics near a bound (why these forms; they replace calibrate's priors' own maps, which
computed the box as ``low + span sigmoid(s)`` and its inverse as ``log p - log1p(-p)`` with
p = (theta - low) / span):

* s is clipped so that the distance to a bound (c exp(s) for the one-sided maps, about
  (high - low) exp(-|s|) for the box) stays within exp(+-L), L = 0.45 log(finfo.max) of the
  dtype (319 in float64, 40 in float32): values, derivatives, their squares and inverses are
  finite normal numbers (a far-out s saturates instead of overflowing; the map's gradient is
  then 0, never inf or NaN). Inside the clip the one-sided maps are exactly ``low + c exp(s)``.
* the box map is evaluated from the nearer end, ``high - (high - low) sigmoid(-s)`` for s > 0:
  the distance to the upper bound is then computed, not obtained as span (1 - sigmoid(s)), so
  theta keeps full relative precision near both bounds (``low + span sigmoid(s)`` loses the
  distance to ``high`` once sigmoid(s) rounds: e.g. Uniform(-100, 1e-3) near its upper end had
  absolute errors of 100 eps ~ 1e-14, relative 1e-11, instead of eps(1e-3) ~ 2e-19).
* the inverse of the box is ``log(theta - low) - log(high - theta)``: both differences are exact
  for theta near its bound (Sterbenz), where 1 - p loses the relative precision of
  high - theta (p rounded to eps relative); the inverse maps clip the distance to a bound at the
  dtype's smallest normal number, so a value on a bound maps to a finite s. Whether a value lies
  inside a domain is the caller's check (this module validates nothing).
* :func:`log_derivative` is written in closed form (``s + log c``;
  ``log span + log_sigmoid(s) + log_sigmoid(-s)``), accurate for every s, not the log of
  :func:`derivative`, which underflows far out.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["KINDS", "Transform", "kind", "forward", "inverse", "derivative", "log_derivative"]

#: The kinds of map, by which ends of (low, high) are finite.
KINDS = ("none", "lower", "upper", "box")


def kind(low: float, high: float) -> str:
    """The kind of map for the domain (low, high); +-inf for an open end."""
    has_lo, has_hi = bool(np.isfinite(low)), bool(np.isfinite(high))
    return ("box" if has_hi else "lower") if has_lo else ("upper" if has_hi else "none")


def _logmax(dtype) -> float:
    """Clip for log distances: exp(+-2 this) / 16 is a finite normal number in ``dtype``."""
    return 0.45 * math.log(float(np.finfo(np.dtype(dtype)).max))


def _dist(s, c: float):
    """c exp(s), the distance to the bound of a one-sided map, clipped to exp(+-_logmax)."""
    L = _logmax(s.dtype)
    return jnp.exp(jnp.clip(s + math.log(c), -L, L))


def _box_s(s, span: float):
    """s clipped so that the distance to either bound of a box, about span exp(-|s|), stays
    at least exp(-_logmax)."""
    m = max(_logmax(s.dtype) + math.log(span), 0.0)
    return jnp.clip(s, -m, m)


def _log_dist(d):
    """log of a distance to a bound, clipped below at the smallest normal number."""
    return jnp.log(jnp.maximum(d, jnp.finfo(d.dtype).tiny))


def forward(k: str, lo: float, hi: float, c: float, s):
    """theta = g(s) for the map of kind ``k`` on (lo, hi) with scale c; s a float array."""
    if k == "none":
        return c * s
    if k == "lower":
        return lo + _dist(s, c)
    if k == "upper":
        return hi - _dist(s, c)
    span = hi - lo
    s = _box_s(s, span)
    return jnp.where(s > 0, hi - span * jax.nn.sigmoid(-s), lo + span * jax.nn.sigmoid(s))


def inverse(k: str, lo: float, hi: float, c: float, v):
    """s = g^-1(theta) of :func:`forward`; theta ``v`` a float array (finite on a bound)."""
    if k == "none":
        return v / c
    if k == "lower":
        return _log_dist(v - lo) - math.log(c)
    if k == "upper":
        return _log_dist(hi - v) - math.log(c)
    return _log_dist(v - lo) - _log_dist(hi - v)


def derivative(k: str, lo: float, hi: float, c: float, s):
    """d theta / d s of :func:`forward`, elementwise (finite and nonzero, module docstring)."""
    if k == "none":
        return jnp.full_like(s, c)
    if k == "lower":
        return _dist(s, c)
    if k == "upper":
        return -_dist(s, c)
    # sigmoid(s) sigmoid(-s) = e^-|s| / (1 + e^-|s|)^2
    e = jnp.exp(-jnp.abs(_box_s(s, hi - lo)))
    return (hi - lo) * e / (1.0 + e) ** 2


def log_derivative(k: str, lo: float, hi: float, c: float, s):
    """log |d theta / d s| of the unclipped map, elementwise: ``log c`` (none), ``s + log c``
    (lower, upper), ``log(hi - lo) + log_sigmoid(s) + log_sigmoid(-s)`` (box). The
    log-Jacobian of a density carried into s: p_s(s) = p(g(s)) |g'(s)|."""
    if k == "none":
        return jnp.full_like(s, math.log(c))
    if k in ("lower", "upper"):
        return s + math.log(c)
    return math.log(hi - lo) + jax.nn.log_sigmoid(s) + jax.nn.log_sigmoid(-s)


@functools.partial(jax.jit, static_argnums=(0, 1, 3))
def _mapped(fn, spec: tuple, a, axis: int):
    """``fn`` (:func:`forward`, ...) applied entry by entry along ``axis`` of the float array
    ``a``, ``spec`` = ((kind, lo, hi, c), ...) one per entry: one program per spec and shape,
    which a trace inlines; called on values outside a trace it compiles once, where op by op
    every kind of map would compile a few small XLA programs of its own."""
    cols = [fn(k, lo, hi, c, jnp.take(a, i, axis=axis)) for i, (k, lo, hi, c) in enumerate(spec)]
    return jnp.stack(cols, axis=axis).astype(a.dtype)


class Transform:
    """Maps between physical parameters theta (..., p) and unconstrained coordinates s.

    Built from numpy constants (closed over by a filter, never traced); every method takes and
    returns jax arrays in the dtype of its argument, with the parameter axis ``axis`` (last by
    default; Liu-West's particles are (p, M), ``axis=0``). The arguments are taken as given:
    low < high and scale > 0 are the caller's checks.

    Attributes:
        low, high: (p,) float64 bounds in physical units, -inf / +inf for open ends.
        scale: (p,) positive units c of the none/lower/upper maps (module docstring).
        kinds: (p,) kind of each map, from :data:`KINDS`.
    """

    def __init__(self, low, high, scale=None):
        self.low = np.asarray(low, dtype=float).reshape(-1)
        self.high = np.asarray(high, dtype=float).reshape(-1)
        p = self.low.shape[0]
        self.scale = np.ones(p) if scale is None else np.asarray(scale, dtype=float).reshape(-1)
        self.kinds = tuple(kind(lo, hi) for lo, hi in zip(self.low, self.high))

    @property
    def bounds(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """(low, high) as tuples of Python floats: ``Estimator.bounds``."""
        return tuple(float(v) for v in self.low), tuple(float(v) for v in self.high)

    @property
    def bounded(self) -> bool:
        """Whether any parameter has a finite bound."""
        return any(k != "none" for k in self.kinds)

    def _map(self, fn, a, axis):
        a = jnp.asarray(a)
        if not jnp.issubdtype(a.dtype, jnp.floating):
            a = a.astype(jnp.asarray(0.0).dtype)
        spec = tuple((k, float(lo), float(hi), float(c))
                     for k, lo, hi, c in zip(self.kinds, self.low, self.high, self.scale))
        return _mapped(fn, spec, a, axis % a.ndim)

    def to_physical(self, s, axis: int = -1):
        """theta = g(s), same shape as s; inside [low, high] for every finite s."""
        return self._map(forward, s, axis)

    def to_unconstrained(self, theta, axis: int = -1):
        """s = g^-1(theta), same shape; a theta on or beyond a bound maps to a finite s."""
        return self._map(inverse, theta, axis)

    def jacobian(self, s, axis: int = -1):
        """The diagonal of dg/ds at s, same shape as s (physical units per unit of s)."""
        return self._map(derivative, s, axis)

    def cov_to_physical(self, s, P_s):
        """Delta method: ``J P_s J^T`` (p, p) with J = diag(dg/ds) at s (p,)."""
        J = self.jacobian(s)
        return P_s * (J[:, None] * J[None, :])

    def cov_to_unconstrained(self, s, P):
        """The inverse delta method for a physical covariance P (p, p) at s (p,): ``K^-1 P K^-T``
        with K = J, |K_i| floored at sqrt(P_ii) for bounded parameters (module docstring)."""
        J = self.jacobian(s)
        bounded = np.array([k != "none" for k in self.kinds])
        if bounded.any():
            sd = jnp.sqrt(jnp.maximum(jnp.diagonal(P), 0.0))
            floored = jnp.sign(J) * jnp.maximum(jnp.abs(J), sd)
            J = jnp.where(bounded, floored, J)
        Ji = 1.0 / J
        return P * (Ji[:, None] * Ji[None, :])
