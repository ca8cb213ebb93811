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

The one sigma-point predict/update every deterministic-sampling filter runs (UKF, CKF, ACKF,
dual and joint UKF, Liu-West's state UKF)::

    predict(rule, x, P, f, Q)      -> x-, P-           points of (x, P) through f, moments, + Q
    measure(rule, x-, P-, h, R)    -> y^, S, C          fresh points of (x-, P-) through h
    update(rule, x-, P-, h, y, R)  -> UpdateResult      measure, then the masked Kalman update

and their square-root forms :func:`sqrt_predict`, :func:`sqrt_update`. ``f`` and ``h`` are
functions of one point (closures over the input and the parameters); they are vmapped here.
The small-matrix kernels (:func:`cholesky`, :func:`solve_lower`) come from
:mod:`vehjax.lib.linalg`.

The same predict and measure entry by entry (:func:`points_entries`, :func:`moments_entries`,
:func:`step_moments_entries`): the moments' algebra unrolled over the entries of nested
lists, each entry a scalar (one run, :func:`vehjax.filters.ukf` on a small model) or an (R,)
array (all runs at once, runs last: :func:`vehjax.filters.runs_last.sigma_step`); the two forms
differ only in how the model is evaluated at the points.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import validation
from ..lib.entrywise import chol_sym, wsum
from ..lib.linalg import cholesky, solve_lower
from .kalman import Measurement, UpdateResult, gaussian_loglik, masked_update, observed

__all__ = [
    "SigmaRule", "unscented_rule", "cubature_rule", "sigma_points", "unscented_transform",
    "cross_covariance", "triangularize", "chol_update", "weighted_sqrt_factor",
    "sqrt_unscented_transform", "predict", "measure", "update", "sqrt_predict", "sqrt_update",
    "moments_cross", "sqrt_moments_joint", "points_entries", "moments_entries",
    "StepMoments", "step_moments_entries",
    "cholesky", "solve_lower",
]


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


@dataclasses.dataclass(frozen=True)
class SigmaPoints:
    """The scaled unscented rule's parameters (dynamax's ``UKFHyperParams``), the option
    ``points`` of :func:`~vehjax.filters.ukf`, the dual and joint UKFs and
    :func:`~vehjax.filters.liu_west_ukf`; :func:`unscented_rule` says what each does.

    Attributes:
        alpha: spread of the points, > 0. The default 1 with kappa 0 puts them at +-sqrt(n)
            standard deviations with non-negative weights, which keeps P positive definite on
            strongly nonlinear vehicle models; small alpha (1e-3) gives a large negative centre
            weight.
        beta: prior-knowledge term; 2 is optimal for a Gaussian.
        kappa: secondary scaling; n + kappa must be > 0 (checked by the builder, which knows n).
    """

    alpha: float = 1.0
    beta: float = 2.0
    kappa: float = 0.0

    def __post_init__(self):
        for name in ("alpha", "beta", "kappa"):
            v = getattr(self, name)
            if np.ndim(v) != 0:
                raise ValueError(f"{name}: expected a finite number, got {v!r}")
            validation.number(name, v)  # finite, real (text, complex: ValueError naming it)
        if float(self.alpha) <= 0.0:
            raise ValueError(f"alpha: expected alpha > 0, got {float(self.alpha)}")

    def rule(self, n: int) -> SigmaRule:
        """:func:`unscented_rule` in ``n`` dimensions with these parameters."""
        return unscented_rule(n, self.alpha, self.beta, self.kappa)


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
        if np.ndim(v) != 0:
            raise ValueError(f"{name}: expected a finite number, got {v!r}")
        validation.number(name, v)  # finite, real (text, complex: ValueError naming it)
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


# --------------------------------------------------------------------------------------------
# the shared predict / update


def _through(fn, X):
    """``fn`` of one point applied to every row of X (m, n), output in X's dtype."""
    return jax.vmap(lambda x: jnp.asarray(fn(x)).astype(X.dtype))(X)


def predict(rule: SigmaRule, x, P, f, Q=None):
    """Sigma-point prediction: points of N(x, P) through ``f`` (one point -> (n',)), their
    weighted mean and covariance, plus ``Q`` when given. Returns (x-, P-)."""
    Xf = _through(f, sigma_points(x, cholesky(P), rule))
    return unscented_transform(Xf, rule, Q)


def measure(rule: SigmaRule, x, P, h, R=None) -> Measurement:
    """Measurement moments from fresh points of N(x, P) through ``h``: y^, S (+ R when given)
    and the cross-covariance C."""
    X = sigma_points(x, cholesky(P), rule)
    Z = _through(h, X)
    y_hat, S = unscented_transform(Z, rule, R)
    return Measurement(y_hat, S, cross_covariance(X, x, Z, y_hat, rule))


def update(rule: SigmaRule, x, P, h, y, R) -> UpdateResult:
    """:func:`measure` then the masked Kalman update (:func:`vehjax.filters.kalman.masked_update`)
    of (x, P) with ``y`` (NaN components missing)."""
    m = measure(rule, x, P, h, R)
    return masked_update(x, P, y, m.y_hat, m.S, m.C)


def sqrt_predict(rule: SigmaRule, x, L, f, LQ):
    """Square-root :func:`predict`: (x-, L-) with L- L-^T = P-, from the factor L of P and a
    square root LQ of Q."""
    Xf = _through(f, sigma_points(x, L, rule))
    return sqrt_unscented_transform(Xf, rule, LQ)


def moments_cross(rule: SigmaRule, X, x, Y, Q=None):
    """Moments of the images ``Y`` (m, d) of sigma points ``X`` (m, n) of N(x, .): the mean
    (d,), the covariance (d, d) (+ ``Q`` when given) and the cross-covariance Cov[x, y] (n, d).
    What a smoother needs from a prediction: ``C = Cov(x_t, x_{t+1})``."""
    y_mean, cov = unscented_transform(Y, rule, Q)
    return y_mean, cov, cross_covariance(X, x, Y, y_mean, rule)


def sqrt_moments_joint(rule: SigmaRule, X, x, Y, LQ=None):
    """Square-root :func:`moments_cross`: one QR of the joint deviations [Y - y^; X - x].

    Returns ``(y^ (d,), L11 (d, d), L21 (n, d), L22 (n, n))``, the lower factor of the joint
    covariance [[P_y, C^T], [C, P_x]] (``LQ`` (d, k) a square root of the noise added to P_y):
    L11 L11^T = P_y, L21 = C L11^-T, L22 L22^T = P_x - C P_y^-1 C^T (the covariance of x given
    y, what the square-root RTS smoother needs)."""
    d, n = Y.shape[1], X.shape[1]
    y_mean = jnp.asarray(rule.wm, Y.dtype) @ Y
    dev = jnp.concatenate([Y - y_mean[None, :], X - x[None, :]], axis=1)
    extra = None if LQ is None else jnp.concatenate([LQ, jnp.zeros((n, LQ.shape[1]), Y.dtype)])
    Lj = weighted_sqrt_factor(dev, rule, extra)
    return y_mean, Lj[:d, :d], Lj[d:, :d], Lj[d:, d:]


def sqrt_update(rule: SigmaRule, x, L, h, y, LR):
    """Square-root :func:`update`: one QR of the joint (measurement, state) deviations.

    The lower factor of the joint covariance [[S, C^T], [C, P-]] is [[L11, 0], [L21, L22]]:
    L11 is the factor of S, the gain is L21 L11^-1 and L22 the factor of the updated
    covariance. Missing components are masked as in the full form. Returns
    (x, L, loglik, nis, n_obs).
    """
    dtype = x.dtype
    X = sigma_points(x, L, rule)
    Z = _through(h, X)
    y_hat = jnp.asarray(rule.wm, dtype) @ Z
    ny, nx = y.shape[0], x.shape[0]
    m, mf, y0 = observed(y)
    e = jnp.where(m, y0 - y_hat, 0)
    dev = jnp.concatenate([(Z - y_hat[None, :]) * mf[None, :], X - x[None, :]], axis=1)
    noise = jnp.concatenate(
        [
            jnp.concatenate([LR * mf[:, None], jnp.diag(1 - mf)], axis=1),
            jnp.zeros((nx, 2 * ny), dtype),
        ]
    )
    Lj = weighted_sqrt_factor(dev, rule, noise)
    L11, L21, L22 = Lj[:ny, :ny], Lj[ny:, :ny], Lj[ny:, ny:]
    w = solve_lower(L11, e)
    n_obs = jnp.sum(m).astype(jnp.int32)
    loglik, nis = gaussian_loglik(w, L11, n_obs)
    return x + L21 @ w, L22, loglik, nis, n_obs


# --------------------------------------------------------------------------------------------
# entry by entry (module docstring)


def points_entries(x, L, rule: SigmaRule) -> list:
    """Sigma points ``x + L xi_k`` entry by entry: x a list (n,), L nested lists (n, n), lower
    triangular; a list over the m points of lists over the n components."""
    pts = []
    for xi in rule.points:
        point = []
        for i in range(len(x)):
            off = wsum(xi[: i + 1], L[i][: i + 1])  # L is lower triangular
            point.append(x[i] if off is None else x[i] + off)
        pts.append(point)
    return pts


def moments_entries(Y, rule: SigmaRule, noise) -> tuple:
    """Weighted mean (list (d,)) and covariance (nested lists (d, d), exactly symmetric) of the
    points ``Y`` (list over m points of lists over d components), plus ``noise`` (nested lists
    (d, d)), and the deviations from the mean (list over points of lists)."""
    d = len(Y[0])
    mean = [wsum(rule.wm, [y[i] for y in Y]) for i in range(d)]
    dev = [[y[i] - mean[i] for i in range(d)] for y in Y]
    cov = [[None] * d for _ in range(d)]
    for i in range(d):
        for j in range(i + 1):
            c = wsum(rule.wc, [e[i] * e[j] for e in dev])
            cov[i][j] = cov[j][i] = c + noise[i][j]
    return mean, cov, dev


class StepMoments(NamedTuple):
    """What one sigma-point step's moments are (:func:`step_moments_entries`), nested lists:
    X the points of N(x, P), dF their images' deviations from x- (for the smoother's
    Cov(x_t-1, x_t)), xp, Pp the prediction, yh, S, C the measurement's moments."""

    X: list
    dF: list
    xp: list
    Pp: list
    yh: list
    S: list
    C: list


def step_moments_entries(x, P, image_f, image_h, Q, R, rule: SigmaRule) -> StepMoments:
    """:func:`predict` then :func:`measure` entry by entry: points of N(x, P) through
    ``image_f``, their moments + Q, fresh points of the prediction through ``image_h``, their
    moments + R and the cross-covariance. x a list (n,), P, Q, R nested lists; ``image_f``,
    ``image_h`` map a list of points (lists of entries) to the list of their images."""
    X = points_entries(x, chol_sym(P), rule)
    xp, Pp, dF = moments_entries(image_f(X), rule, Q)
    pts = points_entries(xp, chol_sym(Pp), rule)
    yh, S, dz = moments_entries(image_h(pts), rule, R)
    dx = [[p[i] - xp[i] for i in range(len(xp))] for p in pts]
    C = [[wsum(rule.wc, [a[i] * b[j] for a, b in zip(dx, dz)]) for j in range(len(yh))]
         for i in range(len(xp))]
    return StepMoments(X, dF, xp, Pp, yh, S, C)
