"""The UKF/CKF step over a whole batch of runs at once, the runs axis last (``Estimator.batch``,
see :mod:`vehjax.filters.base`).

:func:`vehjax.run` normally ``vmap``s an estimator's per-run ``step`` over runs. For a vehicle
model with a handful of states that puts the runs first and 3 x 3 matrices last, so XLA on CPU
runs every small matrix operation as a loop of 3 over runs, and the filter algebra of a UKF
costs several times the model's arithmetic. Here every matrix entry and vector component is
one (R,) array over the runs instead, and the algebra is written out entry by entry: XLA fuses
it into long vectorised loops. Same equations, same order of operations as
:func:`vehjax.filters.gaussian.ukf`; results agree with the vmapped step to rounding.

The model is evaluated at all sigma points of all runs as one flat batch, points laid out
(n, m * R), after :func:`vehjax._hoist.split` has taken out what depends on the input and the
parameters alone: :attr:`Batch.prepare` computes that once for the whole input sequence before
the time loop, instead of XLA recomputing it for every point inside it. When every run uses the
model's own parameters they are constants of the compiled step.

Layout of a batch: state ``x`` (nx, R), ``P`` (nx, nx, R), ``theta`` (np, R); measurement
``y`` (ny, R); input sequence ``u`` (T, nu) shared by all runs or (T, nu, R). Used for
nx, ny <= 8.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .._hoist import Split, split
from .base import StepOutput
from ._linalg import LOG_2PI, UNROLL_MAX, chol_entries, cholesky, forward_entries
from .sigma import SigmaRule

MAX_DIM = UNROLL_MAX  # nx and ny up to this use the runs-last step


def _chol(A):
    """Lower Cholesky factor (nested lists) of a symmetric matrix given as nested lists of (R,)
    arrays; NaN entries where it is not positive definite (the divergence check catches them)."""
    return chol_entries(lambda i, j: A[i][i] if i == j else 0.5 * (A[i][j] + A[j][i]), len(A))


def _wsum(weights, terms):
    """sum_i w_i t_i over the non-zero (numpy constant) weights."""
    acc = None
    for w, t in zip(weights, terms):
        if w == 0.0:
            continue
        term = t if w == 1.0 else float(w) * t
        acc = term if acc is None else acc + term
    return acc


def _points(x, L, rule: SigmaRule):
    """Sigma points x + L xi_k, as a list over points of lists over components."""
    pts = []
    for xi in rule.points:
        point = []
        for i in range(len(x)):
            off = _wsum(xi[: i + 1], L[i][: i + 1])  # L is lower triangular
            point.append(x[i] if off is None else x[i] + off)
        pts.append(point)
    return pts


def _moments(Y, rule: SigmaRule, noise):
    """Weighted mean (list) and covariance (nested lists) of points Y, plus the deviations."""
    d = len(Y[0])
    mean = [_wsum(rule.wm, [y[i] for y in Y]) for i in range(d)]
    dev = [[y[i] - mean[i] for i in range(d)] for y in Y]
    cov = [[None] * d for _ in range(d)]
    for i in range(d):
        for j in range(i + 1):
            c = _wsum(rule.wc, [e[i] * e[j] for e in dev])
            cov[i][j] = cov[j][i] = c + noise[i][j]
    return mean, cov, dev


class Batch(NamedTuple):
    """A filter step over a batch of runs, runs axis last.

    Attributes:
        prepare: ``prepare(u)`` maps the input sequence, (T, nu) shared or (T, nu, R) per run,
            to what ``step`` takes in its place at each time: a pytree of arrays with leading
            axis T. Called once, before the time loop.
        step: ``step(state, y, prepared_t) -> (state, StepOutput)``.
    """

    prepare: Callable
    step: Callable


def _point_model(fn, nx: int, nu: int, n_params: int, dtype, theta_const) -> Split:
    """``fn(x, u, theta)`` of one point split by :func:`vehjax._hoist.split` into
    ``early(u)`` and ``late(x, theta, *residuals)``; with ``theta_const`` (np,) the parameters
    are that constant and the ``theta`` argument of ``late`` is ignored."""
    if theta_const is not None:
        theta_const = jnp.asarray(theta_const, dtype)

        def g(x, u, theta):
            return fn(x, u, theta_const)
    else:
        g = fn

    def reorder(x, theta, u):
        return g(x, u, theta)

    sd = jax.ShapeDtypeStruct
    return split(reorder, (sd((nx,), dtype), sd((n_params,), dtype), sd((nu,), dtype)),
                 late=(True, True, False))


def _evaluate(model: Split, pts, theta, residuals, per_run: bool):
    """The model at sigma points ``pts`` (list over m points of lists over n components, each
    (R,)): evaluated as one batch (n, m * R), returned as a list over points of lists over
    output components, each (R,). ``theta`` (np, R) or None (constant); ``residuals`` of
    ``model.early`` for this time, shared or with a trailing runs axis when ``per_run``."""
    m, R = len(pts), pts[0][0].shape[-1]
    X = jnp.stack([jnp.concatenate([p[i] for p in pts]) for i in range(len(pts[0]))])

    def tile(a):  # (..., R) -> (..., m * R), point-major like X
        lead = a.shape[:-1]
        return jnp.broadcast_to(a[..., None, :], lead + (m, R)).reshape(lead + (m * R,))

    if theta is None:
        th, th_axis = jnp.zeros((0,), X.dtype), None
    else:
        th, th_axis = tile(theta), 1
    if per_run:
        res, res_axes = [tile(r) for r in residuals], (-1,) * len(residuals)
    else:
        res, res_axes = list(residuals), (None,) * len(residuals)
    F = jax.vmap(model.late, in_axes=(1, th_axis) + res_axes, out_axes=1)(X, th, *res)
    return [[F[i, k * R:(k + 1) * R] for i in range(F.shape[0])] for k in range(m)]


def sigma_step(f, h, Qn: np.ndarray, Rn: np.ndarray, rule: SigmaRule, *, nu: int, n_params: int,
               per_run_inputs: bool, dtype, theta=None) -> Batch:
    """The non-square-root UKF/CKF step (:func:`vehjax.filters.gaussian._sigma_filter`) over a
    batch of runs, runs last.

    Args:
        f, h: transition and observation of one point, ``fn(x, u, theta)`` -> (nx,), (ny,),
            returning ``x``'s dtype.
        Qn, Rn: process and measurement noise covariances (numpy).
        rule: the sigma-point rule.
        nu, n_params: input and parameter dimensions.
        per_run_inputs: whether the inputs are (T, nu, R) rather than shared (T, nu).
        dtype: the filter's float dtype.
        theta: the parameters (np,) of every run, as a constant of the step; None to read
            each run's from the state.

    Returns:
        :class:`Batch`; ``step``'s state is a GaussianState of runs-last arrays and its
        StepOutput has mean (nx, R), cov (nx, nx, R), loglik, nis, n_obs (R,), params (0, R),
        params_cov (0, 0, R).
    """
    nx, ny = Qn.shape[0], Rn.shape[0]
    fm = _point_model(f, nx, nu, n_params, dtype, theta)
    hm = _point_model(h, nx, nu, n_params, dtype, theta)

    def prepare(u):
        u = jnp.asarray(u).astype(dtype)

        def early(u_t):
            return fm.early(u_t), hm.early(u_t)

        if per_run_inputs:  # (T, nu, R) -> residuals (T, ..., R)
            return jax.vmap(jax.vmap(early, in_axes=1, out_axes=-1))(u)
        return jax.vmap(early)(u)

    def step(state, y, prepared):
        X0, P0, th = state
        dt = X0.dtype
        y = y.astype(dt)
        th = None if theta is not None else th.astype(dt)  # theta for the model only
        res_f, res_h = prepared
        Q = [[jnp.asarray(Qn[i, j], dt) for j in range(nx)] for i in range(nx)]
        Rm = [[jnp.asarray(Rn[i, j], dt) for j in range(ny)] for i in range(ny)]
        x = [X0[i] for i in range(nx)]
        P = [[P0[i, j] for j in range(nx)] for i in range(nx)]

        F = _evaluate(fm, _points(x, _chol(P), rule), th, res_f, per_run_inputs)
        xp, Pp, _ = _moments(F, rule, Q)
        pts = _points(xp, _chol(Pp), rule)
        Z = _evaluate(hm, pts, th, res_h, per_run_inputs)
        yh, S, dz = _moments(Z, rule, Rm)
        dx = [[p[i] - xp[i] for i in range(nx)] for p in pts]
        C = [[_wsum(rule.wc, [a[i] * b[j] for a, b in zip(dx, dz)]) for j in range(ny)]
             for i in range(nx)]

        # masked update, as gaussian.masked_update: NaN components of y are not observed
        obs = [jnp.isfinite(y[j]) for j in range(ny)]
        mf = [o.astype(dt) for o in obs]
        e = [jnp.where(obs[j], y[j] - yh[j], 0.0) for j in range(ny)]
        Sm = [[S[i][j] * (mf[i] * mf[j]) + ((1.0 - mf[i]) if i == j else 0.0) for j in range(ny)]
              for i in range(ny)]
        Ls = _chol(Sm)
        w = forward_entries(Ls, e)
        W = [forward_entries(Ls, [C[i][j] * mf[j] for j in range(ny)]) for i in range(nx)]
        xn = [xp[i] + sum(W[i][k] * w[k] for k in range(ny)) for i in range(nx)]
        Pn = [[None] * nx for _ in range(nx)]
        for i in range(nx):
            for j in range(i + 1):
                Pn[i][j] = Pn[j][i] = Pp[i][j] - sum(W[i][k] * W[j][k] for k in range(ny))
        nis = sum(v * v for v in w)
        n_obs = sum(o.astype(jnp.int32) for o in obs)
        logdet = 2.0 * sum(jnp.log(Ls[k][k]) for k in range(ny))
        loglik = -0.5 * (nis + logdet + n_obs.astype(dt) * LOG_2PI)

        x_new = jnp.stack(xn)
        P_new = jnp.stack([jnp.stack(row) for row in Pn])
        R_runs = x_new.shape[-1]
        out = StepOutput(
            mean=x_new,
            cov=P_new,
            loglik=loglik,
            nis=nis,
            n_obs=n_obs,
            params=jnp.zeros((0, R_runs), dt),
            params_cov=jnp.zeros((0, 0, R_runs), dt),
            reinit=jnp.zeros((R_runs,), bool),
        )
        return state._replace(x=x_new, P=P_new), out

    return Batch(prepare, step)


def is_pd(C):
    """(R,) bool: whether each run's matrix of C (n, n, R) is finite and positive definite."""
    n = C.shape[0]
    if n == 0:
        return jnp.ones(C.shape[-1], bool)
    if n > MAX_DIM:  # sigma.cholesky on a runs-first copy (it goes to LAPACK for such n)
        Cr = jnp.moveaxis(C, -1, 0)
        return jnp.all(jnp.isfinite(Cr), axis=(1, 2)) & jnp.all(jnp.isfinite(cholesky(Cr)),
                                                                axis=(1, 2))
    L = _chol([[C[i, j] for j in range(n)] for i in range(n)])
    ok = jnp.all(jnp.isfinite(C), axis=(0, 1))
    for i in range(n):
        for j in range(i + 1):
            ok = ok & jnp.isfinite(L[i][j])
    return ok
