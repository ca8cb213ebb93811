"""Variational-Bayes adaptive Kalman filters: unknown measurement noise (Särkkä & Nummenmaa
2009) and inaccurate process and measurement noise (Huang et al. 2017), in EKF, UKF and CKF
forms (Särkkä & Hartikainen's nonlinear variant), with unknown sensor biases and input offsets
as Kalman states.

References:
    S. Särkkä and A. Nummenmaa, "Recursive noise adaptive Kalman filtering by variational
    Bayesian approximations", IEEE TAC 54(3), 2009 ("VB-AKF", :func:`vbakf_r`).
    S. Särkkä and J. Hartikainen, "Non-linear noise adaptive Kalman filtering via variational
    Bayes", IEEE MLSP 2013 (the nonlinear form: Gaussian integrals by linearisation or sigma
    points).
    Y. Huang, Y. Zhang, Z. Wu, N. Li and J. Chambers, "A novel adaptive Kalman filter with
    inaccurate process and measurement noise covariance matrices", IEEE TAC 63(2), 2018
    (online 2017) ("VBAKF-PR", :func:`vbakf_pr`).

My reading of the equations (written from these well-known papers; the variants implemented
are stated).

**Särkkä & Nummenmaa (unknown diagonal R).** x_k = f(x_{k-1}) + q, q ~ N(0, Q) (Q known);
y_k = h(x_k) + r, r ~ N(0, diag(sigma_1^2 .. sigma_m^2)), each sigma_j^2 ~ IG(alpha_j, beta_j)
(density prop. to s^-(alpha+1) exp(-beta / s)); the posterior is approximated by the product
N(x; m, P) prod_j IG(sigma_j^2; alpha_j, beta_j).

* Prediction: m-, P- by the Kalman (EKF/UKF/CKF) prediction with Q; the variances by the
  heuristic dynamics with the forgetting factor rho in (0, 1]::

      alpha_j- = rho (alpha_j - 1) + 1,    beta_j- = rho beta_j

  rho = 1: stationary variances; rho < 1 lets them drift (memory about 1 / (1 - rho) steps).
* Update: alpha_j = alpha_j- + 1/2 once; then N fixed-point iterations, starting from
  beta = beta-::

      R^ = diag(beta_j / alpha_j)                            (= E[R^-1]^-1)
      m, P = Kalman update of (m-, P-) with y_k and R^
      beta_j = beta_j- + 1/2 E[(y_k - h(x_k))_j^2]           over x_k ~ N(m, P)

  Linear h = H x: E[(y - H x)_j^2] = (y - H m)_j^2 + (H P H^T)_jj (the paper's equation).
  Nonlinear (Särkkä & Hartikainen): the same Gaussian integral, by linearising h at m
  (EKF form: (y - h(m))_j^2 + (J P J^T)_jj) or by the sigma-point rule of the filter
  (UKF/CKF form: (y - y^)_j^2 + sum_i wc_i (Z_i - y^)_j^2, Z_i = h(X_i), X_i the points of
  N(m, P)); the Kalman update inside the loop is the filter's own (:mod:`vehjax.filters.sigma`
  and :mod:`vehjax.filters.kalman`, re-used).

**Huang et al. (inaccurate Q and R).** The nominal Q~ gives the nominal predicted covariance
P~- = F P F^T + Q~ (or its sigma-point form). The true predicted covariance P_{k|k-1} and R_k are
unknown, with inverse-Wishart distributions IW(Sigma; nu, Psi) (density prop. to
|Sigma|^-(nu + d + 1)/2 exp(-tr(Psi Sigma^-1) / 2), mean Psi / (nu - d - 1),
E[Sigma^-1] = nu Psi^-1)::

    prior of P_{k|k-1}:  t- = n + tau + 1,           T- = tau P~-       (mean P~-)
    prior of R_k:        u- = rho (u - m - 1) + m + 1,  U- = rho U          (forgetting rho)

  N fixed-point iterations, from x^(0) = x-, P^(0) = P~-::

      A = (x^(i) - x-)(x^(i) - x-)^T + P^(i);        t = t- + 1,  T = T- + A
      B = E[(y - h(x))(y - h(x))^T] over N(x^(i), P^(i));  u = u- + 1,  U = U- + B
      P^- = T / (t - n - 1),  R^ = U / (u - m - 1)           (= E[.^-1]^-1 as written)
      x^(i+1), P^(i+1) = Kalman update of (x-, P^-) with y and R^

  The plug-ins are the IW means, as the paper writes it (:func:`iw_plugin`); u_0 = ``dof0``
  (> m + 1), U_0 = (u_0 - m - 1) R0 with R0 the builders' ``R``, so the prior mean of the
  learnt R is R0; tau >= 0 (the paper recommends 2 <= tau <= 6) weighs the nominal P~-.

**Variants and choices made here.** ``sensors``: the outputs whose noise is learnt (Huang's IW
covers their block of R, full); ``known_std``: outputs of known std; outputs in neither are not
used. ``augment`` (:class:`Augmentation`) adds bias and offset states to the Kalman state (y =
h(x) + b, the model driven by u + offset). Missing measurements (NaN) are skipped by the Kalman
update; in VB-AKF their alpha_j, beta_j keep their prediction, in VBAKF-PR a step with some
sensor missing leaves q(R) at its prediction.
``out.params`` (SI units of the model): ``<input>_offset``, ``<sensor>_bias`` (Kalman means),
``<sensor>_std`` = sqrt(R^_jj); ``params_cov`` the Kalman block and, per std, std^2 psi1(a) / 4
(the delta method; cross-covariances between biases and stds 0). VBAKF-PR learns P_{k|k-1},
not Q: the state keeps the plug-in ``P_pred``.

See docs/vb.md for VBAKF-PR's plug-ins and update in full and each choice with its reason.

Every filter here is a plain :class:`~vehjax.filters.base.Estimator` (vmapped by
:func:`vehjax.run`; no runs-last form). Divergence (NaN/inf in the mean, an indefinite P) is
flagged by :func:`vehjax.filter` / :func:`vehjax.run` as for every filter.
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import polygamma

from .. import validation
from . import input_noise as _inoise
from . import sigma
from ..lib.linalg import sym
from ..models.biases import augmented
from ._model import cast_yu, check_model, in_dtype, model_dims, model_theta, per_point, prior
from .base import Dims, Estimator, ParamSpec, Runtime, StepOutput
from .kalman import linearized_measure, linearized_predict, masked_update

__all__ = ["Augmentation", "VBState", "VBPRState", "vbakf_r", "vbakf_pr", "FORMS", "ig_predict",
           "ig_update",
           "iw_predict", "iw_pred_cov_prior", "iw_plugin", "std_moments", "param_units"]

#: The Gaussian forms: linearisation (EKF) or the sigma-point rules of :mod:`~.sigma`.
FORMS = ("ekf", "ukf", "ckf")


# --------------------------------------------------------------------------------------------
# the mathematics, one function each


def ig_predict(alpha, beta, rho):
    """Särkkä & Nummenmaa's heuristic prediction of the IG statistics:
    ``(rho (alpha - 1) + 1, rho beta)``. alpha, beta (m,); rho in (0, 1]."""
    return rho * (alpha - 1.0) + 1.0, rho * beta


def ig_update(alpha_pred, beta_pred, sq_err, observed):
    """The VB update of the IG statistics given the expected squared residuals.

    Args:
        alpha_pred, beta_pred: predicted shapes and scales, (m,); beta in output units squared.
        sq_err: E[(y - h(x))_j^2] under the current Gaussian of x, (m,).
        observed: (m,) 0/1 floats, the components measured this step.

    Returns:
        (alpha, beta) = (alpha- + 1/2, beta- + sq_err / 2) on observed components, else the
        prediction.
    """
    return alpha_pred + 0.5 * observed, beta_pred + 0.5 * sq_err * observed


def iw_predict(u, U, rho, m: int):
    """Huang et al.'s prediction of the IW statistics of R: ``(rho (u - m - 1) + m + 1, rho U)``,
    u scalar dof, U (m, m) scale, m the dimension."""
    return rho * (u - m - 1.0) + m + 1.0, rho * U


def iw_pred_cov_prior(P_nominal, tau):
    """Huang et al.'s IW prior of the predicted covariance: ``(n + tau + 1, tau P~-)`` (mean
    P~-), P_nominal (n, n) the nominal predicted covariance, tau >= 0."""
    n = P_nominal.shape[-1]
    return n + tau + 1.0, tau * P_nominal


def iw_plugin(dof, scale, d: int):
    """Huang et al.'s plug-in of an IW(dof, scale) matrix in d dimensions:
    ``E[Sigma^-1]^-1`` as the paper writes it, ``scale / (dof - d - 1)`` (the IW mean; module
    docstring)."""
    return scale / (dof - d - 1.0)


def std_moments(var_hat, shape):
    """(std, Var[std]) of a plug-in variance ``var_hat`` whose IG marginal has shape ``shape``:
    std = sqrt(var_hat), Var[std] = std^2 psi1(shape) / 4 (delta method on log sigma, whose
    variance is exactly psi1(shape) / 4). Shapes (m,)."""
    s = jnp.sqrt(var_hat)
    return s, s * s * polygamma(1, shape) / 4.0


def param_units(model, est) -> tuple[str, ...]:
    """Units of ``est.param_names`` for a filter of this module built on ``model``."""
    units = dict(zip(model.output_names, getattr(model, "output_units",
                                                 ("-",) * len(model.output_names))))
    units.update(zip(model.input_names, getattr(model, "input_units",
                                                ("-",) * len(model.input_names))))
    return tuple(units.get(n.rsplit("_", 1)[0], "-") for n in est.param_names)


# --------------------------------------------------------------------------------------------
# the Gaussian moments of one form (re-used from kalman.py / sigma.py)


class _Form(NamedTuple):
    predict: object   # (x, P, f, Q, u, f_uw) -> (x-, P-); f_uw(x, u) for input noise
    measure: object   # (x, P, h) -> Measurement without noise (y^, S0, C, H)
    joseph: bool


def _form(form: str, n: int, Lu):
    """The prediction and the noise-free measurement moments of ``form`` in n dimensions;
    ``Lu`` the input-noise factor (None for none)."""
    if form == "ekf":
        def predict(x, P, f, Q, u, f_uw):
            if Lu is not None:
                Q = Q + _inoise.linearized_input_noise(f_uw, x, u, Lu)
            xp, Pp, _ = linearized_predict(x, P, f, Q)
            return xp, Pp

        def measure(x, P, h):
            return linearized_measure(x, P, h, 0.0)

        return _Form(predict, measure, True)
    make = sigma.unscented_rule if form == "ukf" else sigma.cubature_rule
    rule = make(n)
    rule_a = None if Lu is None else make(n + Lu.shape[1])

    def predict(x, P, f, Q, u, f_uw):
        if Lu is None:
            return sigma.predict(rule, x, P, f, Q)
        return _inoise.sigma_predict(rule_a, x, P, f_uw, u, Lu, Q)

    def measure(x, P, h):
        return sigma.measure(rule, x, P, h)

    return _Form(predict, measure, False)


def _expected_outer(form: _Form, x, P, h, y0):
    """E[(y - h(z))(y - h(z))^T] over z ~ N(x, P) by the form's rule, y0 (ny,) with missing
    components replaced by anything finite (masked by the caller)."""
    m = form.measure(x, P, h)
    e = y0 - m.y_hat
    return jnp.outer(e, e) + m.S


# --------------------------------------------------------------------------------------------
# the shared set-up: augmentation with biases and offsets, known / unused outputs


class _Setup(NamedTuple):
    nx: int
    n: int
    ny: int
    sens: np.ndarray        # indices of the learnt outputs
    known_var: np.ndarray   # (ny,) fixed variances (0 on sensors and unused outputs)
    used: np.ndarray        # (ny,) bool: sensor or known
    Qa: np.ndarray          # (n, n) augmented process noise
    bias_var0: np.ndarray   # prior variances of the bias/offset states
    names: tuple
    f_uw: object            # (z, u, theta) -> z'
    h_z: object             # (z, u, theta) -> y
    Lu: object


@dataclasses.dataclass(frozen=True)
class Augmentation:
    """The bias and offset states :func:`vbakf_r` and :func:`vbakf_pr` add to the Kalman state
    (their option ``augment``): y = h(x) + b, the model driven by u + offset.

    Attributes:
        biases: sensors with an unknown additive bias, estimated as a Kalman state each.
        input_offsets: inputs with an unknown additive offset (the model sees u + offset).
        bias_walk, offset_walk: random-walk stds per step of the biases and offsets (>= 0), in
            the output's / input's units: one number for all or a dict naming each.
        bias_std0, offset_std0: prior stds of the biases and offsets (mean 0), > 0; a number
            or a dict naming each.

    The names are checked against the model by the builder; the numbers when made.
    """

    biases: Any = ()
    input_offsets: Any = ()
    bias_walk: Any = 0.0
    offset_walk: Any = 0.0
    bias_std0: Any = 1.0
    offset_std0: Any = 0.01

    def __post_init__(self):
        for arg, closed in (("bias_walk", True), ("offset_walk", True), ("bias_std0", False),
                            ("offset_std0", False)):
            v = getattr(self, arg)
            for x in (v.values() if isinstance(v, dict) else (v,)):
                validation.number(arg, x, 0.0, low_open=not closed)


def _setup(model, Q, sensors, known_std, augment, input_noise):
    nx, ny = check_model(model)
    outs, ins = tuple(model.output_names), tuple(model.input_names)
    aug = validation.record("augment", augment, Augmentation)
    biases, input_offsets = aug.biases, aug.input_offsets
    bias_walk, offset_walk, bias_std0, offset_std0 = (aug.bias_walk, aug.offset_walk,
                                                      aug.bias_std0, aug.offset_std0)
    known = {} if known_std is None else validation.keyed("known_std", known_std, outs, "outputs")
    if sensors is None:
        sensors = tuple(o for o in outs if o not in known)
    sensors = validation.names("sensors", sensors, outs)
    both = set(sensors) & set(known)
    if both:
        raise ValueError(f"known_std: {sorted(both)} also in sensors; an output's noise is "
                         "either learnt or known")
    for k, v in known.items():
        validation.number(f"known_std[{k!r}]", v, 0.0)
    biases = validation.names("biases", () if biases is None else biases, sensors,
                             allow_empty=True)
    offs = validation.names("input_offsets", () if input_offsets is None else input_offsets,
                           ins, allow_empty=True)
    bw = _per_name("bias_walk", bias_walk, biases, closed=True)
    ow = _per_name("offset_walk", offset_walk, offs, closed=True)
    b0 = _per_name("bias_std0", bias_std0, biases)
    o0 = _per_name("offset_std0", offset_std0, offs)
    Qn = validation.cov("Q", Q, nx, allow_psd=True)
    Lu = _inoise.input_factor(input_noise, ins)
    nb, no = len(biases), len(offs)
    n = nx + nb + no
    Qa = np.zeros((n, n))
    Qa[:nx, :nx] = Qn
    Qa[nx:nx + nb, nx:nx + nb] = np.diag(bw ** 2)
    Qa[nx + nb:, nx + nb:] = np.diag(ow ** 2)
    Lu = None if Lu is None else np.asarray(Lu)
    tr, ob = (in_dtype(g) for g in per_point(model))
    f_uw, h_z = augmented(tr, ob, nx, bias_rows=[outs.index(b) for b in biases],
                          offset_cols=[ins.index(o) for o in offs])

    sens = np.array([outs.index(s) for s in sensors], int)
    known_var = np.zeros(ny)
    used = np.zeros(ny, bool)
    used[sens] = True
    for k, v in known.items():
        known_var[outs.index(k)] = float(v) ** 2
        used[outs.index(k)] = True
    names = (tuple(f"{o}_offset" for o in offs) + tuple(f"{b}_bias" for b in biases)
             + tuple(f"{s}_std" for s in sensors))
    var0 = np.r_[b0 ** 2, o0 ** 2]
    return _Setup(nx, n, ny, sens, known_var, used, Qa, var0, names, f_uw, h_z, Lu)


def _per_name(arg, value, names, closed=False):
    """One std per name, (len(names),): a number for all, or a dict {name: std} naming each;
    > 0 (>= 0 when ``closed``)."""
    if isinstance(value, dict):
        if set(value) != set(names):
            raise ValueError(f"{arg}: expected one std for each of {tuple(names)}, got keys "
                             f"{tuple(value)}")
        vals = [value[n] for n in names]
    else:
        vals = [value] * len(names)
    return np.array([validation.number(arg, v, 0.0, low_open=not closed) for v in vals], float)


def _sensor_R0(R, m, sensors_names):
    R0 = np.asarray(R, float)
    if R0.ndim == 1:
        if R0.shape != (m,) or not np.all(np.isfinite(R0)) or np.any(R0 <= 0):
            raise ValueError(f"R: expected {m} positive variances (one per sensor "
                             f"{sensors_names}), got {R0!r}")
        return np.diag(R0)
    return validation.cov("R", R0, m)


def _param_prior(setup, R0_diag, dof_shape):
    """``Estimator.param_prior``: (theta (p,), P_theta (p, p)) in the reported order: offsets and
    biases 0 with variances offset_std0^2, bias_std0^2; stds sqrt(R0) with the variance of
    :func:`std_moments` at the prior's shape."""
    idx = _reorder(setup) - setup.nx
    k = len(idx)
    std0 = np.sqrt(R0_diag)
    th = np.r_[np.zeros(k), std0]
    var_std = std0 ** 2 * np.asarray(polygamma(1, jnp.asarray(dof_shape, float))) / 4.0
    P = np.diag(np.r_[setup.bias_var0[idx], np.broadcast_to(var_std, std0.shape)])
    return th, P


def _estimator(setup, model, stats0, step, prior_params, name: str) -> Estimator:
    """The VB filter's Estimator: ``step`` with the prior's init (:func:`_init_fn`), the
    reported parameters (offsets, biases, stds) and their default prior."""
    return Estimator(
        init=_init_fn(setup, model, stats0, prior_params),
        step=step,
        name=name,
        dims=Dims(nx=setup.nx, **model_dims(model)),
        params=ParamSpec(names=setup.names, prior=prior_params),
        runtime=Runtime(workload="small_dense"),
    )

def _init_fn(setup, model, stats0, prior_params):
    """``init(x0, P0, theta0, P_theta0, key)``: x0 (nx,), P0 over the model's states; theta0
    (p,), when given, replaces the prior's offsets, biases (Kalman means) and stds (the prior
    R's diagonal); P_theta0 (p, p) or (p,), when given, its offset/bias block is their Kalman
    covariance (its std block is not used: ``dof0`` weighs the prior of R). The model runs at
    ``model.theta``."""
    nx, n = setup.nx, setup.n
    th_def, P_def = prior_params
    p = len(th_def)
    idx = _reorder(setup)
    k = len(idx)

    def init(x0, P0, theta0=None, P_theta0=None, key=None):
        x0, P0 = prior(nx, x0, P0)
        dt = x0.dtype
        if theta0 is None:
            th = jnp.asarray(th_def, dt)
        else:
            if np.shape(theta0) != (p,):
                raise ValueError(f"theta0: expected shape ({p},) for {setup.names}, got "
                                 f"{np.shape(theta0)}")
            th = jnp.asarray(theta0).astype(dt)
        if P_theta0 is None:
            Pb = jnp.asarray(P_def[:k, :k], dt)
        else:
            Pt = jnp.asarray(P_theta0).astype(dt)
            Pb = (jnp.diag(Pt) if Pt.ndim == 1 else Pt)[:k, :k]
        za = jnp.concatenate([x0, jnp.zeros(n - nx, dt)]).at[idx].set(th[:k])
        Pa = jnp.zeros((n, n), dt).at[:nx, :nx].set(P0)
        Pa = Pa.at[jnp.ix_(idx, idx)].set(Pb)
        return stats0(za, Pa, th[k:] ** 2, model_theta(model, None, dt))

    return init


def _reorder(setup):
    """Indices putting the Kalman bias/offset block in the reported order (offsets, biases)."""
    nx, n = setup.nx, setup.n
    nb = sum(1 for s in setup.names if s.endswith("_bias"))
    return np.r_[np.arange(nx + nb, n), np.arange(nx, nx + nb)].astype(int)


def _report(setup, z, P, std, var_std, nis, loglik, n_obs):
    idx = _reorder(setup)
    nx = setup.nx
    params = jnp.concatenate([z[idx], std])
    k = len(idx)
    p = k + std.shape[0]
    pc = jnp.zeros((p, p), z.dtype).at[:k, :k].set(P[jnp.ix_(idx, idx)])
    pc = pc.at[k:, k:].set(jnp.diag(var_std))
    return StepOutput(mean=z[:nx], cov=P[:nx, :nx], loglik=loglik, nis=nis, n_obs=n_obs,
                      params=params, params_cov=sym(pc), reinit=jnp.zeros((), bool))


def _masked_y(setup, y):
    """y with the outputs neither learnt nor known set missing."""
    return jnp.where(jnp.asarray(setup.used), y, jnp.nan)


def _predicted(setup, fm, z, P, y, u, theta):
    """The step's common first part: y and u cast to z's dtype (y with its unused outputs
    masked), the measurement function h(z) at (u, theta) and the prediction (zp, Pp) of the
    Gaussian form ``fm``. Returns (y, u, h, zp, Pp)."""
    y, u = cast_yu(y, u, z.dtype)
    y = _masked_y(setup, y)
    f = lambda v: setup.f_uw(v, u, theta)  # noqa: E731
    h = lambda v: setup.h_z(v, u, theta)  # noqa: E731
    zp, Pp = fm.predict(z, P, f, jnp.asarray(setup.Qa, z.dtype), u,
                        lambda v, w: setup.f_uw(v, w, theta))
    return y, u, h, zp, Pp


#: the most fixed-point iterations a step takes (the papers use 5-10; each is a whole update)
MAX_ITERATIONS = 1000


def _check_common(form, forgetting, iterations):
    form = validation.choice("form", form, FORMS)
    rho = validation.number("forgetting", forgetting, 0.0, 1.0, high_open=False)
    if isinstance(iterations, bool) or not isinstance(iterations, (int, np.integer)) \
            or not 1 <= iterations <= MAX_ITERATIONS:
        raise ValueError(f"iterations: expected an integer from 1 to {MAX_ITERATIONS} (the "
                         f"fixed point settles in a few; each is a whole update, every step), "
                         f"got {iterations!r}")
    return form, rho, int(iterations)


# --------------------------------------------------------------------------------------------
# Särkkä & Nummenmaa: VB-AKF, diagonal R


class VBState(NamedTuple):
    """State of :func:`vbakf_r`.

    Attributes:
        x: filtered mean of the augmented state (model states, output biases, input offsets),
            (n,).
        P: its covariance, (n, n).
        alpha: IG shapes of the sensors' variances, (m,).
        beta: IG scales, (m,), output units squared; R^ = diag(beta / alpha).
        theta: model parameters, (np,).
    """

    x: jnp.ndarray
    P: jnp.ndarray
    alpha: jnp.ndarray
    beta: jnp.ndarray
    theta: jnp.ndarray


def vbakf_r(model, Q, R, *, form: str = "ckf", forgetting: float = 1.0, iterations: int = 5,
            dof0: float = 10.0, sensors=None, known_std=None,
            augment: Augmentation = Augmentation(), input_noise=None) -> Estimator:
    """Särkkä & Nummenmaa's VB adaptive Kalman filter (unknown diagonal R), nonlinear form.

    Args:
        model: a vehjax model (nx states, ny outputs).
        Q: process noise covariance of the model's states, (nx, nx) or (nx,), known.
        R: the sensors' noise variances R0 as the prior states them, (m,) (one per ``sensors``,
            output units squared): the prior mean of the learnt diagonal R (its start), the
            prior IG(dof0, dof0 R0) having plug-in beta / alpha = R0. Only the sensors' block:
            the known outputs' noise is ``known_std``.
        form: "ekf" (linearisation by ``jax.jacfwd``), "ukf" (scaled unscented rule, alpha 1)
            or "ckf" (cubature rule) for every Gaussian integral.
        forgetting: rho in (0, 1] of the variances' dynamics (module docstring); 1: stationary.
        iterations: fixed-point iterations N >= 1 per step.
        dof0: alpha_0 > 0, the prior's weight (about 2 alpha_0 pseudo-measurements); a huge
            dof0 with forgetting 1 is a point mass at R0 (the filter is then the Kalman filter).
        sensors: outputs whose variance is learnt (default: every output not in known_std).
        known_std: {output: std} of outputs with known noise; outputs in neither are unused.
        augment: :class:`Augmentation`, the bias and offset states added to the Kalman state
            (their names, random walks and prior stds); the default adds none.
        input_noise: noise through the inputs (:mod:`vehjax.filters.input_noise`) or None.

    Returns:
        ``Estimator`` with state :class:`VBState`; ``param_names`` = ``<input>_offset...,
        <sensor>_bias..., <sensor>_std...`` (module docstring; units by :func:`param_units`).

    Raises:
        ValueError: naming the argument: form unknown, forgetting outside (0, 1], iterations
            < 1, dof0 <= 0, bad names, R not m positive variances, non-positive stds.
    """
    form, rho, N = _check_common(form, forgetting, iterations)
    a0 = validation.number("dof0", dof0, 0.0)
    st = _setup(model, Q, sensors, known_std, augment, input_noise)
    m = len(st.sens)
    R0m = _sensor_R0(R, m, tuple(str(model.output_names[i]) for i in st.sens))
    if np.any(R0m != np.diag(np.diag(R0m))):
        raise ValueError(
            "R: vbakf_r learns one variance per sensor (a diagonal R, the sensors' noises "
            "independent) and would drop the correlations of a full R; give the (m,) variances "
            "(np.diag(R)), or use vbakf_pr for a full covariance")
    R0 = np.diag(R0m)
    fm = _form(form, st.n, st.Lu)
    sens = st.sens

    def stats0(z, P, r0, theta):
        dt = z.dtype
        return VBState(z, P, jnp.full((m,), a0, dt), a0 * r0, theta)

    def step(state, y, u):
        z, P, alpha, beta, theta = state
        dt = z.dtype
        y, u, h, zp, Pp = _predicted(st, fm, z, P, y, u, theta)
        ap, bp = ig_predict(alpha, beta, rho)
        obs = jnp.isfinite(y[sens]).astype(dt)
        a_new = ap + 0.5 * obs
        mp = fm.measure(zp, Pp, h)
        y0 = jnp.where(jnp.isfinite(y), y, 0.0)
        kv = jnp.asarray(st.known_var, dt)

        def kalman(b):
            r_diag = kv.at[sens].set(b / a_new)
            Rh = jnp.diag(r_diag)
            joseph = (mp.H, Rh) if fm.joseph else None
            return masked_update(zp, Pp, y, mp.y_hat, mp.S + Rh, mp.C, joseph=joseph)

        def iterate(b):
            """One fixed-point iteration: the update with R^ = diag(b / alpha), then the new b."""
            r = kalman(b)
            E = _expected_outer(fm, r.x, r.P, h, y0)
            return r, ig_update(ap, bp, jnp.diagonal(E)[sens], obs)[1]

        # iteration 1 from beta-, then N - 1 more; the Gaussian returned is the last update's
        # (with beta^(N-1)), the statistics beta^(N), as in the paper's algorithm
        r, b_new = iterate(bp)
        r, b_new = jax.lax.fori_loop(1, N, lambda _, c: iterate(c[1]), (r, b_new))
        std, vs = std_moments(b_new / a_new, a_new)
        new = VBState(r.x, r.P, a_new, b_new, theta)
        return new, _report(st, r.x, r.P, std, vs, r.nis, r.loglik, r.n_obs)

    return _estimator(st, model, stats0, step, _param_prior(st, R0, a0),
                      f"VB-A{form.upper()}-R")


# --------------------------------------------------------------------------------------------
# Huang et al.: VBAKF-PR, inverse-Wishart predicted covariance and R


class VBPRState(NamedTuple):
    """State of :func:`vbakf_pr`.

    Attributes:
        x: filtered mean of the augmented state, (n,).
        P: its covariance, (n, n).
        u: IW degrees of freedom of the sensors' R, scalar.
        U: IW scale, (m, m), output units squared; R^ = U / (u - m - 1).
        P_pred: the last plug-in predicted covariance T / (t - n - 1), (n, n); its excess over the
            propagated covariance is the implied process noise.
        theta: model parameters, (np,).
    """

    x: jnp.ndarray
    P: jnp.ndarray
    u: jnp.ndarray
    U: jnp.ndarray
    P_pred: jnp.ndarray
    theta: jnp.ndarray


def vbakf_pr(model, Q, R, *, form: str = "ckf", forgetting: float = 1.0, iterations: int = 10,
             tau: float = 3.0, dof0: float | None = None, sensors=None, known_std=None,
             augment: Augmentation = Augmentation(), input_noise=None) -> Estimator:
    """Huang et al.'s VB adaptive Kalman filter with inaccurate Q and R, nonlinear form.

    Args:
        model: a vehjax model.
        Q: nominal process noise Q~ of the model's states, (nx, nx) or (nx,).
        R: the sensors' nominal noise covariance R0, (m, m) or (m,) variances (one per
            ``sensors``, output units squared): the prior mean of the learnt R, the prior being
            IW(dof0, (dof0 - m - 1) R0). Only the sensors' block: the known outputs' noise is
            ``known_std``.
        form: "ekf", "ukf" or "ckf" (see :func:`vbakf_r`).
        forgetting: rho in (0, 1] of R's IW dynamics.
        iterations: fixed-point iterations N >= 1.
        tau: tuning parameter >= 0 of the predicted covariance's IW prior (weight of the
            nominal P~-; the paper recommends 2..6; huge: P~- taken as exact).
        dof0: u_0 > m + 1; default m + 1 + 10 (ten samples' worth of R0).
        sensors, known_std, augment, input_noise: as in :func:`vbakf_r`.

    Returns:
        ``Estimator`` with state :class:`VBPRState`; ``param_names`` as :func:`vbakf_r`'s, the
        stds the square roots of diag(U / (u - m - 1)).

    Raises:
        ValueError: naming the argument (forgetting, iterations, tau, dof0, R, names, ...).
    """
    form, rho, N = _check_common(form, forgetting, iterations)
    tau = validation.number("tau", tau, 0.0, low_open=False)
    st = _setup(model, Q, sensors, known_std, augment, input_noise)
    m = len(st.sens)
    R0m = _sensor_R0(R, m, tuple(str(model.output_names[i]) for i in st.sens))
    u0 = m + 11.0 if dof0 is None else validation.number("dof0", dof0, m + 1.0)
    fm = _form(form, st.n, st.Lu)
    sens = st.sens
    n = st.n

    R0d = np.diag(R0m)

    def stats0(z, P, r0, theta):
        dt = z.dtype
        # theta0's stds replace R0's diagonal (correlations kept)
        s = jnp.sqrt(r0 / jnp.asarray(R0d, dt))
        R = jnp.asarray(R0m, dt) * s[:, None] * s[None, :]
        return VBPRState(z, P, jnp.asarray(u0, dt), (u0 - m - 1.0) * R, P, theta)

    def step(state, y, u):
        z, P, uu, U, _, theta = state
        dt = z.dtype
        y, u, h, zp, Pn = _predicted(st, fm, z, P, y, u, theta)
        t_pr, T_pr = iw_pred_cov_prior(Pn, tau)
        u_pr, U_pr = iw_predict(uu, U, rho, m)
        all_seen = jnp.all(jnp.isfinite(y[sens]))
        y0 = jnp.where(jnp.isfinite(y), y, 0.0)
        kv = jnp.asarray(st.known_var, dt)
        sel = jnp.asarray(np.eye(st.ny)[sens], dt)  # (m, ny) picks the sensors

        def kalman(Pp, Rs):
            Rh = jnp.diag(kv) + sel.T @ Rs @ sel
            mp = fm.measure(zp, Pp, h)
            joseph = (mp.H, Rh) if fm.joseph else None
            return masked_update(zp, Pp, y, mp.y_hat, mp.S + Rh, mp.C, joseph=joseph)

        def stats(x_i, P_i):
            dx = x_i - zp
            T = T_pr + jnp.outer(dx, dx) + P_i
            B = sel @ _expected_outer(fm, x_i, P_i, h, y0) @ sel.T
            Ui = jnp.where(all_seen, U_pr + B, U_pr)
            ui = jnp.where(all_seen, u_pr + 1.0, u_pr)
            return (sym(iw_plugin(t_pr + 1.0, T, n)), sym(iw_plugin(ui, Ui, m)), ui, Ui)

        def iterate(x_i, P_i):
            """One fixed-point iteration from q(x) = N(x_i, P_i): the IW statistics, then the
            update with their plug-ins."""
            Pp, Rs, ui, Ui = stats(x_i, P_i)
            return kalman(Pp, Rs), (Pp, ui, Ui)

        r, st_i = iterate(zp, Pn)
        r, (Pp, u_new, U_new) = jax.lax.fori_loop(
            1, N, lambda _, c: iterate(c[0].x, c[0].P), (r, st_i))
        # as the paper returns x^(N), P^(N), u^(N), U^(N) (the statistics of the last iteration,
        # from x^(N-1), P^(N-1)); loglik / NIS are those of the last update
        std, vs = std_moments(jnp.diagonal(iw_plugin(u_new, U_new, m)),
                              (u_new - m + 1.0) / 2.0 * jnp.ones(m, dt))
        new = VBPRState(r.x, r.P, u_new, U_new, Pp, theta)
        return new, _report(st, r.x, r.P, std, vs, r.nis, r.loglik, r.n_obs)

    return _estimator(st, model, stats0, step, _param_prior(st, R0d, (u0 - m + 1.0) / 2.0),
                      f"VB-A{form.upper()}-PR")
