"""The fixed-grid consistent marginalized PF (not the paper's) as an
:class:`~vehjax.filters.base.Estimator`: each particle a Kalman filter of the model with the
steering offset and the sensor biases as constant states, at its own steering-noise variance on a
fixed grid that is never resampled, so the weights are the posterior over the grid (a
multiple-model filter over sigma_w). Why and how: :mod:`vehjax.filters.marginalized`'s docstring
in short, docs/marginalized.md ("The consistent filter") in full.

One step (every particle, entries over the particles):

1. predict the sensor statistics with forgetting (eq. 20; sigma_w^2 is the particle's, static);
2. the Kalman step with the noisy input's error as process noise at the particle's sigma_w^2,
   its sensor covariance the scored variances (or the inverse-Wishart mean), conditioning the
   joint of (x_t, z_t, w_t) on y_t; its Gaussian predictive of y_t is the particle's weight;
3. update the sensor statistics with the expected data (and the innovations' scoring terms);
4. weight the grid by the likelihood so far times its prior (Jeffreys' by default);
5. report the mixture's estimates, the steering std's from the grid's posterior where the grid
   does not resolve it (:mod:`.grid`). Nothing is drawn and nothing resampled.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np

from ... import validation
from .. import smc
from ...lib.entrywise import add, dot, entries, matmul, stack, sub
from ..base import Dims, Estimator, ParamSpec, Runtime, StepOutput
from . import means as _means
from .grid import grid_posterior, ridge_covariance, with_resolved_std
from .jeffreys import covariance_information, grid_derivative
from .jeffreys import log_prior as jeffreys_log_prior
from .kalman import input_noise_kalman_step
from .mixture import mixture_moments, mixture_nis
from .niw import niw_predict, niw_update, noise_estimates, static_prior_grid
from .parts import (finite_or_old, linear_noise_entries, linearisation, measured, sensor_data,
                    used_noise)
from .sensor_scoring import (plug_in_variance, prior_terms, ridge_sensitivity, scored_variances,
                             scoring_terms, weighted_covariance)
from .setup import ModelFns, NiW, Setup, configure, model_fns, std_dict
from .staging import stage, staged
from .state import MPFState, initial_state, prior_in_dtype

__all__ = ["InputStdGrid", "MeanStates", "marginalized_pf_grid"]


class InputStdGrid(NamedTuple):
    """The grid of the noisy input's std and its prior.

    Attributes:
        input_std_range: (low, high), 0 < low < high, the range of the noisy input's std (input
            units) over which the N particles' grid is log-uniform; its weights are
            ``input_std_prior``'s. None: a decade either side of the ``std0`` guess (Jeffreys'
            prior). The grid's spacing is log(high / low) / (N - 1) in log std (0.19 for 25
            points over a decade either side). Where the data pin the std more narrowly than
            that, its estimate and interval come from the Laplace approximation on the grid
            (:mod:`vehjax.filters.marginalized.grid`); the states still mix the grid's Kalman
            filters, each at its own std, so a finer grid still serves them better.
        input_std_prior: "jeffreys" (None, the default): Jeffreys' prior, each grid point
            weighted by the square root of the Fisher information the data so far carry about
            the std there (the covariance part, from the particles' predictive covariances;
            :mod:`vehjax.filters.marginalized.jeffreys`). "log-uniform": equal weights over
            ``input_std_range`` (required). "inverse-wishart": the grid over the
            inverse-Wishart prior's marginal of sigma_w^2 (``std0`` and ``nu0``; no
            ``input_std_range``), weighted by that prior (at the default nu0 it spans 0.35 to
            7.6 times the guess, 99 % of the prior between 0.42 and 2.7 times). A std that the
            data see only beside other noise has a likelihood flat below the truth; Jeffreys'
            prior takes the weight off that flat end, where equal weights leave the states'
            covariance too small and a prior at a guess above the truth too large (numbers:
            ``benchmarks/mpf_consistent_steering.py``). With Jeffreys' prior the reported
            ``loglik`` is each step's predictive under the prior at that step (the prior moves
            as information comes), not a marginal likelihood.
    """

    input_std_range: Any = None
    input_std_prior: str | None = None


class MeanStates(NamedTuple):
    """The steering offset and the sensor biases as constant Kalman states of each particle.

    Attributes:
        mean_std0: dict of their prior stds: the offset (key ``noisy_input``) and the biases
            (sensor names), the input's and outputs' units; missing names sqrt(gamma0) std0
            (the paper's NiW prior). A Kalman state's prior need not be tied to the noise std:
            give the size the offset and biases may have.
        bias_walk: dict sensor -> std per step of a random walk of its bias (sensor units;
            missing sensors 0: constant biases), the process noise of the bias states.
    """

    mean_std0: Any = None
    bias_walk: Any = None


class _Grid(NamedTuple):
    """The grid filter's own constants: the grid's range (None: from the guess or the
    inverse-Wishart prior), whether its prior is Jeffreys', whether the sensor variances are
    scored."""

    input_std_range: Any
    jeffreys_prior: bool
    scored_variances: bool


def _std_range(value):
    """Checked ``input_std_range``: None or (low, high) with 0 < low < high, finite."""
    if value is None:
        return None
    try:
        lo, hi = (float(v) for v in value)
    except (TypeError, ValueError):
        lo = hi = float("nan")
    if not (0.0 < lo < hi < math.inf) or isinstance(value, str):
        raise ValueError(f"input_std_range: expected (low, high) with 0 < low < high, got "
                         f"{value!r}")
    return lo, hi


INPUT_STD_PRIORS = ("jeffreys", "inverse-wishart", "log-uniform")
SENSOR_VARIANCES = ("inverse-wishart", "scored")


def _sensor_variances(value) -> bool:
    """Whether ``sensor_variances`` asks for the scored variances (None: scored, the
    default)."""
    if value is None:
        return True
    if value not in SENSOR_VARIANCES:
        raise ValueError(f"sensor_variances: expected one of {SENSOR_VARIANCES}, got {value!r}")
    return value == "scored"


def _input_std_prior(prior, std_range) -> bool:
    """Checked ``input_std_prior`` against ``input_std_range``: True for Jeffreys' prior."""
    if prior is None:
        prior = "jeffreys"
    if prior not in INPUT_STD_PRIORS:
        raise ValueError(f"input_std_prior: expected one of {INPUT_STD_PRIORS}, got {prior!r}")
    if prior == "log-uniform" and std_range is None:
        raise ValueError("input_std_prior: 'log-uniform' needs input_std_range=(low, high)")
    if prior == "inverse-wishart" and std_range is not None:
        raise ValueError("input_std_prior: 'inverse-wishart' spans its own grid; give no "
                         "input_std_range")
    return prior == "jeffreys"
def _scored_scale(s: Setup, lam_e, nu, v):
    """The sensor covariance's scale with the scored variances ``v`` (n_s, N)
    (:mod:`.sensor_scoring`): diagonal, (nu - d - 1) v; where v is NaN (not
    positive), Lambda_e's diagonal. The sensors' noises are taken as uncorrelated: Lambda_e's
    correlations come from the same slowly forgetting statistics, and kept they made the
    filter suboptimal (the r and roll-rate stds ended 1.1-1.4 % above the oracle's on the
    consistency study's data; docs/sensor_scoring.md). Also returns the variances
    it gives, (n_s, N)."""
    den = nu - s.noise_dim - 1.0
    lam_diag = jnp.diagonal(lam_e, axis1=0, axis2=1).T  # (ns, N)
    used = jnp.where(jnp.isnan(v), lam_diag / den, v)
    eye = jnp.eye(lam_e.shape[0], dtype=lam_e.dtype)[:, :, None]
    return eye * (den * used)[None], used


def _update(s: Setup, g: _Grid, mdl: ModelFns, x, m, P, lam_w, lam_e, y, obs, u, theta, nu_p,
            J, h, H, v_ref, v_est):
    """One step of every particle (module docstring): the Kalman
    step with the noisy input's error as process noise at the particle's own sigma_w^2
    (``lam_w``, static) and its sensor covariance (the inverse-Wishart statistics' mean; with
    scored sensor variances its variances the last step's scored ``v_est``, the scoring
    sums ``J``, ``h``, ``H`` updated with the prior guess ``v_ref``), the Gaussian predictive
    of y_t as the weight, the sensor statistics updated with the expected data (and the
    innovations' scoring terms). Returns (log-likelihoods (N,), x, z, P, None,
    lam_w, lam_e, predictive means (n_yu, N), predictive covariances (n_yu, n_yu, N), the
    posterior mean of w_t (N,)), then J, h, H after the step (None unless scored)."""
    nxs, nz, ns, srow = s.n_sampled, s.n_linear, s.n_sensors, s.sensor_rows
    nk = s.n_kalman
    nyu = len(s.used_rows)
    lin = linearisation(s, mdl, x, m, u, theta)
    ye = [y[i] for i in range(nyu)]
    ob = [obs[i] for i in range(nyu)]
    lam_use = lam_e
    if g.scored_variances:
        lam_use = stage(_scored_scale(s, lam_e, nu_p, v_est)[0])
    Pe, lee = entries(P), entries(lam_use)
    Qe = linear_noise_entries(s, x.dtype)
    inv_den = 1.0 / (nu_p - s.noise_dim - 1.0)
    R_s = [[lee[i][j] * inv_den for j in range(ns)] for i in range(ns)]
    sig_w2, R_y = stage((lam_w, used_noise(s, R_s)))
    post, C, o, ll, S = stage(input_noise_kalman_step(lin, Pe, sig_w2, ye, ob, [0.0] * nyu, R_y,
                                                      Qe))
    x_new = [add(lin.xb[k], post[k]) for k in range(nxs)]
    z_new = [add(lin.zb[i], post[nxs + i]) for i in range(nz)]
    P_new = [row[:nk] for row in C[:nk]]
    # the statistics' data: w's and the sensor residuals' posterior means and covariances
    Hs = [list(lin.Cx[r]) + list(lin.Cz[r]) + [lin.d[r]] for r in srow]
    eta_e = [sub(o[r], dot(Hs[j], post)) for j, r in enumerate(srow)]
    CH = matmul(Hs, C)
    V = [[dot(CH[i], Hs[j]) for j in range(ns)] for i in range(ns)]
    eta_e, extra = sensor_data(s, eta_e, V, ob, R_s)
    like = x[0]
    eta_v = stack([post[nk]] + eta_e, like)
    _, _, _, _, le_new = niw_update(0.0, nu_p, jnp.zeros_like(eta_v), lam_w, lam_e, eta_v,
                                    stack(extra, like), means_known=True)
    x_new, z_new, P_new = stack(x_new, like), stack(z_new, like), stack(P_new, like)
    if g.scored_variances:
        Wb, Wz, Hs_t = stage(scoring_terms(S, R_y, o, ob, srow, entries(v_ref)))
        J_new, h_new, H_new = J + stack(Wb, like), h + stack(Wz, like), H + stack(Hs_t, like)
        ll, (x_new, z_new, P_new, le_new, J_new, h_new, H_new) = finite_or_old(
            ll, (x_new, z_new, P_new, le_new, J_new, h_new, H_new), (x, m, P, lam_e, J, h, H))
    else:
        J_new = h_new = H_new = None
        ll, (x_new, z_new, P_new, le_new) = finite_or_old(
            ll, (x_new, z_new, P_new, le_new), (x, m, P, lam_e))
    mu_y = stack([lin.yb[i] for i in range(nyu)], like)
    # lam_w (the particle's sigma_w^2) is static: returned as it came
    return (ll, x_new, z_new, P_new, None, lam_w, le_new, mu_y, stack(S, like),
            post[nk] + 0.0 * like, J_new, h_new, H_new)


def _grid_start(s: Setup, g: _Grid, state: MPFState, x0, P0, theta0) -> MPFState:
    """The grid filter's start: every particle the prior (sampled, linear order), its own
    sigma_w^2 a point of the grid, and the grid's prior weights; with Jeffreys' prior no
    information yet, with scored variances the scoring sums of the prior alone."""
    x0, P0, th, dtype = prior_in_dtype(s, x0, P0, theta0)
    nl, li, n, ns = s.sampled_idx, s.linear_idx, s.n_particles, s.n_sensors
    order = np.concatenate([nl, li]).astype(int)
    Pk = P0[np.ix_(order, order)]
    sd_w, sd_e = th[1], th[2 + ns:]
    scale = s.nu0 - s.noise_dim - 1.0
    log_w0 = state.log_weights
    if g.input_std_range is None and not g.jeffreys_prior:
        lam_w, log_w0 = static_prior_grid(state.lam_w[0], s.nu0 - s.noise_dim + 1.0, n)
    else:  # log-uniform over the range, by default a decade either side of the guess
        lo, hi = g.input_std_range or (sd_w * 0.1, sd_w * 10.0)
        lam_w = jnp.exp(jnp.linspace(2.0 * jnp.log(lo), 2.0 * jnp.log(hi), n, dtype=dtype))
    extra = {}
    if g.jeffreys_prior:
        extra = dict(info=jnp.zeros((n,), dtype), base_log_weights=log_w0)
    if g.scored_variances:
        v_ref = jnp.broadcast_to((sd_e ** 2)[:, None], (ns, n))
        J0, h0 = prior_terms(v_ref, scale)
        extra.update(var_info=J0, var_stat=h0, var_sand=J0, var_ref=v_ref, var_est=v_ref)
    return state._replace(
        x=jnp.broadcast_to(x0[nl][:, None], (s.n_sampled, n)),
        z=jnp.broadcast_to(x0[li][:, None], (s.n_linear, n)),
        P=jnp.broadcast_to(Pk[:, :, None], (s.n_kalman, s.n_kalman, n)),
        lam_w=lam_w, log_weights=log_w0, weights=jnp.exp(log_w0), **extra)


def _step(s: Setup, g: _Grid, mdl: ModelFns, state: MPFState, y, u):
    """One step of the grid filter over the augmented model (module docstring)."""
    dtype = state.x.dtype
    y0, obs, n_obs, u, theta = measured(s, mdl, y, u, dtype)
    with staged(u):
        return _staged_step(s, g, mdl, state, y0, obs, n_obs, u, theta)


def _weights(g: _Grid, state: MPFState, ll, cov_y, lam_w, obs, n):
    """The grid's weights after the step: the likelihood so far times the prior (Jeffreys' of
    the information so far, or the grid's own). Returns (reweighting, underflow, w, log w,
    the state's Jeffreys fields)."""
    rw = smc.reweight(state.log_weights, ll)  # the step's predictive and its underflow
    under = rw.underflow
    jeff = {}
    if g.jeffreys_prior:  # the likelihood so far times Jeffreys' prior of the information so far
        info = state.info + covariance_information(
            cov_y, grid_derivative(cov_y, jnp.log(lam_w)), obs)
        base = smc.reweight(state.base_log_weights, ll)
        under = under | base.underflow
        rj = smc.reweight(base.log_w, jeffreys_log_prior(info))
        base_lw = jnp.where(under, -math.log(n), base.log_w)
        jeff = dict(info=info, base_log_weights=base_lw)
        rw_w, rw_lw = rj.w, rj.log_w
    else:
        rw_w, rw_lw = rw.w, rw.log_w
    w_now = jnp.where(under, 1.0 / n, rw_w)
    lw_now = jnp.where(under, -math.log(n), rw_lw)
    return rw, under, w_now, lw_now, jeff


def _estimates(s: Setup, g: _Grid, w_now, lw_now, mu, lam_w, lam_e, nu, gamma, v_est, J,
               var_cov):
    """Eq. 23's estimates over the grid: the scored sensor variances and what their plug-in
    adds to sigma_w's variance, sigma_w's from the grid's posterior where the grid is too
    coarse."""
    lam_rep, w_extra = lam_e, None
    t = jnp.log(lam_w)
    post = grid_posterior(lw_now, t)
    if g.scored_variances:  # the scored sensor variances, and what their plug-in adds
        lam_rep, v_used = _scored_scale(s, lam_e, nu, v_est)
        cov_vt = jnp.where(post.narrow, ridge_covariance(post, t, v_used),
                           weighted_covariance(w_now, t, v_used))
        grad = ridge_sensitivity(w_now, t, v_used, J, cov_vt)
        w_extra = 0.25 * lam_w * plug_in_variance(grad, var_cov)
    params, params_cov = noise_estimates(w_now, mu, lam_w, lam_rep, nu, gamma,
                                        means_known=True, var_cov=var_cov,
                                        input_var_extra=w_extra)
    within = 0.0 if w_extra is None else jnp.sum(w_now * w_extra)
    return with_resolved_std(params, params_cov, 1, post, within)


def _staged_step(s: Setup, g: _Grid, mdl: ModelFns, state: MPFState, y0, obs, n_obs, u, theta):
    n = s.n_particles
    gam_p, nu_p, _, le_p = niw_predict(state.gamma, state.nu, state.lam_w, state.lam_e,
                                       s.forgetting)
    key_next, _ = smc.split(state.key)
    lam = s.forgetting
    sums = ((lam * state.var_info, lam * state.var_stat, lam * state.var_sand, state.var_ref,
             state.var_est) if g.scored_variances else (None,) * 5)
    # nothing drawn; sigma_w^2 is the particle's static value, not forgotten
    ll, x, z, P, _, lam_w, lam_e, mu_y, cov_y, w_draw, J, h, H = _update(
        s, g, mdl, state.x, state.z, state.P, state.lam_w, le_p, y0, obs, u, theta, nu_p, *sums)
    mu = state.mu
    scoring, v_est, var_cov = {}, None, None
    if g.scored_variances:  # the scored variances (J^-1 h does not see the forgetting)
        v_est, var_cov = scored_variances(J, h, H)
        J, h, H, v_est, var_cov = stage((J, h, H, v_est, var_cov))
        scoring = dict(var_info=J, var_stat=h, var_sand=H, var_ref=state.var_ref, var_est=v_est)
    gamma = gam_p / (1.0 + gam_p)
    nu = nu_p + 1.0
    rw, under, w_now, lw_now, jeff = _weights(g, state, ll, cov_y, lam_w, obs, n)
    mean, cov = mixture_moments(s, w_now, x, z, P)
    params, params_cov = _estimates(s, g, w_now, lw_now, mu, lam_w, lam_e, nu, gamma, v_est, J,
                                    var_cov)
    nis = mixture_nis(state.weights, mu_y, cov_y, y0, obs)
    # a fixed grid of sigma_w^2: never resampled
    new_state = MPFState(
        x=x, z=z, P=P, mu=mu, lam_w=lam_w, lam_e=lam_e, gamma=gamma, nu=nu,
        log_weights=lw_now, weights=w_now, key=key_next,
        ess=jnp.where(under, 0.0, smc.ess(w_now)),
        flag_diverged=state.flag_diverged | under,
        n_reinit=state.n_reinit + under.astype(jnp.int32),
        offset=w_draw, ancestors=jnp.arange(n, dtype=jnp.int32), **jeff, **scoring,
    )
    out = StepOutput(mean=mean, cov=cov, loglik=smc.step_loglik(rw), nis=nis, n_obs=n_obs,
                     params=params, params_cov=params_cov, reinit=under)
    return new_state, out


def _options(means, grid):
    """Checked types of ``means`` and ``grid`` (None: the defaults) and the grid's constants."""
    means = MeanStates() if means is None else means
    grid = InputStdGrid() if grid is None else grid
    if not isinstance(means, MeanStates):
        raise ValueError(f"means: expected vehjax.filters.marginalized.MeanStates(...), got "
                         f"{means!r}")
    if not isinstance(grid, InputStdGrid):
        raise ValueError(f"grid: expected vehjax.filters.marginalized.InputStdGrid(...), got "
                         f"{grid!r}")
    return means, grid


def marginalized_pf_grid(
    model,
    n_particles: int = 500,
    *,
    noisy_input: str = "delta",
    sensors=("ay", "r", "roll_rate"),
    known_std=None,
    linear_states=("phi", "phi_dot", "phi_ddot"),
    Q=None,
    niw: NiW | None = None,
    means: MeanStates | None = None,
    grid: InputStdGrid | None = None,
    sensor_variances: str | None = None,
) -> Estimator:
    """The consistent marginalized PF over a fixed grid of the noisy input's std (not the
    paper's; module docstring): the offset and the sensor biases as constant states of each
    particle's Kalman filter (exact Gaussian posterior, correlated with the states and each
    other; prior N(mean0, gamma0 std0^2) or ``means.mean_std0``), the input error as process
    noise (not drawn), each particle a Kalman filter over every state at its own steering
    variance on a fixed grid (never resampled: the weights are the posterior over it), the
    sensor variances learnt by scoring. The model must be affine in ``noisy_input`` (checked
    with the linear states). The estimator declares no Rao-Blackwell structure
    (``vehjax.smooth`` does not smooth it). Its cost per step against the paper's filter:
    ``vehjax reproduce noise-learning`` measures both.

    Args:
        model, noisy_input, sensors, known_std, linear_states, Q, niw: as
            :func:`~vehjax.filters.marginalized.marginalized_pf`'s (``niw``: the sensor
            covariances' inverse-Wishart statistics, and the means' prior by ``gamma0``).
        n_particles: N >= 2, the grid's points.
        means: :class:`MeanStates`, the prior stds of the offset and bias states and their
            random walks; None: ``MeanStates()``.
        grid: :class:`InputStdGrid`, the grid's range and prior; None: ``InputStdGrid()``
            (Jeffreys' prior over a decade either side of the guess).
        sensor_variances: how the sensor variances are learnt. "scored" (default, None): Fisher
            scoring of the innovations weighted at the ``std0`` guess, with a sandwich
            covariance, the sensors' noises taken as uncorrelated, and sigma_w's reported
            variance widened by their plug-in (:mod:`vehjax.filters.marginalized.
            sensor_scoring`). "inverse-wishart": the mean of the inverse-Wishart statistics
            (sensor correlations included), which a sensor seen beside other noise (ay beside
            the steering noise's direct term) forgets its start only slowly from; 0.6 times the
            scored option's time per step.

    Returns:
        ``Estimator`` as :func:`~vehjax.filters.marginalized.marginalized_pf`'s (over the
        model's own states and the same ``param_names`` and ``param_prior``), without
        ``rao_blackwell``.

    Raises:
        ValueError: naming the argument, as :func:`~vehjax.filters.marginalized.marginalized_pf`
            does, and for a bad ``means`` (``mean_std0``, ``bias_walk``), ``grid``
            (``input_std_range``, ``input_std_prior``) or ``sensor_variances``, or a model
            that already has states named as the added ones.
    """
    means, grid = _options(means, grid)
    validation.model(model)
    smc.check_n_particles(n_particles)  # before the augmented model is built (it computes)
    sensors = validation.names("sensors", sensors, tuple(model.output_names))
    linear_states = validation.names("linear_states", linear_states, tuple(model.state_names),
                                    allow_empty=True)
    if not isinstance(noisy_input, str) or noisy_input not in tuple(model.input_names):
        raise ValueError(f"noisy_input: expected one of the model's inputs "
                         f"{tuple(model.input_names)}, got {noisy_input!r}")
    extra = _means.mean_state_names(sensors, noisy_input)
    clash = [n for n in extra if n in tuple(model.state_names)]
    if clash:
        raise ValueError(f"model: already has states named {clash}, which "
                         f"marginalized_pf_grid adds (the offset and the biases)")
    aug = _means.with_noise_means(model, sensors, noisy_input)
    Q = _means.pad_linear_noise(Q, len(linear_states), len(extra),
                                hasattr(model, "bank_noise_gain"))
    s_user = configure(aug, n_particles, noisy_input, sensors, known_std,
                       tuple(linear_states) + extra, Q, niw, "all")
    ns, nx = s_user.n_sensors, len(model.state_names)
    names = (noisy_input,) + tuple(sensors)
    msd = std_dict("mean_std0", {} if means.mean_std0 is None else means.mean_std0, (), names,
                   "input and output units")
    # prior stds of the added states (biases, then the offset); NaN: sqrt(gamma0) std0
    mean_sd = np.array([msd.get(k, np.nan) for k in tuple(sensors) + (noisy_input,)])
    mi = np.concatenate([[0], np.arange(2, 2 + ns)])  # offset and biases in params order
    walk = _means.bias_walk_stds(means.bias_walk, sensors)
    Qz = np.array(s_user.linear_noise)
    Qz[-ns - 1:-1, -ns - 1:-1] = np.diag(walk ** 2)
    # the filter's own NiW: the offset's and the sensors' means zero and known
    prior = np.where(np.isin(np.arange(2 + 2 * ns), mi), 0.0, s_user.theta_prior)
    s = s_user._replace(linear_noise=Qz, theta_prior=prior)
    g = _Grid(input_std_range=_std_range(grid.input_std_range),
              jeffreys_prior=_input_std_prior(grid.input_std_prior, grid.input_std_range),
              scored_variances=_sensor_variances(sensor_variances))
    mdl = model_fns(aug, s)

    def init(x0, P0, theta0=None, P_theta0=None, key=None):
        del P_theta0
        validation.prior(nx, x0, P0)
        p = len(s.param_names)
        if theta0 is not None and np.shape(theta0) != (p,):
            raise ValueError(f"theta0: expected shape ({p},) for {s.param_names}, got "
                             f"{np.shape(theta0)}")
        th = jnp.asarray(s_user.theta_prior if theta0 is None else theta0)
        th = th.astype(jnp.result_type(th.dtype, jnp.asarray(x0).dtype, float))
        xa, Pa = _means.augment_prior(x0, P0, th, s_user.gamma0, ns, mean_sd)
        th_filter = th.at[mi].set(0.0)
        state = initial_state(s, xa, Pa, th_filter, None, key)
        return _grid_start(s, g, state, xa, Pa, th_filter)

    def step(state, y, u):
        state, out = _step(s, g, mdl, state, y, u)
        params, params_cov = _means.map_estimates(out.mean, out.cov, out.params,
                                                  out.params_cov, nx, ns)
        return state, out._replace(mean=out.mean[:nx], cov=out.cov[:nx, :nx], params=params,
                                   params_cov=params_cov)

    return Estimator(
        init=init,
        step=step,
        name="marginalized_pf_grid",
        dims=Dims(nx=nx, ny=s.n_outputs, nu=s.n_inputs),
        params=ParamSpec(names=s.param_names, prior=(s_user.theta_prior, s_user.P_prior)),
        runtime=Runtime(needs_key=True, workload="small_dense"),
    )
