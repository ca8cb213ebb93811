"""Gaussian filters: EKF, UKF, CKF and the square-root UKF and CKF.

Each builder returns an :class:`~vehjax.filters.base.Estimator` of pure functions that works on
any vehjax model. The filters estimate the state only; they run the model at the parameter
vector ``theta0`` given to ``init`` (``model.theta`` when omitted), which is carried unchanged in
the state.

One step (time convention of :mod:`vehjax.filters.base`)::

    predict:  x- = E[f(x, u_t, theta)],   P- = Cov[f(x, u_t, theta)] + Q
    update:   y^ = E[h(x-, u_t, theta)],  S = Cov[h] + R,  C = Cov[x-, h]
              x = x- + C S^-1 (y_t - y^),  P = P- - C S^-1 C^T

The EKF linearises f at the filtered mean and h at the predicted mean with ``jax.jacfwd``
(G_s of Dutta et al. 2019, Algorithm 1). The UKF and CKF propagate the sigma points of
:mod:`vehjax.filters.sigma` through the model (vmapped) and, as in Algorithm 2 of Dutta et al.,
draw fresh points from (x-, P-) for the update, so that Q enters S and C.

Missing measurements: components of ``y_t`` that are NaN are not observed; the update uses
only the observed ones (exactly, by masking) and ``loglik``/``nis``/``n_obs`` count only them.
A step with every component missing is a pure prediction.

The state dtype follows ``x0``/``P0``: float32 priors run the whole filter in float32 (theta,
Q, R and the inputs are cast to it).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from . import runs_last as _runs_last
from .base import Estimator, StepOutput
from .sigma import (
    SigmaRule,
    cholesky,
    cross_covariance,
    cubature_rule,
    sigma_points,
    solve_lower,
    sqrt_unscented_transform,
    unscented_rule,
    unscented_transform,
    weighted_sqrt_factor,
)

_LOG_2PI = float(np.log(2.0 * np.pi))


class GaussianState(NamedTuple):
    """State of EKF, UKF, CKF.

    Attributes:
        x: filtered mean, (nx,).
        P: its covariance, (nx, nx).
        theta: model parameters the filter runs with, (np,).
    """

    x: jnp.ndarray
    P: jnp.ndarray
    theta: jnp.ndarray


class SqrtGaussianState(NamedTuple):
    """State of the square-root UKF and CKF.

    Attributes:
        x: filtered mean, (nx,).
        L: lower Cholesky factor of its covariance, (nx, nx), positive diagonal.
        theta: model parameters the filter runs with, (np,).
    """

    x: jnp.ndarray
    L: jnp.ndarray
    theta: jnp.ndarray


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


# --------------------------------------------------------------------------------------------
# validation (numpy, before tracing)


def _is_tracer(a) -> bool:
    return isinstance(a, jax.core.Tracer)


def check_cov(name: str, value, n: int, allow_diag: bool = True):
    """A symmetric positive-definite (n, n) covariance from ``value``, as a float64 numpy array.

    ``value`` is (n, n), or (n,) variances of a diagonal covariance when ``allow_diag``.
    Raises ValueError naming ``name`` for a wrong shape, non-finite entries, asymmetry or a
    matrix that is not positive definite. A traced ``value`` (a builder called inside a
    function being differentiated, as when tuning Q and R) has only its shape checked and is
    returned as a symmetrised jax array.
    """
    expect = f"({n}, {n})" + (f" or ({n},) variances" if allow_diag else "")
    if _is_tracer(value):
        # Traced (e.g. tune.py differentiating the log-likelihood): only the shape can be checked.
        if np.shape(value) not in (((n,), (n, n)) if allow_diag else ((n, n),)):
            raise ValueError(f"{name}: expected shape {expect}, got shape {np.shape(value)}")
        A = jnp.diag(value) if value.ndim == 1 else value
        return 0.5 * (A + A.T)
    try:
        A = np.array(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected a numeric array, got {value!r}") from None
    if allow_diag and A.shape == (n,):
        A = np.diag(A)
    if A.shape != (n, n):
        raise ValueError(f"{name}: expected shape {expect}, got shape {A.shape}")
    if not np.all(np.isfinite(A)):
        raise ValueError(f"{name}: expected finite entries, got {A}")
    scale = np.max(np.abs(A)) if A.size else 0.0
    if not np.allclose(A, A.T, rtol=1e-8, atol=1e-12 * scale):
        raise ValueError(f"{name}: expected a symmetric matrix, got {A}")
    A = 0.5 * (A + A.T)
    try:
        np.linalg.cholesky(A)
    except np.linalg.LinAlgError:
        raise ValueError(
            f"{name}: expected a positive-definite covariance, got eigenvalues "
            f"{np.linalg.eigvalsh(A)}"
        ) from None
    return A


def validate_prior(est, x0, P0) -> None:
    """Check a prior before tracing; ``est`` is an Estimator or the state dimension nx.

    ``x0`` is (nx,) or batched (R, nx); ``P0`` is (nx, nx) or (nx,) variances, or batched
    (R, nx, nx). Raises ValueError naming ``x0`` or ``P0`` for a wrong shape, non-finite
    entries or a covariance that is not symmetric positive definite. Traced values are skipped
    (only their shapes are checked).
    """
    nx = est if isinstance(est, (int, np.integer)) else est.nx
    xs, Ps = np.shape(x0), np.shape(P0)
    if len(xs) not in (1, 2) or xs[-1] != nx:
        raise ValueError(f"x0: expected shape ({nx},) or (runs, {nx}), got shape {xs}")
    if Ps not in ((nx,), (nx, nx)) and not (len(Ps) == 3 and Ps[1:] == (nx, nx)):
        raise ValueError(
            f"P0: expected shape ({nx}, {nx}), ({nx},) variances or (runs, {nx}, {nx}), "
            f"got shape {Ps}"
        )
    if not _is_tracer(x0) and not np.all(np.isfinite(np.asarray(x0, dtype=float))):
        raise ValueError("x0: expected finite values")
    if not _is_tracer(P0):
        P = np.asarray(P0, dtype=float)
        for i, Pi in enumerate(P.reshape((-1,) + Ps[-2:]) if P.ndim == 3 else [P]):
            check_cov("P0" if P.ndim < 3 else f"P0[{i}]", Pi, nx)


def _prior(nx: int, x0, P0):
    """x0, P0 as arrays of one float dtype, checked (shapes always, values when concrete)."""
    if np.ndim(x0) != 1 or np.shape(x0)[0] != nx:
        raise ValueError(f"x0: expected shape ({nx},), got shape {np.shape(x0)}")
    if np.shape(P0) not in ((nx, nx), (nx,)):
        raise ValueError(
            f"P0: expected shape ({nx}, {nx}) or ({nx},) variances, got shape {np.shape(P0)}"
        )
    validate_prior(nx, x0, P0)
    x0, P0 = jnp.asarray(x0), jnp.asarray(P0)
    dtype = jnp.result_type(x0.dtype, P0.dtype)
    if not jnp.issubdtype(dtype, jnp.floating):
        dtype = jnp.asarray(0.0).dtype  # the default float (float64 under vehjax)
    if P0.ndim == 1:
        P0 = jnp.diag(P0)
    return x0.astype(dtype), P0.astype(dtype)


def _theta(model, theta0, dtype):
    if theta0 is None:
        theta0 = model.theta
    if np.shape(theta0) != (model.n_params,):
        raise ValueError(
            f"theta0: expected shape ({model.n_params},) for parameters {model.param_names}, "
            f"got shape {np.shape(theta0)}"
        )
    return jnp.asarray(theta0).astype(dtype)


def _check_model(model):
    for attr in ("transition", "observe", "theta", "nx", "ny", "n_params"):
        if not hasattr(model, attr):
            raise ValueError(
                f"model: expected a vehjax model with .{attr}, got {type(model).__name__}"
            )
    return model.nx, model.ny


def _prior_init(model, sqrt: bool):
    nx = model.nx

    def init(x0, P0, theta0=None, P_theta0=None, key=None):
        """State from the prior x0 (nx,), P0 (nx, nx) or (nx,); theta0 (np,) or model.theta."""
        x0, P0 = _prior(nx, x0, P0)
        theta = _theta(model, theta0, x0.dtype)
        if sqrt:
            return SqrtGaussianState(x0, jnp.linalg.cholesky(P0), theta)
        return GaussianState(x0, P0, theta)

    return init


# --------------------------------------------------------------------------------------------
# shared pieces


def _chol(A):
    """Lower Cholesky factor, in numpy for a constant, in jax for a traced matrix."""
    return np.linalg.cholesky(A) if isinstance(A, np.ndarray) else jnp.linalg.cholesky(A)


def _sym(A):
    return 0.5 * (A + A.T)


def _cast(a, dtype):
    return jnp.asarray(a).astype(dtype)


def _observed(y, dtype):
    """Mask of observed components, the same mask as float, and y with NaNs replaced by 0."""
    m = jnp.isfinite(y)
    return m, m.astype(dtype), jnp.where(m, y, 0)


def step_output(x, P, loglik, nis, n_obs) -> StepOutput:
    """StepOutput of a state-only filter (params of shape (0,), params_cov (0, 0))."""
    return StepOutput(
        mean=x,
        cov=P,
        loglik=loglik,
        nis=nis,
        n_obs=n_obs,
        params=jnp.zeros((0,), x.dtype),
        params_cov=jnp.zeros((0, 0), x.dtype),
    )


def masked_update(x_pred, P_pred, y, y_hat, S, C) -> UpdateResult:
    """Kalman update with the NaN components of ``y`` treated as missing.

    Args:
        x_pred: predicted mean, (nx,).
        P_pred: predicted covariance, (nx, nx).
        y: measurement, (ny,), NaN where missing.
        y_hat: predicted measurement, (ny,).
        S: innovation covariance including the measurement noise, (ny, ny).
        C: cross-covariance of state and measurement, (nx, ny).

    With the observation mask M (diagonal 0/1), the update uses the innovation M e, the
    covariance M S M + (I - M) and the cross-covariance C M: exactly the Kalman update on the
    observed subset, in fixed shapes. Everything goes through the Cholesky factor of S.
    """
    dtype = x_pred.dtype
    m, mf, y0 = _observed(y, dtype)
    e = jnp.where(m, y0 - y_hat, 0)
    Sm = S * (mf[:, None] * mf[None, :]) + jnp.diag(1 - mf)
    Ls = cholesky(Sm)  # symmetrises
    w = solve_lower(Ls, e)
    W = solve_lower(Ls, (C * mf[None, :]).T)  # Ls^-1 C^T, so K = W^T Ls^-1
    x = x_pred + W.T @ w
    P = _sym(P_pred - W.T @ W)
    n_obs = jnp.sum(m).astype(jnp.int32)
    nis = w @ w
    logdet = 2.0 * jnp.sum(jnp.log(jnp.diagonal(Ls)))
    loglik = -0.5 * (nis + logdet + n_obs.astype(dtype) * _LOG_2PI)
    return UpdateResult(x, P, loglik, nis, n_obs, e)


def _in_dtype(fn):
    """``fn`` with its output cast to the dtype of ``x`` (a model with float64 constants
    must not silently turn a float32 filter into a float64 one)."""
    return lambda x, u, theta: jnp.asarray(fn(x, u, theta)).astype(x.dtype)


def _vmap_model(fn):
    return jax.vmap(_in_dtype(fn), in_axes=(0, None, None))


# --------------------------------------------------------------------------------------------
# EKF


def ekf(model, Q, R) -> Estimator:
    """Extended Kalman filter, Jacobians of transition and observe by ``jax.jacfwd``.

    Args:
        model: a vehjax model (nx states, ny outputs).
        Q: process noise covariance, (nx, nx), or (nx,) variances; in state units squared.
        R: measurement noise covariance, (ny, ny), or (ny,) variances; in output units squared.

    Returns:
        ``Estimator`` with state :class:`GaussianState` (x, P, theta).
    """
    nx, ny = _check_model(model)
    Qn, Rn = check_cov("Q", Q, nx), check_cov("R", R, ny)
    f, h = _in_dtype(model.transition), _in_dtype(model.observe)
    F_of, H_of = jax.jacfwd(f), jax.jacfwd(h)

    def step(state, y, u):
        x, P, theta = state
        dt = x.dtype
        y, u = _cast(y, dt), _cast(u, dt)
        F = F_of(x, u, theta)
        x_pred = f(x, u, theta)
        P_pred = _sym(F @ P @ F.T + jnp.asarray(Qn, dt))
        H = H_of(x_pred, u, theta)
        y_hat = h(x_pred, u, theta)
        C = P_pred @ H.T
        r = masked_update(x_pred, P_pred, y, y_hat, H @ C + jnp.asarray(Rn, dt), C)
        return GaussianState(r.x, r.P, theta), step_output(r.x, r.P, r.loglik, r.nis, r.n_obs)

    return Estimator(init=_prior_init(model, False), step=step, nx=nx, name="EKF")


# --------------------------------------------------------------------------------------------
# UKF / CKF


def _sigma_filter(model, Q, R, rule: SigmaRule, sqrt: bool, name: str) -> Estimator:
    nx, ny = _check_model(model)
    Qn, Rn = check_cov("Q", Q, nx), check_cov("R", R, ny)
    f, h = _vmap_model(model.transition), _vmap_model(model.observe)

    if not sqrt:

        def step(state, y, u):
            x, P, theta = state
            dt = x.dtype
            y, u = _cast(y, dt), _cast(u, dt)
            Xf = f(sigma_points(x, cholesky(P), rule), u, theta)
            x_pred, P_pred = unscented_transform(Xf, rule, jnp.asarray(Qn, dt))
            X = sigma_points(x_pred, cholesky(P_pred), rule)
            Z = h(X, u, theta)
            y_hat, S = unscented_transform(Z, rule, jnp.asarray(Rn, dt))
            C = cross_covariance(X, x_pred, Z, y_hat, rule)
            r = masked_update(x_pred, P_pred, y, y_hat, S, C)
            return GaussianState(r.x, r.P, theta), step_output(r.x, r.P, r.loglik, r.nis, r.n_obs)

        small = max(nx, ny) <= _runs_last.MAX_DIM
        if small and isinstance(Qn, np.ndarray) and isinstance(Rn, np.ndarray):
            f1, h1 = _in_dtype(model.transition), _in_dtype(model.observe)

            def batch(per_run_inputs: bool, dtype, default_theta: bool):
                # every run at model.theta (init's default): a constant of the compiled step
                const = default_theta and not _is_tracer(model.theta)
                return _runs_last.sigma_step(
                    f1, h1, Qn, Rn, rule, nu=model.nu, n_params=model.n_params,
                    per_run_inputs=per_run_inputs, dtype=dtype,
                    theta=np.asarray(model.theta) if const else None,
                )

            step.runs_last = batch  # vehjax.run's batched form of this very step

        return Estimator(init=_prior_init(model, False), step=step, nx=nx, name=name)

    LQn, LRn = _chol(Qn), _chol(Rn)

    def sqrt_step(state, y, u):
        x, L, theta = state
        dt = x.dtype
        y, u = _cast(y, dt), _cast(u, dt)
        Xf = f(sigma_points(x, L, rule), u, theta)
        x_pred, L_pred = sqrt_unscented_transform(Xf, rule, jnp.asarray(LQn, dt))
        X = sigma_points(x_pred, L_pred, rule)
        Z = h(X, u, theta)
        y_hat = jnp.asarray(rule.wm, dt) @ Z
        x_new, L_new, loglik, nis, n_obs = _sqrt_masked_update(
            x_pred, X, y, y_hat, Z, jnp.asarray(LRn, dt), rule
        )
        out = step_output(x_new, L_new @ L_new.T, loglik, nis, n_obs)
        return SqrtGaussianState(x_new, L_new, theta), out

    return Estimator(init=_prior_init(model, True), step=sqrt_step, nx=nx, name="SR-" + name)


def _sqrt_masked_update(x_pred, X, y, y_hat, Z, LR, rule: SigmaRule):
    """Square-root update: one QR of the joint (measurement, state) deviations.

    The lower factor of the joint covariance [[S, C^T], [C, P-]] is [[L11, 0], [L21, L22]]:
    L11 is the factor of S, the gain is L21 L11^-1 and L22 the factor of the updated covariance.
    Missing components are masked as in :func:`masked_update`.
    """
    dtype = x_pred.dtype
    ny, nx = y.shape[0], x_pred.shape[0]
    m, mf, y0 = _observed(y, dtype)
    e = jnp.where(m, y0 - y_hat, 0)
    dev = jnp.concatenate([(Z - y_hat[None, :]) * mf[None, :], X - x_pred[None, :]], axis=1)
    noise = jnp.concatenate(
        [
            jnp.concatenate([LR * mf[:, None], jnp.diag(1 - mf)], axis=1),
            jnp.zeros((nx, 2 * ny), dtype),
        ]
    )
    Lj = weighted_sqrt_factor(dev, rule, noise)
    L11, L21, L22 = Lj[:ny, :ny], Lj[ny:, :ny], Lj[ny:, ny:]
    w = solve_lower(L11, e)
    n_obs = jnp.sum(m).astype(jnp.int32)
    nis = w @ w
    logdet = 2.0 * jnp.sum(jnp.log(jnp.diagonal(L11)))
    loglik = -0.5 * (nis + logdet + n_obs.astype(dtype) * _LOG_2PI)
    return x_pred + L21 @ w, L22, loglik, nis, n_obs


def ukf(
    model, Q, R, alpha: float = 1.0, beta: float = 2.0, kappa: float = 0.0, sqrt: bool = False
) -> Estimator:
    """Unscented Kalman filter with the scaled sigma points of Dutta et al. 2019 eq. 14-19.

    Args:
        model: a vehjax model (nx states, ny outputs).
        Q: process noise covariance, (nx, nx), or (nx,) variances; in state units squared.
        R: measurement noise covariance, (ny, ny), or (ny,) variances; in output units squared.
        alpha, beta, kappa: sigma-point scaling (see :func:`vehjax.filters.sigma.unscented_rule`).
            The defaults alpha = 1, beta = 2, kappa = 0 put the points at +-sqrt(nx) standard
            deviations with non-negative weights, which keeps P positive definite on strongly
            nonlinear vehicle models; small alpha (1e-3) gives a large negative centre weight.
        sqrt: propagate the Cholesky factor of P by QR (square-root UKF). A negative centre
            weight is handled by a rank-1 Cholesky downdate.

    Returns:
        ``Estimator`` with state :class:`GaussianState` (x, P, theta), or
        :class:`SqrtGaussianState` (x, L, theta) when ``sqrt``.
    """
    nx, _ = _check_model(model)
    return _sigma_filter(model, Q, R, unscented_rule(nx, alpha, beta, kappa), bool(sqrt), "UKF")


def ckf(model, Q, R, sqrt: bool = False) -> Estimator:
    """Cubature Kalman filter: third-degree spherical-radial rule, 2 nx equally weighted points.

    Args:
        model: a vehjax model (nx states, ny outputs).
        Q: process noise covariance, (nx, nx), or (nx,) variances; in state units squared.
        R: measurement noise covariance, (ny, ny), or (ny,) variances; in output units squared.
        sqrt: propagate the Cholesky factor of P by QR (square-root CKF, Arasaratnam & Haykin
            2009).

    Returns:
        ``Estimator`` with state :class:`GaussianState` (x, P, theta), or
        :class:`SqrtGaussianState` (x, L, theta) when ``sqrt``.
    """
    nx, _ = _check_model(model)
    return _sigma_filter(model, Q, R, cubature_rule(nx), bool(sqrt), "CKF")
