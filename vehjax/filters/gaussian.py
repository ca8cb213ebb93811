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

The algebra is the one Gaussian core: :func:`vehjax.filters.sigma.predict` /
:func:`~vehjax.filters.sigma.update` and their square-root forms, and the Jacobian forms of
:mod:`vehjax.filters.kalman`. This file holds what is particular to these filters: their state,
their prior, and which of them get the runs-last form of :mod:`vehjax.filters.runs_last`.

Missing measurements: components of ``y_t`` that are NaN (or +-inf) are not observed; the update
uses only the observed ones (exactly, by masking) and ``loglik``/``nis``/``n_obs`` count only
them. A step with every component missing is a pure prediction.

The state dtype follows ``x0``/``P0``: float32 priors run the whole filter in float32 (theta,
Q, R and the inputs are cast to it).
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import validation
from . import input_noise as _inoise
from . import runs_last
from . import sigma
from ._model import (
    cast_yu,
    chol_const,
    check_model,
    in_dtype,
    model_dims,
    model_theta,
    per_point,
    point_fns,
    prior,
    validate_prior,
)
from .base import Backward, Dims, Estimator, GaussianSmoother, Runtime, state_output
from ..lib.linalg import UNROLL_MAX
from .kalman import (
    UpdateResult,
    cov_entries,
    jacobian_entries,
    linearized_measure,
    linearized_predict,
    masked_update,
    masked_update_entries,
    measure_entries,
    predict_entries,
)
from .sigma import SigmaPoints, SigmaRule, cubature_rule

__all__ = ["GaussianState", "SqrtGaussianState", "ekf", "ukf", "ckf", "masked_update",
           "UpdateResult", "validate_prior", "check_cov"]

check_cov = validation.cov


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


def _prior_init(model, sqrt: bool):
    nx = len(model.state_names)

    def init(x0, P0, theta0=None, P_theta0=None, key=None):
        """State from the prior x0 (nx,), P0 (nx, nx) or (nx,); theta0 (np,) or model.theta."""
        x0, P0 = prior(nx, x0, P0)
        theta = model_theta(model, theta0, x0.dtype)
        if sqrt:
            return SqrtGaussianState(x0, jnp.linalg.cholesky(P0), theta)
        return GaussianState(x0, P0, theta)

    return init


# --------------------------------------------------------------------------------------------
# EKF


def ekf(model, Q, R, *, input_noise=None) -> Estimator:
    """Extended Kalman filter, Jacobians of transition and observe by ``jax.jacfwd``; the
    covariance update in Joseph form (stays positive definite for very wide priors).

    :func:`vehjax.run` runs models with at most 8 states and outputs and constant ``Q``, ``R``
    through the same step written for all runs at once (:func:`vehjax.filters.runs_last.ekf_step`,
    results equal to rounding).

    Args:
        model: a vehjax model (nx states, ny outputs).
        Q: process noise covariance, (nx, nx), or (nx,) variances; in state units squared.
            Positive semi-definite: zero variances for noise-free states are allowed.
        R: measurement noise covariance, (ny, ny), or (ny,) variances; in output units squared.
        input_noise: noise entering through the inputs (:mod:`vehjax.filters.input_noise`):
            ``{input name: std}`` in the input's units (rad, m/s, ...) or an (nu, nu)
            covariance in input units squared; None (default) for none. The step's process
            noise becomes ``Q + G Sigma_u G^T``, ``G = df/du`` at the filtered mean by
            ``jax.jacfwd``; Q may then be zero. Such a filter has no runs-last form
            (``batch=None``): :func:`vehjax.run` vmaps this per-run step.

    Returns:
        ``Estimator`` with state :class:`GaussianState` (x, P, theta).
    """
    nx, ny = check_model(model)
    Qn, Rn = validation.cov("Q", Q, nx, allow_psd=True), validation.cov("R", R, ny)
    Lu = _inoise.input_factor(input_noise, model.input_names)
    tr = in_dtype(per_point(model)[0])

    def step(state, y, u):
        x, P, theta = state
        dt = x.dtype
        y, u = cast_yu(y, u, dt)
        f, h = point_fns(model, u, theta)
        if max(nx, ny) <= UNROLL_MAX:  # entry by entry (vehjax.filters.kalman)
            r = _ekf_entries(x, P, y, u, theta, f, h, tr, Qn, Rn, Lu)
        else:
            Qd = jnp.asarray(Qn, dt)
            if Lu is not None:
                Qd = Qd + _inoise.linearized_input_noise(lambda v, w: tr(v, w, theta), x, u, Lu)
            x_pred, P_pred, _ = linearized_predict(x, P, f, Qd)
            Rd = jnp.asarray(Rn, dt)
            m = linearized_measure(x_pred, P_pred, h, Rd)
            # Joseph form: with a very wide prior (P0 ~ 1e16) P- - K S K^T cancels to rounding
            r = masked_update(x_pred, P_pred, y, m.y_hat, m.S, m.C, joseph=(m.H, Rd))
        return GaussianState(r.x, r.P, theta), state_output(r.x, r.P, r.loglik, r.nis, r.n_obs)

    batch = None if Lu is not None else _runs_last_form(model, Qn, Rn, runs_last.ekf_step)
    return Estimator(
        init=_prior_init(model, False),
        step=step,
        name="EKF",
        dims=Dims(nx=nx, **model_dims(model)),
        runtime=Runtime(batch=batch, workload="small_dense"),
        backward=Backward(smoother=_ekf_smoother(model, Qn, Rn, Lu, tr)),
    )


def _ekf_entries(x, P, y, u, theta, f, h, tr, Qn, Rn, Lu):
    """One EKF step of a small model entry by entry (:mod:`vehjax.filters.kalman`'s
    ``*_entries``): the Jacobians of the transition along the state and along the k
    standardised input noises (``G Lu``) from one forward-mode pass over ``(x, e)``, ``e = 0``
    (k), then ``P- = F P F^T + Q + (G Lu)(G Lu)^T``, the measurement Jacobian at the predicted
    mean, the Joseph-form masked update. x (nx,), P (nx, nx), y (ny,), u (nu,) arrays of the
    filter's dtype; f, h the model at (u, theta); tr the transition ``tr(x, u, theta)``; Qn, Rn
    the noise covariances (numpy constants or traced); Lu (nu, k) or None.
    Returns :class:`vehjax.filters.kalman.UpdateResult`."""
    nx, dt = x.shape[0], x.dtype
    if Lu is None:
        xp, J = jacobian_entries(f, x)
        B = None
    else:
        Lw = jnp.asarray(Lu, dt)
        xp, J = jacobian_entries(lambda z: tr(z[:nx], u + Lw @ z[nx:], theta),
                                 jnp.concatenate([x, jnp.zeros((Lw.shape[1],), dt)]))
        B = [row[nx:] for row in J]
    F = [row[:nx] for row in J]
    Pe = [[P[i, j] for j in range(nx)] for i in range(nx)]
    Pp = predict_entries(F, Pe, cov_entries(Qn, dt), B)
    yh, H = jacobian_entries(h, jnp.stack(xp))
    Rm = cov_entries(Rn, dt)
    C, S = measure_entries(Pp, H, Rm)
    return masked_update_entries(xp, Pp, y, yh, S, C, joseph=(H, Rm))


def _sigma_entries(x, P, y, f, h, Qn, Rn, rule: SigmaRule):
    """One UKF/CKF step of a small model entry by entry: the moments of
    :func:`vehjax.filters.sigma.step_moments_entries` (the runs-last step's,
    :func:`vehjax.filters.runs_last.sigma_step`), the model evaluated at the points by one
    ``vmap``, then the masked update (:func:`vehjax.filters.kalman.masked_update_entries`).
    x (nx,), P (nx, nx), y (ny,) arrays of the filter's dtype; f, h the model at (u, theta);
    Qn, Rn numpy constants. Returns :class:`vehjax.filters.kalman.UpdateResult`."""
    nx, dt = x.shape[0], x.dtype

    def images(fn):
        def at(points):
            Y = jax.vmap(fn)(jnp.stack([jnp.stack(p) for p in points]))
            return [[Y[k, i] for i in range(Y.shape[1])] for k in range(Y.shape[0])]
        return at

    # the noise's entries as arrays of the filter's dtype, as the runs-last step takes them
    m = sigma.step_moments_entries([x[i] for i in range(nx)],
                                   [[P[i, j] for j in range(nx)] for i in range(nx)],
                                   images(f), images(h), cov_entries(jnp.asarray(Qn, dt)),
                                   cov_entries(jnp.asarray(Rn, dt)), rule)
    return masked_update_entries(m.xp, m.Pp, y, m.yh, m.S, m.C)


def _runs_last_form(model, Qn, Rn, build):
    """``Estimator.batch`` from a builder of :mod:`vehjax.filters.runs_last` (``sigma_step``,
    ``ekf_step``), for models with at most ``runs_last.MAX_DIM`` states and outputs and constant
    (numpy) noise covariances; None otherwise (``run`` then vmaps the per-run step)."""
    small = max(Qn.shape[0], Rn.shape[0]) <= runs_last.MAX_DIM
    if not (small and isinstance(Qn, np.ndarray) and isinstance(Rn, np.ndarray)):
        return None
    f1, h1 = in_dtype(model.transition), in_dtype(model.observe)

    def batch_form(per_run_inputs: bool, dtype, default_theta: bool):
        # every run at model.theta (init's default): a constant of the compiled step
        const = default_theta and not validation.is_tracer(model.theta)
        return build(f1, h1, Qn, Rn, nu=len(model.input_names),
                     n_params=len(model.param_names), per_run_inputs=per_run_inputs, dtype=dtype,
                     theta=np.asarray(model.theta) if const else None)

    return batch_form


# --------------------------------------------------------------------------------------------
# UKF / CKF


def _sigma_filter(model, Q, R, rule: SigmaRule, sqrt: bool, name: str, input_noise=None,
                  make_rule=None) -> Estimator:
    """The UKF/CKF and their square-root forms with ``rule`` (nx dimensions); with
    ``input_noise`` the prediction uses ``make_rule(nx + k)`` on the state augmented with the
    k standardised input-noise components (:mod:`vehjax.filters.input_noise`)."""
    nx, ny = check_model(model)
    Qn, Rn = validation.cov("Q", Q, nx, allow_psd=True), validation.cov("R", R, ny)
    Lu = _inoise.input_factor(input_noise, model.input_names)
    tr = in_dtype(per_point(model)[0])
    rule_a = None if Lu is None else make_rule(nx + Lu.shape[1])

    def predict(x, P, f, u, theta, Qd):
        if Lu is None:
            return sigma.predict(rule, x, P, f, Qd)
        return _inoise.sigma_predict(rule_a, x, P, lambda v, w: tr(v, w, theta), u, Lu, Qd)

    def sqrt_predict(x, L, f, u, theta, LQd):
        if Lu is None:
            return sigma.sqrt_predict(rule, x, L, f, LQd)
        return _inoise.sqrt_sigma_predict(rule_a, x, L, lambda v, w: tr(v, w, theta), u, Lu,
                                          LQd)

    if not sqrt:

        def step(state, y, u):
            x, P, theta = state
            dt = x.dtype
            y, u = cast_yu(y, u, dt)
            f, h = point_fns(model, u, theta)
            if Lu is None and max(nx, ny) <= UNROLL_MAX:  # entry by entry (vehjax.filters.sigma)
                r = _sigma_entries(x, P, y, f, h, Qn, Rn, rule)
            else:
                x_pred, P_pred = predict(x, P, f, u, theta, jnp.asarray(Qn, dt))
                r = sigma.update(rule, x_pred, P_pred, h, y, jnp.asarray(Rn, dt))
            return GaussianState(r.x, r.P, theta), state_output(r.x, r.P, r.loglik, r.nis, r.n_obs)

        batch = None if Lu is not None else _runs_last_form(
            model, Qn, Rn, partial(runs_last.sigma_step, rule=rule))

        return Estimator(
            init=_prior_init(model, False),
            step=step,
            name=name,
            dims=Dims(nx=nx, **model_dims(model)),
            runtime=Runtime(batch=batch, workload="small_dense"),
            backward=Backward(smoother=_sigma_smoother(model, Qn, Rn, rule, rule_a, Lu, tr, False)),
        )

    LQn, LRn = chol_const(Qn), chol_const(Rn)

    def sqrt_step(state, y, u):
        x, L, theta = state
        dt = x.dtype
        y, u = cast_yu(y, u, dt)
        f, h = point_fns(model, u, theta)
        x_pred, L_pred = sqrt_predict(x, L, f, u, theta, jnp.asarray(LQn, dt))
        x_new, L_new, loglik, nis, n_obs = sigma.sqrt_update(
            rule, x_pred, L_pred, h, y, jnp.asarray(LRn, dt))
        out = state_output(x_new, L_new @ L_new.T, loglik, nis, n_obs)
        return SqrtGaussianState(x_new, L_new, theta), out

    return Estimator(
        init=_prior_init(model, True),
        step=sqrt_step,
        name="SR-" + name,
        dims=Dims(nx=nx, **model_dims(model)),
        runtime=Runtime(workload="small_dense"),
        backward=Backward(smoother=_sigma_smoother(model, Qn, Rn, rule, rule_a, Lu, tr, True)),
    )


def ukf(
    model, Q, R, *, points: SigmaPoints = SigmaPoints(), sqrt: bool = False, input_noise=None,
) -> Estimator:
    """Unscented Kalman filter with the scaled sigma points of Dutta et al. 2019 eq. 14-19.

    Args:
        model: a vehjax model (nx states, ny outputs).
        Q: process noise covariance, (nx, nx), or (nx,) variances; in state units squared.
            Positive semi-definite: zero variances for noise-free states are allowed.
        R: measurement noise covariance, (ny, ny), or (ny,) variances; in output units squared.
        points: the sigma-point scaling, :class:`~vehjax.filters.SigmaPoints` (alpha, beta,
            kappa; see :func:`vehjax.filters.sigma.unscented_rule`). The defaults alpha = 1,
            beta = 2, kappa = 0 put the points at +-sqrt(nx) standard deviations with
            non-negative weights, which keeps P positive definite on strongly nonlinear vehicle
            models; small alpha (1e-3) gives a large negative centre weight.
        sqrt: propagate the Cholesky factor of P by QR (square-root UKF). A negative centre
            weight is handled by a rank-1 Cholesky downdate. Use it for priors far wider than
            the measurement noise (P0 ~ 1e12 R and more): the plain form's P- - K S K^T then
            cancels to rounding noise and the run is flagged diverged.
        input_noise: noise entering through the inputs (:mod:`vehjax.filters.input_noise`):
            ``{input name: std}`` in the input's units or an (nu, nu) covariance in input units
            squared; None (default) for none. The prediction's sigma points are those of the
            state augmented with the k noisy input components (the rule in nx + k dimensions,
            same ``points``); Q may then be zero. No runs-last form (``batch=None``).

    Returns:
        ``Estimator`` with state :class:`GaussianState` (x, P, theta), or
        :class:`SqrtGaussianState` (x, L, theta) when ``sqrt``.
    """
    nx, _ = check_model(model)
    points = validation.record("points", points, SigmaPoints)
    sqrt = validation.flag("sqrt", sqrt)
    return _sigma_filter(model, Q, R, points.rule(nx), sqrt, "UKF", input_noise, points.rule)


def ckf(model, Q, R, *, sqrt: bool = False, input_noise=None) -> Estimator:
    """Cubature Kalman filter: third-degree spherical-radial rule, 2 nx equally weighted points.

    Args:
        model: a vehjax model (nx states, ny outputs).
        Q: process noise covariance, (nx, nx), or (nx,) variances; in state units squared.
            Positive semi-definite: zero variances for noise-free states are allowed.
        R: measurement noise covariance, (ny, ny), or (ny,) variances; in output units squared.
        sqrt: propagate the Cholesky factor of P by QR (square-root CKF, Arasaratnam & Haykin
            2009).
        input_noise: as for :func:`ukf`: the prediction's cubature points are those of the
            state augmented with the k noisy input components (2 (nx + k) points).

    Returns:
        ``Estimator`` with state :class:`GaussianState` (x, P, theta), or
        :class:`SqrtGaussianState` (x, L, theta) when ``sqrt``.
    """
    nx, _ = check_model(model)
    sqrt = validation.flag("sqrt", sqrt)
    return _sigma_filter(model, Q, R, cubature_rule(nx), sqrt, "CKF", input_noise,
                         cubature_rule)


# --------------------------------------------------------------------------------------------
# Estimator.smoother: the steps' own moments, for vehjax.smooth


def _split(state):
    """(mean, covariance or its factor, theta) of a :class:`GaussianState` / :class:`SqrtGaussianState`."""
    return state[0], state[1], state[2]


def _ekf_smoother(model, Qn, Rn, Lu, tr) -> GaussianSmoother:
    """``Estimator.smoother`` of :func:`ekf`: the step's linearised prediction (with its input
    noise) and measurement; ``C = P F^T``."""

    def predict(x, P, u, theta):
        dt = x.dtype
        u = jnp.asarray(u).astype(dt)
        f, _ = point_fns(model, u, theta)
        Qd = jnp.asarray(Qn, dt)
        if Lu is not None:
            Qd = Qd + _inoise.linearized_input_noise(lambda v, w: tr(v, w, theta), x, u, Lu)
        x_pred, P_pred, F = linearized_predict(x, P, f, Qd)
        return x_pred, P_pred, P @ F.T

    def measure(x, P, u, theta):
        u = jnp.asarray(u).astype(x.dtype)
        return linearized_measure(x, P, point_fns(model, u, theta)[1], jnp.asarray(Rn, x.dtype))

    return GaussianSmoother(split=_split, predict=predict, measure=measure, taylor=True)


def _sigma_smoother(model, Qn, Rn, rule, rule_a, Lu, tr, sqrt: bool) -> GaussianSmoother:
    """``Estimator.smoother`` of the UKF/CKF (``sqrt``: their square-root forms): the step's
    sigma points (augmented with the input noise when there is some) and their images, with
    the cross-covariance C = Cov(x_t, x_{t+1}); the square-root form one QR of the joint
    deviations (:func:`vehjax.filters.sigma.sqrt_moments_joint`)."""
    nx = len(model.state_names)

    def points(x, L, u, theta):
        if Lu is None:
            X = sigma.sigma_points(x, L, rule)
            return X, sigma._through(point_fns(model, u, theta)[0], X), rule
        A = _inoise.augmented_points(rule_a, x, L, Lu.shape[1])
        return A[:, :nx], _inoise.through_inputs(lambda v, w: tr(v, w, theta), u, Lu, A, nx), rule_a

    def predict(x, S, u, theta):
        dt = x.dtype
        u = jnp.asarray(u).astype(dt)
        if sqrt:
            X, Y, r = points(x, S, u, theta)
            return sigma.sqrt_moments_joint(r, X, x, Y, jnp.asarray(chol_const(Qn), dt))
        X, Y, r = points(x, sigma.cholesky(S), u, theta)
        return sigma.moments_cross(r, X, x, Y, jnp.asarray(Qn, dt))

    def measure(x, S, u, theta):
        dt = x.dtype
        u = jnp.asarray(u).astype(dt)
        X = sigma.sigma_points(x, S if sqrt else sigma.cholesky(S), rule)
        Z = sigma._through(point_fns(model, u, theta)[1], X)
        y_hat, Sy = sigma.unscented_transform(Z, rule, jnp.asarray(Rn, dt))
        return sigma.Measurement(y_hat, Sy, sigma.cross_covariance(X, x, Z, y_hat, rule))

    return GaussianSmoother(split=_split, predict=predict, measure=measure, sqrt=sqrt)
