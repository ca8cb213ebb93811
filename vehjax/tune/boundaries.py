"""Fitted quantities on a bound of their domain: which quantities have one, how far the
optimiser may walk their unconstrained coordinates, and which end on one.

A quantity with a bound is fitted through a map that reaches the bound only at an infinite
coordinate (a model parameter's box ``lo + (hi - lo) sigmoid(s)`` or half line ``lo + exp(s)``,
a variance of a diagonal Q or R ``exp(2 d)``, an input-noise std ``exp(z)``,
:mod:`vehjax.tune.parameterisation`). When the likelihood increases beyond the bound the
maximum over the box is the bound: the coordinate runs off towards infinity, the map's
derivative and with it the gradient and the curvature along that coordinate vanish. Such a
quantity is not "not determined by the data" (a flat likelihood): it is *on its bound*, and the
report says so with the bound and the one-sided information, the derivative of the
log-likelihood in the quantity's units pointing out of the box (the Karush-Kuhn-Tucker
condition of the bounded maximum), while the standard errors of the other quantities come from
the curvature along the free directions, the bound quantities held at their bounds.

Limits: the bound of a full covariance (a singular matrix) is not detected; those quantities are
reported by the curvature rule of :mod:`vehjax.tune.information`.
"""

from __future__ import annotations

import numpy as np

__all__ = ["quantity_bounds", "coordinate_box", "on_bounds", "BOUND_TOL", "LOG_RANGE"]

#: a quantity is on a bound when its distance to it is at most this fraction of its range (a box)
#: or of its starting distance to the bound (a half line) and the likelihood increases beyond it
BOUND_TOL = 1e-3

#: the optimiser keeps the coordinate of a bounded quantity within this distance of its start
#: (the map is then at most e^-25 ~ 1e-11 of its range from the bound, a variance ~ e^-50 of its
#: start): beyond, the map's value rounds to the bound (an exp underflowing to a variance of 0 or
#: a sigmoid to 1), where the estimator cannot be built and the likelihood not be evaluated
LOG_RANGE = 25.0


def quantity_bounds(info, model) -> dict:
    """``{quantity name: (low, high, start value)}`` of the fitted quantities with a finite bound
    whose unconstrained coordinate has the same name (one coordinate, one quantity): model
    parameters with a lower and/or upper bound, the variances of a diagonal Q or R (low 0), the
    input-noise stds given by name (low 0)."""
    out = {}
    tm = info.theta_map
    for j, p in enumerate(info.params):
        lo, hi = float(tm.low[j]), float(tm.high[j])
        if np.isfinite(lo) or np.isfinite(hi):
            out[p] = (lo, hi, float(info.theta0[info.idx[j]]))
    for name, diag, cnames, A0 in (("Q", info.diagQ, model.state_names, info.Qa),
                                   ("R", info.diagR, model.output_names, info.Ra)):
        if name in info.noise and diag:
            for a, c in enumerate(cnames):
                out[f"{name}[{c},{c}]"] = (0.0, np.inf, float(A0[a, a]))
    inp = info.input
    if inp is not None and inp.cov is None:
        for n, z in zip(inp.names, inp.z0):
            out[f"input[{n}]"] = (0.0, np.inf, float(np.exp(z)))
    return out


def coordinate_box(names, x0, bounds: dict):
    """(low (n,), high (n,)): the coordinates of bounded quantities (:func:`quantity_bounds`)
    within :data:`LOG_RANGE` of their start ``x0``, the others unlimited."""
    x0 = np.asarray(x0, dtype=float)
    guarded = np.array([n in bounds for n in names], dtype=bool)
    return (np.where(guarded, x0 - LOG_RANGE, -np.inf),
            np.where(guarded, x0 + LOG_RANGE, np.inf))


def on_bounds(bounds: dict, names, values: dict, grad, jac, quantity_names, n_steps: int):
    """``{quantity: (side, bound, d logL / d quantity)}`` of the quantities on a bound.

    Args:
        bounds: :func:`quantity_bounds`.
        names: (n,) names of the unconstrained coordinates.
        values: fitted value of each quantity by name.
        grad: (n,) gradient of the loss (the mean negative log-likelihood per step) in the
            unconstrained coordinates at the result.
        jac: (m, n) derivatives of the quantities with respect to the coordinates.
        quantity_names: (m,) the quantities in the rows of ``jac``.
        n_steps: the run-steps the loss is averaged over.

    A quantity v is on its lower (upper) bound B when ``|v - B|`` is at most :data:`BOUND_TOL`
    of its range (or of its start's distance to B) and ``d logL / dv = -n_steps g_i / (dv/dz_i)``
    is negative (positive): the likelihood increases beyond the bound.
    """
    out = {}
    g, J = np.asarray(grad, dtype=float), np.asarray(jac, dtype=float)
    for k, q in enumerate(quantity_names):
        if q not in bounds or q not in names:
            continue
        lo, hi, v0 = bounds[q]
        i = list(names).index(q)
        d = J[k, i]  # > 0: every map is increasing
        score = -n_steps * g[i] / d if d > 0 else -np.sign(g[i]) * np.inf
        v = values[q]
        for side, b, outward in (("lower", lo, score < 0), ("upper", hi, score > 0)):
            if not np.isfinite(b) or not outward:
                continue
            size = hi - lo if np.isfinite(lo) and np.isfinite(hi) else abs(v0 - b)
            if abs(v - b) <= BOUND_TOL * size:
                out[q] = (side, float(b), float(score))
    return out
