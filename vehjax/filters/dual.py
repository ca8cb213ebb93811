"""Dual and joint EKF/UKF: the state and a chosen subset of the model parameters, together.

Four builders, each returning an :class:`~vehjax.filters.base.Estimator` whose ``params`` are the
parameters named in ``estimate`` (the others stay at ``model.theta``):

* :func:`dual_ekf` - Dutta et al. 2019, Algorithm 1 (after Wan & Nelson 2001): two EKFs, one for
  the state and one for the parameters, run one after the other in each step.
* :func:`dual_ukf` - Algorithm 2: the same with two separate sets of unscented sigma points.
* :func:`joint_ekf`, :func:`joint_ukf` - one EKF/UKF on the augmented state ``[x; theta]``.

Parameters are random walks, ``theta_t = theta_{t-1} + w``, ``w ~ N(0, Q_theta_t)``, with
``Q_theta_t = gamma^t Q_theta`` (``theta_decay`` = gamma, the paper's R_p <- gamma R_p, which
lets the parameter covariance shrink once the estimate has settled).

One dual step (time convention of :mod:`vehjax.filters.base`; written for theta, run on the
unconstrained coordinate of the parameter domains below)::

    parameter prediction:  th- = th,  Pth- = Pth + Q_theta_t
    state prediction:      x- = f(x, u_t, th-),  P- = G P G^T + Q          (G = df/dx, eq. 11)
    state correction:      y^ = h(x-, u_t, th-), S = H P- H^T + R, x, P updated with y_t
    parameter correction:  Hp = d h(f(x_{t-1}(th), u_t, th), u_t, th) / d th   (eq. 13)
                           Sp = Hp Pth- Hp^T + S,  th, Pth updated with the same innovation
    recurrent derivative:  D- = G D + df/dth,  D = D- - K Hp   (K the state gain)
    Q_theta_{t+1} = gamma Q_theta_t

The recurrent derivative (``recurrent=True``, the default; Wan & Nelson 2001, the paper's [12]):
the previous filtered state x_{t-1} was itself computed with the parameters, so the parameter
Jacobian is taken through the state filter's recursion, x_{t-1}(th) = x_{t-1} + D (th - th-),
D = d x_{t-1} / d th carried in :class:`DualState` (gain held fixed, as Wan & Nelson; the dual
UKF differentiates its whole state step with ``jax.jacfwd`` and propagates its parameter sigma
points from x_{t-1} + D (th_i - th-)). ``recurrent=False`` is Algorithm 1/2 as printed, which
treats x_{t-1} as fixed: the parameter then only explains the one-step part of the innovation,
whereas a parameter error mostly shows as a slowly built-up state error that the state filter
has already absorbed, so the parameter learns late and ends biased. Measured on
the dutta2019 kinematic stage, the recurrent dual filters end with the joint EKF's bias and
error (the printed ones' lf bias 3 times theirs); what remains, inherent to dual estimation,
is a slower start: the two filters do not share the state-parameter cross-covariance until D
has built up (docs/dual.md has the table and a scalar example).

Reading of the transcription, where it is garbled or loose:

* Eq. 13 writes ``Hp = H_s df/dtheta`` evaluated at the predicted state; the parameter gain must
  relate the innovation ``y_t - h(f(x_{t-1}, u_t, theta))`` to theta, so the Jacobian is taken of
  the one-step prediction from the previous filtered state, total derivative through f and h
  (equal to ``H_s df/dtheta`` for the paper's ``H_s = I``).
* Algorithm 2 omits ``+ R_p`` in the parameter prediction, yet decays R_p at its end; it is added
  as in Algorithm 1. Its parameter correction propagates each parameter sigma point through the
  model from the previous state estimate (``Z_p = nextState(chi_p, mu_s_{t-1}, u_t)``); the
  measurement function is applied to those points (the paper measures every state).
* Both algorithms write the parameter innovation covariance as ``Hp Pth Hp^T + Q_t`` (measurement
  noise only). The innovation also carries the state's prediction uncertainty, so by default it
  is ``Hp Pth Hp^T + S`` with S the state filter's innovation covariance (the law of total
  variance: Cov_theta[E(y|theta)] + E_theta[Cov(y|theta)]). ``param_innovation="measurement"``
  gives the paper's form as printed, which is overconfident when the state is uncertain.

Parameter domains (``bounds``): each estimated parameter theta lives in (low, high), by default
(0, inf) for a parameter whose nominal value (``model.theta``) is positive (masses, lengths,
stiffnesses) and unbounded otherwise. The filters estimate an unconstrained coordinate s instead
of theta (:mod:`vehjax.lib.transforms`): ``theta = c s`` unbounded, ``low + c exp(s)``,
``high - c exp(s)`` one-sided, ``low + (high - low) sigmoid(s)`` two-sided, with c the parameter's
``theta_scale``. Every sigma point and every linearisation point is mapped to theta before the
model is called, so the model never sees a parameter outside its domain. In and out of the
filter, in physical units:

* the prior: ``s0 = g^-1(theta0)``, ``P_s0 = J^-1 P_theta0 J^-T`` (delta method, J = dg/ds at s0,
  diagonal); a ``theta0`` outside (low, high) is a ValueError naming theta0;
* the random walk: ``Q_theta_t`` (physical) enters as ``J^-1 Q_theta_t J^-T`` with J at the
  current estimate (the parameter prediction step), so its physical size is what was asked for
  near the estimate;
* the output: ``params = g(s)``, ``params_cov = J P_s J^T`` with J at s. For the UKFs too the
  estimate is the map of the mean (inside the domain; docs/dual.md says why not the mean of the
  mapped sigma points).

With no finite bound (``bounds={}``, or a parameter whose nominal value is not positive) the map
is ``theta = c s`` and the filters are exactly those above. Parameters of vehicle models differ
in scale by 1e5 (m ~ 1.7e3 kg, cx ~ 1.5e5 N, lf ~ 1.5 m), so c = ``theta_scale`` (default
|model.theta| of each estimated parameter, 1 where that is 0) keeps the unconstrained
coordinates near unit size. EKF covariance updates use the Joseph form; sigma-point updates the
symmetric ``P - K S K^T`` of :func:`~vehjax.filters.gaussian.masked_update`. NaN measurement
components are skipped.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import validation
from . import input_noise as _inoise
from . import sigma
from ..lib.transforms import Transform
from .bounds import check_inside, parse as _parse_bounds
from ..lib.linalg import sym
from .base import (Backward, Dims, Estimator, GaussianSmoother,
    ParamSpec, Runtime, StepOutput, check_estimate)
from ._model import cast_yu, check_model, model_dims, per_point
from ._model import prior as _state_prior
from .kalman import linearized_measure, linearized_predict, masked_update
from .sigma import SigmaPoints

__all__ = ["DualState", "JointState", "dual_ekf", "dual_ukf", "joint_ekf", "joint_ukf"]

_PARAM_INNOVATIONS = ("predictive", "measurement")


class DualState(NamedTuple):
    """State of :func:`dual_ekf` and :func:`dual_ukf`.

    Attributes:
        x: filtered state mean, (nx,), state units.
        P: its covariance, (nx, nx).
        z: unconstrained coordinates s of the estimated parameters, (p,), dimensionless (module
            docstring; ``theta / theta_scale`` for an unbounded parameter).
        Pz: covariance of z, (p, p).
        Q_theta: parameter random-walk covariance for the next step, physical units squared,
            (p, p) (mapped to z at each step).
        D: recurrent derivative d x / d z of the filtered state through the state filter's
            recursion, (nx, p) (Wan & Nelson 2001; zeros when ``recurrent=False``).
    """

    x: jnp.ndarray
    P: jnp.ndarray
    z: jnp.ndarray
    Pz: jnp.ndarray
    Q_theta: jnp.ndarray
    D: jnp.ndarray


class JointState(NamedTuple):
    """State of :func:`joint_ekf` and :func:`joint_ukf`.

    Attributes:
        a: augmented mean [x; z], (nx + p,); z the unconstrained coordinates of the parameters
            (see :class:`DualState`).
        Pa: its covariance, (nx + p, nx + p).
        Q_theta: parameter random-walk covariance for the next step, physical units squared,
            (p, p).
    """

    a: jnp.ndarray
    Pa: jnp.ndarray
    Q_theta: jnp.ndarray


class _Setup(NamedTuple):
    nx: int
    ny: int
    names: tuple
    idx: np.ndarray  # (p,) indices of the estimated parameters in model.theta
    tf: Transform  # theta <-> z, with the bounds and theta_scale
    theta_nom: np.ndarray  # (np,) model.theta
    Q: np.ndarray
    R: np.ndarray
    Q_theta: np.ndarray  # (p, p) physical units
    decay: float
    Lu: np.ndarray | None = None  # (nu, k) factor of the input noise covariance, input units


# --------------------------------------------------------------------------------------------
# validation (numpy, before tracing)


def _setup(model, Q, R, Q_theta, estimate, theta_decay, theta_scale, bounds,
           input_noise=None) -> _Setup:
    nx, ny = check_model(model)
    names, idx = check_estimate(model, estimate)
    idx = np.array(idx, dtype=int)
    p = len(names)
    theta_nom = np.asarray(model.theta, dtype=float)

    if theta_scale is None:
        scale = np.abs(theta_nom[idx])
        scale = np.where(scale > 0, scale, 1.0)
    else:
        try:
            scale = np.asarray(theta_scale, dtype=float)
        except (TypeError, ValueError):
            raise ValueError(
                f"theta_scale: expected ({p},) positive numbers, got {theta_scale!r}"
            ) from None
        if scale.ndim == 0:
            scale = np.full(p, float(scale))
        if scale.shape != (p,) or not np.all(np.isfinite(scale)) or np.any(scale <= 0):
            raise ValueError(
                f"theta_scale: expected a positive scalar or ({p},) positive finite numbers for "
                f"{names}, got {theta_scale!r}"
            )

    decay = validation.number("theta_decay", theta_decay, 0.0, 1.0, high_open=False)

    Qn, Rn = validation.cov("Q", Q, nx, allow_psd=True), validation.cov("R", R, ny)
    Qth = validation.cov("Q_theta", Q_theta, p)
    if not isinstance(Qth, np.ndarray):
        raise ValueError("Q_theta: expected a concrete array (it is decayed in the filter state)")
    low, high = _parse_bounds(bounds, names, theta_nom[idx])
    tf = Transform(low, high, scale)
    Lu = _inoise.input_factor(input_noise, model.input_names)
    return _Setup(nx, ny, names, idx, tf, theta_nom, Qn, Rn, Qth, decay, Lu)


def _check_param_innovation(value) -> bool:
    if value not in _PARAM_INNOVATIONS:
        raise ValueError(f"param_innovation: expected one of {_PARAM_INNOVATIONS}, got {value!r}")
    return value == "predictive"


def _prior(cfg: _Setup, x0, P0, theta0, P_theta0):
    """(x0, P0, z0, Pz0) as arrays of one float dtype, checked; z0, Pz0 in unconstrained units
    (z0 = g^-1(theta0), Pz0 by the delta method at z0)."""
    nx, p = cfg.nx, len(cfg.names)
    x0, P0 = _state_prior(nx, x0, P0)
    if theta0 is None:
        theta0 = cfg.theta_nom[cfg.idx]
    if np.shape(theta0) != (p,):
        raise ValueError(
            f"theta0: expected shape ({p},) for the estimated parameters {cfg.names}, "
            f"got shape {np.shape(theta0)}"
        )
    check_inside("theta0", theta0, cfg.tf.low, cfg.tf.high, cfg.names)
    if P_theta0 is None:
        raise ValueError(f"P_theta0: required, the covariance ({p}, {p}) of theta0 for {cfg.names}")
    Pth0 = validation.cov("P_theta0", P_theta0, p)

    dtype = x0.dtype
    z0 = cfg.tf.to_unconstrained(jnp.asarray(theta0).astype(dtype))
    Pz0 = cfg.tf.cov_to_unconstrained(z0, jnp.asarray(Pth0).astype(dtype))
    return x0, P0, z0, Pz0


# --------------------------------------------------------------------------------------------
# shared pieces


def _model_fns(model, cfg: _Setup):
    """f(x, u, z) and h(x, u, z) on unconstrained parameters z (p,), outputs in the dtype of x;
    z is mapped to physical units (inside the bounds) before the model is called."""
    idx = cfg.idx
    tr, ob = per_point(model)  # the step is per run, vmapped over runs

    def full(z):
        th = jnp.asarray(cfg.theta_nom, z.dtype)
        return th.at[idx].set(cfg.tf.to_physical(z))

    def f(x, u, z):
        return jnp.asarray(tr(x, u, full(z))).astype(x.dtype)

    def h(x, u, z):
        return jnp.asarray(ob(x, u, full(z))).astype(x.dtype)

    return f, h


def _out(cfg: _Setup, x, P, z, Pz, r) -> StepOutput:
    """StepOutput with the parameters in physical units: g(z) and J Pz J^T (delta method)."""
    return StepOutput(
        mean=x, cov=P, loglik=r.loglik, nis=r.nis, n_obs=r.n_obs,
        params=cfg.tf.to_physical(z), params_cov=sym(cfg.tf.cov_to_physical(z, Pz)),
        reinit=jnp.zeros((), bool),
    )


def _walk(cfg: _Setup, z, Q_theta):
    """The random-walk covariance Q_theta (physical, (p, p)) in z units at the estimate z."""
    return cfg.tf.cov_to_unconstrained(z, Q_theta)


def _estimator(cfg: _Setup, model, init, step, name: str, smoother=None) -> Estimator:
    return Estimator(
        init=init,
        step=step,
        name=name,
        dims=Dims(nx=cfg.nx, **model_dims(model)),
        params=ParamSpec(names=cfg.names, bounds=cfg.tf.bounds),
        runtime=Runtime(workload="small_dense"),
        backward=Backward(smoother=smoother),
    )


def _dual_init(cfg: _Setup):
    def init(x0, P0, theta0=None, P_theta0=None, key=None):
        """Prior x0 (nx,), P0 (nx, nx) or (nx,); theta0 (p,) (default: nominal), P_theta0 (p, p)
        or (p,) variances, both in physical units of the estimated parameters."""
        x0, P0, z0, Pz0 = _prior(cfg, x0, P0, theta0, P_theta0)
        D0 = jnp.zeros((cfg.nx, z0.shape[0]), x0.dtype)
        return DualState(x0, P0, z0, Pz0, jnp.asarray(cfg.Q_theta, x0.dtype), D0)

    return init


def _joint_init(cfg: _Setup):
    def init(x0, P0, theta0=None, P_theta0=None, key=None):
        """Prior x0 (nx,), P0 (nx, nx) or (nx,); theta0 (p,) (default: nominal), P_theta0 (p, p)
        or (p,) variances, both in physical units; state and parameters start uncorrelated."""
        x0, P0, z0, Pz0 = _prior(cfg, x0, P0, theta0, P_theta0)
        nx, p = cfg.nx, z0.shape[0]
        Pa = jnp.zeros((nx + p, nx + p), x0.dtype).at[:nx, :nx].set(P0).at[nx:, nx:].set(Pz0)
        return JointState(jnp.concatenate([x0, z0]), Pa, jnp.asarray(cfg.Q_theta, x0.dtype))

    return init


_ARGS_DOC = """
    Args:
        model: a vehjax model (nx states, ny outputs, parameters ``model.param_names``).
        Q: state process noise covariance, (nx, nx) or (nx,) variances, state units squared.
        R: measurement noise covariance, (ny, ny) or (ny,) variances, output units squared.
        Q_theta: parameter random-walk covariance per step, (p, p) or (p,) variances, in the
            physical units of the estimated parameters squared.
        estimate: names of the p parameters to estimate (a name or a sequence of names).
        theta_decay: gamma in (0, 1]; Q_theta is multiplied by it after every step.
        theta_scale: scalar or (p,) positive units c of the unconstrained coordinates (module
            docstring; default |model.theta| of each estimated parameter, 1 where that is 0).
            Results do not depend on it beyond rounding.
        bounds: ``{name: (low, high)}`` domains of the estimated parameters in physical units,
            None for an open end (``(0, None)``: positive). Default (None): (0, inf) for every
            estimated parameter whose nominal value ``model.theta`` is positive, unbounded
            otherwise. A dict is the whole specification: parameters it does not name are
            unbounded, so ``bounds={}`` turns the domains off (the filter on theta itself). The
            filter works on an unconstrained coordinate and reports physical units (module
            docstring); ``theta0`` must lie strictly inside.
        input_noise: noise entering through the inputs (:mod:`vehjax.filters.input_noise`):
            ``{input name: std}`` in the input's units or an (nu, nu) covariance in input units
            squared; None (default) for none. The EKF forms add ``G Sigma_u G^T`` (G = df/du by
            ``jax.jacfwd``) to the state's process noise, the UKF forms augment the prediction's
            sigma points with the noisy input components; Q may then be zero.
"""


# --------------------------------------------------------------------------------------------
# dual filters


def dual_ekf(
    model, Q, R, *, Q_theta, estimate, theta_decay: float = 1.0, theta_scale=None,
    param_innovation: str = "predictive", bounds=None, recurrent: bool = True, input_noise=None,
) -> Estimator:
    """Dual extended Kalman filter (Dutta et al. 2019, Algorithm 1), Jacobians by ``jax.jacfwd``.
    {args}
        param_innovation: "predictive" (default): the parameter innovation covariance is
            ``Hp Pth Hp^T + S`` with S the state filter's; "measurement": ``Hp Pth Hp^T + R``
            as Algorithm 1 is printed. See the module docstring.

    Returns:
        ``Estimator`` with state :class:`DualState`; ``param_names`` = ``estimate``;
        ``init(x0, P0, theta0, P_theta0)`` with theta0 (p,), P_theta0 (p, p) in physical units.
    """
    recurrent = validation.flag("recurrent", recurrent)
    cfg = _setup(model, Q, R, Q_theta, estimate, theta_decay, theta_scale, bounds, input_noise)
    predictive = _check_param_innovation(param_innovation)
    f, h = _model_fns(model, cfg)

    def step(state, y, u):
        x, P, z, Pz, Qth, D = state
        dt = x.dtype
        y, u = cast_yu(y, u, dt)
        Qn, Rn = jnp.asarray(cfg.Q, dt), jnp.asarray(cfg.R, dt)
        if cfg.Lu is not None:
            Qn = Qn + _inoise.linearized_input_noise(lambda v, w: f(v, w, z), x, u, cfg.Lu)
        # parameter prediction
        Pz_pred = sym(Pz + _walk(cfg, z, Qth))
        # state prediction and correction
        x_pred, P_pred, G = linearized_predict(x, P, lambda v: f(v, u, z), Qn)
        m = linearized_measure(x_pred, P_pred, lambda v: h(v, u, z), Rn)

        def correct(y_hat):
            return masked_update(x_pred, P_pred, y, y_hat, m.S, m.C, joseph=(m.H, Rn))

        r = correct(m.y_hat)
        # parameter correction: Hp = d y^ / d z, through f (eq. 13) and h; with the recurrent
        # derivative also through the previous filtered state, d x_{t-1} / d z = D
        Fz = jax.jacfwd(lambda v: f(x, u, v))(z)
        Hz = jax.jacfwd(lambda v: h(x_pred, u, v))(z)
        D_pred = G @ D + Fz if recurrent else Fz
        Hp = m.H @ D_pred + Hz
        N = m.S if predictive else Rn
        Cp = Pz_pred @ Hp.T
        Sp = sym(Hp @ Cp + N)
        rp = masked_update(z, Pz_pred, y, m.y_hat, Sp, Cp, joseph=(Hp, N))
        if recurrent:
            # x_t = x- + K (y - y^): d x_t / d z = D- - K Hp (gain held fixed), K = -dx_t/dy^
            dx_dyhat = jax.jacfwd(lambda v: correct(v).x)(m.y_hat)
            D = D_pred + dx_dyhat @ Hp
        new = DualState(r.x, r.P, rp.x, rp.P, cfg.decay * Qth, D)
        return new, _out(cfg, r.x, r.P, rp.x, rp.P, r)

    return _estimator(cfg, model, _dual_init(cfg), step, "DEKF")


def dual_ukf(
    model, Q, R, *, Q_theta, estimate, theta_decay: float = 1.0, theta_scale=None,
    points: SigmaPoints = SigmaPoints(),
    param_innovation: str = "predictive", bounds=None, recurrent: bool = True, input_noise=None,
) -> Estimator:
    """Dual unscented Kalman filter (Dutta et al. 2019, Algorithm 2).

    The state filter is the UKF of :func:`vehjax.filters.gaussian.ukf` run at the predicted
    parameters; the parameter filter draws its own sigma points (p dimensions) from
    (th-, Pth-) and propagates each through the model from the previous state estimate:
    ``Z_i = h(f(x_(t-1), u_t, th_i), u_t, th_i)``.
    {args}
        points: scaling of both sigma-point sets, :class:`~vehjax.filters.SigmaPoints` (eq.
            14-19, see :func:`vehjax.filters.sigma.unscented_rule`).
        param_innovation: "predictive" (default): the parameter innovation covariance is
            ``Cov_i[Z_i] + S`` with S the state filter's; "measurement": ``Cov_i[Z_i] + R`` as
            Algorithm 2 is printed.

    Returns:
        ``Estimator`` with state :class:`DualState`; ``param_names`` = ``estimate``.
    """
    points = validation.record("points", points, SigmaPoints)
    recurrent = validation.flag("recurrent", recurrent)
    cfg = _setup(model, Q, R, Q_theta, estimate, theta_decay, theta_scale, bounds, input_noise)
    predictive = _check_param_innovation(param_innovation)
    rule_s = points.rule(cfg.nx)
    rule_a = None if cfg.Lu is None else points.rule(cfg.nx + cfg.Lu.shape[1])
    rule_p = points.rule(len(cfg.names))
    f, h = _model_fns(model, cfg)

    def step(state, y, u):
        x, P, z, Pz, Qth, D = state
        dt = x.dtype
        y, u = cast_yu(y, u, dt)
        Qn, Rn = jnp.asarray(cfg.Q, dt), jnp.asarray(cfg.R, dt)
        # parameter prediction (identity propagation of the points keeps mean and covariance)
        Pz_pred = sym(Pz + _walk(cfg, z, Qth))
        # state prediction, then correction with fresh points from (x-, P-)

        def state_step(v):
            # the state filter's step from x_{t-1}(v) = x + D (v - z) at parameters v; at v = z
            # it is the step itself, its Jacobian in v the recurrent derivative
            xv = x + D @ (v - z)
            if cfg.Lu is None:
                x_pred, P_pred = sigma.predict(rule_s, xv, P, lambda w: f(w, u, v), Qn)
            else:
                x_pred, P_pred = _inoise.sigma_predict(rule_a, xv, P, lambda w, uu: f(w, uu, v),
                                                       u, cfg.Lu, Qn)
            m = sigma.measure(rule_s, x_pred, P_pred, lambda w: h(w, u, v), Rn)
            r = masked_update(x_pred, P_pred, y, m.y_hat, m.S, m.C)
            return r.x, (m, r)

        if recurrent:
            D_new, (m, r) = jax.jacfwd(state_step, has_aux=True)(z)
        else:
            D_new, (m, r) = D, state_step(z)[1]
        # parameter correction, sigma points of (th-, Pth-) through the model from x_{t-1},
        # moved along the recurrent derivative: x_{t-1} + D (th_i - th-)
        rp = sigma.update(rule_p, z, Pz_pred, lambda v: h(f(x + D @ (v - z), u, v), u, v), y,
                          m.S if predictive else Rn)
        D = D_new
        new = DualState(r.x, r.P, rp.x, rp.P, cfg.decay * Qth, D)
        return new, _out(cfg, r.x, r.P, rp.x, rp.P, r)

    return _estimator(cfg, model, _dual_init(cfg), step, "DUKF")


# --------------------------------------------------------------------------------------------
# joint filters


def _augmented(model, cfg: _Setup):
    f, h = _model_fns(model, cfg)
    nx = cfg.nx

    def fa(a, u):
        return jnp.concatenate([f(a[:nx], u, a[nx:]), a[nx:]])

    def ha(a, u):
        return h(a[:nx], u, a[nx:])

    return fa, ha


def _joint_out(cfg: _Setup, a, Pa, r) -> StepOutput:
    nx = cfg.nx
    return _out(cfg, a[:nx], Pa[:nx, :nx], a[nx:], Pa[nx:, nx:], r)


def _noise_aug(cfg: _Setup, a, Q_theta, dt, fa=None, u=None):
    """Process noise of [x; z]: Q and the random walk mapped to z at the estimate a[nx:]; with
    ``fa`` (and input noise) plus ``G Sigma_u G^T``, G = d fa / du at (a, u)."""
    nx = cfg.nx
    n = nx + Q_theta.shape[0]
    Qz = _walk(cfg, a[nx:], Q_theta)
    Qa = jnp.zeros((n, n), dt).at[:nx, :nx].set(jnp.asarray(cfg.Q, dt)).at[nx:, nx:].set(Qz)
    if fa is not None and cfg.Lu is not None:
        Qa = Qa + _inoise.linearized_input_noise(fa, a, u, cfg.Lu)
    return Qa


def joint_ekf(
    model, Q, R, *, Q_theta, estimate, theta_decay: float = 1.0, theta_scale=None, bounds=None,
    input_noise=None,
) -> Estimator:
    """Joint EKF on the augmented state [x; theta] with random-walk parameters.
    {args}
    Returns:
        ``Estimator`` with state :class:`JointState`; ``param_names`` = ``estimate``.
    """
    cfg = _setup(model, Q, R, Q_theta, estimate, theta_decay, theta_scale, bounds, input_noise)
    fa, ha = _augmented(model, cfg)

    def step(state, y, u):
        a, Pa, Qth = state
        dt = a.dtype
        y, u = cast_yu(y, u, dt)
        Rn = jnp.asarray(cfg.R, dt)
        a_pred, P_pred, _ = linearized_predict(a, Pa, lambda v: fa(v, u),
                                               _noise_aug(cfg, a, Qth, dt, fa, u))
        m = linearized_measure(a_pred, P_pred, lambda v: ha(v, u), Rn)
        r = masked_update(a_pred, P_pred, y, m.y_hat, m.S, m.C, joseph=(m.H, Rn))
        return JointState(r.x, r.P, cfg.decay * Qth), _joint_out(cfg, r.x, r.P, r)

    return _estimator(cfg, model, _joint_init(cfg), step, "JEKF", _joint_smoother(cfg, model))


def joint_ukf(
    model, Q, R, *, Q_theta, estimate, theta_decay: float = 1.0, theta_scale=None,
    points: SigmaPoints = SigmaPoints(), bounds=None, input_noise=None,
) -> Estimator:
    """Joint UKF on the augmented state [x; theta] (nx + p sigma-point dimensions).
    {args}
        points: sigma-point scaling, :class:`~vehjax.filters.SigmaPoints` (see
            :func:`vehjax.filters.sigma.unscented_rule`).

    Returns:
        ``Estimator`` with state :class:`JointState`; ``param_names`` = ``estimate``.
    """
    points = validation.record("points", points, SigmaPoints)
    cfg = _setup(model, Q, R, Q_theta, estimate, theta_decay, theta_scale, bounds, input_noise)
    rule = points.rule(cfg.nx + len(cfg.names))
    rule_a = None if cfg.Lu is None else points.rule(cfg.nx + len(cfg.names) + cfg.Lu.shape[1])
    fa, ha = _augmented(model, cfg)

    def step(state, y, u):
        a, Pa, Qth = state
        dt = a.dtype
        y, u = cast_yu(y, u, dt)
        Qa = _noise_aug(cfg, a, Qth, dt)
        if cfg.Lu is None:
            a_pred, P_pred = sigma.predict(rule, a, Pa, lambda v: fa(v, u), Qa)
        else:
            a_pred, P_pred = _inoise.sigma_predict(rule_a, a, Pa, fa, u, cfg.Lu, Qa)
        r = sigma.update(rule, a_pred, P_pred, lambda v: ha(v, u), y, jnp.asarray(cfg.R, dt))
        return JointState(r.x, r.P, cfg.decay * Qth), _joint_out(cfg, r.x, r.P, r)

    return _estimator(cfg, model, _joint_init(cfg), step, "JUKF",
                      _joint_smoother(cfg, model, rule))


def _joint_smoother(cfg: _Setup, model, rule=None) -> GaussianSmoother:
    """``Estimator.smoother`` of the joint filters: the step's prediction and measurement on the
    augmented state [x; z] (``rule`` None: the EKF's Jacobians), aux the random-walk covariance
    the next step uses; the parameters are smoothed as states and reported in physical units
    (delta method, as the filter's output). The dual filters have none: their two filters do
    not share the state-parameter cross-covariance, so there is no joint Gaussian to smooth."""
    fa, ha = _augmented(model, cfg)
    nx = cfg.nx

    def predict(a, P, u, Qth):
        dt = a.dtype
        u = jnp.asarray(u).astype(dt)
        Qa = _noise_aug(cfg, a, Qth, dt)
        if rule is None:
            a_pred, P_pred, F = linearized_predict(a, P, lambda v: fa(v, u), Qa)
            return a_pred, P_pred, P @ F.T
        X = sigma.sigma_points(a, sigma.cholesky(P), rule)
        return sigma.moments_cross(rule, X, a, sigma._through(lambda v: fa(v, u), X), Qa)

    def measure(a, P, u, Qth):
        dt = a.dtype
        u = jnp.asarray(u).astype(dt)
        if rule is None:
            return linearized_measure(a, P, lambda v: ha(v, u), jnp.asarray(cfg.R, dt))
        return sigma.measure(rule, a, P, lambda v: ha(v, u), jnp.asarray(cfg.R, dt))

    def report(a, P):
        z, Pz = a[nx:], P[nx:, nx:]
        return a[:nx], P[:nx, :nx], cfg.tf.to_physical(z), sym(cfg.tf.cov_to_physical(z, Pz))

    return GaussianSmoother(split=lambda st: (st.a, st.Pa, st.Q_theta), predict=predict,
                            measure=measure, taylor=rule is None, report=report)


for _fn in (dual_ekf, dual_ukf, joint_ekf, joint_ukf):
    if _fn.__doc__:  # None under python -OO
        _fn.__doc__ = _fn.__doc__.replace("{args}", _ARGS_DOC.strip())
del _fn
