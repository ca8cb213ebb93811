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
from jax.scipy.linalg import cho_solve

from .base import Estimator, StepOutput, check_estimate
from .gaussian import _prior as _state_prior
from .gaussian import check_cov, masked_update
from .sigma import cross_covariance, sigma_points, unscented_rule, unscented_transform

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
    for attr in ("transition", "observe", "theta", "param_names", "nx", "ny"):
        if not hasattr(model, attr):
            raise ValueError(
                f"model: expected a vehjax model with .{attr}, got {type(model).__name__}"
            )
    nx, ny = int(model.nx), int(model.ny)
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

    try:
        decay = float(theta_decay)
    except (TypeError, ValueError):
        raise ValueError(f"theta_decay: expected a number in (0, 1], got {theta_decay!r}") from None
    if not (0.0 < decay <= 1.0):
        raise ValueError(f"theta_decay: expected a number in (0, 1], got {theta_decay!r}")

    Qn, Rn = check_cov("Q", Q, nx), check_cov("R", R, ny)
    Qth = check_cov("Q_theta", Q_theta, p)
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
    Pth0 = check_cov("P_theta0", P_theta0, p)

    dtype = x0.dtype
    s = jnp.asarray(cfg.scale, dtype)
    z0 = jnp.asarray(theta0).astype(dtype) / s
    Pz0 = jnp.asarray(Pth0).astype(dtype) / jnp.outer(s, s)
    return x0, P0, z0, Pz0


# --------------------------------------------------------------------------------------------
# shared pieces


def _sym(A):
    return 0.5 * (A + A.T)


def _cast(a, dtype):
    return jnp.asarray(a).astype(dtype)


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


def _joseph(P_pred, C, S, H, N, y):
    """Joseph-form covariance after a masked update: (I - K H) P- (I - K H)^T + K N K^T.

    ``C`` = P- H^T (n, ny), ``S`` = H P- H^T + N (ny, ny), ``N`` the noise part of S. NaN
    components of ``y`` are missing: their columns of K are zero, as in ``masked_update``.
    """
    mf = jnp.isfinite(y).astype(P_pred.dtype)
    Sm = S * (mf[:, None] * mf[None, :]) + jnp.diag(1 - mf)
    L = jnp.linalg.cholesky(_sym(Sm))
    K = cho_solve((L, True), (C * mf[None, :]).T).T
    A = jnp.eye(P_pred.shape[0], dtype=P_pred.dtype) - K @ H
    return _sym(A @ P_pred @ A.T + K @ N @ K.T)


def _out(cfg: _Setup, x, P, z, Pz, r) -> StepOutput:
    s = jnp.asarray(cfg.scale, z.dtype)
    return StepOutput(
        mean=x, cov=P, loglik=r.loglik, nis=r.nis, n_obs=r.n_obs,
        params=z * s, params_cov=Pz * jnp.outer(s, s),
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
    jac_f = jax.jacfwd(f, argnums=(0, 2))
    jac_h = jax.jacfwd(h, argnums=(0, 2))

    def step(state, y, u):
        x, P, z, Pz, Qz = state
        dt = x.dtype
        y, u = _cast(y, dt), _cast(u, dt)
        Qn, Rn = jnp.asarray(cfg.Q, dt), jnp.asarray(cfg.R, dt)
        # parameter prediction
        Pz_pred = _sym(Pz + Qz)
        # state prediction
        G, Fz = jac_f(x, u, z)
        x_pred = f(x, u, z)
        P_pred = _sym(G @ P @ G.T + Qn)
        # state correction
        H, Hz = jac_h(x_pred, u, z)
        y_hat = h(x_pred, u, z)
        C = P_pred @ H.T
        S = _sym(H @ C + Rn)
        r = masked_update(x_pred, P_pred, y, y_hat, S, C)
        P_new = _joseph(P_pred, C, S, H, Rn, y)
        # parameter correction: Hp = d y^ / d z, through f (eq. 13) and h
        Hp = H @ Fz + Hz
        N = S if predictive else Rn
        Cp = Pz_pred @ Hp.T
        Sp = _sym(Hp @ Cp + N)
        rp = masked_update(z, Pz_pred, y, y_hat, Sp, Cp)
        Pz_new = _joseph(Pz_pred, Cp, Sp, Hp, N, y)
        new = DualState(r.x, P_new, rp.x, Pz_new, cfg.decay * Qz)
        return new, _out(cfg, r.x, P_new, rp.x, Pz_new, r)

    return Estimator(
        init=_dual_init(cfg), step=step, nx=cfg.nx, param_names=cfg.names, name="DEKF"
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
    f_pts = jax.vmap(f, in_axes=(0, None, None))
    h_pts = jax.vmap(h, in_axes=(0, None, None))
    y_of_z = jax.vmap(lambda x, u, z: h(f(x, u, z), u, z), in_axes=(None, None, 0))

    def step(state, y, u):
        x, P, z, Pz, Qz = state
        dt = x.dtype
        y, u = _cast(y, dt), _cast(u, dt)
        Qn, Rn = jnp.asarray(cfg.Q, dt), jnp.asarray(cfg.R, dt)
        # parameter prediction (identity propagation of the points keeps mean and covariance)
        Pz_pred = _sym(Pz + Qz)
        # state prediction
        Xf = f_pts(sigma_points(x, jnp.linalg.cholesky(P), rule_s), u, z)
        x_pred, P_pred = unscented_transform(Xf, rule_s, Qn)
        # state correction, fresh points from (x-, P-)
        X = sigma_points(x_pred, jnp.linalg.cholesky(P_pred), rule_s)
        Zs = h_pts(X, u, z)
        y_hat, S = unscented_transform(Zs, rule_s, Rn)
        C = cross_covariance(X, x_pred, Zs, y_hat, rule_s)
        r = masked_update(x_pred, P_pred, y, y_hat, S, C)
        # parameter correction, sigma points of (th-, Pth-) through the model from x_{t-1}
        Zp = sigma_points(z, jnp.linalg.cholesky(Pz_pred), rule_p)
        Yp = y_of_z(x, u, Zp)
        yp_hat, Sp = unscented_transform(Yp, rule_p, S if predictive else Rn)
        Cp = cross_covariance(Zp, z, Yp, yp_hat, rule_p)
        rp = masked_update(z, Pz_pred, y, yp_hat, Sp, Cp)
        new = DualState(r.x, r.P, rp.x, rp.P, cfg.decay * Qz)
        return new, _out(cfg, r.x, r.P, rp.x, rp.P, r)

    return Estimator(
        init=_dual_init(cfg), step=step, nx=cfg.nx, param_names=cfg.names, name="DUKF"
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
    Fa_of, Ha_of = jax.jacfwd(fa), jax.jacfwd(ha)

    def step(state, y, u):
        a, Pa, Qz = state
        dt = a.dtype
        y, u = _cast(y, dt), _cast(u, dt)
        Rn = jnp.asarray(cfg.R, dt)
        F = Fa_of(a, u)
        a_pred = fa(a, u)
        P_pred = _sym(F @ Pa @ F.T + _noise_aug(cfg, Qz, dt))
        H = Ha_of(a_pred, u)
        y_hat = ha(a_pred, u)
        C = P_pred @ H.T
        S = _sym(H @ C + Rn)
        r = masked_update(a_pred, P_pred, y, y_hat, S, C)
        P_new = _joseph(P_pred, C, S, H, Rn, y)
        return JointState(r.x, P_new, cfg.decay * Qz), _joint_out(cfg, r.x, P_new, r)

    return Estimator(
        init=_joint_init(cfg), step=step, nx=cfg.nx, param_names=cfg.names, name="JEKF"
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
    fa_pts = jax.vmap(fa, in_axes=(0, None))
    ha_pts = jax.vmap(ha, in_axes=(0, None))

    def step(state, y, u):
        a, Pa, Qz = state
        dt = a.dtype
        y, u = _cast(y, dt), _cast(u, dt)
        Xf = fa_pts(sigma_points(a, jnp.linalg.cholesky(Pa), rule), u)
        a_pred, P_pred = unscented_transform(Xf, rule, _noise_aug(cfg, Qz, dt))
        X = sigma_points(a_pred, jnp.linalg.cholesky(P_pred), rule)
        Z = ha_pts(X, u)
        y_hat, S = unscented_transform(Z, rule, jnp.asarray(cfg.R, dt))
        C = cross_covariance(X, a_pred, Z, y_hat, rule)
        r = masked_update(a_pred, P_pred, y, y_hat, S, C)
        return JointState(r.x, r.P, cfg.decay * Qz), _joint_out(cfg, r.x, r.P, r)

    return Estimator(
        init=_joint_init(cfg), step=step, nx=cfg.nx, param_names=cfg.names, name="JUKF"
    )


for _fn in (dual_ekf, dual_ukf, joint_ekf, joint_ukf):
    if _fn.__doc__:  # None under python -OO
        _fn.__doc__ = _fn.__doc__.replace("{args}", _ARGS_DOC.strip())
del _fn
