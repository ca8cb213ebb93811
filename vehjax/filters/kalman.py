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
import numpy as np

from ..lib.entrywise import (add, chol_masked, dot, is_const, is_zero, joseph_entries, sub,
                              sym_entries)
from ..lib.gaussian import log_density, log_density_entries
from ..lib.linalg import cholesky, forward_entries, logdet_from_chol, solve_lower, sym


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
    components (the masked ones contribute 0 to ``w @ w`` and to the log-determinant): the
    matrix form of :func:`vehjax.lib.gaussian.log_density`. Returns (loglik, nis = w @ w)."""
    nis = w @ w
    return log_density(nis, logdet_from_chol(L), n_obs), nis


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


# ------------------------------------------------------------------------------------------------
# The same EKF algebra entry by entry (small models)
#
# A vehicle model has a handful of states and outputs. Written with matrix products, one EKF
# step is some thirty tiny dot products and triangular solves, each its own XLA operation; the
# forward-mode derivatives of :mod:`vehjax.tune` (a batch of tangents through every one of them)
# triple that. Written entry by entry (nested lists of scalars, :mod:`vehjax.lib.entrywise`),
# the step is elementwise arithmetic only, which XLA fuses into a few loops and compiles
# faster; structural zeros (a zero Q, an output that is a state) drop out at trace time. Same
# algebra as :func:`linearized_predict`, :func:`linearized_measure` and :func:`masked_update`
# (Joseph form), rounding-level differences.


def jacobian_entries(g, z):
    """Value and Jacobian of ``g: (n,) -> (m,)`` at ``z`` (n,) by forward mode, the n basis
    tangents vmapped through one ``jax.jvp`` (the primal evaluated once).

    Returns (value as a list of m scalars, Jacobian as nested lists (m, n) of scalars)."""
    n = z.shape[0]
    val, cols = jax.vmap(lambda t: jax.jvp(g, (z,), (t,)), out_axes=(None, 0))(
        jnp.eye(n, dtype=z.dtype))
    m = val.shape[0]
    return [val[i] for i in range(m)], [[cols[j, i] for j in range(n)] for i in range(m)]


def cov_entries(A, dtype=None):
    """Entries of a covariance (n, n) as nested lists: Python floats for a numpy constant (its
    zeros are structural and drop out of the algebra; weakly typed, they take the filter's
    dtype), scalars of the array, cast to ``dtype`` when given, for a jax array."""
    if isinstance(A, np.ndarray):
        return [[float(v) for v in row] for row in A]
    A = A if dtype is None else jnp.asarray(A).astype(dtype)
    return [[A[i, j] for j in range(A.shape[1])] for i in range(A.shape[0])]


def predict_entries(F, P, Q, B=None):
    """Predicted covariance ``F P F^T + Q + B B^T`` (nested lists (nx, nx), symmetric by
    construction): F (nx, nx) the transition Jacobian, P (nx, nx), Q (nx, nx) entries (Python
    floats allowed), B (nx, k) the Jacobian of the transition along the k standardised input
    noises (``G Lu``, :mod:`vehjax.filters.input_noise`) or None."""
    nx = len(F)
    FP = [[dot(F[i], [P[j][k] for j in range(nx)]) for k in range(nx)] for i in range(nx)]

    def entry(i, l):
        v = add(dot(FP[i], F[l]), Q[i][l])
        return v if B is None else add(v, dot(B[i], B[l]))

    return sym_entries(entry, nx)


def measure_entries(Pp, H, R):
    """EKF measurement moments entry by entry: ``C = P- H^T`` (nx, ny) and ``S = H C + R``
    (ny, ny, symmetric by construction), nested lists; H (ny, nx), R entries (floats allowed)."""
    nx, ny = len(Pp), len(H)
    C = [[dot(Pp[i], H[j]) for j in range(ny)] for i in range(nx)]
    S = sym_entries(lambda a, b: add(dot(H[a], [C[i][b] for i in range(nx)]), R[a][b]), ny)
    return C, S


def _observed_part(c, o):
    """``c`` on an observed component, 0 on a missing one (a structural zero stays one)."""
    return 0.0 if is_zero(c) else jnp.where(o, c, 0.0)


def _sym_pair(a, b):
    """(a + b) / 2 of a covariance's entries (i, j) and (j, i); ``a`` itself when they are one
    entry (symmetric by construction, known at trace time)."""
    return a if (a is b or (is_const(a) and is_const(b) and a == b)) else 0.5 * add(a, b)


def condition_entries(xp, Pp, e, S, C, obs, joseph=None):
    """The masked Kalman update entry by entry, from the innovation's moments: N(xp, Pp)
    conditioned on the observed components of a measurement whose innovation is ``e``.

    Args:
        xp (nx,): list of the predicted state's entries.
        Pp (nx, nx), S (ny, ny), C (nx, ny) = Cov(x, y): nested lists (Python-float entries
            allowed: a structural zero of C costs nothing). Pp's and S's symmetric parts are
            used.
        e (ny,): the innovation y - y^, zero on the missing components.
        obs (ny,): booleans (scalars or arrays), the observed components.
        joseph: ``(H, N)`` nested lists (N the noise part of S) for the Joseph-form covariance
            (I - K H) P- (I - K H)^T + K N K^T; None for P- - K S K^T.

    Everything goes through the Cholesky factor Ls of S on the observed components (identity
    rows elsewhere): w = Ls^-1 e, W[i] = Ls^-1 (C M)[i] (M the observation mask), so that
    x = xp + W w and P = Pp - W W^T.

    Returns:
        (x list (nx,), P nested lists (nx, nx) symmetric, w the whitened innovation list (ny,),
        Ls nested lists (ny, ny)).
    """
    nx, ny = len(xp), len(e)
    Ls = chol_masked(S, obs)
    w = forward_entries(Ls, e)
    W = [forward_entries(Ls, [_observed_part(C[i][j], obs[j]) for j in range(ny)])
         for i in range(nx)]
    x = [add(xp[i], dot(W[i], w)) for i in range(nx)]
    if joseph is None:
        P = sym_entries(lambda i, j: sub(_sym_pair(Pp[i][j], Pp[j][i]), dot(W[i], W[j])), nx)
    else:
        P = joseph_entries(Ls, W, *joseph, Pp)
    return x, P, w, Ls


def update_entries(xp, Pp, y, yh, S, C, joseph=None):
    """The masked Kalman update entry by entry for a measurement ``y`` (NaN where missing):
    :func:`condition_entries` with the innovation and the log-likelihood. The one entry form, for
    one run (scalar entries, :func:`masked_update_entries`), for all runs at once (entries (R,)
    arrays, runs last: :mod:`vehjax.filters.runs_last`) and for the particles of the marginalized
    PF (:mod:`vehjax.filters.marginalized.kalman`, through :func:`condition_entries`).
    :func:`masked_update` is its matrix form.

    Args:
        xp (nx,), yh (ny,): lists of the predicted state and measurement entries.
        Pp (nx, nx), S (ny, ny), C (nx, ny) = Cov(x, y): nested lists (Python-float entries
            allowed).
        y: (ny,) or (ny, R) array, NaN where a component is missing (not observed).
        joseph: as in :func:`condition_entries`.

    Returns:
        (x list (nx,), P nested lists (nx, nx), loglik, nis, n_obs, innovation list (ny,)),
        the innovation zero on the missing components.
    """
    ny = len(yh)
    obs = [jnp.isfinite(y[j]) for j in range(ny)]
    e = [jnp.where(obs[j], y[j] - yh[j], 0.0) for j in range(ny)]
    x, P, w, Ls = condition_entries(xp, Pp, e, S, C, obs, joseph)
    n_obs = sum(o.astype(jnp.int32) for o in obs)
    loglik, nis = log_density_entries(w, Ls, n_obs)
    return x, P, loglik, nis, n_obs, e


def masked_update_entries(xp, Pp, y, yh, S, C, joseph=None) -> UpdateResult:
    """:func:`update_entries` for one run: xp (nx,), yh (ny,) lists of scalars, Pp (nx, nx),
    S (ny, ny), C (nx, ny) nested lists (Python-float entries allowed); y (ny,) an array, NaN
    where missing; ``joseph`` = (H (ny, nx), N (ny, ny) the noise part of S) for the Joseph
    form (the EKF), None for P- - K S K^T (the sigma-point filters).

    Returns :class:`UpdateResult` of arrays: x (nx,), P (nx, nx), loglik, nis, n_obs,
    innovation (ny,)."""
    x, P, loglik, nis, n_obs, e = update_entries(xp, Pp, y, yh, S, C, joseph)
    dt = y.dtype
    stack = lambda v: jnp.broadcast_to(jnp.asarray(v, dt), jnp.shape(y[0]))  # noqa: E731
    return UpdateResult(jnp.stack([stack(v) for v in x]),
                        jnp.stack([jnp.stack([stack(v) for v in row]) for row in P]),
                        loglik, nis, n_obs, jnp.stack(e))
