"""The extended, unscented and cubature RTS smoothers: the backward pass over a Gaussian filter's
own states, with the filter's own prediction (:class:`vehjax.filters.base.GaussianSmoother`).

For t = T-1 .. 0 the prediction from the filtered N(m_t, P_t) with the input of step t + 1 is
computed again, exactly as the filter's step computed it (the EKF's Jacobians, the UKF's /
CKF's sigma points, the input noise and the joint filters' random walk included), now with the
cross-covariance C = Cov(x_t, x_{t+1} | y_1:t) (P F^T for the EKF, the points' cross-moment
for the sigma-point filters, Särkkä 2008), and the RTS step of
:func:`vehjax.smoothers.linear.rts_step` runs; the square-root filters' backward pass works on
Cholesky factors throughout (:func:`vehjax.smoothers.linear.sqrt_rts_step`).

Index 0 is the prior (the filter state before the first step), so the pass also smooths x_0.

Also here: the linearisation of a Gaussian filter's moments into an affine model
(:func:`linearize`), what the parallel-in-time and iterated smoothers run on.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ..filters._linalg import cholesky, sym
from ..filters.base import GaussianSmoother
from .linear import Affine, rts_step, slr, sqrt_rts_step

__all__ = ["backward", "plain_moments", "linearize", "linearize_filtered"]


def backward(spec: GaussianSmoother, states, us):
    """The RTS backward pass over stacked filter states.

    Args:
        spec: the filter's :class:`~vehjax.filters.base.GaussianSmoother`.
        states: the filter's states at t = 0..T (the init state first), stacked on a leading
            axis of T + 1.
        us: (T, nu) inputs; ``us[t]`` is the input of the prediction from t to t + 1.

    Returns:
        (means (T+1, n), covariances (T+1, n, n), cross-covariances Cov(x_t, x_{t+1} | y)
        (T, n, n)); covariances formed from the smoothed factors for a square-root filter.
    """
    m, S, aux = jax.vmap(spec.split)(states)
    aux_prev = jax.tree_util.tree_map(lambda a: a[:-1], aux)

    if spec.sqrt:

        def body(carry, inp):
            ms_next, Ls_next = carry
            mt, Lt, u, a = inp
            m_pred, L11, L21, L22 = spec.predict(mt, Lt, u, a)
            m_s, L_s, cross = sqrt_rts_step(mt, m_pred, L11, L21, L22, ms_next, Ls_next)
            return (m_s, L_s), (m_s, L_s, cross)
    else:

        def body(carry, inp):
            ms_next, Ps_next = carry
            mt, Pt, u, a = inp
            m_pred, P_pred, C = spec.predict(mt, Pt, u, a)
            m_s, P_s, cross = rts_step(mt, Pt, m_pred, P_pred, C, ms_next, Ps_next)
            return (m_s, P_s), (m_s, P_s, cross)

    _, (m_s, S_s, cross) = jax.lax.scan(body, (m[-1], S[-1]), (m[:-1], S[:-1], us, aux_prev),
                                        reverse=True)
    m_s = jnp.concatenate([m_s, m[-1:]])
    S_s = jnp.concatenate([S_s, S[-1:]])
    P_s = sym(S_s @ jnp.swapaxes(S_s, -1, -2)) if spec.sqrt else S_s
    return m_s, P_s, cross


def plain_moments(spec: GaussianSmoother):
    """(predict, measure) of ``spec`` on covariances (not factors): ``predict(m, P, u, aux) ->
    (m-, P-, C)``, ``measure(m, P, u, aux) -> Measurement``; a square-root spec's joint factor
    turned into moments (P- = L11 L11^T, C = L21 L11^T)."""
    if not spec.sqrt:
        return spec.predict, spec.measure

    def predict(m, P, u, aux):
        m_pred, L11, L21, _ = spec.predict(m, cholesky(P), u, aux)
        return m_pred, sym(L11 @ L11.T), L21 @ L11.T

    def measure(m, P, u, aux):
        return spec.measure(m, cholesky(P), u, aux)

    return predict, measure


def _transition(spec, predict, m, P, u, a):
    """(F, c, Q) of one transition linearised about N(m, P) (identity covariance for a Taylor
    spec), and the prediction (m-, P-) itself."""
    P_lin = jnp.eye(m.shape[0], dtype=m.dtype) if spec.taylor else P
    m_pred, P_pred, C = predict(m, P_lin, u, a)
    F, c, Q = slr(m, P_lin, m_pred, P_pred, C)
    return F, c, Q


def _measurement(spec, measure, m, P, u, a):
    """(H, d, R) of the measurement linearised about N(m, P)."""
    P_lin = jnp.eye(m.shape[0], dtype=m.dtype) if spec.taylor else P
    mm = measure(m, P_lin, u, a)
    return slr(m, P_lin, mm.y_hat, mm.S, mm.C)


def _prior_step(x0, P0, ny: int):
    """The affine step of t = 0: F = 0, c = x0, Q = P0, no measurement (H = 0, R = I)."""
    n, dt = x0.shape[0], x0.dtype
    return (jnp.zeros((1, n, n), dt), x0[None], P0[None], jnp.zeros((1, ny, n), dt),
            jnp.zeros((1, ny), dt), jnp.eye(ny, dtype=dt)[None])


def linearize(spec: GaussianSmoother, M, P, us, aux, x0, P0, ny: int) -> Affine:
    """The affine model of the filter's moments linearised about a trajectory of Gaussians
    (the iterated smoothers): transition t about N(M[t-1], P[t-1]), measurement t about
    N(M[t], P[t]); Taylor (EKF, IEKS) or statistical (sigma points, IPLS) as the spec is.

    Args:
        spec: the filter's GaussianSmoother.
        M, P: (T+1, n), (T+1, n, n) the trajectory (index 0 the prior's time).
        us: (T, nu) inputs; aux: the spec's aux of the filter states t = 0..T-1 (leading T).
        x0, P0: the prior, (n,), (n, n). ny: measurement width.

    Returns:
        :class:`~vehjax.smoothers.linear.Affine` over t = 0..T.
    """
    predict, measure = plain_moments(spec)
    F, c, Q = jax.vmap(lambda *a: _transition(spec, predict, *a))(M[:-1], P[:-1], us, aux)
    H, d, R = jax.vmap(lambda *a: _measurement(spec, measure, *a))(M[1:], P[1:], us, aux)
    return Affine(*(jnp.concatenate([p, q]) for p, q in
                    zip(_prior_step(x0, P0, ny), (F, c, Q, H, d, R))))


def linearize_filtered(spec: GaussianSmoother, states, us, ny: int) -> Affine:
    """The affine model that the filter itself ran on: transition t about the filtered
    N(m_{t-1}, P_{t-1}), measurement t about the predicted N(m-_t, P-_t); the prior is the
    filter's init state (``states`` at t = 0..T, stacked). The Kalman filter on it gives the
    filter's own means, covariances and log-likelihood (to rounding), and the RTS smoother the
    filter's own RTS: what the parallel-in-time form of the non-iterated smoothers runs on."""
    m, S, aux = jax.vmap(spec.split)(states)
    P = sym(S @ jnp.swapaxes(S, -1, -2)) if spec.sqrt else S
    predict, measure = plain_moments(spec)

    def one(mt, Pt, u, a):
        F, c, Q = _transition(spec, predict, mt, Pt, u, a)
        m_pred, P_pred = F @ mt + c, sym(F @ Pt @ F.T + Q)
        return (F, c, Q) + _measurement(spec, measure, m_pred, P_pred, u, a)

    aux_prev = jax.tree_util.tree_map(lambda a: a[:-1], aux)
    parts = jax.vmap(one)(m[:-1], P[:-1], us, aux_prev)
    return Affine(*(jnp.concatenate([p, q]) for p, q in zip(_prior_step(m[0], P[0], ny), parts)))
