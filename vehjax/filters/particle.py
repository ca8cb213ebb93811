"""The bootstrap particle filter (Gordon, Salmond & Smith 1993) as an :class:`Estimator`.

Each step, for particles x_i and normalised weights W_i carried from the last step::

    x_i <- f(x_i, u_t, theta) + v_i,   v_i ~ N(0, Q)                      (propagate)
    l_i  = log N(y_t; h(x_i, u_t, theta), R), observed components only     (weigh)
    loglik_t = logsumexp_i(log W_i + l_i)                                  log p(y_t | y_1:t-1)
    log W_i <- log W_i + l_i - loglik_t
    mean, cov = weighted moments of the particles                          (output)
    resample when ESS = 1 / sum_i W_i^2 < ess_threshold * N                (for the next step)

``exp(sum_t loglik_t)`` is the standard unbiased estimator of the likelihood (Del Moral 2004);
its log, ``sum_t loglik_t``, is biased low by about half its variance. Weights stay in log space.

Divergence. When the weights collapse onto a single particle (the weighted covariance is not
positive definite, e.g. with R far below the data's noise), or when every particle's likelihood
underflows at a step (``loglik_t`` below
``log(finfo.tiny)``, about -708 in float64 and -87 in float32, or -inf/NaN because the model
returned nothing finite), the weights carry no information and the run is re-initialised around
its last estimate (m, P): that step outputs mean f(m, u_t, theta) and covariance P + Q, and the
next step draws all its particles afresh, from that mean propagated through the model plus noise
N(0, P + 2Q), with equal weights. ``StepOutput.reinit`` says so for that step (``vehjax.run``
reads it), ``state.flag_diverged`` is set and stays set, ``state.n_reinit`` counts such steps, and the step's ``loglik`` is ``loglik_t`` when it
is finite, ``log(finfo.tiny)`` otherwise. Outputs are never NaN. A single particle whose
propagated state or predicted measurement is not finite gets weight zero.

Random numbers. A step splits its key once and hashes counters with Threefry-2x32 for all its
draws (process noise and resampling uniforms), see :mod:`vehjax._random`: in float64 mode on CPU
that is several times cheaper than ``jax.random.normal``. The process-noise standard normals are
Box-Muller transforms of float32 uniforms on a 2^-24 grid, scaled by chol(Q) in the working
precision: their resolution (~1e-7) and truncation (|z| <= 5.77) are far below the Monte-Carlo
error of any feasible particle count. Resampling uniforms use 32 random bits (24 in float32).

Layout. Particles are kept as (nx, N), one row per state component, and the model is vmapped
over the columns: each component is then one contiguous vector over the particles, which halves
the cost of a vehicle model on CPU against (N, nx).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import _validate
from . import input_noise as _inoise
from . import resampling as _rs
from . import smc
from ._linalg import cholesky, is_pd, solve_lower
from .base import Estimator, ParticleTransition, StepOutput
from ._model import chol_const, check_model, in_dtype, model_dims, model_theta, prior

__all__ = ["PFState", "bootstrap_pf"]


class PFState(NamedTuple):
    """State of :func:`bootstrap_pf` for one run (``run`` adds a leading runs axis).

    Attributes:
        particles: (nx, N) particles after the last step (resampled when that step resampled),
            one row per state component: the model then runs each component over all
            particles as one contiguous vector operation, about twice as fast on CPU as (N, nx).
        log_weights: (N,) their normalised log weights (``logsumexp == 0``).
        weights: (N,) the same weights, ``exp(log_weights)``.
        key: (2,) uint32 raw Threefry-2x32 key for the next step's draws.
        theta: (np,) model parameters the filter uses (``theta0`` or the model's nominal ones).
        mean: (nx,) last state estimate (the prior mean before the first step).
        cov: (nx, nx) its covariance.
        ess: effective sample size 1 / sum W_i^2 after the last update, before resampling
            (0 after a step that diverged).
        pending_reinit: bool, the last step diverged; this step draws the particles afresh.
        flag_diverged: bool, True once any step had to re-initialise (see module docstring).
        n_reinit: int32, how many steps re-initialised.
        ancestors: (N,) int32, the genealogy for ancestor tracing: particle j descends from
            column ``ancestors[j]`` of the previous state's ``particles`` (its resampling index;
            ``arange(N)`` after a step that did not resample, at ``init``, and after a
            re-initialisation, which draws every particle afresh and breaks the genealogy).
    """

    particles: jnp.ndarray
    log_weights: jnp.ndarray
    weights: jnp.ndarray
    key: jnp.ndarray
    theta: jnp.ndarray
    mean: jnp.ndarray
    cov: jnp.ndarray
    ess: jnp.ndarray
    pending_reinit: jnp.ndarray
    flag_diverged: jnp.ndarray
    n_reinit: jnp.ndarray
    ancestors: jnp.ndarray


def _is_diagonal(A) -> bool:
    """Whether A is a constant (numpy) diagonal matrix."""
    return isinstance(A, np.ndarray) and A.ndim == 2 and A.shape[0] == A.shape[1] and not np.any(
        A - np.diag(np.diagonal(A))
    )


def _const(A, dtype):
    """A matrix in the filter's dtype: numpy stays a numpy constant, a traced array is cast."""
    if isinstance(A, np.ndarray):
        return A.astype(np.dtype(dtype))
    return jnp.asarray(A).astype(dtype)


def _add_noise(fx, L, z):
    """``fx + L @ z`` for fx (n, N), L (n, n) and normals z (n, N).

    The noise is a dot, so the normals are hashed once rather than once per use in a fused
    loop; for small n it is added row by row before the rows are stacked, which measured a few
    per cent faster on CPU than adding two stacked (n, N) arrays.
    """
    noise = L @ z
    n = fx.shape[0]
    if n * n > 64:
        return fx + noise
    return jnp.stack([fx[i] + noise[i] for i in range(n)])


def _chol_or_none(Q):
    """Lower Cholesky factor of Q (numpy for a constant, jax for a traced Q), None for a
    constant Q that is only positive semi-definite (its transition has no density)."""
    if not isinstance(Q, np.ndarray):
        return jnp.linalg.cholesky(Q)
    try:
        return np.linalg.cholesky(Q)
    except np.linalg.LinAlgError:
        return None


# -- the filter -------------------------------------------------------------------------------


def bootstrap_pf(
    model,
    Q,
    R,
    n_particles: int = 1000,
    resampling: str = "systematic",
    ess_threshold: float = 0.5,
    input_noise=None,
) -> Estimator:
    """Bootstrap particle filter: propagate through the model plus Gaussian noise, weigh by the
    Gaussian measurement likelihood, resample when the effective sample size drops.

    Args:
        model: a vehjax model: ``transition(x, u, theta)``, ``observe(x, u, theta)``.
        Q: process-noise covariance, (nx, nx) or (nx,) variances, positive definite, in state
            units squared per step; the noise is added after the transition.
        R: measurement-noise covariance, (ny, ny) or (ny,) variances, positive definite, in
            output units squared.
        n_particles: number of particles N >= 2.
        resampling: "systematic", "stratified", "multinomial" or "residual"
            (see :mod:`vehjax.filters.resampling`).
        ess_threshold: resample when ESS < ess_threshold * N; 0 never resamples, 1 resamples
            whenever the weights are not all equal.
        input_noise: noise entering through the inputs (:mod:`vehjax.filters.input_noise`):
            ``{input name: std}`` in the input's units or an (nu, nu) covariance in input units
            squared; None (default) for none. Each particle is propagated with its own input
            ``u_t + Lu z_i`` (z_i standard normal, drawn with the process noise), so the
            transition sees the input noise exactly; the measurement uses u_t. Q may then be
            zero.

    Returns:
        ``Estimator`` with ``needs_key=True``:

        ``init(x0, P0, theta0=None, P_theta0=None, key=None) -> PFState`` draws N particles
        (stored as ``particles`` (nx, N)) from
        N(x0, P0); x0 (nx,), P0 (nx, nx) positive definite or (nx,) variances. Their dtype sets
        the filter's (float32 priors run it in float32). ``theta0`` (np,) replaces the model's
        nominal parameters (the filter does not estimate them); ``P_theta0`` is ignored.
        ``key`` is required.

        ``step(state, y, u) -> (PFState, StepOutput)``, y (ny,) with NaN for missing components,
        u (nu,). StepOutput: ``mean`` (nx,) and ``cov`` (nx, nx) the weighted mean and
        (symmetrised) weighted covariance of the particles after the update; ``loglik`` the
        increment ``logsumexp(log W + l)``; ``nis`` the innovation y - y_hat normalised by
        S = R + weighted covariance of h(x_i), both from the propagated particles and their
        prior weights, observed components only; ``n_obs``; ``params`` (0,), ``params_cov``
        (0, 0). ``state.flag_diverged`` says whether the run ever re-initialised.

    Raises:
        ValueError: naming the argument, for a wrong model, a Q or R of the wrong shape or not
            positive definite, n_particles < 2, an unknown resampling scheme, an ess_threshold
            outside [0, 1].
    """
    nx, ny = check_model(model)
    n = smc.check_n_particles(n_particles, low=2)
    scheme = _rs.check_scheme(resampling)
    thr = smc.check_ess_threshold(ess_threshold)
    Qn, Rn = _validate.cov("Q", Q, nx, allow_psd=True), _validate.cov("R", R, ny)
    LQn = chol_const(Qn)
    Lu = _inoise.input_factor(input_noise, model.input_names)
    k_u = 0 if Lu is None else Lu.shape[1]
    r_diag = np.diagonal(Rn).copy() if _is_diagonal(Rn) else None
    uniform_stream = (nx + k_u + 1) // 2  # after the noise rows' counters
    log_n = math.log(n)
    f = in_dtype(model.transition)
    h = in_dtype(model.observe)
    f_all = jax.vmap(f, in_axes=(1, None, None), out_axes=1)
    f_each = jax.vmap(f, in_axes=(1, 1, None), out_axes=1)  # one input per particle
    h_all = jax.vmap(h, in_axes=(1, None, None), out_axes=1)

    def init(x0, P0, theta0=None, P_theta0=None, key=None):
        del P_theta0  # state-only filter
        if key is None:
            raise ValueError("key: bootstrap_pf draws its particles at random; pass a PRNG key")
        x0, P0 = prior(nx, x0, P0)
        dtype = x0.dtype
        theta = model_theta(model, theta0, dtype)
        k_init, k_run = jax.random.split(key)
        z = jax.random.normal(k_init, (nx, n), dtype)
        particles = x0[:, None] + jnp.linalg.cholesky(P0) @ z
        return PFState(
            particles=particles,
            log_weights=jnp.full((n,), -log_n, dtype),
            weights=jnp.full((n,), 1.0 / n, dtype),
            key=smc.raw_key(k_run),
            theta=theta,
            mean=x0,
            cov=P0,
            ess=jnp.asarray(float(n), dtype),
            pending_reinit=jnp.asarray(False),
            flag_diverged=jnp.asarray(False),
            n_reinit=jnp.asarray(0, jnp.int32),
            ancestors=jnp.arange(n, dtype=jnp.int32),
        )

    def step(state: PFState, y, u):
        dtype = state.particles.dtype
        y, u = jnp.asarray(y).astype(dtype), jnp.asarray(u).astype(dtype)
        Qd = _const(Qn, dtype)
        LQ = _const(LQn, dtype)
        theta = state.theta
        key_next, key_step = smc.split(state.key)
        z = smc.normals(key_step, nx + k_u, n, dtype)  # (nx + k, N): state, then input noise
        z, z_u = z[:nx], z[nx:]

        # propagate (a re-initialisation pending from the last step draws the particles
        # around its estimate instead: all from the mean, noise covariance P + Q)
        pending = state.pending_reinit
        L_re = cholesky(state.cov + Qd)
        L_re = jnp.where(jnp.all(jnp.isfinite(L_re)), L_re, LQ)
        start = jnp.where(pending, state.mean[:, None], state.particles)
        fx = (f_all(start, u, theta) if Lu is None
              else f_each(start, _inoise.perturbed_inputs(u, Lu, z_u), theta))
        x = _add_noise(fx, jnp.where(pending, L_re, LQ), z)
        prior_lw = jnp.where(pending, -log_n, state.log_weights)
        prior_w = jnp.where(pending, 1.0 / n, state.weights)

        # predict the measurement; particles that are not finite get weight zero
        obs = jnp.isfinite(y)  # NaN and +-inf are missing, as in every vehjax filter
        n_obs = jnp.sum(obs, dtype=jnp.int32)
        e = jnp.where(obs[:, None], y[:, None] - h_all(x, u, theta), 0.0)  # (ny, N)
        bad = ~(jnp.all(jnp.isfinite(x), axis=0) & jnp.all(jnp.isfinite(e), axis=0))
        x = jnp.where(bad, 0.0, x)
        e = jnp.where(bad, 0.0, e)

        # weigh: Gaussian log-likelihood of the observed components
        if r_diag is not None:
            ll = smc.gaussian_logliks(e, obs, var=_const(r_diag, dtype))
        else:
            ll = smc.gaussian_logliks(e, obs, L=smc.masked_chol(_const(Rn, dtype), obs))
        rw = smc.reweight(prior_lw, jnp.where(bad, -jnp.inf, ll))
        diverged = rw.underflow

        # weighted moments of the updated particles; a cloud collapsed onto one particle (R far
        # below the data's noise) has a singular covariance: re-initialised like an underflow
        mean, cov = smc.moments(rw.w, x)
        collapsed = ~rw.underflow & ~is_pd(cov)

        # NIS from the predicted measurement moments (prior weights, finite particles only)
        wp = jnp.where(bad, 0.0, prior_w)
        wp = wp / jnp.maximum(jnp.sum(wp), jnp.finfo(dtype).tiny)
        r_hat, S_h = smc.moments(wp, e)  # r_hat = y - y_hat on the observed components
        w_nis = solve_lower(smc.masked_chol(S_h + _const(Rn, dtype), obs), r_hat)
        nis = w_nis @ w_nis

        # resample for the next step; after an underflow, equal weights (re-drawn next step)
        u_res = smc.uniforms(key_step, scheme, n, dtype, stream=uniform_stream)
        identity = jnp.arange(n, dtype=jnp.int32)
        (x_next, anc), lw_next, w_next, _ = smc.resample(
            (x, identity), rw.w, rw.log_w, u_res, scheme, thr)
        x_next, lw_next, w_next = smc.reinitialise(diverged, x_next, x_next, lw_next, w_next)
        anc = jnp.where(pending | diverged, identity, anc)

        # divergence: the estimate moves on with the model, its covariance grows by Q, and the
        # next step re-draws the particles around it
        m_re = f(state.mean, u, theta)
        m_re = jnp.where(jnp.all(jnp.isfinite(m_re)), m_re, state.mean)
        mean_out = jnp.where(diverged, m_re, mean)
        cov_out = jnp.where(diverged | collapsed, state.cov + Qd, cov)
        diverged = diverged | collapsed
        new_state = PFState(
            particles=x_next,
            log_weights=lw_next,
            weights=w_next,
            key=key_next,
            theta=theta,
            mean=mean_out,
            cov=cov_out,
            ess=jnp.where(diverged, 0.0, smc.ess(rw.w)),
            pending_reinit=diverged,
            flag_diverged=state.flag_diverged | diverged,
            n_reinit=state.n_reinit + diverged.astype(jnp.int32),
            ancestors=anc,
        )
        out = StepOutput(
            mean=mean_out,
            cov=cov_out,
            loglik=smc.step_loglik(rw),
            nis=nis,
            n_obs=n_obs,
            params=jnp.zeros((0,), dtype),
            params_cov=jnp.zeros((0, 0), dtype),
            reinit=diverged,
        )
        return new_state, out

    return Estimator(
        init=init, step=step, nx=nx, param_names=(), name="bootstrap_pf", needs_key=True,
        # with input noise the transition density is not N(f(x, u), Q): no backward simulation
        particle_transition=None if Lu is not None else ParticleTransition(f, _chol_or_none(Qn)),
        workload="particles",
        **model_dims(model)
    )
