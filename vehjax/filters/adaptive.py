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
step runs on the user's Q0, R0, and ``loglik`` stays the predictive log-likelihood given
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

from .base import Estimator
from .gaussian import (
    _cast,
    _check_model,
    _chol,
    _prior,
    _sym,
    _theta,
    _vmap_model,
    check_cov,
    masked_update,
    step_output,
)
from .sigma import cholesky, cross_covariance, cubature_rule, sigma_points, unscented_transform

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


def _projector(prior: np.ndarray, floor: float):
    """A -> nearest matrix (in the metric of ``prior``) with A >= floor * prior."""
    L0 = _chol(prior)
    L0inv = np.linalg.inv(L0) if isinstance(L0, np.ndarray) else jnp.linalg.inv(L0)

    def project(A):
        dt = A.dtype
        Li, L = jnp.asarray(L0inv, dt), jnp.asarray(L0, dt)
        w, V = jnp.linalg.eigh(_sym(Li @ A @ Li.T))
        B = L @ V
        return _sym((B * jnp.maximum(w, floor)[None, :]) @ B.T)

    return project


def ackf(
    model,
    Q0,
    R0,
    forgetting: float = 0.98,
    adapt=("Q", "R"),
    floor: float = 1e-6,
    prior_steps: float = 0.0,
) -> Estimator:
    """Sage-Husa adaptive CKF of Wang et al. 2016, eq. 21-30.

    Args:
        model: a vehjax model (nx states, ny outputs).
        Q0: initial process noise covariance, (nx, nx) or (nx,) variances; state units squared.
        R0: initial measurement noise covariance, (ny, ny) or (ny,) variances.
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

    Returns:
        ``Estimator`` with state :class:`AckfState` (x, P, Q, R, k, theta).
    """
    nx, ny = _check_model(model)
    Q0n, R0n = check_cov("Q0", Q0, nx), check_cov("R0", R0, ny)
    try:
        b = float(forgetting)
    except (TypeError, ValueError):
        raise ValueError(f"forgetting: expected a number in (0, 1], got {forgetting!r}") from None
    if not (0.0 < b <= 1.0):
        raise ValueError(f"forgetting: expected 0 < b <= 1 (the paper uses 0.95-0.995), got {b}")
    if isinstance(adapt, str):
        adapt = (adapt,)
    adapt = tuple(adapt)
    if not set(adapt) <= set(_ADAPT):
        raise ValueError(f"adapt: expected a subset of {_ADAPT}, got {adapt!r}")
    try:
        floor = float(floor)
    except (TypeError, ValueError):
        raise ValueError(f"floor: expected a number in (0, 1), got {floor!r}") from None
    if not (0.0 < floor < 1.0):
        raise ValueError(f"floor: expected 0 < floor < 1, got {floor}")
    try:
        s0 = float(prior_steps)
    except (TypeError, ValueError):
        raise ValueError(f"prior_steps: expected a number >= 0, got {prior_steps!r}") from None
    if not (np.isfinite(s0) and s0 >= 0.0):
        raise ValueError(f"prior_steps: expected a finite number >= 0, got {s0}")

    rule = cubature_rule(nx)
    f, h = _vmap_model(model.transition), _vmap_model(model.observe)
    project_Q, project_R = _projector(Q0n, floor), _projector(R0n, floor)

    def init(x0, P0, theta0=None, P_theta0=None, key=None):
        """State from the prior x0 (nx,), P0 (nx, nx) or (nx,); theta0 (np,) or model.theta."""
        x0, P0 = _prior(nx, x0, P0)
        dt = x0.dtype
        theta = _theta(model, theta0, dt)
        return AckfState(x0, P0, jnp.asarray(Q0n, dt), jnp.asarray(R0n, dt), jnp.int32(0), theta)

    def step(state, y, u):
        x, P, Qh, Rh, k, theta = state
        dt = x.dtype
        y, u = _cast(y, dt), _cast(u, dt)
        Xf = f(sigma_points(x, cholesky(P), rule), u, theta)
        x_pred, Pxx0 = unscented_transform(Xf, rule)
        P_pred = _sym(Pxx0 + Qh)
        X = sigma_points(x_pred, cholesky(P_pred), rule)
        Z = h(X, u, theta)
        y_hat, Pzz0 = unscented_transform(Z, rule)
        C = cross_covariance(X, x_pred, Z, y_hat, rule)
        r = masked_update(x_pred, P_pred, y, y_hat, Pzz0 + Rh, C)

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
        return new, step_output(r.x, r.P, r.loglik, r.nis, r.n_obs)

    return Estimator(init=init, step=step, nx=nx, name="ACKF")
