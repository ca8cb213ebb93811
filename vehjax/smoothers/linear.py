"""Gaussian smoothing mathematics: the RTS backward step (plain and square-root), the affine
(linearised) state-space model, statistical linear regression, and the sequential Kalman filter
and RTS smoother on an affine model.

Time convention (:mod:`vehjax.filtering`): x_0 ~ N(m0, P0) is the state before the first step;
step t = 1..T predicts with u_t, then updates with y_t. The affine model of this module covers
t = 0..T (leading axis T + 1) so that the prior is one more step of the same recursion: a
transition with F_0 = 0, c_0 = m0, Q_0 = P0 and no measurement. Every array below carries that
leading axis::

    x_t = F_t x_{t-1} + c_t + q_t,   q_t ~ N(0, Q_t)
    y_t = H_t x_t + d_t + r_t,       r_t ~ N(0, R_t)          (NaN components of y_t missing)

The RTS step (Rauch, Tung & Striebel 1965; Särkkä 2008 for the sigma-point form, where the
cross-covariance C comes from the points instead of P F^T)::

    G = C P-^-1,  m^s_t = m_t + G (m^s_{t+1} - m-_{t+1}),  P^s_t = P_t + G (P^s_{t+1} - P-_{t+1}) G^T
    Cov(x_t, x_{t+1} | y_1:T) = G P^s_{t+1}

with (m-_{t+1}, P-_{t+1}, C = Cov(x_t, x_{t+1} | y_1:t)) the prediction from the filtered
N(m_t, P_t). The square-root form (:func:`sqrt_rts_step`) works on the lower factor of the joint
covariance of (x_{t+1}, x_t) and never forms a covariance.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.scipy.linalg import solve_triangular

from ..lib.linalg import cholesky, solve_lower, sym
from ..filters.kalman import masked_update
from ..filters.sigma import triangularize

__all__ = ["Affine", "rts_step", "rts_gain", "rts_apply", "sqrt_rts_step", "sqrt_rts_gain",
           "sqrt_rts_apply", "slr", "affine_predict", "kalman_filter",
           "rts_smoother", "chol_solve"]


class Affine(NamedTuple):
    """An affine Gaussian state-space model over t = 0..T (module docstring); every field has a
    leading axis T + 1.

    Attributes:
        F: (T+1, n, n) transition matrices (F[0] = 0: the prior).
        c: (T+1, n) transition offsets (c[0] = m0).
        Q: (T+1, n, n) process noise covariances (Q[0] = P0).
        H: (T+1, ny, n) measurement matrices.
        d: (T+1, ny) measurement offsets.
        R: (T+1, ny, ny) measurement noise covariances, positive definite.
    """

    F: jnp.ndarray
    c: jnp.ndarray
    Q: jnp.ndarray
    H: jnp.ndarray
    d: jnp.ndarray
    R: jnp.ndarray


def solve_upper_t(L, B):
    """``L^-T B`` for lower-triangular L (n, n) and B (n,) or (n, k): back substitution, as the
    forward substitution of :func:`vehjax.lib.linalg.solve_lower` on the reversed system
    (J L^T J is lower triangular for the reversal permutation J); unrolled for n <= 8."""
    Lr = jnp.swapaxes(L, -1, -2)[..., ::-1, ::-1]
    vec = B.ndim == L.ndim - 1
    Br = B[..., ::-1] if vec else B[..., ::-1, :]
    X = solve_lower(Lr, Br)
    return X[..., ::-1] if vec else X[..., ::-1, :]


def chol_solve(P, B):
    """``P^-1 B`` for symmetric positive-definite P (n, n) and B (n, k), by Cholesky and two
    triangular solves (unrolled for n <= 8: on XLA:CPU a batch of 3 x 3 LAPACK solves costs
    about ten times the unrolled arithmetic, measured on 10^4 gains of the 3-DOF model)."""
    L = cholesky(P)
    return solve_upper_t(L, solve_lower(L, B))


def rts_step(m, P, m_pred, P_pred, C, ms_next, Ps_next):
    """One RTS backward step (module docstring).

    Args:
        m, P: filtered mean (n,) and covariance (n, n) at t.
        m_pred, P_pred: the prediction of x_{t+1} from them, (n,), (n, n).
        C: Cov(x_t, x_{t+1} | y_1:t), (n, n).
        ms_next, Ps_next: smoothed mean and covariance at t + 1.

    Returns:
        (m^s_t (n,), P^s_t (n, n), Cov(x_t, x_{t+1} | y_1:T) (n, n)).
    """
    return rts_apply(rts_gain(P_pred, C), m, P, m_pred, P_pred, ms_next, Ps_next)


def rts_gain(P_pred, C):
    """The RTS gain G = C P-^-1, (n, n), by Cholesky of the predicted covariance P- (n, n);
    C = Cov(x_t, x_{t+1} | y_1:t) (n, n). It depends on the filter's moments only, so a
    backward pass computes all gains before its recursion (:func:`rts_apply`)."""
    return chol_solve(P_pred, C.T).T


def rts_apply(G, m, P, m_pred, P_pred, ms_next, Ps_next):
    """The recursion of one RTS step (:func:`rts_step`) with its gain G (n, n) given
    (:func:`rts_gain`): (m^s_t (n,), P^s_t (n, n), Cov(x_t, x_{t+1} | y_1:T) (n, n))."""
    cross = G @ Ps_next
    return m + G @ (ms_next - m_pred), sym(P + G @ (Ps_next - P_pred) @ G.T), cross


def sqrt_rts_step(m, m_pred, L11, L21, L22, ms_next, Ls_next):
    """Square-root RTS step: factors only.

    Args:
        m: filtered mean at t, (n,).
        m_pred: predicted mean at t + 1, (n,).
        L11, L21, L22: the lower factor [[L11, 0], [L21, L22]] of the joint covariance of
            (x_{t+1}, x_t) given y_1:t (:func:`vehjax.filters.sigma.sqrt_moments_joint`).
        ms_next, Ls_next: smoothed mean at t + 1 and the lower factor of its covariance.

    Returns:
        (m^s_t, L^s_t lower factor of P^s_t, Cov(x_t, x_{t+1} | y_1:T)): with G = L21 L11^-1,
        P^s_t = L22 L22^T + G L^s_{t+1} (G L^s_{t+1})^T, one QR of [L22, G L^s_{t+1}].
    """
    return sqrt_rts_apply(sqrt_rts_gain(L11, L21), m, m_pred, L22, ms_next, Ls_next)


def sqrt_rts_gain(L11, L21):
    """The RTS gain G = L21 L11^-1 = C P-^-1 (n, n) from the joint factor's blocks
    (:func:`sqrt_rts_step`), by one triangular solve."""
    return solve_triangular(L11, L21.T, lower=True, trans=1).T


def sqrt_rts_apply(G, m, m_pred, L22, ms_next, Ls_next):
    """The recursion of one square-root RTS step (:func:`sqrt_rts_step`) with its gain G given
    (:func:`sqrt_rts_gain`): (m^s_t, L^s_t, Cov(x_t, x_{t+1} | y_1:T))."""
    GL = G @ Ls_next
    Ls = triangularize(jnp.concatenate([L22, GL], axis=1))
    return m + G @ (ms_next - m_pred), Ls, GL @ Ls_next.T


def slr(m, P, y_mean, P_yy, C):
    """Statistical linear regression of y on x ~ N(m, P) from the moments of y: y ~ A x + b + e,
    e ~ N(0, Omega), with the same mean, covariance and cross-covariance.

    Args:
        m, P: (n,), (n, n) the Gaussian linearised about.
        y_mean, P_yy: (d,), (d, d) mean and covariance of y (noise included).
        C: Cov(x, y), (n, d).

    Returns:
        (A (d, n) = C^T P^-1, b (d,) = y_mean - A m, Omega (d, d) = P_yy - A P A^T).
    """
    A = chol_solve(P, C).T
    return A, y_mean - A @ m, sym(P_yy - A @ P @ A.T)


def affine_predict(m, P, F, c, Q):
    """(F m + c, F P F^T + Q, P F^T): the prediction and the cross-covariance Cov(x_t, x_{t+1})."""
    C = P @ F.T
    return F @ m + c, sym(F @ C + Q), C


def kalman_filter(model: Affine, ys):
    """Sequential Kalman filter on an affine model (module docstring), NaN components missing.

    Args:
        model: :class:`Affine` over t = 0..T.
        ys: (T+1, ny) measurements, NaN where missing (row 0 all NaN: the prior).

    Returns:
        (means (T+1, n), covariances (T+1, n, n), loglik (T+1,) of the observed components).
    """
    n = model.F.shape[-1]
    dt = model.F.dtype

    def body(carry, inp):
        m, P = carry
        F, c, Q, H, d, R, y = inp
        mp, Pp, _ = affine_predict(m, P, F, c, Q)
        Cy = Pp @ H.T
        r = masked_update(mp, Pp, y, H @ mp + d, sym(H @ Cy + R), Cy)
        return (r.x, r.P), (r.x, r.P, r.loglik)

    carry0 = (jnp.zeros((n,), dt), jnp.eye(n, dtype=dt))
    _, (ms, Ps, ll) = jax.lax.scan(body, carry0, (*model, ys))
    return ms, Ps, ll


def rts_smoother(model: Affine, ms, Ps):
    """Sequential RTS smoother on an affine model from the filtered moments of
    :func:`kalman_filter`: smoothed means (T+1, n), covariances (T+1, n, n) and the lag-one
    cross-covariances Cov(x_t, x_{t+1} | y) (T, n, n)."""

    def body(carry, inp):
        ms_next, Ps_next = carry
        m, P, F, c, Q = inp
        mp, Pp, C = affine_predict(m, P, F, c, Q)
        m_s, P_s, cross = rts_step(m, P, mp, Pp, C, ms_next, Ps_next)
        return (m_s, P_s), (m_s, P_s, cross)

    xs = (ms[:-1], Ps[:-1], model.F[1:], model.c[1:], model.Q[1:])
    _, (m_s, P_s, cross) = jax.lax.scan(body, (ms[-1], Ps[-1]), xs, reverse=True)
    return (jnp.concatenate([m_s, ms[-1:]]), jnp.concatenate([P_s, Ps[-1:]]), cross)
