"""Parameter domains: maps between a bounded parameter and an unconstrained coordinate.

Every parameter-estimating filter (:mod:`vehjax.filters.dual`, :mod:`vehjax.filters.liu_west`)
and :mod:`vehjax.tune` keep a parameter theta inside its domain (low, high) by working on an
unconstrained coordinate s instead; ``low = -inf`` or ``high = +inf`` is an open end. The kind of
map follows from which ends are finite, with c > 0 the parameter's scale (its units)::

    none    theta = c s                          (-inf, inf)
    lower   theta = low + c exp(s)               (low, inf)
    upper   theta = high - c exp(s)              (-inf, high)
    box     theta = low + (high - low) sigmoid(s) (low, high)    (c unused)

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

Numerics: s is clipped so that the distance to a bound (c exp(s) for the one-sided maps, about
(high - low) exp(-|s|) for the box) stays within exp(+-L), L = 0.45 log(finfo.max) of the dtype
(319 in float64, 40 in float32): values, derivatives, their squares and inverses are finite
normal numbers (a far-out s saturates instead of overflowing; the map's gradient is then 0,
never inf or NaN);
the box map is evaluated from the nearer end, ``high - (high - low) sigmoid(-s)`` for s > 0, so
it keeps full relative precision near both bounds; the inverse maps clip the distance to a bound
at the dtype's smallest normal number, so a value on a bound maps to a finite s.

Validation: :func:`check_pair` reads one ``(low, high)`` entry (None for an open end),
:func:`parse` a whole ``bounds={name: (low, high)}`` argument of a filter builder.
"""

from __future__ import annotations

import math
from typing import Mapping

import jax
import jax.numpy as jnp
import numpy as np

from .. import _validate

__all__ = ["KINDS", "Transform", "kind", "check_pair", "parse", "check_inside"]

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


def _forward(k: str, lo: float, hi: float, c: float, s):
    if k == "none":
        return c * s
    if k == "lower":
        return lo + _dist(s, c)
    if k == "upper":
        return hi - _dist(s, c)
    span = hi - lo
    s = _box_s(s, span)
    return jnp.where(s > 0, hi - span * jax.nn.sigmoid(-s), lo + span * jax.nn.sigmoid(s))


def _inverse(k: str, lo: float, hi: float, c: float, v):
    if k == "none":
        return v / c
    if k == "lower":
        return _log_dist(v - lo) - math.log(c)
    if k == "upper":
        return _log_dist(hi - v) - math.log(c)
    return _log_dist(v - lo) - _log_dist(hi - v)


def _derivative(k: str, lo: float, hi: float, c: float, s):
    """d theta / d s, elementwise (finite and nonzero, see the module docstring)."""
    if k == "none":
        return jnp.full_like(s, c)
    if k == "lower":
        return _dist(s, c)
    if k == "upper":
        return -_dist(s, c)
    # sigmoid(s) sigmoid(-s) = e^-|s| / (1 + e^-|s|)^2
    e = jnp.exp(-jnp.abs(_box_s(s, hi - lo)))
    return (hi - lo) * e / (1.0 + e) ** 2


class Transform:
    """Maps between physical parameters theta (..., p) and unconstrained coordinates s.

    Built from numpy constants (closed over by a filter, never traced); every method takes and
    returns jax arrays in the dtype of its argument, with the parameter axis ``axis`` (last by
    default; Liu-West's particles are (p, M), ``axis=0``).

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
        if self.high.shape != (p,) or self.scale.shape != (p,) or np.any(self.scale <= 0):
            raise ValueError("Transform: low, high and scale must be (p,), scale positive")
        if np.any(self.low >= self.high):
            raise ValueError("Transform: expected low < high")
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
        axis = axis % a.ndim
        cols = [fn(k, float(lo), float(hi), float(c), jnp.take(a, i, axis=axis))
                for i, (k, lo, hi, c) in enumerate(zip(self.kinds, self.low, self.high,
                                                        self.scale))]
        return jnp.stack(cols, axis=axis).astype(a.dtype)

    def to_physical(self, s, axis: int = -1):
        """theta = g(s), same shape as s; inside [low, high] for every finite s."""
        return self._map(_forward, s, axis)

    def to_unconstrained(self, theta, axis: int = -1):
        """s = g^-1(theta), same shape; a theta on or beyond a bound maps to a finite s."""
        return self._map(_inverse, theta, axis)

    def jacobian(self, s, axis: int = -1):
        """The diagonal of dg/ds at s, same shape as s (physical units per unit of s)."""
        return self._map(_derivative, s, axis)

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


def check_inside(arg: str, theta, low, high, names: tuple) -> None:
    """ValueError naming ``arg`` unless every row of a concrete ``theta`` ((p,) or (R, p),
    physical units) lies strictly inside (low, high) and is finite; traced values pass."""
    if _validate.is_tracer(theta):
        return
    th = np.asarray(theta, dtype=float)
    low, high = np.asarray(low, dtype=float), np.asarray(high, dtype=float)
    out = ~((th > low) & (th < high))  # NaN is outside
    if np.any(out):
        cols = np.flatnonzero(np.any(out.reshape(-1, low.shape[0]), axis=0))
        what = {names[j]: (float(low[j]), float(high[j])) for j in cols}
        raise ValueError(
            f"{arg}: expected finite values strictly inside the parameters' domains (the "
            f"builder's bounds=); not so for name: (low, high) {what}"
        )


def check_pair(arg: str, name: str, value) -> tuple[float, float]:
    """One ``(low, high)`` entry for parameter ``name`` as floats, +-inf for None ends.

    Raises ValueError naming ``arg`` unless it is a pair of finite numbers or None with
    low < high.
    """
    try:
        lo, hi = value
    except (TypeError, ValueError):
        raise ValueError(f"{arg}: expected a pair (low, high) for {name!r}, None for an open "
                         f"end, got {value!r}") from None
    lo = -np.inf if lo is None else _validate.number(f"{arg}[{name!r}] low", lo)
    hi = np.inf if hi is None else _validate.number(f"{arg}[{name!r}] high", hi)
    if not lo < hi:
        raise ValueError(f"{arg}: expected low < high for {name!r}, got ({lo}, {hi})")
    return lo, hi


def parse(bounds, names: tuple, nominal, arg: str = "bounds") -> tuple[np.ndarray, np.ndarray]:
    """(low, high), each (p,) float64 with +-inf for open ends, for the parameters ``names``.

    ``bounds`` None: the default, (0, inf) for a parameter whose ``nominal`` value is positive
    (masses, lengths, stiffnesses), open otherwise. A dict ``{name: (low, high)}`` (None for an
    open end) is the whole specification: a parameter it does not name is unbounded, so
    ``bounds={}`` turns every bound off. Raises ValueError naming ``arg`` for names not in
    ``names``, entries that are not pairs of finite numbers or None, or low >= high.
    """
    nominal = np.asarray(nominal, dtype=float).reshape(-1)
    if bounds is None:
        low = np.where(nominal > 0, 0.0, -np.inf)
        return low, np.full(len(names), np.inf)
    if not isinstance(bounds, Mapping):
        raise ValueError(f"{arg}: expected a dict name -> (low, high) or None, got {bounds!r}")
    given = _validate.keyed(arg, bounds, names, "the estimated parameters")
    pairs = [check_pair(arg, n, given[n]) if n in given else (-np.inf, np.inf) for n in names]
    return (np.array([lo for lo, _ in pairs], dtype=float),
            np.array([hi for _, hi in pairs], dtype=float))
