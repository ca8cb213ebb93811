"""How sure a fit is: the observed information (the Hessian of minus the log-likelihood in the
unconstrained coordinates, by differences of JAX's exact gradient or by ``jax.hessian``),
inverted over the directions the data determine and carried to the physical quantities by the
delta method; the directions with no or too little curvature are named.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .. import validation

__all__ = ["Uncertainty", "uncertainty", "hessian_from_gradients", "difference_hessian",
           "FORWARD_REL", "RCOND", "MAX_SCALED_STD"]

RCOND = 1e-8  # undetermined: eigenvalue of the scaled information below this x the largest
MAX_SCALED_STD = 1.0  # ... or a standard error above the quantity's own size (scaled units)

#: forward differences of the gradient for the Hessian (:func:`difference_hessian`): steps of
#: this fraction of each coordinate's scale. Truncation error ~ rel, rounding of the gradient
#: ~ 1e-14 / rel (relative); agreement with central differences measured in
#: ``benchmarks/results/notes_tune.md``
FORWARD_REL = 1e-6



class Uncertainty(NamedTuple):
    """What :func:`uncertainty` returns.

    Attributes:
        cov: (m, m) covariance of the fitted quantities in their units (delta method), with
            inf on the diagonal of a quantity an undetermined direction moves.
        std_errors: (m,) standard errors, sqrt of its diagonal (inf: undetermined; NaN: on a
            bound, ``pinned``).
        correlations: (m, m), NaN in the rows and columns of undetermined quantities.
        undetermined: names of the coordinates in the undetermined directions.
        eigenvalues: (n,) eigenvalues of the scaled observed information, ascending.
        determined: (n,) bool, which eigen-directions the data determine.
    """

    cov: np.ndarray
    std_errors: np.ndarray
    correlations: np.ndarray
    undetermined: tuple
    eigenvalues: np.ndarray
    determined: np.ndarray


def _max_std(max_std, shape) -> np.ndarray:
    """``max_std`` of :func:`uncertainty` as (n,) positive values (inf for no limit)."""
    try:
        out = np.broadcast_to(np.asarray(max_std, dtype=float), shape)
    except (TypeError, ValueError):
        out = np.full(shape, np.nan)
    if isinstance(max_std, (str, bytes, bool)) or not np.all(out > 0):
        raise ValueError(f"max_std: expected a positive number or {shape} of them (inf for no "
                         f"limit), got {max_std!r}")
    return out


def uncertainty(info_matrix, jac, scales, coord_names, rcond: float = RCOND,
                max_std=MAX_SCALED_STD, fixed=None, pinned=None) -> Uncertainty:
    """Standard errors and correlations of fitted quantities from the observed information.

    With ``I`` (n, n) the observed information of the unconstrained coordinates z (the Hessian
    of minus the log-likelihood), ``S = diag(scales)`` and ``I_s = S I S = V diag(lam) V^T``,
    an eigen-direction is undetermined when ``lam <= rcond * max(lam)`` (no curvature: the data
    do not move the likelihood along it) or ``lam < 1 / max_std^2`` (its standard error exceeds
    ``max_std`` of the scale, the quantity's own size: not determined to within a factor of
    about e for a log coordinate). The covariance of z over the determined directions is
    ``S V_d diag(1/lam_d) V_d^T S``, that of the quantities ``J cov_z J^T`` (delta method,
    ``jac`` = J = d quantities / dz, (m, n)). A coordinate is named undetermined when its
    component in an undetermined direction is at least 0.3 (the largest always).

    ``max_std`` may be given per coordinate, (n,): a direction v is then undetermined by size
    when ``lam < sum_i v_i^2 / max_std_i^2``; inf exempts a coordinate whose scale is not the
    quantity's own size (x0: its scale is the prior's standard deviation, and the data's
    information on x0 through the first steps is always below the prior's 1 / P0, so the rule
    would name every fitted x0 undetermined).

    ``fixed`` (n,) bool: coordinates held where they are, the quantities on a bound of their
    domain (:mod:`vehjax.tune.boundaries`): the information is that of the free coordinates
    (the curvature along the free directions, the fixed ones at their bounds); ``pinned`` (m,)
    bool, the quantities on a bound: their standard errors and correlations are NaN.
    ``eigenvalues`` and ``determined`` are then those of the free coordinates.
    """
    scales = validation.shaped("scales", scales, (None,))
    Iz = validation.shaped("info_matrix", info_matrix, scales.shape * 2)  # non-finite: NaNs out
    J = validation.shaped("jac", jac, (None,) + scales.shape)
    rcond = validation.number("rcond", rcond, 0.0, 1.0, low_open=False)
    max_std = _max_std(max_std, scales.shape)
    if fixed is not None and np.any(fixed):
        return _with_fixed(Iz, J, scales, coord_names, rcond, max_std, np.asarray(fixed, bool),
                           pinned)
    Is = 0.5 * (Iz + Iz.T) * np.outer(scales, scales)
    if not np.all(np.isfinite(Is)):
        n = len(scales)
        return Uncertainty(np.full((J.shape[0],) * 2, np.nan), np.full(J.shape[0], np.nan),
                           np.full((J.shape[0],) * 2, np.nan), tuple(coord_names),
                           np.full(n, np.nan), np.zeros(n, bool))
    lam, V = np.linalg.eigh(Is)
    top = max(float(lam.max()), np.finfo(float).tiny)
    det = (lam > rcond * top) & (lam >= (V**2).T @ (1.0 / max_std**2))
    Vd = V[:, det]
    cov_z = (scales[:, None] * Vd / lam[det]) @ (Vd.T * scales[None, :])
    cov = J @ cov_z @ J.T
    bad_coords = np.zeros(len(scales), bool)
    for k in np.flatnonzero(~det):
        v = np.abs(V[:, k])
        bad_coords |= (v >= 0.3) | (v == v.max())
    moved = np.any((J != 0) & bad_coords[None, :], axis=1)
    se = np.sqrt(np.maximum(np.diag(cov), 0.0))
    se[moved] = np.inf
    cov[np.ix_(moved, moved)] = np.nan
    cov[moved, moved] = np.inf
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(se, se)
    corr[moved, :] = np.nan
    corr[:, moved] = np.nan
    names = tuple(n for n, b in zip(coord_names, bad_coords) if b)
    return Uncertainty(cov, se, corr, names, lam, det)


def _with_fixed(Iz, J, scales, coord_names, rcond, max_std, fixed, pinned) -> Uncertainty:
    """:func:`uncertainty` over the free coordinates, NaN for the ``pinned`` quantities."""
    free = ~fixed
    if not np.any(free):
        m = J.shape[0]
        return Uncertainty(np.full((m, m), np.nan), np.full(m, np.nan), np.full((m, m), np.nan),
                           (), np.zeros(0), np.zeros(0, bool))
    names = tuple(n for n, f in zip(coord_names, free) if f)
    u = uncertainty(Iz[np.ix_(free, free)], J[:, free], scales[free], names, rcond,
                    max_std[free])
    pinned = np.zeros(J.shape[0], bool) if pinned is None else np.asarray(pinned, bool)
    cov, se, corr = u.cov.copy(), u.std_errors.copy(), u.correlations.copy()
    cov[pinned, :] = np.nan
    cov[:, pinned] = np.nan
    se[pinned] = np.nan
    corr[pinned, :] = np.nan
    corr[:, pinned] = np.nan
    return u._replace(cov=cov, std_errors=se, correlations=corr)


def hessian_from_gradients(vg, x, scales, rel: float = 1e-4, grads=None, g0=None, many=None):
    """The Hessian (n, n) of the loss at x by differences of its exact (JAX) gradient, column i
    from steps of rel * scales[i] (the coordinate's natural size,
    :func:`vehjax.tune.quantities.coordinates`), symmetrised.

    Central differences (default): steps +-h, 2 n gradient evaluations of the compiled loss,
    no further compilation, truncation error O(rel^2) relative; or, with ``grads(F (2 n, n))
    -> (2 n, n)`` (``CompiledLoss.grads``), the same 2 n points in one call. Forward differences
    when ``g0`` (n,), the gradient at x, is given: ``(g(x + h e_i) - g0) / h``, n evaluations,
    truncation error O(rel) relative, rounding O(1e-14 / rel) (:func:`vehjax.tune.fit` takes
    rel = :data:`FORWARD_REL`). ``many(points) -> [vg(p) for p in points]``
    (``CompiledLoss.many``: side by side) evaluates the difference points where given."""
    n = len(x)
    x = np.asarray(x, dtype=float)
    h = rel * np.asarray(scales, dtype=float)
    E = np.diag(h)
    if grads is not None and g0 is None:
        G = grads(np.concatenate([x + E, x - E]))
    else:
        points = [x + E[i] for i in range(n)] + ([] if g0 is not None else
                                                  [x - E[i] for i in range(n)])
        G = np.stack([r[2] for r in (many(points) if many is not None else map(vg, points))])
        G = np.asarray(G, dtype=float)
    if g0 is not None:
        H = ((G - np.asarray(g0, dtype=float)) / h[:, None]).T
    else:
        H = ((G[:n] - G[n:]) / (2 * h)[:, None]).T
    return 0.5 * (H + H.T)


def difference_hessian(loss, x, scales):
    """The Hessian of the mean loss at x for :func:`vehjax.tune.fit`
    (:func:`hessian_from_gradients`) on its compiled loss: the 2 n central-difference points
    in one call of ``loss.grads`` where the fit has that batched
    program, else forward differences from the gradient at x (n evaluations of the compiled
    loss, side by side: ``CompiledLoss.many``; the one at x is the latest evaluation, not
    repeated) with steps :data:`FORWARD_REL` of each coordinate's scale."""
    if loss.grads is not None:
        return hessian_from_gradients(loss.vg, x, scales, grads=loss.grads)
    return hessian_from_gradients(loss.vg, x, scales, rel=FORWARD_REL, g0=loss.vg(x)[2],
                                  many=loss.many)
