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

One dual step (time convention of :mod:`vehjax.filters.base`)::

    parameter prediction:  th- = th,  Pth- = Pth + Q_theta_t
    state prediction:      x- = f(x, u_t, th-),  P- = G P G^T + Q          (G = df/dx, eq. 11)
    state correction:      y^ = h(x-, u_t, th-), S = H P- H^T + R, x, P updated with y_t
    parameter correction:  Hp = d h(f(x_{t-1}, u_t, th), u_t, th) / d th   (eq. 13)
                           Sp = Hp Pth- Hp^T + S,  th, Pth updated with the same innovation
    Q_theta_{t+1} = gamma Q_theta_t

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

Numerics: parameters of vehicle models differ in scale by 1e5 (m ~ 1.7e3 kg, cx ~ 1.5e5 N,
lf ~ 1.5 m), so the filters work internally on ``theta / theta_scale`` (default |model.theta| of
each estimated parameter, 1 where that is 0) and return physical units. EKF covariance updates
use the Joseph form; sigma-point updates the symmetric ``P - K S K^T`` of
:func:`~vehjax.filters.gaussian.masked_update`. NaN measurement components are skipped.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import _validate
from . import sigma
from ._linalg import sym
from .base import Estimator, StepOutput, check_estimate
from ._model import cast_yu, check_model, model_dims
from ._model import prior as _state_prior
from .kalman import linearized_measure, linearized_predict, masked_update
from .sigma import unscented_rule

__all__ = ["DualState", "JointState", "dual_ekf", "dual_ukf", "joint_ekf", "joint_ukf"]

_PARAM_INNOVATIONS = ("predictive", "measurement")


class DualState(NamedTuple):
    """State of :func:`dual_ekf` and :func:`dual_ukf`.

    Attributes:
        x: filtered state mean, (nx,), state units.
        P: its covariance, (nx, nx).
        z: estimated parameters divided by ``theta_scale``, (p,), dimensionless.
        Pz: covariance of z, (p, p).
        Qz: parameter random-walk covariance for the next step, in scaled units, (p, p).
    """

    x: jnp.ndarray
    P: jnp.ndarray
    z: jnp.ndarray
    Pz: jnp.ndarray
    Qz: jnp.ndarray


class JointState(NamedTuple):
    """State of :func:`joint_ekf` and :func:`joint_ukf`.

    Attributes:
        a: augmented mean [x; z], (nx + p,); z = parameters / ``theta_scale``.
        Pa: its covariance, (nx + p, nx + p).
        Qz: parameter random-walk covariance for the next step, in scaled units, (p, p).
    """

    a: jnp.ndarray
    Pa: jnp.ndarray
    Qz: jnp.ndarray


class _Setup(NamedTuple):
    nx: int
    ny: int
    names: tuple
    idx: np.ndarray  # (p,) indices of the estimated parameters in model.theta
    scale: np.ndarray  # (p,) theta_scale
    theta_nom: np.ndarray  # (np,) model.theta
    Q: np.ndarray
    R: np.ndarray
    Qz: np.ndarray  # Q_theta / (scale scale^T)
    decay: float


# --------------------------------------------------------------------------------------------
# validation (numpy, before tracing)


def _setup(model, Q, R, Q_theta, estimate, theta_decay, theta_scale) -> _Setup:
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

    decay = _validate.number("theta_decay", theta_decay, 0.0, 1.0, high_open=False)

    Qn, Rn = _validate.cov("Q", Q, nx, allow_psd=True), _validate.cov("R", R, ny)
    Qth = _validate.cov("Q_theta", Q_theta, p)
    if not isinstance(Qth, np.ndarray):
        raise ValueError("Q_theta: expected a concrete array (it is decayed in the filter state)")
    Qz = Qth / np.outer(scale, scale)
    return _Setup(nx, ny, names, idx, scale, theta_nom, Qn, Rn, Qz, decay)


def _check_param_innovation(value) -> bool:
    if value not in _PARAM_INNOVATIONS:
        raise ValueError(f"param_innovation: expected one of {_PARAM_INNOVATIONS}, got {value!r}")
    return value == "predictive"


def _prior(cfg: _Setup, x0, P0, theta0, P_theta0):
    """(x0, P0, z0, Pz0) as arrays of one float dtype, checked; z0, Pz0 in scaled units."""
    nx, p = cfg.nx, len(cfg.names)
    x0, P0 = _state_prior(nx, x0, P0)
    if theta0 is None:
        theta0 = cfg.theta_nom[cfg.idx]
    if np.shape(theta0) != (p,):
        raise ValueError(
            f"theta0: expected shape ({p},) for the estimated parameters {cfg.names}, "
            f"got shape {np.shape(theta0)}"
        )
    concrete = not isinstance(theta0, jax.core.Tracer)
    if concrete and not np.all(np.isfinite(np.asarray(theta0, dtype=float))):
        raise ValueError(f"theta0: expected finite values, got {theta0}")
    if P_theta0 is None:
        raise ValueError(f"P_theta0: required, the covariance ({p}, {p}) of theta0 for {cfg.names}")
    Pth0 = _validate.cov("P_theta0", P_theta0, p)

    dtype = x0.dtype
    s = jnp.asarray(cfg.scale, dtype)
    z0 = jnp.asarray(theta0).astype(dtype) / s
    Pz0 = jnp.asarray(Pth0).astype(dtype) / jnp.outer(s, s)
    return x0, P0, z0, Pz0


# --------------------------------------------------------------------------------------------
# shared pieces


def _model_fns(model, cfg: _Setup):
    """f(x, u, z) and h(x, u, z) on scaled parameters z (p,), outputs in the dtype of x."""
    idx = cfg.idx

    def full(z):
        th = jnp.asarray(cfg.theta_nom, z.dtype)
        return th.at[idx].set(z * jnp.asarray(cfg.scale, z.dtype))

    def f(x, u, z):
        return jnp.asarray(model.transition(x, u, full(z))).astype(x.dtype)

    def h(x, u, z):
        return jnp.asarray(model.observe(x, u, full(z))).astype(x.dtype)

    return f, h


def _out(cfg: _Setup, x, P, z, Pz, r) -> StepOutput:
    s = jnp.asarray(cfg.scale, z.dtype)
    return StepOutput(
        mean=x, cov=P, loglik=r.loglik, nis=r.nis, n_obs=r.n_obs,
        params=z * s, params_cov=Pz * jnp.outer(s, s), reinit=jnp.zeros((), bool),
    )


def _dual_init(cfg: _Setup):
    def init(x0, P0, theta0=None, P_theta0=None, key=None):
        """Prior x0 (nx,), P0 (nx, nx) or (nx,); theta0 (p,) (default: nominal), P_theta0 (p, p)
        or (p,) variances, both in physical units of the estimated parameters."""
        x0, P0, z0, Pz0 = _prior(cfg, x0, P0, theta0, P_theta0)
        return DualState(x0, P0, z0, Pz0, jnp.asarray(cfg.Qz, x0.dtype))

    return init


def _joint_init(cfg: _Setup):
    def init(x0, P0, theta0=None, P_theta0=None, key=None):
        """Prior x0 (nx,), P0 (nx, nx) or (nx,); theta0 (p,) (default: nominal), P_theta0 (p, p)
        or (p,) variances, both in physical units; state and parameters start uncorrelated."""
        x0, P0, z0, Pz0 = _prior(cfg, x0, P0, theta0, P_theta0)
        nx, p = cfg.nx, z0.shape[0]
        Pa = jnp.zeros((nx + p, nx + p), x0.dtype).at[:nx, :nx].set(P0).at[nx:, nx:].set(Pz0)
        return JointState(jnp.concatenate([x0, z0]), Pa, jnp.asarray(cfg.Qz, x0.dtype))

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
        theta_scale: scalar or (p,) positive units the filter works in internally (default
            |model.theta| of each estimated parameter, 1 where that is 0). Results do not depend
            on it beyond rounding.
"""


# --------------------------------------------------------------------------------------------
# dual filters


def dual_ekf(
    model, Q, R, Q_theta, estimate, theta_decay: float = 1.0, theta_scale=None,
    param_innovation: str = "predictive",
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
    cfg = _setup(model, Q, R, Q_theta, estimate, theta_decay, theta_scale)
    predictive = _check_param_innovation(param_innovation)
    f, h = _model_fns(model, cfg)

    def step(state, y, u):
        x, P, z, Pz, Qz = state
        dt = x.dtype
        y, u = cast_yu(y, u, dt)
        Qn, Rn = jnp.asarray(cfg.Q, dt), jnp.asarray(cfg.R, dt)
        # parameter prediction
        Pz_pred = sym(Pz + Qz)
        # state prediction and correction
        x_pred, P_pred, _ = linearized_predict(x, P, lambda v: f(v, u, z), Qn)
        m = linearized_measure(x_pred, P_pred, lambda v: h(v, u, z), Rn)
        r = masked_update(x_pred, P_pred, y, m.y_hat, m.S, m.C, joseph=(m.H, Rn))
        # parameter correction: Hp = d y^ / d z, through f (eq. 13) and h
        Fz = jax.jacfwd(lambda v: f(x, u, v))(z)
        Hz = jax.jacfwd(lambda v: h(x_pred, u, v))(z)
        Hp = m.H @ Fz + Hz
        N = m.S if predictive else Rn
        Cp = Pz_pred @ Hp.T
        Sp = sym(Hp @ Cp + N)
        rp = masked_update(z, Pz_pred, y, m.y_hat, Sp, Cp, joseph=(Hp, N))
        new = DualState(r.x, r.P, rp.x, rp.P, cfg.decay * Qz)
        return new, _out(cfg, r.x, r.P, rp.x, rp.P, r)

    return Estimator(
        init=_dual_init(cfg), step=step, nx=cfg.nx, param_names=cfg.names, name="DEKF",
        **model_dims(model)
    )


def dual_ukf(
    model, Q, R, Q_theta, estimate, theta_decay: float = 1.0, theta_scale=None,
    alpha: float = 1.0, beta: float = 2.0, kappa: float = 0.0,
    param_innovation: str = "predictive",
) -> Estimator:
    """Dual unscented Kalman filter (Dutta et al. 2019, Algorithm 2).

    The state filter is the UKF of :func:`vehjax.filters.gaussian.ukf` run at the predicted
    parameters; the parameter filter draws its own sigma points (p dimensions) from
    (th-, Pth-) and propagates each through the model from the previous state estimate:
    ``Z_i = h(f(x_(t-1), u_t, th_i), u_t, th_i)``.
    {args}
        alpha, beta, kappa: scaling of both sigma-point sets (eq. 14-19, see
            :func:`vehjax.filters.sigma.unscented_rule`).
        param_innovation: "predictive" (default): the parameter innovation covariance is
            ``Cov_i[Z_i] + S`` with S the state filter's; "measurement": ``Cov_i[Z_i] + R`` as
            Algorithm 2 is printed.

    Returns:
        ``Estimator`` with state :class:`DualState`; ``param_names`` = ``estimate``.
    """
    cfg = _setup(model, Q, R, Q_theta, estimate, theta_decay, theta_scale)
    predictive = _check_param_innovation(param_innovation)
    rule_s = unscented_rule(cfg.nx, alpha, beta, kappa)
    rule_p = unscented_rule(len(cfg.names), alpha, beta, kappa)
    f, h = _model_fns(model, cfg)

    def step(state, y, u):
        x, P, z, Pz, Qz = state
        dt = x.dtype
        y, u = cast_yu(y, u, dt)
        Qn, Rn = jnp.asarray(cfg.Q, dt), jnp.asarray(cfg.R, dt)
        # parameter prediction (identity propagation of the points keeps mean and covariance)
        Pz_pred = sym(Pz + Qz)
        # state prediction, then correction with fresh points from (x-, P-)
        x_pred, P_pred = sigma.predict(rule_s, x, P, lambda v: f(v, u, z), Qn)
        m = sigma.measure(rule_s, x_pred, P_pred, lambda v: h(v, u, z), Rn)
        r = masked_update(x_pred, P_pred, y, m.y_hat, m.S, m.C)
        # parameter correction, sigma points of (th-, Pth-) through the model from x_{t-1}
        rp = sigma.update(rule_p, z, Pz_pred, lambda v: h(f(x, u, v), u, v), y,
                          m.S if predictive else Rn)
        new = DualState(r.x, r.P, rp.x, rp.P, cfg.decay * Qz)
        return new, _out(cfg, r.x, r.P, rp.x, rp.P, r)

    return Estimator(
        init=_dual_init(cfg), step=step, nx=cfg.nx, param_names=cfg.names, name="DUKF",
        **model_dims(model)
    )


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


def _noise_aug(cfg: _Setup, Qz, dt):
    nx = cfg.nx
    n = nx + Qz.shape[0]
    return jnp.zeros((n, n), dt).at[:nx, :nx].set(jnp.asarray(cfg.Q, dt)).at[nx:, nx:].set(Qz)


def joint_ekf(
    model, Q, R, Q_theta, estimate, theta_decay: float = 1.0, theta_scale=None
) -> Estimator:
    """Joint EKF on the augmented state [x; theta] with random-walk parameters.
    {args}
    Returns:
        ``Estimator`` with state :class:`JointState`; ``param_names`` = ``estimate``.
    """
    cfg = _setup(model, Q, R, Q_theta, estimate, theta_decay, theta_scale)
    fa, ha = _augmented(model, cfg)

    def step(state, y, u):
        a, Pa, Qz = state
        dt = a.dtype
        y, u = cast_yu(y, u, dt)
        Rn = jnp.asarray(cfg.R, dt)
        a_pred, P_pred, _ = linearized_predict(a, Pa, lambda v: fa(v, u), _noise_aug(cfg, Qz, dt))
        m = linearized_measure(a_pred, P_pred, lambda v: ha(v, u), Rn)
        r = masked_update(a_pred, P_pred, y, m.y_hat, m.S, m.C, joseph=(m.H, Rn))
        return JointState(r.x, r.P, cfg.decay * Qz), _joint_out(cfg, r.x, r.P, r)

    return Estimator(
        init=_joint_init(cfg), step=step, nx=cfg.nx, param_names=cfg.names, name="JEKF",
        **model_dims(model)
    )


def joint_ukf(
    model, Q, R, Q_theta, estimate, theta_decay: float = 1.0, theta_scale=None,
    alpha: float = 1.0, beta: float = 2.0, kappa: float = 0.0,
) -> Estimator:
    """Joint UKF on the augmented state [x; theta] (nx + p sigma-point dimensions).
    {args}
        alpha, beta, kappa: sigma-point scaling (see :func:`vehjax.filters.sigma.unscented_rule`).

    Returns:
        ``Estimator`` with state :class:`JointState`; ``param_names`` = ``estimate``.
    """
    cfg = _setup(model, Q, R, Q_theta, estimate, theta_decay, theta_scale)
    rule = unscented_rule(cfg.nx + len(cfg.names), alpha, beta, kappa)
    fa, ha = _augmented(model, cfg)

    def step(state, y, u):
        a, Pa, Qz = state
        dt = a.dtype
        y, u = cast_yu(y, u, dt)
        a_pred, P_pred = sigma.predict(rule, a, Pa, lambda v: fa(v, u), _noise_aug(cfg, Qz, dt))
        r = sigma.update(rule, a_pred, P_pred, lambda v: ha(v, u), y, jnp.asarray(cfg.R, dt))
        return JointState(r.x, r.P, cfg.decay * Qz), _joint_out(cfg, r.x, r.P, r)

    return Estimator(
        init=_joint_init(cfg), step=step, nx=cfg.nx, param_names=cfg.names, name="JUKF",
        **model_dims(model)
    )


for _fn in (dual_ekf, dual_ukf, joint_ekf, joint_ukf):
    if _fn.__doc__:  # None under python -OO
        _fn.__doc__ = _fn.__doc__.replace("{args}", _ARGS_DOC.strip())
del _fn
