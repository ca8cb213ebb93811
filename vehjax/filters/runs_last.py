"""The EKF and UKF/CKF steps over a whole batch of runs at once, the runs axis last
(``Estimator.batch``, see :mod:`vehjax.filters.base`).

:func:`vehjax.run` normally ``vmap``s an estimator's per-run ``step`` over runs. For a vehicle
model with a handful of states that puts the runs first and 3 x 3 matrices last, so XLA on CPU
runs every small matrix operation as a loop of 3 over runs, and the filter algebra of a UKF
costs several times the model's arithmetic. Here every matrix entry and vector component is
one (R,) array over the runs instead, and the algebra is written out entry by entry: XLA fuses
it into long vectorised loops. Same equations, same order of operations as
:func:`vehjax.filters.gaussian.ukf`; results agree with the vmapped step to rounding.

The EKF's step is :func:`vehjax.filters.gaussian.ekf`'s the same way: the model and its
forward-mode tangents at every run's mean, the entries of the measurement Jacobian that are
constants of the model (outputs that are states) folded in at trace time, the Joseph-form update
entry by entry. With many runs it is faster than the vmapped step, since the same entry-by-entry
vectorisation applies (``vehjax bench all``, rows ekf and ukf, measures vehjax with it); with few
runs both are bound by XLA's fixed cost per kernel and step.

The UKF/CKF model is evaluated at all sigma points of all runs as one flat batch, points laid out
(n, m * R), after :func:`vehjax.runtime.hoist.split` has taken out what depends on the input and the
parameters alone: :attr:`Batch.prepare` computes that once for the whole input sequence before
the time loop, instead of XLA recomputing it for every point inside it. When every run uses the
model's own parameters they are constants of the compiled step. What ``prepare`` computes goes
into the time loop packed as one array per dtype (:func:`_prepare`).

Layout of a batch: state ``x`` (nx, R), ``P`` (nx, nx, R), ``theta`` (np, R); measurement
``y`` (ny, R); input sequence ``u`` (T, nu) shared by all runs or (T, nu, R). Used for
nx, ny <= 8.
"""

from __future__ import annotations

import math
from functools import partial
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..runtime import hoist
from ..runtime.hoist import Split, split
from .base import StepOutput
from .kalman import cov_entries, measure_entries, predict_entries, update_entries
from ..lib.entrywise import dot, stack, wsum
from ..lib.linalg import UNROLL_MAX, cholesky_succeeds, is_pd
from .sigma import SigmaRule, step_moments_entries

MAX_DIM = UNROLL_MAX  # nx and ny up to this use the runs-last step


class Batch(NamedTuple):
    """A filter step over a batch of runs, runs axis last.

    Attributes:
        prepare: ``prepare(u)`` maps the input sequence, (T, nu) shared or (T, nu, R) per run,
            to what ``step`` takes in its place at each time: a pytree of arrays with leading
            axis T. Called once, before the time loop.
        step: ``step(state, y, prepared_t) -> (state, StepOutput)``.
        prefetch: whether :func:`vehjax.run` hands ``prepared_t`` to the step through the scan's
            carry (read at the end of the previous step) rather than as a slice of the scanned
            sequence, which XLA fuses into the kernels that read it. Which is faster depends
            on the filter (the EKF's prepared Jacobian entries gain from the carry, the UKF's
            sigma-point inputs lose); ``vehjax bench all`` measures both.
        smooth_step: ``smooth_step(state, y, prepared_t) -> (state, (StepOutput, Prediction))``:
            ``step`` that also returns its prediction (:class:`Prediction`), what the runs-last
            RTS backward pass needs (:func:`vehjax.smoothers.gaussian.backward_predicted`);
            ``vehjax.run(smooth=True)`` scans it, the filter alone scans ``step``. None when
            the filter has none.
    """

    prepare: Callable
    step: Callable
    prefetch: bool = True
    smooth_step: Callable | None = None


class Prediction(NamedTuple):
    """One step's prediction over a batch of runs, runs last: from the state that the step
    starts from, N(x_{t-1}, P_{t-1}), with the step's input, to time t.

    Attributes:
        mean: predicted mean x-_t, (nx, R).
        cov: predicted covariance P-_t, (nx, nx, R).
        cross: Cov(x_{t-1}, x_t | y_1:t-1), (nx, nx, R): P_{t-1} F^T for the EKF (F the
            transition's Jacobian at x_{t-1}), the weighted cross-moment of the sigma points and
            their images for the UKF/CKF (Särkkä 2008).
    """

    mean: jnp.ndarray
    cov: jnp.ndarray
    cross: jnp.ndarray


def _prediction(xp, Pp, C) -> Prediction:
    """:class:`Prediction` from entries: lists xp (nx,), nested lists Pp, C (nx, nx) of (R,)."""
    like = xp[0]
    return Prediction(stack(xp, like), stack(Pp, like), stack(C, like))


def _point_model(fn, nx: int, nu: int, n_params: int, dtype, theta_const) -> Split:
    """``fn(x, u, theta)`` of one point split by :func:`vehjax.runtime.hoist.split` into
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


def _prepare(fm: Split, hm: Split, nu: int, per_run_inputs: bool, dtype):
    """:attr:`Batch.prepare` and the matching unpacking of one time's share: the input-only
    parts (``early``) of transition and observation over the whole input sequence, (T, nu) ->
    residuals (T, ...) or (T, nu, R) -> (T, ..., R), packed into one (T, K[, R]) array per dtype.
    One array per step is what the time loop then slices (the residuals of a model with
    trigonometry number dozens; each one its own slice or copy per step costs more than the
    model's arithmetic on a few runs)."""

    def early(u_t):
        return fm.early(u_t), hm.early(u_t)

    leaves, treedef = jax.tree.flatten(jax.eval_shape(early, jax.ShapeDtypeStruct((nu,), dtype)))
    groups: dict = {}  # dtype -> [(leaf index, shape), ...]
    for i, a in enumerate(leaves):
        groups.setdefault(jnp.dtype(a.dtype), []).append((i, a.shape))
    trail = 1 if per_run_inputs else 0

    def prepare(u):
        u = jnp.asarray(u).astype(dtype)
        if per_run_inputs:
            res = jax.vmap(jax.vmap(early, in_axes=1, out_axes=-1))(u)
        else:
            res = jax.vmap(early)(u)
        flat, T = jax.tree.leaves(res), u.shape[0]
        out = []
        for members in groups.values():
            parts = [flat[i].reshape((T, -1) + flat[i].shape[flat[i].ndim - trail:])
                     for i, _ in members]
            out.append(jnp.concatenate(parts, axis=1) if len(parts) > 1 else parts[0])
        return tuple(out)

    def unpack(packed_t):
        """One time's packed residuals, (K[, R]) per dtype -> (residuals of f, of h)."""
        out = [None] * len(leaves)
        for arr, members in zip(packed_t, groups.values()):
            k = 0
            for i, shape in members:
                size = math.prod(shape)
                out[i] = arr[k:k + size].reshape(shape + arr.shape[1:])
                k += size
        return jax.tree.unflatten(treedef, out)

    return prepare, unpack


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
    nx = Qn.shape[0]
    fm = _point_model(f, nx, nu, n_params, dtype, theta)
    hm = _point_model(h, nx, nu, n_params, dtype, theta)

    prepare, unpack = _prepare(fm, hm, nu, per_run_inputs, dtype)

    def step(state, y, prepared, with_prediction):
        X0, P0, th = state
        dt = X0.dtype
        y = y.astype(dt)
        th = None if theta is not None else th.astype(dt)  # theta for the model only
        res_f, res_h = unpack(prepared)
        Q, Rm = cov_entries(jnp.asarray(Qn, dt)), cov_entries(jnp.asarray(Rn, dt))
        x = [X0[i] for i in range(nx)]
        P = [[P0[i, j] for j in range(nx)] for i in range(nx)]

        # the one-run UKF's algebra (vehjax.filters.sigma), the model evaluated for all runs
        m = step_moments_entries(x, P, lambda X: _evaluate(fm, X, th, res_f, per_run_inputs),
                                 lambda X: _evaluate(hm, X, th, res_h, per_run_inputs), Q, Rm,
                                 rule)
        x_new, P_new, loglik, nis, n_obs = _update(m.xp, m.Pp, y, m.yh, m.S, m.C)
        out = _output(x_new, P_new, loglik, nis, n_obs)
        if not with_prediction:
            return state._replace(x=x_new, P=P_new), out
        # Cov(x_{t-1}, x_t | y_1:t-1): the points' deviations from x_{t-1} against their images'
        Cx = [[wsum(rule.wc, [(p[i] - x[i]) * d[j] for p, d in zip(m.X, m.dF)])
               for j in range(nx)] for i in range(nx)]
        return state._replace(x=x_new, P=P_new), (out, _prediction(m.xp, m.Pp, Cx))

    return Batch(prepare, partial(step, with_prediction=False), prefetch=False,
                 smooth_step=partial(step, with_prediction=True))


# -- the Kalman update, shared by the UKF/CKF and EKF steps -------------------------------------


def _update(xp, Pp, y, yh, S, C, joseph=None):
    """:func:`vehjax.filters.kalman.update_entries` on the runs-last entries ((R,) arrays; y
    (ny, R)), stacked: x (nx, R), P (nx, nx, R), loglik, nis, n_obs (R,)."""
    x, P, loglik, nis, n_obs, _ = update_entries(xp, Pp, y, yh, S, C, joseph)
    return jnp.stack(x), jnp.stack([jnp.stack(row) for row in P]), loglik, nis, n_obs


def _output(x, P, loglik, nis, n_obs) -> StepOutput:
    """StepOutput of a state-only runs-last step."""
    R, dt = x.shape[-1], x.dtype
    return StepOutput(mean=x, cov=P, loglik=loglik, nis=nis, n_obs=n_obs,
                      params=jnp.zeros((0, R), dt), params_cov=jnp.zeros((0, 0, R), dt),
                      reinit=jnp.zeros((R,), bool))


# -- EKF ------------------------------------------------------------------------------------------


def _jacobian_constants(fn, nx: int, nu: int, n_params: int, dtype, theta_const):
    """Nested lists over the entries of d fn / dx: the entry's value (a Python float) where it
    is the same number for every state, input and parameter vector (a structural zero or one,
    :func:`vehjax.runtime.hoist.dependence`), None where it varies. With ``theta_const`` the
    parameters are that constant."""
    th0 = np.zeros(n_params) if theta_const is None else np.asarray(theta_const)

    def jac(x, u, th):
        th = th if theta_const is None else jnp.asarray(theta_const, dtype)
        return jax.jacfwd(fn)(x, u, th)

    args = (np.ones(nx, dtype), np.ones(nu, dtype), np.asarray(th0, dtype))
    dep, val = hoist.dependence(jac, args), hoist.evaluate(jac, args)
    return [[None if dep[i, j] else float(val[i, j]) for j in range(nx)]
            for i in range(dep.shape[0])]


def _linearise(model: Split, x, theta, residuals, per_run: bool, consts):
    """Value (list over output components of (R,)) and Jacobian (nested lists) of
    ``model.late`` at the points ``x`` (list over n components of (R,)), by forward mode; the
    entries that ``consts`` (:func:`_jacobian_constants`) gives are those Python floats."""
    n = len(x)
    X = jnp.stack(x)

    def g(z, th, *res):
        return model.late(z, th, *res)

    th, th_axis = (jnp.zeros((0,), X.dtype), None) if theta is None else (theta, 1)
    res_axes = (-1 if per_run else None,) * len(residuals)
    gv = jax.vmap(g, in_axes=(1, th_axis) + res_axes, out_axes=1)
    # the n tangents as one batch (n, ..., R): the model's primal once, its tangent equations
    # once over (n, R) (as many equations as one tangent: a shorter compile than n jvps)
    basis = jnp.broadcast_to(jnp.eye(n, dtype=X.dtype)[:, :, None], (n,) + X.shape)
    Y, cols = jax.vmap(lambda t: jax.jvp(lambda z: gv(z, th, *residuals), (X,), (t,)),
                       out_axes=(None, 0))(basis)
    J = [[cols[j][i] if consts[i][j] is None else consts[i][j] for j in range(n)]
         for i in range(Y.shape[0])]
    return [Y[i] for i in range(Y.shape[0])], J


def ekf_step(f, h, Qn: np.ndarray, Rn: np.ndarray, *, nu: int, n_params: int,
             per_run_inputs: bool, dtype, theta=None) -> Batch:
    """The EKF step (:func:`vehjax.filters.gaussian.ekf`: Jacobians by forward mode, Joseph-form
    covariance update) over a batch of runs, runs last. Arguments and result as
    :func:`sigma_step`. Entries of the measurement Jacobian that are constants of the model (an
    output that is a state) are folded into the algebra at trace time."""
    nx = Qn.shape[0]
    fm = _point_model(f, nx, nu, n_params, dtype, theta)
    hm = _point_model(h, nx, nu, n_params, dtype, theta)
    prepare, unpack = _prepare(fm, hm, nu, per_run_inputs, dtype)
    # the structural constants of H (outputs that are states: most of a vehicle model's) save
    # a fifth of the 3-DOF EKF's time; finding those of F would cost seconds of compile time
    # for a model integrated with RK4 and save little (few of its entries are constants)
    F_const = [[None] * nx for _ in range(nx)]
    H_const = _jacobian_constants(h, nx, nu, n_params, dtype, theta)

    def step(state, y, prepared, with_prediction):
        X0, P0, th = state
        dt = X0.dtype
        y = y.astype(dt)
        th = None if theta is not None else th.astype(dt)
        res_f, res_h = unpack(prepared)
        Q, Rm = cov_entries(jnp.asarray(Qn, dt)), cov_entries(jnp.asarray(Rn, dt))
        P = [[P0[i, j] for j in range(nx)] for i in range(nx)]

        xp, F = _linearise(fm, [X0[i] for i in range(nx)], th, res_f, per_run_inputs, F_const)
        Pp = predict_entries(F, P, Q)  # the one-run EKF's algebra (vehjax.filters.kalman)
        yh, H = _linearise(hm, xp, th, res_h, per_run_inputs, H_const)
        C, S = measure_entries(Pp, H, Rm)
        x_new, P_new, loglik, nis, n_obs = _update(xp, Pp, y, yh, S, C, joseph=(H, Rm))
        out = _output(x_new, P_new, loglik, nis, n_obs)
        if not with_prediction:
            return state._replace(x=x_new, P=P_new), out
        # Cov(x_{t-1}, x_t | y_1:t-1) = P F^T (P symmetric)
        Cx = [[dot(F[j], [P[k][i] for k in range(nx)]) for j in range(nx)] for i in range(nx)]
        return state._replace(x=x_new, P=P_new), (out, _prediction(xp, Pp, Cx))

    return Batch(prepare, partial(step, with_prediction=False),
                 smooth_step=partial(step, with_prediction=True))


def all_finite(a):
    """(R,) bool: whether every entry of a (..., R) is finite, entry by entry (one fused
    elementwise kernel rather than a reduction)."""
    flat = a.reshape((-1, a.shape[-1]))
    ok = jnp.ones(a.shape[-1], bool)
    for k in range(flat.shape[0]):
        ok = ok & jnp.isfinite(flat[k])
    return ok


def runs_pd(C):
    """(R,) bool: whether each run's matrix of C (n, n, R) is finite and positive definite:
    :func:`vehjax.lib.linalg.cholesky_succeeds` on the runs-last entries (one fused elementwise
    kernel), :func:`vehjax.lib.linalg.is_pd` on a runs-first copy for n > MAX_DIM."""
    n = C.shape[0]
    if n == 0:
        return jnp.ones(C.shape[-1], bool)
    if n > MAX_DIM:
        return is_pd(jnp.moveaxis(C, -1, 0))
    return all_finite(C) & cholesky_succeeds(
        lambda i, j: C[i, i] if i == j else 0.5 * (C[i, j] + C[j, i]), n)
