"""The paper's filter: Algorithm 1 of Berntorp & Di Cairano 2018 (paper 004) as an
:class:`~vehjax.filters.base.Estimator`. The reading of the paper behind each formula is in
:mod:`vehjax.filters.marginalized`.

Time convention (vehjax's, see :mod:`vehjax.run`): step t takes the particles x_{t-1}, the input
u_t and the measurement y_t, where x_t = f(x_{t-1}, u_t + w_t) and y_t = h(x_t, u_t + w_t): the
same offset sample w_t drives the transition into x_t and enters y_t directly (eq. 6 and 8, where
the paper indexes the pre-transition state by k). One step is Algorithm 1 with its loops rotated
so that w_t is drawn given y_t (the paper's sec. 3.5 choice: eq. 30 conditions on the innovation):

1. predict the statistics with forgetting (eq. 20);
2. weight every particle by the Student-t predictive p(y_t | x_{0:t-1}, y_{0:t-1}) (eq. 26-27),
   which marginalises w_t, the sensor noise and its parameters, and the bank;
3. draw w_t from its Student-t conditional given y_t (eq. 30) and set
   x_t = f(x_{t-1}, u_t) + A_bar z_hat + g w_t (eq. 6);
4. Kalman-update the bank with y_t and the vehicle model (sec. 3.4);
5. update the statistics with the data (w_t, e_t) (eq. 18-19);
6. report the weighted estimates (eq. 23), then resample when the ESS is low (for the next step).

Random numbers: two standard-normal rows per step from the particle core (:mod:`smc`), one for
the t draw and one for its chi-square through the Wilson-Hilferty cube (Johnson, Kotz &
Balakrishnan 1994, eq. 18.25; its base floored at 0.1, which only touches dof < 10 beyond 3.4
sigma), and the resampling uniforms. Resampling is ``smc.resample`` unless the caller passes
another function (``resample=``).
"""

from __future__ import annotations

import functools
import math
from typing import Callable, NamedTuple

import jax.numpy as jnp

from ... import validation
from .. import smc
from ...lib.entrywise import add, dot, entries, matmul, mul, stack, sub
from ..base import Backward, Dims, Estimator, ParamSpec, Runtime, StepOutput
from .contract import LinearStep, RBTransition
from .kalman import bank_kalman_step, joint_kalman_step, joint_prediction
from .linearise import linearise
from .mixture import mixture_moments, mixture_nis
from .niw import (draw_offset, niw_predict, niw_update, noise_estimates, t_predictive,
                  t_weight_and_proposal)
from .parts import (finite_or_old, linear_noise_entries, linearisation, measured, sensor_data,
                    used_noise)
from .setup import ModelFns, NiW, Setup, configure, model_fns
from .staging import stage, staged
from .state import MPFState, initial_state

__all__ = ["marginalized_pf"]


class _Resampling(NamedTuple):
    """How the paper's filter resamples: the scheme, the ESS threshold and the function."""

    scheme: str
    ess_threshold: float
    resample: Callable


def _kalman_stage(s: Setup, lin, Pe, Qe, w, dw, dx, x_new, ye, ob, eta, mu_w, b_y, sig_w2, R_y,
                  D):
    """The particles' Kalman step after the draw of w_t and the sensor residuals for the
    statistics: (x_t, z_t entries, P_t entries, sensor residuals, their covariance from the
    Kalman posterior)."""
    nxs, nz, srow = s.n_sampled, s.n_linear, s.sensor_rows
    ns = len(srow)
    if s.gaussian_states:
        xi, C, o2 = stage(joint_kalman_step(lin, Pe, w, ye, ob, b_y, R_y, Qe, D))
        x_new = [add(x_new[k], xi[k]) for k in range(nxs)]
        z_new = [add(add(lin.zb[i], mul(lin.gz[i], w)), xi[nxs + i]) for i in range(nz)]
        Hs = [list(lin.Cx[r]) + list(lin.Cz[r]) for r in srow]
        eta_e = [sub(o2[r], dot(Hs[j], xi)) for j, r in enumerate(srow)]
        CP = matmul(Hs, C)
        V = [[dot(CP[i], Hs[j]) for j in range(ns)] for i in range(ns)]
        return x_new, z_new, C, eta_e, V
    if nz:
        s3, P3, o2, _ = stage(bank_kalman_step(lin, Pe, dx, ye, ob, mu_w, b_y, sig_w2, R_y, Qe))
        z_new = [add(add(lin.zb[i], mul(lin.gz[i], mu_w)), s3[i]) for i in range(nz)]
        eta_e = [sub(sub(o2[r], dot(lin.Cz[r], s3)), mul(lin.d[r], dw)) for r in srow]
        CP = matmul([lin.Cz[r] for r in srow], P3)
        V = [[dot(CP[i], lin.Cz[srow[j]]) for j in range(ns)] for i in range(ns)]
        return x_new, z_new, P3, eta_e, V
    # o2 = y - yb - Cx dx - d mu_w - b_y = eta - Cx g (w - mu_w)
    eta_e = [sub(sub(eta[r], mul(dot(lin.Cx[r], lin.g), dw)), mul(lin.d[r], dw)) for r in srow]
    return x_new, [], [], eta_e, [[0.0] * ns for _ in range(ns)]


def _particle_update(s: Setup, mdl: ModelFns, x, m, P, mu, lam_w, lam_e, z1, z2, y, obs, u,
                     theta, gam, nu_p):
    """One step for all particles (entries over the last axis) before the weights are
    normalised: the Student-t weight (eq. 26-27), the draw of w_t (eq. 30, eq. 6), the Kalman
    step and the statistics update (eq. 18-19). The statistics come in predicted (eq. 20).
    y, obs: (n_yu,) the used rows. Returns (log-likelihoods (N,), x, z, P, mu, lam_w, lam_e,
    predictive means (n_yu, N), predictive covariances (n_yu, n_yu, N), offset draws (N,))."""
    dtype = x.dtype
    nxs, nz, ns = s.n_sampled, s.n_linear, s.n_sensors
    spos, kvu = s.sensor_of_row, s.known_variances
    nyu = len(s.used_rows)
    lin = linearisation(s, mdl, x, m, u, theta)
    ye = [y[i] for i in range(nyu)]
    ob = [obs[i] for i in range(nyu)]
    Pe, lee = entries(P), entries(lam_e)
    Qe = linear_noise_entries(s, dtype)
    mu_w = mu[0]
    b = [mu[1 + j] for j in range(ns)]
    b_y = [b[spos[i]] if i in spos else 0.0 for i in range(nyu)]
    # predictive of y (eq. 26): w and the sensor noise through the NiW, the rest moment-matched
    mu_y, S, D, sw, df = t_predictive(lin, Pe, Qe, lam_w, lee, mu_w, b_y, gam, nu_p,
                                      s.noise_dim, kvu, spos, nxs if s.gaussian_states else 0)
    ll, shift, sc, dfy, eta = stage(t_weight_and_proposal(
        ye, ob, mu_y, S, [mul(sw, v) for v in D], sw, df))
    # draw w_t from eq. 30 (Student-t via Wilson-Hilferty) and propagate (eq. 6)
    w = draw_offset(mu_w, shift, sc, dfy, z1, z2)
    dw = w - mu_w
    dx = [mul(gk, w) for gk in lin.g]
    x_new = [add(lin.xb[k], dx[k]) for k in range(nxs)]
    w, dw, dx, x_new = stage((w, dw, dx, x_new))
    # bank Kalman step and the sensor residuals, with the point estimates of eq. 23
    inv_den = 1.0 / (nu_p - s.noise_dim - 1.0)
    sig_w2 = lam_w * inv_den
    R_s = [[lee[i][j] * inv_den for j in range(ns)] for i in range(ns)]
    R_y = used_noise(s, R_s)
    x_new, z_new, P3, eta_e, V = _kalman_stage(s, lin, Pe, Qe, w, dw, dx, x_new, ye, ob, eta,
                                               mu_w, b_y, sig_w2, R_y, D)
    eta_e, V = stage((eta_e, V))
    eta_e, extra = sensor_data(s, eta_e, V, ob, R_s)
    like = x[0]
    _, _, mu_new, lw_new, le_new = niw_update(gam, nu_p, mu, lam_w, lam_e,
                                             stack([dw] + eta_e, like), stack(extra, like))
    x_new = stack(x_new, like)
    z_new = stack(z_new, like) if nz else m
    P_new = stack(P3, like) if nz else P
    ll, kept = finite_or_old(ll, (x_new, z_new, P_new, mu_new, lw_new, le_new),
                              (x, m, P, mu, lam_w, lam_e))
    cov_y = stack(S, like) * (df / (df - 2.0))
    return (ll, *kept, stack(mu_y, like), cov_y, w)
def _rb_predict(s: Setup, mdl: ModelFns, x, z, P, w, u, theta):
    """:attr:`RBTransition.predict`: the linearisation at the particle's means and
    :func:`joint_prediction` with its draw w."""
    lin = linearise(mdl.transition, mdl.observe, x, z, u, theta, s.sampled_idx, s.linear_idx,
                    s.input_idx)
    return joint_prediction(lin, w, P, jnp.asarray(s.linear_noise, x.dtype))


def _step(s: Setup, rule: _Resampling, mdl: ModelFns, state: MPFState, y, u):
    """The filter's ``step`` (module docstring, steps 1-6)."""
    dtype = state.x.dtype
    y0, obs, n_obs, u, theta = measured(s, mdl, y, u, dtype)
    with staged(u):
        return _staged_step(s, rule, mdl, state, y0, obs, n_obs, u, theta)


def _staged_step(s: Setup, rule: _Resampling, mdl: ModelFns, state: MPFState, y0, obs, n_obs, u,
                 theta):
    n = s.n_particles
    dtype = state.x.dtype
    gam_p, nu_p, lw_p, le_p = niw_predict(state.gamma, state.nu, state.lam_w, state.lam_e,
                                          s.forgetting)
    key_next, key_step = smc.split(state.key)
    zn = stage(smc.normals(key_step, 2, n, dtype))
    ll, x, z, P, mu, lam_w, lam_e, mu_y, cov_y, w_draw = _particle_update(
        s, mdl, state.x, state.z, state.P, state.mu, lw_p, le_p, zn[0], zn[1],
        y0, obs, u, theta, gam_p, nu_p)
    gamma = gam_p / (1.0 + gam_p)
    nu = nu_p + 1.0
    rw = smc.reweight(state.log_weights, ll)  # the step's predictive and its underflow
    under = rw.underflow
    w_now = jnp.where(under, 1.0 / n, rw.w)
    lw_now = jnp.where(under, -math.log(n), rw.log_w)

    mean, cov = mixture_moments(s, w_now, x, z, P)
    params, params_cov = noise_estimates(w_now, mu, lam_w, lam_e, nu, gamma)
    nis = mixture_nis(state.weights, mu_y, cov_y, y0, obs)

    # resample for the next step
    # the draws and the particles' own indices ride along: the genealogy for smoothing
    parts = (x, mu, lam_w, lam_e, w_draw, jnp.arange(n, dtype=jnp.int32)) + (
        (z, P) if s.n_linear else ())  # no empty leaves
    u_res = smc.uniforms(key_step, rule.scheme, n, dtype, stream=1)
    parts, lw_next, w_next, _ = rule.resample(parts, w_now, lw_now, u_res, rule.scheme,
                                              rule.ess_threshold)
    x, mu, lam_w, lam_e, w_draw, anc = parts[:6]
    if s.n_linear:
        z, P = parts[6:]
    new_state = MPFState(
        x=x, z=z, P=P, mu=mu, lam_w=lam_w, lam_e=lam_e, gamma=gamma, nu=nu,
        log_weights=lw_next, weights=w_next, key=key_next,
        ess=jnp.where(under, 0.0, smc.ess(w_now)),
        flag_diverged=state.flag_diverged | under,
        n_reinit=state.n_reinit + under.astype(jnp.int32),
        offset=w_draw, ancestors=anc,
    )
    out = StepOutput(mean=mean, cov=cov, loglik=smc.step_loglik(rw), nis=nis, n_obs=n_obs,
                     params=params, params_cov=params_cov, reinit=under)
    return new_state, out


def marginalized_pf(
    model,
    n_particles: int = 500,
    *,
    noisy_input: str = "delta",
    sensors=("ay", "r", "roll_rate"),
    known_std=None,
    linear_states=("phi", "phi_dot", "phi_ddot"),
    Q=None,
    niw: NiW | None = None,
    kalman_states: str = "linear",
    resampling: smc.Resampling = smc.Resampling(),
) -> Estimator:
    """Noise-adaptive marginalized particle filter (Berntorp & Di Cairano 2018): the state, an
    unknown-mean unknown-variance input error and the biases and covariance of some sensors,
    with the affine substate in a Kalman filter per particle (:mod:`vehjax.filters.marginalized`
    and this module's docstring).

    Args:
        model: a vehjax model, e.g. :class:`~vehjax.models.bank.SingleTrackBank`.
        n_particles: N >= 2.
        noisy_input: the input whose error w ~ N(mu_w, sigma_w^2) is learnt (eq. 4-5), in
            ``model.input_names``.
        sensors: outputs with noise N(b, R) of unknown bias and covariance (eq. 7-8), at least
            one, in ``model.output_names``.
        known_std: dict output -> std of zero-mean Gaussian noise known a priori (phi_m and the
            virtual yaw rate of eq. 10); outputs in neither are not used.
        linear_states: states entering transition and observe affinely (checked), estimated by
            a Kalman filter per particle (eq. 3, sec. 3.4); () for the planar filter. States
            that are neither linear states nor driven by ``noisy_input`` are particles without
            process noise: each particle keeps the value it drew from P0 (or its consequence).
            For the planar filter on a model with bank states (SingleTrackBank) give those
            states a negligible variance in P0 (e.g. 1e-20): with a 1e-3 rad/s^2 spread on
            phi_ddot each particle's bank grows by 1.8 rad a minute and the offset and ay bias
            drift to explain it.
        Q: the linear states' process noise covariance per step: for a model with
            ``bank_noise_gain()`` a scalar sigma_phi^2 of eq. 3 [rad^2/s^6] (the covariance
            sigma_phi^2 B B^T on the linear states); otherwise, or given as one value per
            linear state, additive variances (a diagonal covariance); or the (n, n) covariance
            of the n linear states. Required when there are linear states; >= 0.
        niw: :class:`~vehjax.filters.marginalized.NiW`, the noise statistics' start (``std0``,
            required; ``mean0``, ``gamma0``, ``nu0``) and their ``forgetting`` (eq. 17-20).
        resampling: :class:`~vehjax.filters.Resampling`: the scheme, the ESS rule (resample
            when ESS < ess_threshold * N) and the resampling function (``resample``, e.g.
            :func:`vehjax.filters.smc.resample_stop_gradient`, what :mod:`vehjax.tune` builds
            the filter with to differentiate its log-likelihood).
        kalman_states: what each particle's Kalman filter covers. "linear" (the paper's
            Algorithm 1): the linear states; a particle's other states are a point, x_t built
            by eq. 6 from the bank's Kalman mean. "all": every state; a particle is a sequence
            of offset draws and carries the Gaussian of all states given them, so the bank's
            uncertainty reaches vy and r (with known noise statistics this is exact for models
            affine in the states: it matches the exact Kalman filter, where "linear" reports
            vy's variance about 8 % too small on SingleTrackBank;
            :mod:`vehjax.filters.marginalized`). 1.2-1.3x
            the time per step. No difference without linear states.

    Returns:
        ``Estimator`` (``needs_key=True``), ``nx`` = all model states, ``param_names`` =
        ``<noisy_input>_offset, <noisy_input>_std, <sensor>_bias..., <sensor>_std...`` in SI
        units. ``init(x0, P0, theta0=None, P_theta0=None, key)``: x0 (nx,), P0 over all model
        states (the bank's Kalman filters start from the Gaussian conditional of the linear
        states given each particle); ``theta0``, when given, replaces the guesses (offset, std,
        biases, stds) of ``niw.mean0``/``niw.std0`` (``P_theta0`` is ignored).
        ``step(state, y, u)``:
        StepOutput ``mean``/``cov`` the weighted mean and covariance over all model states
        (linear states from the mixture of the Kalman filters), ``params`` eq. 23's estimates,
        ``params_cov`` their mixture covariance, ``loglik`` log p(y_t | y_1:t-1) of the used
        components, ``nis`` and ``n_obs`` over them, ``reinit`` when every weight underflowed
        (the weights are then reset to equal, the particles kept).

    Raises:
        ValueError: naming the argument: unknown input, sensor, known-std output or state
            names, a name in both ``sensors`` and ``known_std``, a model not affine in the linear
            states, non-positive stds, a negative ``Q``, lambda outside (0, 1] or
            too small for nu0, gamma0 <= 0, nu0 <= d + 1, n_particles < 2, a bad
            kalman_states, a ``niw`` that is not a :class:`~vehjax.filters.marginalized.NiW`,
            or a ``resampling`` that is not a :class:`~vehjax.filters.Resampling` (which checks
            its own fields when made).
    """
    resampling = validation.record("resampling", resampling, smc.Resampling)
    rule = _Resampling(scheme=resampling.scheme, ess_threshold=resampling.ess_threshold,
                       resample=resampling.function())
    s = configure(model, n_particles, noisy_input, sensors, known_std, linear_states,
                  Q, niw, kalman_states)
    mdl = model_fns(model, s)
    linear = LinearStep(
        transition=mdl.transition, observe=mdl.observe, sampled_idx=s.sampled_idx,
        linear_idx=s.linear_idx, input_idx=s.input_idx, used_rows=s.used_rows,
        sensor_rows=s.sensor_rows, known_variances=s.known_variances,
        linear_noise=s.linear_noise, forgetting=s.forgetting, noise_dim=s.noise_dim)
    rb = RBTransition(predict=functools.partial(_rb_predict, s, mdl), theta=mdl.theta,
                      order=s.model_order, nz=s.n_linear, gauss=s.gaussian_states, linear=linear)
    return Estimator(
        init=functools.partial(initial_state, s),
        step=functools.partial(_step, s, rule, mdl),
        name="marginalized_pf",
        dims=Dims(nx=s.n_states, ny=s.n_outputs, nu=s.n_inputs),
        params=ParamSpec(names=s.param_names, prior=(s.theta_prior, s.P_prior)),
        runtime=Runtime(needs_key=True, workload="small_dense"),
        backward=Backward(rao_blackwell=rb),
    )
