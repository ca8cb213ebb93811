"""Parallel-in-time Kalman filter and RTS smoother (Särkkä & García-Fernández 2021): the
filtering and smoothing recursions of an affine model written as associative operators and run
with ``jax.lax.associative_scan``, O(log T) span instead of O(T).

The model is :class:`vehjax.smoothers.linear.Affine` over t = 0..T (the prior as the step with
F_0 = 0, c_0 = m0, Q_0 = P0, so that every element has the one general form below). Missing
measurement components (NaN) are masked as in :mod:`vehjax.filters.kalman`: their rows of H and
d are zeroed, their block of R becomes the identity and the innovation is zero there, which is
the update on the observed components only.

Filtering elements (paper, Lemma 7/8), per t with S = H Q H^T + R, K = Q H^T S^-1,
e = y - H c - d::

    A = (I - K H) F,  b = c + K e,  C = Q - K S K^T,  eta = F^T H^T S^-1 e,  J = F^T H^T S^-1 H F

combined (i before j) with M = I + C_i J_j::

    A_ij = A_j M^-1 A_i,  b_ij = A_j M^-1 (b_i + C_i eta_j) + b_j,  C_ij = A_j M^-1 C_i A_j^T + C_j
    eta_ij = A_i^T M^-T (eta_j - J_j b_i) + eta_i,  J_ij = A_i^T M^-T J_j A_i + J_i

The prefix combination up to t holds the filtered mean b and covariance C. Smoothing elements
(Lemma 10/11): E_t = P_t F_{t+1}^T (P-_{t+1})^-1, g_t = m_t - E_t m-_{t+1},
L_t = P_t - E_t P-_{t+1} E_t^T (E_T = 0, g_T = m_T, L_T = P_T), combined
E_ij = E_i E_j, g_ij = E_i g_j + g_i, L_ij = E_i L_j E_i^T + L_i; the suffix combination from t
holds the smoothed mean and covariance.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from ..lib.linalg import sym
from ..filters.kalman import masked_update, observed
from .linear import Affine, affine_predict, chol_solve

__all__ = ["doubling_scan", "mask_measurement", "filtering_element", "filtering_combine", "kalman_filter",
           "smoothing_element", "smoothing_combine", "rts_smoother"]


def mask_measurement(H, d, R, y):
    """(H, d, R, y) with the missing (non-finite) components of y masked out: rows of H and d
    zeroed, R the identity on them, y 0 there. Shapes (ny, n), (ny,), (ny, ny), (ny,)."""
    _, mf, y0 = observed(y)
    Rm = R * (mf[:, None] * mf[None, :]) + jnp.diag(1 - mf)
    return H * mf[:, None], d * mf, Rm, y0


def filtering_element(F, c, Q, H, d, R, y):
    """The filtering element (A, b, C, eta, J) of one step (module docstring), y (ny,) with NaN
    missing; shapes (n, n), (n,), (n, n), (n,), (n, n)."""
    H, d, R, y = mask_measurement(H, d, R, y)
    QHt = Q @ H.T
    S = sym(H @ QHt + R)
    SinvH = chol_solve(S, H)                      # S^-1 H, (ny, n)
    K = Q @ SinvH.T                               # Q H^T S^-1
    e = y - H @ c - d
    HtSinvH = sym(H.T @ SinvH)
    A = F - K @ (H @ F)
    C = sym(Q - Q @ HtSinvH @ Q)
    eta = F.T @ (SinvH.T @ e)
    J = sym(F.T @ HtSinvH @ F)
    return A, c + K @ e, C, eta, J


def filtering_combine(ei, ej):
    """The associative filtering operator: element i (earlier) then j (later), one pair."""
    Ai, bi, Ci, etai, Ji = ei
    Aj, bj, Cj, etaj, Jj = ej
    n = Ai.shape[-1]
    M = jnp.eye(n, dtype=Ai.dtype) + Ci @ Jj
    X = jnp.linalg.solve(M, jnp.concatenate([Ai, Ci, (bi + Ci @ etaj)[:, None]], axis=1))
    MA, MC, Mb = X[:, :n], X[:, n:2 * n], X[:, 2 * n]
    Y = jnp.linalg.solve(M.T, jnp.concatenate([(etaj - Jj @ bi)[:, None], Jj @ Ai], axis=1))
    return (Aj @ MA, Aj @ Mb + bj, sym(Aj @ MC @ Aj.T + Cj),
            Ai.T @ Y[:, 0] + etai, sym(Ai.T @ Y[:, 1:] + Ji))


def doubling_scan(fn, elems, identity, reverse: bool = False):
    """Inclusive scan by recursive doubling (Hillis & Steele 1986): ceil(log2 T) passes of one
    vmapped ``fn`` in a ``fori_loop``, pass k combining each element with the one 2^k before
    it (``identity`` before the start). Same results as ``jax.lax.associative_scan(fn, elems,
    reverse=reverse)`` (same argument order of ``fn``), O(T log T) work instead of O(T), but
    one copy of ``fn`` in the program: it compiles in a time independent of T, where the
    associative scan's 2 log2 T copies take minutes on XLA:CPU for T = 10^4."""
    flip = partial(jax.tree_util.tree_map, lambda a: jnp.flip(a, 0))
    x = flip(elems) if reverse else elems
    T = jax.tree_util.tree_leaves(x)[0].shape[0]
    levels = max(int(np.ceil(np.log2(T))), 0) if T > 1 else 0
    idx = jnp.arange(T)
    vfn = jax.vmap(fn)

    def body(k, x):
        d = jnp.left_shift(1, k)

        def shifted(a, e):
            keep = (idx >= d).reshape((T,) + (1,) * (a.ndim - 1))
            return jnp.where(keep, jnp.roll(a, d, axis=0), e[None])

        return vfn(jax.tree_util.tree_map(shifted, x, identity), x)

    x = jax.lax.fori_loop(0, levels, body, x)
    return flip(x) if reverse else x


def _scan(fn, elems, identity, reverse, method):
    if method == "associative":
        return jax.lax.associative_scan(jax.vmap(fn), elems, reverse=reverse)
    return doubling_scan(fn, elems, identity, reverse)


def kalman_filter(model: Affine, ys, scan: str = "associative"):
    """Parallel-in-time Kalman filter, the same results as
    :func:`vehjax.smoothers.linear.kalman_filter` (to rounding).

    Args:
        model: :class:`Affine` over t = 0..T.
        ys: (T+1, ny) measurements, NaN where missing.
        scan: "associative" (``jax.lax.associative_scan``, O(T) work) or "doubling"
            (:func:`doubling_scan`, O(T log T) work, compile time independent of T).

    Returns:
        (means (T+1, n), covariances (T+1, n, n), loglik (T+1,) of the observed components).
    """
    elems = jax.vmap(filtering_element)(*model, ys)
    n, dt = model.F.shape[-1], model.F.dtype
    eye, z = jnp.eye(n, dtype=dt), jnp.zeros((n, n), dt)
    identity = (eye, jnp.zeros((n,), dt), z, jnp.zeros((n,), dt), z)
    _, ms, Ps, _, _ = _scan(filtering_combine, elems, identity, False, scan)
    # the log-likelihood: each step's prediction from the previous filtered moments (any
    # moments before t = 0, where F_0 = 0)
    n = ms.shape[-1]
    prev_m = jnp.concatenate([jnp.zeros((1, n), ms.dtype), ms[:-1]])
    prev_P = jnp.concatenate([jnp.eye(n, dtype=ms.dtype)[None], Ps[:-1]])

    def loglik(m, P, F, c, Q, H, d, R, y):
        mp, Pp, _ = affine_predict(m, P, F, c, Q)
        Cy = Pp @ H.T
        return masked_update(mp, Pp, y, H @ mp + d, sym(H @ Cy + R), Cy).loglik

    return ms, Ps, jax.vmap(loglik)(prev_m, prev_P, *model, ys)


def smoothing_element(m, P, F, c, Q):
    """The smoothing element (E, g, L) of t < T from its filtered (m, P) and the transition
    (F, c, Q) of t + 1; shapes (n, n), (n,), (n, n)."""
    mp, Pp, C = affine_predict(m, P, F, c, Q)
    E = chol_solve(Pp, C.T).T
    return E, m - E @ mp, sym(P - E @ C.T)


def smoothing_combine(ej, ei):
    """The associative smoothing operator, one pair: ``ej`` the later suffix, ``ei`` the
    earlier element (the argument order of ``associative_scan(..., reverse=True)``)."""
    Ej, gj, Lj = ej
    Ei, gi, Li = ei
    return Ei @ Ej, Ei @ gj + gi, sym(Ei @ Lj @ Ei.T + Li)


def rts_smoother(model: Affine, ms, Ps, scan: str = "associative"):
    """Parallel-in-time RTS smoother from filtered moments (T+1, n), (T+1, n, n): smoothed
    means, covariances and lag-one cross-covariances Cov(x_t, x_{t+1} | y) (T, n, n), the
    same as :func:`vehjax.smoothers.linear.rts_smoother` to rounding; ``scan`` as for
    :func:`kalman_filter`."""
    n = ms.shape[-1]
    E, g, L = jax.vmap(smoothing_element)(ms[:-1], Ps[:-1], model.F[1:], model.c[1:],
                                          model.Q[1:])
    E = jnp.concatenate([E, jnp.zeros((1, n, n), E.dtype)])
    g = jnp.concatenate([g, ms[-1:]])
    L = jnp.concatenate([L, Ps[-1:]])
    identity = (jnp.eye(n, dtype=E.dtype), jnp.zeros((n,), E.dtype), jnp.zeros((n, n), E.dtype))
    _, m_s, P_s = _scan(smoothing_combine, (E, g, L), identity, True, scan)
    cross = E[:-1] @ P_s[1:]
    return m_s, P_s, cross
