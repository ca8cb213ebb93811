"""The Kalman update and the Jacobian (EKF) predict/measure: the linear-algebra half of the one
Gaussian core that every Gaussian filter uses (the sigma-point half is in
:mod:`vehjax.filters.sigma`).

Missing measurements: components of ``y`` that are NaN or +-inf are not observed. With the
observation mask M (diagonal 0/1) the update uses the innovation M e, the covariance
M S M + (I - M) and the cross-covariance C M: exactly the Kalman update on the observed subset,
in fixed shapes, and with finite gradients (the masked entries never enter an arithmetic
operation whose derivative could be NaN). ``loglik``, ``nis`` and ``n_obs`` count only the
observed components.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from ._linalg import LOG_2PI, cholesky, logdet_from_chol, solve_lower, sym


class UpdateResult(NamedTuple):
    """Result of :func:`masked_update`.

    Attributes:
        x: updated mean, (nx,).
        P: updated covariance, (nx, nx).
        loglik: log N(e; 0, S) over the observed components, scalar.
        nis: e^T S^-1 e over the observed components, scalar.
        n_obs: number of observed components, int32 scalar.
        innovation: y - y^ with zeros on the missing components, (ny,).
    """

    x: jnp.ndarray
    P: jnp.ndarray
    loglik: jnp.ndarray
    nis: jnp.ndarray
    n_obs: jnp.ndarray
    innovation: jnp.ndarray


class Measurement(NamedTuple):
    """Predicted measurement moments: ``y_hat`` (ny,), ``S`` (ny, ny) (noise included when it was
    given), ``C`` = Cov[x, y] (nx, ny), and ``H`` (ny, nx) for the Jacobian form (None for
    sigma points)."""

    y_hat: jnp.ndarray
    S: jnp.ndarray
    C: jnp.ndarray
    H: jnp.ndarray | None = None


def observed(y):
    """(mask, mask as y's float dtype, y with the missing components set to 0)."""
    m = jnp.isfinite(y)
    return m, m.astype(y.dtype), jnp.where(m, y, 0)


def gaussian_loglik(w, L, n_obs):
    """log N(e; 0, L L^T) from the whitened innovation ``w = L^-1 e`` over ``n_obs`` observed
    components (the masked ones contribute 0 to ``w @ w`` and to the log-determinant)."""
    nis = w @ w
    return -0.5 * (nis + logdet_from_chol(L) + n_obs.astype(w.dtype) * LOG_2PI), nis


def masked_update(x_pred, P_pred, y, y_hat, S, C, joseph=None) -> UpdateResult:
    """Kalman update with the NaN components of ``y`` treated as missing (module docstring).

    Args:
        x_pred: predicted mean, (nx,).
        P_pred: predicted covariance, (nx, nx).
        y: measurement, (ny,), NaN where missing.
        y_hat: predicted measurement, (ny,).
        S: innovation covariance including the measurement noise, (ny, ny).
        C: cross-covariance of state and measurement, (nx, ny).
        joseph: ``(H, N)`` for the Joseph-form covariance (I - K H) P- (I - K H)^T + K N K^T,
            H (ny, nx) the measurement Jacobian and N the noise part of S; None for the
            symmetric P- - K S K^T.

    Everything goes through the Cholesky factor of the masked S.
    """
    m, mf, y0 = observed(y)
    e = jnp.where(m, y0 - y_hat, 0)
    Sm = S * (mf[:, None] * mf[None, :]) + jnp.diag(1 - mf)
    Ls = cholesky(Sm)  # symmetrises
    w = solve_lower(Ls, e)
    W = solve_lower(Ls, (C * mf[None, :]).T)  # Ls^-1 C^T, so K = W^T Ls^-1
    x = x_pred + W.T @ w
    if joseph is None:
        P = sym(P_pred - W.T @ W)
    else:
        H, N = joseph
        K = jax.scipy.linalg.solve_triangular(Ls, W, lower=True, trans=1).T  # K^T = Ls^-T W
        A = jnp.eye(P_pred.shape[0], dtype=P_pred.dtype) - K @ H
        P = sym(A @ P_pred @ A.T + K @ N @ K.T)
    n_obs = jnp.sum(m).astype(jnp.int32)
    loglik, nis = gaussian_loglik(w, Ls, n_obs)
    return UpdateResult(x, P, loglik, nis, n_obs, e)


def linearized_predict(x, P, f, Q):
    """EKF prediction: ``f(x) -> x'`` linearised at x by ``jax.jacfwd``.

    Returns (x', F P F^T + Q, F).
    """
    F = jax.jacfwd(f)(x)
    return f(x), sym(F @ P @ F.T + Q), F


def linearized_measure(x, P, h, R) -> Measurement:
    """EKF measurement moments at the predicted (x, P): y^ = h(x), S = H P H^T + R, C = P H^T."""
    H = jax.jacfwd(h)(x)
    C = P @ H.T
    return Measurement(h(x), sym(H @ C + R), C, H)
