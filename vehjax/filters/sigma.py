"""Sigma-point and cubature rules shared by every deterministic-sampling filter.

A rule is a set of ``m`` unit points ``xi_i`` (rows of an (m, n) array) with mean weights ``wm``
and covariance weights ``wc``. For a Gaussian N(mean, L L^T) the sigma points are
``X_i = mean + L xi_i`` (:func:`sigma_points`); propagating them through a function and taking
weighted moments (:func:`unscented_transform`, :func:`cross_covariance`) approximates the moments
of the transformed variable. Both rules here reproduce the input mean and covariance exactly:
``sum wm_i xi_i = 0`` and ``sum wc_i xi_i xi_i^T = I``.

* :func:`unscented_rule` - the scaled unscented transform, Dutta et al. 2019 eq. 14-19
  (Julier 2002, van der Merwe 2004): 2n + 1 points.
* :func:`cubature_rule` - the third-degree spherical-radial cubature rule, 2n equally weighted
  points at ``+-sqrt(n) e_j`` (Arasaratnam & Haykin 2009).

Rules are plain numpy constants built once per filter and closed over; they are never traced
(the square-root transform needs the signs of the weights at trace time).

Square-root helpers: :func:`triangularize` (a lower Cholesky factor of ``A A^T`` by QR),
:func:`chol_update` (rank-1 update or downdate), :func:`sqrt_unscented_transform`.

Small dense algebra: :func:`cholesky` and :func:`solve_lower` are the textbook Cholesky and
forward substitution, written out entry by entry for n <= 8 (vehicle state and output
dimensions). Under ``vmap`` over runs every entry is one vector across runs, so XLA fuses the
whole factorisation into a few vectorised loops instead of one LAPACK call per run and matrix;
larger n use ``jnp.linalg`` / ``jax.scipy.linalg``. Same algorithm, rounding-level differences.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.linalg import solve_triangular


class SigmaRule(NamedTuple):
    """A deterministic sampling rule in ``n`` dimensions.

    Attributes:
        points: unit points, (m, n) numpy array; sigma point i is ``mean + L @ points[i]``.
        wm: mean weights, (m,) numpy array, summing to 1.
        wc: covariance weights, (m,) numpy array (the unscented wc[0] may be negative).
        kind: "unscented" or "cubature".
    """

    points: np.ndarray
    wm: np.ndarray
    wc: np.ndarray
    kind: str

    @property
    def n(self) -> int:
        return self.points.shape[1]

    @property
    def m(self) -> int:
        return self.points.shape[0]


def _check_dim(n) -> int:
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"n: expected a positive integer dimension, got {n!r}")
    return int(n)


def unscented_rule(n: int, alpha: float = 1.0, beta: float = 2.0, kappa: float = 0.0) -> SigmaRule:
    """The scaled unscented rule (Dutta et al. 2019 eq. 14-19): 2n + 1 points.

    ``lambda = alpha^2 (n + kappa) - n``; points ``0`` and ``+-sqrt(n + lambda) e_j``; weights
    ``wm0 = lambda / (n + lambda)``, ``wc0 = wm0 + 1 - alpha^2 + beta``,
    ``wm_i = wc_i = 1 / (2 (n + lambda))``. Same points and weights as filterpy's
    ``MerweScaledSigmaPoints(n, alpha, beta, kappa)``.

    Args:
        n: dimension.
        alpha: spread of the points, > 0. alpha = 1, kappa = 0 puts them at +-sqrt(n) standard
            deviations with non-negative weights (wm0 = 0, wc0 = beta).
        beta: prior-knowledge term; 2 is optimal for a Gaussian.
        kappa: secondary scaling; n + kappa must be > 0.
    """
    n = _check_dim(n)
    for name, v in (("alpha", alpha), ("beta", beta), ("kappa", kappa)):
        if not np.isfinite(np.asarray(v, dtype=float)).all() or np.ndim(v) != 0:
            raise ValueError(f"{name}: expected a finite number, got {v!r}")
    alpha, beta, kappa = float(alpha), float(beta), float(kappa)
    if alpha <= 0.0:
        raise ValueError(f"alpha: expected alpha > 0, got {alpha}")
    if n + kappa <= 0.0:
        raise ValueError(f"kappa: expected n + kappa > 0 (n = {n}), got kappa = {kappa}")
    lam = alpha**2 * (n + kappa) - n
    c = n + lam
    eye = np.eye(n)
    points = np.concatenate([np.zeros((1, n)), np.sqrt(c) * eye, -np.sqrt(c) * eye])
    wm = np.full(2 * n + 1, 0.5 / c)
    wc = wm.copy()
    wm[0] = lam / c
    wc[0] = lam / c + (1.0 - alpha**2 + beta)
    return SigmaRule(points, wm, wc, "unscented")


def cubature_rule(n: int) -> SigmaRule:
    """Third-degree spherical-radial cubature rule: 2n points ``+-sqrt(n) e_j``, weights 1/(2n)."""
    n = _check_dim(n)
    eye = np.eye(n)
    points = np.sqrt(n) * np.concatenate([eye, -eye])
    w = np.full(2 * n, 0.5 / n)
    return SigmaRule(points, w, w.copy(), "cubature")


# Largest dimension for which cholesky/solve_lower are unrolled (n^3 / 6 scalar ops at trace).
_UNROLL_MAX = 8


def cholesky(A):
    """Lower Cholesky factor of symmetric positive-definite ``A`` (..., n, n).

    Like ``jnp.linalg.cholesky``: ``A`` is symmetrised first, and a matrix that is not
    positive definite (or not finite) gives a factor of NaNs. For n <= 8 the factorisation is
    unrolled into elementwise operations over the leading (batch) axes.
    """
    n = A.shape[-1]
    if A.shape[-2] != n:
        raise ValueError(f"A: expected a square matrix (..., n, n), got shape {A.shape}")
    if n == 0 or n > _UNROLL_MAX:
        return jnp.linalg.cholesky(A)

    def a(i, j):
        return A[..., i, i] if i == j else 0.5 * (A[..., i, j] + A[..., j, i])

    L = [[None] * n for _ in range(n)]
    ok = None
    for j in range(n):
        d = a(j, j)
        for k in range(j):
            d = d - L[j][k] * L[j][k]
        pos = d > 0  # False for NaN too
        ok = pos if ok is None else ok & pos
        L[j][j] = jnp.sqrt(jnp.where(pos, d, 1))
        for i in range(j + 1, n):
            t = a(i, j)
            for k in range(j):
                t = t - L[i][k] * L[j][k]
            L[i][j] = t / L[j][j]
    zero = jnp.zeros_like(L[0][0])
    rows = [jnp.stack([L[i][j] if j <= i else zero for j in range(n)], axis=-1) for i in range(n)]
    out = jnp.stack(rows, axis=-2)
    finite = jnp.all(jnp.isfinite(out), axis=(-2, -1))
    return jnp.where((ok & finite)[..., None, None], out, jnp.nan)


def solve_lower(L, b):
    """``L^-1 b`` for lower-triangular ``L`` (..., n, n) and ``b`` (..., n) or (..., n, k).

    Forward substitution, unrolled over rows for n <= 8 (the upper triangle of L is not read).
    """
    n = L.shape[-1]
    vec = b.ndim == L.ndim - 1
    if L.shape[-2] != n or b.shape[-1 if vec else -2] != n:
        raise ValueError(f"b: expected shape (..., {n}) or (..., {n}, k), got shape {b.shape}")
    if n == 0 or n > _UNROLL_MAX:
        return solve_triangular(L, b[..., None] if vec else b, lower=True)[..., 0] if vec else (
            solve_triangular(L, b, lower=True)
        )
    B = b[..., None] if vec else b
    xs = []
    for i in range(n):
        t = B[..., i, :]
        for k in range(i):
            t = t - L[..., i, k, None] * xs[k]
        xs.append(t / L[..., i, i, None])
    X = jnp.stack(xs, axis=-2)
    return X[..., 0] if vec else X


def sigma_points(mean, chol, rule: SigmaRule):
    """Sigma points of N(mean, chol chol^T): (m, n), row i = ``mean + chol @ rule.points[i]``."""
    xi = jnp.asarray(rule.points, dtype=mean.dtype)
    return mean[None, :] + xi @ chol.T


def unscented_transform(Y, rule: SigmaRule, noise_cov=None):
    """Weighted mean (d,) and covariance (d, d) of transformed points ``Y`` (m, d).

    ``noise_cov`` (d, d), when given, is added to the covariance (additive noise).
    """
    wm = jnp.asarray(rule.wm, dtype=Y.dtype)
    wc = jnp.asarray(rule.wc, dtype=Y.dtype)
    mean = wm @ Y
    dev = Y - mean[None, :]
    cov = (dev * wc[:, None]).T @ dev
    if noise_cov is not None:
        cov = cov + noise_cov
    return mean, 0.5 * (cov + cov.T)


def cross_covariance(X, x_mean, Y, y_mean, rule: SigmaRule):
    """Weighted cross-covariance (dx, dy) of points ``X`` (m, dx) and ``Y`` (m, dy)."""
    wc = jnp.asarray(rule.wc, dtype=X.dtype)
    return ((X - x_mean[None, :]) * wc[:, None]).T @ (Y - y_mean[None, :])


def triangularize(A):
    """Lower-triangular L with positive diagonal and ``L L^T = A A^T``, for A (n, k), by QR.

    With positive diagonal L is the Cholesky factor of ``A A^T`` (when that is non-singular).
    """
    n, k = A.shape
    if k < n:
        A = jnp.concatenate([A, jnp.zeros((n, n - k), A.dtype)], axis=1)
    L = jnp.linalg.qr(A.T, mode="r").T
    s = jnp.sign(jnp.diagonal(L))
    return L * jnp.where(s == 0, 1, s).astype(A.dtype)[None, :]


def chol_update(L, v, downdate: bool = False):
    """Cholesky factor of ``L L^T + v v^T`` (or ``- v v^T`` when ``downdate``), L lower (n, n).

    The classic O(n^2) rotation sweep; a downdate that would leave the matrix indefinite returns
    NaN entries.
    """
    n = L.shape[0]
    sgn = -1.0 if downdate else 1.0
    idx = jnp.arange(n)

    def body(k, carry):
        L, x = carry
        lkk = L[k, k]
        xk = x[k]
        r = jnp.sqrt(lkk * lkk + sgn * xk * xk)
        c = r / lkk
        s = xk / lkk
        below = idx > k
        col = jnp.where(below, (L[:, k] + sgn * s * x) / c, L[:, k]).at[k].set(r)
        x = jnp.where(below, c * x - s * col, x)
        return L.at[:, k].set(col), x

    L, _ = jax.lax.fori_loop(0, n, body, (L, jnp.asarray(v).astype(L.dtype)))
    return L


def weighted_sqrt_factor(dev, rule: SigmaRule, extra=None):
    """Lower factor L with ``L L^T = sum_i wc_i dev_i dev_i^T + extra extra^T``.

    ``dev`` (m, d) are the deviations of the points from their mean; ``extra`` (d, k) an
    optional square root of an additive term (e.g. the Cholesky factor of Q). Points with
    positive weight enter one QR; those with negative weight (the unscented centre point when
    lambda / (n + lambda) + 1 - alpha^2 + beta < 0) are removed by rank-1 downdates.
    """
    wc = np.asarray(rule.wc)
    pos = np.flatnonzero(wc > 0)
    neg = np.flatnonzero(wc < 0)
    cols = [(dev[pos] * jnp.asarray(np.sqrt(wc[pos]), dev.dtype)[:, None]).T]
    if extra is not None:
        cols.append(extra)
    L = triangularize(jnp.concatenate(cols, axis=1))
    for i in neg:
        L = chol_update(L, float(np.sqrt(-wc[i])) * dev[i], downdate=True)
    return L


def sqrt_unscented_transform(Y, rule: SigmaRule, noise_chol=None):
    """Like :func:`unscented_transform` but returns the lower Cholesky factor of the covariance.

    ``noise_chol`` (d, d) is a square root of the additive noise covariance.
    """
    wm = jnp.asarray(rule.wm, dtype=Y.dtype)
    mean = wm @ Y
    return mean, weighted_sqrt_factor(Y - mean[None, :], rule, noise_chol)
