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

Where the forward pass ran the runs-last filter step (``vehjax.run(smooth=True)`` on the CPU,
:mod:`vehjax.filters.runs_last`), that step has kept its predictions and cross-covariances, and
:func:`backward_predicted` runs the recursion from them, the runs axis last, without evaluating
the model again.

Also here: the linearisation of a Gaussian filter's moments into an affine model
(:func:`linearize`), what the parallel-in-time and iterated smoothers run on.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ..lib.entrywise import backward_entries, chol_sym, dot
from ..lib.linalg import cholesky, forward_entries, sym
from ..filters.base import GaussianSmoother
from .linear import Affine, rts_apply, rts_gain, slr, sqrt_rts_apply, sqrt_rts_gain

__all__ = ["backward", "backward_moments", "backward_predicted", "gains_runs_last", "gains",
           "plain_moments", "linearize", "linearize_filtered"]


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
    return backward_moments(spec, m, S, aux_prev, us)


def gains(spec: GaussianSmoother, m, S, aux, us):
    """Every step's prediction and RTS gain at once (``vmap`` over time): they depend on the
    filtered moments only, not on the backward recursion.

    Args:
        spec: the filter's GaussianSmoother.
        m, S: filtered means (T, n) and covariances (T, n, n) (lower factors when
            ``spec.sqrt``) at t = 0..T-1.
        aux: the spec's aux at t = 0..T-1 (leading T).
        us: (T, nu) inputs of the predictions from t to t + 1.

    Returns:
        (G (T, n, n), m- (T, n), P- (T, n, n)) or, when ``spec.sqrt``, (G, m-, L22 (T, n, n))
        (:func:`vehjax.smoothers.linear.sqrt_rts_step`).
    """
    if spec.sqrt:
        m_pred, L11, L21, L22 = jax.vmap(spec.predict)(m, S, us, aux)
        return jax.vmap(sqrt_rts_gain)(L11, L21), m_pred, L22
    m_pred, P_pred, C = jax.vmap(spec.predict)(m, S, us, aux)
    return jax.vmap(rts_gain)(P_pred, C), m_pred, P_pred


def backward_moments(spec: GaussianSmoother, m, S, aux_prev, us):
    """:func:`backward` from the filtered moments: m (T+1, n), S (T+1, n, n) (covariances,
    or lower factors when ``spec.sqrt``) at t = 0..T, ``aux_prev`` the spec's aux at
    t = 0..T-1 (leading T), us (T, nu). The predictions and gains first (:func:`gains`), then
    the recursion, a scan of a few small matrix products per step. Returns as :func:`backward`.
    """
    G, m_pred, B = gains(spec, m[:-1], S[:-1], aux_prev, us)
    if spec.sqrt:

        def body(carry, inp):
            ms_next, Ls_next = carry
            g, mt, mp, L22 = inp
            m_s, L_s, cross = sqrt_rts_apply(g, mt, mp, L22, ms_next, Ls_next)
            return (m_s, L_s), (m_s, L_s, cross)

        xs = (G, m[:-1], m_pred, B)
    else:

        def body(carry, inp):
            ms_next, Ps_next = carry
            g, mt, Pt, mp, Pp = inp
            m_s, P_s, cross = rts_apply(g, mt, Pt, mp, Pp, ms_next, Ps_next)
            return (m_s, P_s), (m_s, P_s, cross)

        xs = (G, m[:-1], S[:-1], m_pred, B)

    _, (m_s, S_s, cross) = jax.lax.scan(body, (m[-1], S[-1]), xs, reverse=True)
    m_s = jnp.concatenate([m_s, m[-1:]])
    S_s = jnp.concatenate([S_s, S[-1:]])
    P_s = sym(S_s @ jnp.swapaxes(S_s, -1, -2)) if spec.sqrt else S_s
    return m_s, P_s, cross


def _entries(A):
    """Nested lists (n, m) of the entries of runs-last matrices (n, m, ...)."""
    return [[A[i, j] for j in range(A.shape[1])] for i in range(A.shape[0])]


def gains_runs_last(P_pred, C):
    """:func:`vehjax.smoothers.linear.rts_gain` G = C P-^-1 of many steps and runs at once,
    entry by entry: P_pred, C (T, n, n, R) -> G (T, n, n, R). Row i of G solves
    P- g_i = c_i (c_i row i of C) with the Cholesky factor of (the symmetric part of) P-; a
    P- that is not positive definite gives NaN."""
    Pe = [[P_pred[:, i, j] for j in range(P_pred.shape[2])] for i in range(P_pred.shape[1])]
    L = chol_sym(Pe)
    rows = [backward_entries(L, forward_entries(L, [C[:, i, k] for k in range(C.shape[2])]))
            for i in range(C.shape[1])]
    return jnp.stack([jnp.stack(r, axis=1) for r in rows], axis=1)


def _lower(n: int):
    """(i, j), j <= i: the lower-triangle entries of an n x n matrix, row by row."""
    return [(i, j) for i in range(n) for j in range(i + 1)]


def _recursion_terms(G, m, P, m_pred, P_pred):
    """The terms of the RTS recursion that do not depend on the smoothed moments, for all steps
    and runs at once, entry by entry (entries (T, R)): b = m - G m- (list n) and the lower
    triangle of A = P - G P- G^T (list, :func:`_lower` order), so that
    m^s_t = b_t + G_t m^s_{t+1} and P^s_t = A_t + G_t P^s_{t+1} G_t^T."""
    n = m.shape[1]
    g = _entries(jnp.moveaxis(G, 0, 2))
    b = [m[:, i] - dot(g[i], [m_pred[:, k] for k in range(n)]) for i in range(n)]
    GP = [[dot(g[i], [P_pred[:, k, j] for k in range(n)]) for j in range(n)] for i in range(n)]
    A = [P[:, i, j] - dot(GP[i], g[j]) for i, j in _lower(n)]
    return g, b, A


def _recursion_step(n: int, s, x):
    """One backward step of the recursion on packed runs-last arrays: ``s`` (n + n(n+1)/2, R)
    the smoothed mean and lower triangle of the covariance at t + 1, ``x`` (n^2 + n +
    n(n+1)/2, R) G_t (row by row), b_t, A_t (:func:`_recursion_terms`); returns the same
    packing of t. The covariance's upper triangle is its lower one (exactly symmetric)."""
    pairs = _lower(n)
    ms = [s[i] for i in range(n)]
    Ps = [[None] * n for _ in range(n)]
    for k, (i, j) in enumerate(pairs):
        Ps[i][j] = Ps[j][i] = s[n + k]
    g = [[x[i * n + j] for j in range(n)] for i in range(n)]
    m_new = [x[n * n + i] + dot(g[i], ms) for i in range(n)]
    GP = [[dot(g[i], [Ps[k][j] for k in range(n)]) for j in range(n)] for i in range(n)]
    P_new = [x[n * n + n + k] + dot(GP[i], g[j]) for k, (i, j) in enumerate(pairs)]
    return jnp.stack(m_new + P_new)


def _unpack_sym(packed, n: int):
    """(..., n + n(n+1)/2, R) packed moments (:func:`_recursion_step`) -> means (..., n, R)
    and full covariances (..., n, n, R)."""
    idx = {}
    for k, (i, j) in enumerate(_lower(n)):
        idx[i, j] = idx[j, i] = n + k
    M = packed[..., :n, :]
    rows = [jnp.stack([packed[..., idx[i, j], :] for j in range(n)], axis=-2) for i in range(n)]
    return M, jnp.stack(rows, axis=-3)


def backward_predicted(m, P, m_pred, P_pred, C):
    """The RTS backward pass (:func:`backward`, plain covariances) over a batch of R runs with
    the runs axis last, from the forward pass's own predictions (the runs-last filter steps'
    ``smooth_step``, :mod:`vehjax.filters.runs_last`): nothing of the model is evaluated
    again. All that does not depend on the smoothed moments is computed for every step at
    once, entry by entry: the gains (:func:`gains_runs_last`), b = m - G m-,
    A = P - G P- G^T (:func:`_recursion_terms`); the scan over time then runs
    m^s_t = b_t + G_t m^s_{t+1}, P^s_t = A_t + G_t P^s_{t+1} G_t^T on one packed array per
    step (:func:`_recursion_step`), and the cross-covariances G_t P^s_{t+1} come after it, all
    at once. The equations of :func:`vehjax.smoothers.linear.rts_apply`, regrouped (equal to
    rounding).

    Args:
        m: filtered means at t = 0..T (index 0 the prior), (T+1, n, R).
        P: their covariances, (T+1, n, n, R).
        m_pred: the predictions from t to t + 1, t = 0..T-1: means (T, n, R),
        P_pred: covariances (T, n, n, R),
        C: and cross-covariances Cov(x_t, x_{t+1} | y_1:t) (T, n, n, R).

    Returns:
        (means (T+1, n, R), covariances (T+1, n, n, R), cross-covariances (T, n, n, R)).
    """
    n = m.shape[1]
    G = gains_runs_last(P_pred, C)
    g, b, A = _recursion_terms(G, m[:-1], P[:-1], m_pred, P_pred)
    xs = jnp.stack([g[i][j] for i in range(n) for j in range(n)] + b + A, axis=1)
    last = jnp.stack([m[-1, i] for i in range(n)] + [P[-1, i, j] for i, j in _lower(n)])
    _, out = jax.lax.scan(lambda s, x: (lambda new: (new, new))(_recursion_step(n, s, x)),
                          last, xs, reverse=True)
    M, Ps = _unpack_sym(jnp.concatenate([out, last[None]]), n)
    Pn = _entries(jnp.moveaxis(Ps[1:], 0, 2))  # P^s_{t+1}, entries (T, R)
    cross = [[dot(g[i], [Pn[k][j] for k in range(n)]) for j in range(n)] for i in range(n)]
    return M, Ps, jnp.stack([jnp.stack(r, axis=1) for r in cross], axis=1)


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
