"""Sage-Husa adaptive cubature Kalman filter (Wang et al. 2016, eq. 21-30).

A CKF whose process and measurement noise covariances are re-estimated at every step from the
innovations, with the memory index ``d_k = (1 - b) / (1 - b^k)`` (b the forgetting factor,
k = 1, 2, ... the number of steps with at least one observed component; ``prior_steps`` shifts k
so that the prior counts as that many earlier steps, 0 by default as in the paper)::

    R_k = (1 - d_k) R_{k-1} + d_k (e e^T - P_zz0)                      (eq. 30)
    Q_k = (1 - d_k) Q_{k-1} + d_k (K e e^T K^T + P_k - P_xx0)          (eq. 29)

e = y_k - y^_k the innovation, P_zz0 the spread of the measurement cubature points (the
predicted measurement covariance without R), P_xx0 the spread of the propagated state points
(the predicted covariance without Q), K e = x_k - x^-_k and P_k the updated covariance.
The transcription's ``-1/2n sum X X^T + x^- x^-T`` is the negated spread P_xx0 (and likewise
for Z); the two signs of eq. 29-30 are read that way.

Order within a step: the gain at step k uses Q_{k-1}, R_{k-1}; the new estimates are formed
after the update and used from step k + 1 on. Thus an innovation never weights itself, the first
step runs on the user's ``Q``, ``R`` (written Q0, R0 here), and ``loglik`` stays the predictive log-likelihood given
y_1..y_{k-1}.

Positive definiteness: the raw recursions are differences of covariances and can become
indefinite. Each estimate is projected, in the metric of its prior (Q0 = L0 L0^T), onto
``{A : A >= floor * Q0}``: eigenvalues of ``L0^-1 A L0^-T`` below ``floor`` are raised to it.
That is the nearest admissible matrix in that metric, it never changes an estimate that is
already admissible, and being relative to Q0, R0 it respects the very different scales of
vehicle states (m, rad, m/s).

Missing measurements: a step with no observed component is a plain prediction and leaves
Q, R and k unchanged; with some components missing only the observed block of R moves.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from .. import validation
from . import input_noise as _inoise
from . import sigma
from ..lib.linalg import sym
from .base import Dims, Estimator, Runtime, state_output
from ._model import (
    cast_yu, chol_const, check_model, in_dtype, model_dims, model_theta, per_point, point_fns,
    prior,
)
from .kalman import masked_update

_ADAPT = ("Q", "R")


class AckfState(NamedTuple):
    """State of the adaptive CKF.

    Attributes:
        x: filtered mean, (nx,).
        P: its covariance, (nx, nx).
        Q: current process noise estimate, (nx, nx), used by the next prediction.
        R: current measurement noise estimate, (ny, ny), used by the next update.
        k: number of steps that adapted Q and R so far, int32 scalar.
        theta: model parameters the filter runs with, (np,).

    Read the noise estimates from the state: ``state.Q``, ``state.R`` after any step, or, for
    their history, scan ``est.step`` and return the states (``jax.lax.scan`` stacks them).
    """

    x: jnp.ndarray
    P: jnp.ndarray
    Q: jnp.ndarray
    R: jnp.ndarray
    k: jnp.ndarray
    theta: jnp.ndarray


def _projector(ref: np.ndarray, floor: float):
    """A -> nearest matrix (in the metric of ``prior``) with A >= floor * prior."""
    L0 = chol_const(ref)
    L0inv = np.linalg.inv(L0) if isinstance(L0, np.ndarray) else jnp.linalg.inv(L0)

    def project(A):
        dt = A.dtype
        Li, L = jnp.asarray(L0inv, dt), jnp.asarray(L0, dt)
        w, V = jnp.linalg.eigh(sym(Li @ A @ Li.T))
        B = L @ V
        return sym((B * jnp.maximum(w, floor)[None, :]) @ B.T)

    return project


def ackf(
    model,
    Q,
    R,
    *,
    forgetting: float = 0.98,
    adapt=("Q", "R"),
    floor: float = 1e-6,
    prior_steps: float = 0.0,
    input_noise=None,
) -> Estimator:
    """Sage-Husa adaptive CKF of Wang et al. 2016, eq. 21-30.

    Args:
        model: a vehjax model (nx states, ny outputs).
        Q: initial value of the adapted process noise covariance (Q0 below and in the module
            docstring), (nx, nx) or (nx,) variances; state units squared.
            Positive definite when ``adapt`` includes "Q" (it is the metric of the projection
            below); otherwise positive semi-definite (zero with ``input_noise``).
        R: initial value of the adapted measurement noise covariance (R0), (ny, ny) or (ny,)
            variances.
        forgetting: forgetting factor b in (0, 1]; the memory index is d_k = (1-b)/(1-b^k), so
            past steps fade with weight b per step (memory of about 1/(1-b) steps). The paper
            uses b in [0.95, 0.995]; other values are accepted (smaller b tracks faster and is
            noisier) and b = 1 gives the plain running mean d_k = 1/k of eq. 26 and 28.
        adapt: which covariances to re-estimate, a subset of ("Q", "R"); the others stay at
            Q0 or R0. Estimating both from the same innovations is weakly identifiable
            (Sage-Husa's known weakness); adapting R alone is the robust choice when Q is known.
        floor: the estimates stay >= floor * Q0 and >= floor * R0 (Loewner order), 0 < floor < 1.
        prior_steps: how many earlier steps Q0 and R0 count for: d_k = (1-b)/(1-b^(k + s0)).
            The paper's estimator is s0 = 0: d_1 = 1, so the first innovation replaces the
            prior entirely; with a broad P0 that one-sample estimate is indefinite and lands on
            the floor, and R, Q take tens to hundreds of steps to recover. Giving a trusted
            prior s0 of the order of the memory 1/(1-b) damps that start-up transient. (While
            P- is large next to R, e e^T - P_zz0 is a small difference of large terms, so an R0
            that is too small can still be driven onto the floor early on.)
        input_noise: noise entering through the inputs (:mod:`vehjax.filters.input_noise`):
            ``{input name: std}`` in the input's units or an (nu, nu) covariance in input units
            squared; None (default) for none. The cubature points of the prediction are those
            of the state augmented with the k noisy input components, so P_xx0 includes the
            input noise and the adapted Q is the process noise beyond it.

    Returns:
        ``Estimator`` with state :class:`AckfState` (x, P, Q, R, k, theta).
    """
    nx, ny = check_model(model)
    if isinstance(adapt, str):
        adapt = (adapt,)
    adapt = validation.names("adapt", adapt, _ADAPT, allow_empty=True)
    Q0n = validation.cov("Q", Q, nx, allow_psd="Q" not in adapt)
    R0n = validation.cov("R", R, ny)
    b = validation.number("forgetting", forgetting, 0.0, 1.0, high_open=False)
    Lu = _inoise.input_factor(input_noise, model.input_names)
    tr = in_dtype(per_point(model)[0])
    floor = validation.number("floor", floor, 0.0, 1.0)
    s0 = validation.number("prior_steps", prior_steps, 0.0, low_open=False)

    rule = sigma.cubature_rule(nx)
    rule_a = None if Lu is None else sigma.cubature_rule(nx + Lu.shape[1])
    project_Q = _projector(Q0n, floor) if "Q" in adapt else None
    project_R = _projector(R0n, floor)

    def init(x0, P0, theta0=None, P_theta0=None, key=None):
        """State from the prior x0 (nx,), P0 (nx, nx) or (nx,); theta0 (np,) or model.theta."""
        x0, P0 = prior(nx, x0, P0)
        dt = x0.dtype
        theta = model_theta(model, theta0, dt)
        return AckfState(x0, P0, jnp.asarray(Q0n, dt), jnp.asarray(R0n, dt), jnp.int32(0), theta)

    def step(state, y, u):
        x, P, Qh, Rh, k, theta = state
        dt = x.dtype
        y, u = cast_yu(y, u, dt)
        f, h = point_fns(model, u, theta)
        if Lu is None:
            x_pred, Pxx0 = sigma.predict(rule, x, P, f)
        else:
            x_pred, Pxx0 = _inoise.sigma_predict(rule_a, x, P, lambda v, w: tr(v, w, theta), u,
                                                 Lu)
        P_pred = sym(Pxx0 + Qh)
        m = sigma.measure(rule, x_pred, P_pred, h)
        Pzz0 = m.S
        r = masked_update(x_pred, P_pred, y, m.y_hat, Pzz0 + Rh, m.C)

        seen = r.n_obs > 0
        k_new = k + seen.astype(jnp.int32)
        kf = jnp.maximum(k_new, 1).astype(dt) + s0
        d = 1.0 / kf if b == 1.0 else (1.0 - b) / (1.0 - jnp.asarray(b, dt) ** kf)
        if "R" in adapt:
            mf = jnp.isfinite(y).astype(dt)
            e = r.innovation
            R_new = (1 - d) * Rh + d * (jnp.outer(e, e) - Pzz0)
            obs2 = mf[:, None] * mf[None, :]
            R_new = project_R(obs2 * R_new + (1 - obs2) * Rh)
            Rh = jnp.where(seen, R_new, Rh)
        if "Q" in adapt:
            dx = r.x - x_pred
            Q_new = project_Q((1 - d) * Qh + d * (jnp.outer(dx, dx) + r.P - Pxx0))
            Qh = jnp.where(seen, Q_new, Qh)
        new = AckfState(r.x, r.P, Qh, Rh, k_new, theta)
        return new, state_output(r.x, r.P, r.loglik, r.nis, r.n_obs)

    return Estimator(
        init=init,
        step=step,
        name="ACKF",
        dims=Dims(nx=nx, **model_dims(model)),
        runtime=Runtime(workload="small_dense"),
    )
