"""The ``bounds=`` argument of the parameter-estimating filters and of ``vehjax.tune``: reading
it and checking values against it (validation, before anything is traced).

A parameter's domain (low, high), -inf / +inf for an open end, is turned into the unconstrained
coordinate the estimators work on by :class:`vehjax.lib.transforms.Transform` (the mathematics,
which validates nothing); this module is the checking in front of it:
:func:`check_pair` reads one ``(low, high)`` entry (None for an open end), :func:`parse` a whole
``bounds={name: (low, high)}`` argument of a filter builder, :func:`check_inside` a concrete
theta0 against the domains. :class:`Transform` is re-exported here so that a caller reads its
domains and builds their map from one module.
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

from .. import validation
from ..lib.transforms import Transform

__all__ = ["Transform", "check_pair", "parse", "check_inside"]


def check_inside(arg: str, theta, low, high, names: tuple) -> None:
    """ValueError naming ``arg`` unless every row of a concrete ``theta`` ((p,) or (R, p),
    physical units) lies strictly inside (low, high) and is finite; traced values pass."""
    if validation.is_tracer(theta):
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
    lo = -np.inf if lo is None else validation.number(f"{arg}[{name!r}] low", lo)
    hi = np.inf if hi is None else validation.number(f"{arg}[{name!r}] high", hi)
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
    given = validation.keyed(arg, bounds, names, "the estimated parameters")
    pairs = [check_pair(arg, n, given[n]) if n in given else (-np.inf, np.inf) for n in names]
    return (np.array([lo for lo, _ in pairs], dtype=float),
            np.array([hi for _, hi in pairs], dtype=float))
