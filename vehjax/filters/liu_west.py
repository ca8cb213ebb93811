"""Liu-West particle filter for the parameters + UKF for the state (Dutta et al. 2019, Alg. 3).

The parameters named in ``estimate`` are carried as M weighted particles theta_i (physical units),
drawn at ``init`` from a uniform prior on the box [theta_low, theta_high]. The state is estimated
by a UKF (:func:`vehjax.filters.gaussian.ukf`) that runs the model at the weighted parameter mean.
One step, with (mu, P) the UKF's filtered state from the last step and W_i the carried weights::

    y_i   = h(f(mu, u_t, theta_i), u_t, theta_i)                           (one-step prediction)
    log W_i <- log W_i + log N(y_t; y_i, S)  then normalised                (weigh, log space)
    mean, V = weighted mean and covariance of the theta_i
    resample when ESS = 1 / sum W_i^2 < ess_threshold * M                   (vehjax resampling)
    m_i = a theta_i + (1 - a) mean,  theta_i <- N(m_i, h^2 V),  h^2 = 1 - a^2   (Liu-West kernel)
    theta_bar = sum_i W_i theta_i                                           (StepOutput.params)
    W_i <- gamma W_i + (1 - gamma) / M                                      (residual weight)
    UKF predict + update with theta_bar

The kernel keeps the weighted mean and covariance of the cloud: E[sum W_i m_i] = mean and the
mixture covariance is a^2 V + h^2 V = V (Liu & West 2001), so it restores diversity without the
over-dispersion of plain jittering.

Choices where the transcription of Algorithm 3 is unclear:

* Likelihood covariance S. The paper weighs with the measurement noise only (its Q, vehjax's
  ``R``): S = R. Every particle is predicted from the same filtered state mu, whose error is
  common to all of them; with S = R a filter whose state error exceeds the measurement noise
  weighs particles by how well they explain that common error. ``likelihood="predictive"``
  (the default) uses instead the UKF's innovation covariance S = Cov[h(f(x))] + R of the
  one-step prediction from (mu, P) at the last parameter mean, the covariance of y_t given the
  past and theta; ``likelihood="measurement"`` is the paper's S = R.
* gamma, "the residual weight factor". The algorithm's last line ``w_t = gamma w_t`` multiplies
  every weight by the same number, which the next step's normalisation undoes. The text says a
  fraction gamma of each particle's weight is carried to later steps so that good particles that
  happen to perform poorly are not eliminated; we read the remaining fraction 1 - gamma as
  spread evenly: W_i <- gamma W_i + (1 - gamma) / M after the estimate is formed. Every particle
  then keeps at least (1 - gamma) / M of the weight going into the next step (and the ESS at
  least ~1 / gamma^2); gamma = 1 is Liu and West's filter.
* V is the weighted covariance of the particles (the transcription's formula for V is garbled).
  To keep it positive definite when the cloud collapses, 1e3 * eps * (theta_high - theta_low)^2
  is added to its diagonal (eps the dtype's machine epsilon: a standard deviation of 5e-7 of the
  box width in float64), both in the kernel and in ``params_cov``.
* The kernel does not confine particles to the box; a particle whose prediction is not finite
  (e.g. a negative mass) gets weight zero.
* The parameter prior is the box: ``theta0``/``P_theta0`` are not needed. ``run`` and ``filter``
  report the box's centre and covariance diag((high - low)^2 / 12) as the estimate of a run
  that diverges at its first step (``Estimator.param_prior``).

Weights, ESS, resampling and moments are the shared particle core :mod:`vehjax.filters.smc`
(particles (p, M), particle axis last); the state UKF and the predictive S are the shared
sigma-point core :mod:`vehjax.filters.sigma`.

Divergence: when every particle's weight underflows at a step (log-sum of the updated weights
below ``log(finfo.tiny)``, or not finite), that step keeps the prior weights (no update, no
kernel), and the next step starts from M fresh draws from the uniform prior with equal weights;
``StepOutput.reinit`` says so (``vehjax.run`` reads it), ``state.flag_diverged`` is set and stays set and ``state.n_reinit``
counts such steps. Outputs are never NaN from the particle part.

Missing measurements: NaN components of y_t are skipped in the weights and in the UKF update. A
step with every component missing leaves the particles and weights untouched (no resampling, no
kernel, no gamma) and the UKF only predicts.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import _validate
from . import resampling as _rs
from . import sigma, smc
from ._linalg import cholesky
from .base import Estimator, check_estimate
from ._model import check_model, in_dtype, model_dims, prior
from .gaussian import GaussianState, ukf

__all__ = ["LiuWestState", "liu_west_ukf"]

_LIKELIHOODS = ("predictive", "measurement")


class LiuWestState(NamedTuple):
    """State of :func:`liu_west_ukf` for one run (``run`` adds a leading runs axis).

    Attributes:
        x: (nx,) the UKF's filtered state mean (x0 before the first step).
        P: (nx, nx) its covariance.
        particles: (p, M) parameter particles (particle axis last), physical units, after the
            last step's kernel.
        log_weights: (M,) their normalised log weights (``logsumexp == 0``), residual weight
            applied.
        key: (2,) uint32 threefry2x32 key data for the next step's draws.
        theta_mean: (p,) the parameter estimate the UKF last ran with (the prior box's mean
            before the first step).
        theta_cov: (p, p) its covariance (weighted covariance of the cloud plus jitter).
        ess: effective sample size after the last update, before resampling (0 after a step
            that diverged).
        flag_diverged: bool, True once any step had to re-initialise (see module docstring).
        n_reinit: int32, how many steps re-initialised.
    """

    x: jnp.ndarray
    P: jnp.ndarray
    particles: jnp.ndarray
    log_weights: jnp.ndarray
    key: jnp.ndarray
    theta_mean: jnp.ndarray
    theta_cov: jnp.ndarray
    ess: jnp.ndarray
    flag_diverged: jnp.ndarray
    n_reinit: jnp.ndarray


# -- validation (before anything is traced) --------------------------------------------------


def _check_box(theta_low, theta_high, names) -> tuple[np.ndarray, np.ndarray]:
    p = len(names)
    out = []
    for arg, v in (("theta_low", theta_low), ("theta_high", theta_high)):
        try:
            a = np.array(v, dtype=float).reshape(-1) if np.ndim(v) <= 1 else np.asarray(v)
        except (TypeError, ValueError):
            raise ValueError(f"{arg}: expected {p} numbers for {names}, got {v!r}") from None
        if a.shape != (p,):
            raise ValueError(
                f"{arg}: expected shape ({p},), one bound per estimated parameter {names}, "
                f"got shape {np.shape(v)}"
            )
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{arg}: expected finite values, got {a}")
        out.append(a)
    low, high = out
    if np.any(low >= high):
        bad = [n for n, lo, hi in zip(names, low, high) if lo >= hi]
        raise ValueError(
            f"theta_low, theta_high: expected theta_low < theta_high for every parameter; "
            f"not so for {bad} (low {low}, high {high})"
        )
    return low, high


# -- helpers ----------------------------------------------------------------------------------


def _kernel(key, particles, mean, V, a: float):
    """Liu-West move of particles (p, M): N(a theta_i + (1 - a) mean, (1 - a^2) V), V (p, p).

    With weights W summing to 1 whose weighted mean and covariance of ``particles`` are
    ``mean`` and ``V``, the moved cloud has the same weighted mean and covariance in expectation.
    """
    L_V = cholesky(V)
    # drawn (M, p) and transposed: the same normals per particle and parameter as in the
    # (M, p) layout this filter had before the shared particle core
    z = jax.random.normal(key, particles.shape[::-1], dtype=particles.dtype).T
    return a * particles + (1.0 - a) * mean[:, None] + math.sqrt(1.0 - a * a) * (L_V @ z)


def _draw_box(key, low, high, n):
    """n uniform draws from the box, (p, n)."""
    u = jax.random.uniform(key, (n, low.shape[0]), dtype=low.dtype).T  # as drawn (M, p) before
    return low[:, None] + (high - low)[:, None] * u


# -- the filter -------------------------------------------------------------------------------


def liu_west_ukf(
    model,
    Q,
    R,
    n_particles: int = 1000,
    estimate=None,
    theta_low=None,
    theta_high=None,
    a: float = 0.98,
    gamma: float = 1.0,
    resampling: str = "systematic",
    ess_threshold: float = 0.5,
    likelihood: str = "predictive",
    alpha: float = 1.0,
    beta: float = 2.0,
    kappa: float = 0.0,
) -> Estimator:
    """Liu-West particle filter for the parameters ``estimate`` plus a UKF for the state.

    Args:
        model: a vehjax model: ``transition(x, u, theta)``, ``observe(x, u, theta)``.
        Q: process-noise covariance of the state, (nx, nx) or (nx,) variances, state units
            squared per step (the paper's R_s).
        R: measurement-noise covariance, (ny, ny) or (ny,) variances, output units squared (the
            paper's Q).
        n_particles: number of parameter particles M >= 1.
        estimate: names of the estimated parameters, a subset of ``model.param_names`` (p of
            them); the others stay at ``model.theta``.
        theta_low, theta_high: (p,) bounds of the uniform prior, physical units, low < high.
        a: Liu-West shrinkage in (0, 1); the kernel variance is h^2 V with h^2 = 1 - a^2.
            Liu and West's discount factor delta in [0.95, 0.99] gives a = (3 delta - 1) /
            (2 delta) in [0.974, 0.995].
        gamma: residual weight factor in (0, 1]: the fraction of each particle's weight carried
            to the next step, the rest spread evenly (module docstring). 1 is plain Liu-West.
        resampling: "systematic", "stratified", "multinomial" or "residual"
            (see :mod:`vehjax.filters.resampling`).
        ess_threshold: resample when ESS < ess_threshold * M, in [0, 1]; 1 resamples every step
            whose weights are not all equal, 0 never.
        likelihood: "predictive" (S = the UKF's one-step innovation covariance) or
            "measurement" (S = R, as in the paper); see the module docstring.
        alpha, beta, kappa: the UKF's sigma-point scaling
            (:func:`vehjax.filters.sigma.unscented_rule`).

    Returns:
        ``Estimator`` with ``needs_key=True`` and ``param_names = estimate``:

        ``init(x0, P0, theta0=None, P_theta0=None, key=None) -> LiuWestState``: x0 (nx,), P0
        (nx, nx) or (nx,) variances: the UKF's prior (their dtype sets the filter's). The
        parameter prior is the uniform box, M draws with equal weights; ``theta0`` (p,) and
        ``P_theta0`` (p, p) are only checked for shape and otherwise not used (``vehjax.run``
        requires them of parameter-estimating filters and reports them as the estimate of a run
        that diverges at its first step: the box's centre and covariance diag((high - low)^2 /
        12) are natural values). ``key`` is required.

        ``step(state, y, u) -> (LiuWestState, StepOutput)``, y (ny,) with NaN for missing
        components, u (nu,). StepOutput: ``mean`` (nx,), ``cov`` (nx, nx), ``loglik``, ``nis``,
        ``n_obs`` from the UKF's update at the parameter estimate; ``params`` (p,) the weighted
        mean of the particles after the kernel, ``params_cov`` (p, p) their weighted
        covariance plus the jitter above.

    Raises:
        ValueError: naming the argument, for a wrong model, Q or R of the wrong shape or not
            positive definite, n_particles < 1, unknown or empty ``estimate``, bounds of the wrong
            length or not low < high, a outside (0, 1), gamma outside (0, 1], an unknown
            resampling scheme or likelihood, ess_threshold outside [0, 1].
    """
    nx, ny = check_model(model)
    names, idx = check_estimate(model, estimate)
    p = len(names)
    if theta_low is None or theta_high is None:
        raise ValueError(
            "theta_low, theta_high: required, the bounds of the uniform prior of " f"{names}"
        )
    low_n, high_n = _check_box(theta_low, theta_high, names)
    n = smc.check_n_particles(n_particles)
    a = _validate.number("a", a, 0.0, 1.0)
    gamma = _validate.number("gamma", gamma, 0.0, 1.0, high_open=False)
    scheme = _rs.check_scheme(resampling)
    thr = smc.check_ess_threshold(ess_threshold)
    likelihood = _validate.choice("likelihood", likelihood, _LIKELIHOODS)
    Qn, Rn = _validate.cov("Q", Q, nx, allow_psd=True), _validate.cov("R", R, ny)
    rule = sigma.unscented_rule(nx, alpha, beta, kappa)
    state_filter = ukf(model, Qn, Rn, alpha=alpha, beta=beta, kappa=kappa)
    idx_a = np.asarray(idx)
    log_n = math.log(n)
    n_unif = _rs.uniforms_needed(scheme, n)
    predictive = likelihood == "predictive"
    f, hobs = in_dtype(model.transition), in_dtype(model.observe)

    def full_theta(base, values):
        """Model parameter vector(s) with the estimated entries set: values (..., p)."""
        shape = values.shape[:-1] + base.shape
        return jnp.broadcast_to(base, shape).at[..., idx_a].set(values)

    def predict_one(x, u, th):
        return hobs(f(x, u, th), u, th)

    predict_all = jax.vmap(predict_one, in_axes=(None, None, 0))

    def jitter(dtype):
        eps = float(np.finfo(np.dtype(dtype)).eps)
        return jnp.asarray(np.diag(1e3 * eps * (high_n - low_n) ** 2), dtype)

    def init(x0, P0, theta0=None, P_theta0=None, key=None):
        x0, P0 = prior(nx, x0, P0)
        dtype = x0.dtype
        if theta0 is not None and np.shape(theta0) != (p,):
            raise ValueError(
                f"theta0: expected shape ({p},) for parameters {names} or None (the prior is "
                f"the box), got shape {np.shape(theta0)}"
            )
        if P_theta0 is not None and np.shape(P_theta0) != (p, p):
            raise ValueError(
                f"P_theta0: expected shape ({p}, {p}) for parameters {names} or None, "
                f"got shape {np.shape(P_theta0)}"
            )
        if key is None:
            raise ValueError("key: liu_west_ukf draws random numbers; pass key=jax.random.key(...)")
        low, high = jnp.asarray(low_n, dtype), jnp.asarray(high_n, dtype)
        k_run, k_draw = jax.random.split(key)
        return LiuWestState(
            x=x0,
            P=P0,
            particles=_draw_box(k_draw, low, high, n),
            log_weights=jnp.full((n,), -log_n, dtype),
            key=smc.raw_key(k_run),
            theta_mean=0.5 * (low + high),
            theta_cov=jnp.diag((high - low) ** 2 / 12.0),
            ess=jnp.asarray(float(n), dtype),
            flag_diverged=jnp.asarray(False),
            n_reinit=jnp.asarray(0, jnp.int32),
        )

    def step(state: LiuWestState, y, u):
        dtype = state.x.dtype
        y, u = jnp.asarray(y).astype(dtype), jnp.asarray(u).astype(dtype)
        base = jnp.asarray(model.theta).astype(dtype)
        low, high = jnp.asarray(low_n, dtype), jnp.asarray(high_n, dtype)
        Rd = jnp.asarray(Rn, dtype)
        k_next, k_res, k_kernel, k_box = smc.jax_keys(state.key, 4)
        obs = jnp.isfinite(y)
        has_obs = jnp.any(obs)
        theta_prev = full_theta(base, state.theta_mean)

        # weigh: one-step prediction of every particle from the UKF's filtered mean
        y_i = predict_all(state.x, u, full_theta(base, state.particles.T))  # (M, ny)
        e = jnp.where(obs, y[None, :] - y_i, 0.0)
        bad = ~jnp.all(jnp.isfinite(e), axis=1)
        e = jnp.where(bad[:, None], 0.0, e)
        if predictive:
            x_pred, P_pred = sigma.predict(rule, state.x, state.P,
                                           lambda v: f(v, u, theta_prev), jnp.asarray(Qn, dtype))
            S = sigma.measure(rule, x_pred, P_pred, lambda v: hobs(v, u, theta_prev), Rd).S
        else:
            S = Rd
        L = smc.masked_chol(S, obs)
        L = jnp.where(jnp.all(jnp.isfinite(L)), L, smc.masked_chol(Rd, obs))  # broken S: R
        ll = smc.gaussian_logliks(e.T, obs, L=L)
        rw = smc.reweight(state.log_weights, jnp.where(bad, -jnp.inf, ll))
        diverged = has_obs & rw.underflow
        keep = diverged | ~has_obs
        lw = jnp.where(keep, state.log_weights, rw.log_w)
        w = jnp.exp(lw)

        # Liu-West: resample when the weights degenerate, then shrink towards the mean and jitter
        mean, V = smc.moments(w, state.particles)
        ess = smc.ess(w)
        u_res = jax.random.uniform(k_res, (n_unif,), dtype=dtype)
        parts, lw_k, _, _ = smc.resample(state.particles, w, lw, u_res, scheme, thr)
        moved = _kernel(k_kernel, parts, mean, V + jitter(dtype), a)
        move = ~keep & jnp.all(jnp.isfinite(moved))
        parts = jnp.where(move, moved, state.particles)
        lw_k = jnp.where(move, lw_k, lw)

        # parameter estimate: weighted moments of the moved cloud
        theta_bar, cov_bar = smc.moments(jnp.exp(lw_k), parts)
        cov_bar = cov_bar + jitter(dtype)

        # residual weight: a fraction gamma of each weight goes on, the rest evenly
        if gamma < 1.0:
            lw_next = jnp.logaddexp(math.log(gamma) + lw_k, math.log1p(-gamma) - log_n)
        else:
            lw_next = lw_k
        lw_next = jnp.where(move, lw_next, lw_k)

        # divergence: the next step starts from fresh draws from the prior box
        fresh = _draw_box(k_box, low, high, n)
        parts_next, lw_next, _ = smc.reinitialise(diverged, fresh, parts, lw_next,
                                                  jnp.exp(lw_next))

        # state: UKF at the parameter estimate
        ukf_state, out = state_filter.step(
            GaussianState(state.x, state.P, full_theta(base, theta_bar)), y, u
        )
        new_state = LiuWestState(
            x=ukf_state.x,
            P=ukf_state.P,
            particles=parts_next,
            log_weights=lw_next,
            key=jax.random.key_data(k_next),
            theta_mean=theta_bar,
            theta_cov=cov_bar,
            ess=jnp.where(diverged, 0.0, jnp.where(has_obs, ess, state.ess)),
            flag_diverged=state.flag_diverged | diverged,
            n_reinit=state.n_reinit + diverged.astype(jnp.int32),
        )
        return new_state, out._replace(params=theta_bar, params_cov=cov_bar, reinit=diverged)

    box = (0.5 * (low_n + high_n), np.diag((high_n - low_n) ** 2 / 12.0))
    return Estimator(
        init=init, step=step, nx=nx, param_names=names, name="liu_west_ukf", needs_key=True,
        param_prior=box, **model_dims(model),
    )
