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
draws (process noise and resampling uniforms), see :mod:`vehjax.runtime.prng` for why that is cheaper
than ``jax.random.normal`` in float64 mode on CPU. The process-noise standard normals are
Box-Muller transforms of float32 uniforms on a 2^-24 grid, scaled by chol(Q) in the working
precision: their resolution (~1e-7) and truncation (|z| <= 5.77) are far below the Monte-Carlo
error of any feasible particle count. Resampling uniforms use 32 random bits (24 in float32).

Layout. Particles are kept as (nx, N), one row per state component, and the model is vmapped
over the columns: each component is then one contiguous vector over the particles, which XLA on
CPU runs as one vectorised loop (``vehjax bench particle`` measures the model's cost in both
layouts, rows "model (N, nx)" and "model (nx, N)").
"""

from __future__ import annotations

import math
from functools import partial
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import validation
from . import input_noise as _inoise
from . import smc
from ..lib.entrywise import cholesky_observed
from ..lib.linalg import cholesky, is_pd, solve_lower
from .base import Backward, Dims, Estimator, ParamSpec, ParticleTransition, Runtime, StepOutput
from ._model import chol_const, check_model, in_dtype, model_dims, model_theta, prior

__all__ = ["PFState", "bootstrap_pf", "propagate", "residuals", "measurement_logliks",
           "predicted_nis", "reinit_factor", "resample_or_restart", "moved_estimate"]


class PFState(NamedTuple):
    """State of :func:`bootstrap_pf` for one run (``run`` adds a leading runs axis).

    Attributes:
        particles: (nx, N) particles after the last step (resampled when that step resampled),
            one row per state component: the model then runs each component over all
            particles as one contiguous vector operation (module docstring, "Layout").
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
    loop; for small n it is added row by row before the rows are stacked (each row one
    contiguous vector) rather than as two stacked (n, N) arrays.
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


# -- the mathematics of one step, one function each -------------------------------------------


def reinit_factor(cov, Q, LQ):
    """Noise factor of a re-initialisation: chol(P + Q) for the last estimate's covariance
    ``cov`` = P (n, n) and the process noise Q (n, n), or ``LQ`` = chol(Q) (n, n) when that
    factor is not finite. Returns (n, n) lower triangular."""
    L_re = cholesky(cov + Q)
    return jnp.where(jnp.all(jnp.isfinite(L_re)), L_re, LQ)


def propagate(transition, x, u, theta, L, z, Lu=None, z_u=None):
    """Particles moved by the model plus Gaussian noise, x_i' = f(x_i, u_i, theta) + L z_i.

    Args:
        transition: ``f(x, u, theta) -> x'`` of one point (nx,).
        x: (nx, N) particles, one column each.
        u: (nu,) the step's input, shared by every particle when ``Lu`` is None.
        theta: (np,) model parameters.
        L: (nx, nx) noise factor (chol(Q), in state units per step).
        z: (nx, N) standard normals.
        Lu: (nu, k) input-noise factor or None: particle i then runs with its own input
            u_i = u + Lu z_u[:, i] (:func:`vehjax.filters.input_noise.perturbed_inputs`).
        z_u: (k, N) standard normals for the inputs (with ``Lu``).

    Returns:
        (nx, N) propagated particles.
    """
    if Lu is None:
        fx = jax.vmap(transition, in_axes=(1, None, None), out_axes=1)(x, u, theta)
    else:
        fx = jax.vmap(transition, in_axes=(1, 1, None), out_axes=1)(
            x, _inoise.perturbed_inputs(u, Lu, z_u), theta)
    return _add_noise(fx, L, z)


def residuals(observe, x, y, u, theta):
    """Measurement residuals of every particle, with the particles that cannot be weighed.

    Args:
        observe: ``h(x, u, theta) -> y`` of one point.
        x: (nx, N) particles; y: (ny,) measurement, NaN or +-inf for a missing component;
        u: (nu,) input; theta: (np,) model parameters.

    Returns:
        (obs, e, bad, x): ``obs`` (ny,) bool, the observed components; ``e`` (ny, N) the
        residuals y - h(x_i) on them and 0 elsewhere; ``bad`` (N,) bool, particles whose state
        or residual is not finite; ``x`` (nx, N) with those particles' columns set to 0 (their
        residuals too), so that nothing not finite reaches the moments.
    """
    obs = jnp.isfinite(y)  # NaN and +-inf are missing, as in every vehjax filter
    h_all = jax.vmap(observe, in_axes=(1, None, None), out_axes=1)
    e = jnp.where(obs[:, None], y[:, None] - h_all(x, u, theta), 0.0)  # (ny, N)
    bad = ~(jnp.all(jnp.isfinite(x), axis=0) & jnp.all(jnp.isfinite(e), axis=0))
    return obs, jnp.where(bad, 0.0, e), bad, jnp.where(bad, 0.0, x)


def measurement_logliks(e, obs, R, r_diag=None):
    """log N(e_i; 0, R) of every particle over the observed components: e (ny, N), obs (ny,)
    bool, R (ny, ny) in output units squared; ``r_diag`` (ny,) its diagonal when R is diagonal
    (the cheaper form of :func:`vehjax.filters.smc.gaussian_logliks`). Returns (N,)."""
    if r_diag is not None:
        return smc.gaussian_logliks(e, obs, var=r_diag)
    return smc.gaussian_logliks(e, obs, L=cholesky_observed(R, obs))


def predicted_nis(e, prior_w, bad, R, obs):
    """Normalised innovation squared from the predicted measurement moments of the particles.

    With the prior weights W_i (renormalised over the particles that are not ``bad``) and the
    residuals e_i = y - h(x_i): r = sum_i W_i e_i (= y - y_hat), S = sum_i W_i (e_i - r)(e_i -
    r)^T + R, and NIS = r^T S^-1 r over the observed components (via Cholesky).

    Args:
        e: (ny, N) residuals, 0 on missing components; prior_w: (N,) prior weights;
        bad: (N,) bool, particles left out; R: (ny, ny); obs: (ny,) bool.

    Returns:
        scalar NIS.
    """
    wp = jnp.where(bad, 0.0, prior_w)
    wp = wp / jnp.maximum(jnp.sum(wp), jnp.finfo(e.dtype).tiny)
    r_hat, S_h = smc.moments(wp, e)
    w_nis = solve_lower(cholesky_observed(S_h + R, obs), r_hat)
    return w_nis @ w_nis


def resample_or_restart(resample, x, rw, u_res, scheme, threshold, pending, diverged):
    """The particles and weights the next step starts from, with their genealogy.

    ``resample`` (signature of :func:`vehjax.filters.smc.resample`) resamples ``x`` (nx, N)
    with the updated weights ``rw`` (:class:`vehjax.filters.smc.Reweighted`) and uniforms
    ``u_res``; where ``diverged`` the weights are made equal instead (the next step re-draws
    the particles). Returns (x_next (nx, N), log_w (N,), w (N,), ancestors (N,) int32): the
    column each particle descends from, ``arange(N)`` without resampling and after a
    re-initialisation (``pending``, this step's draw, or ``diverged``)."""
    n = rw.w.shape[-1]
    identity = jnp.arange(n, dtype=jnp.int32)
    (x_next, anc), lw_next, w_next, _ = resample(
        (x, identity), rw.w, rw.log_w, u_res, scheme, threshold)
    x_next, lw_next, w_next = smc.reinitialise(diverged, x_next, x_next, lw_next, w_next)
    return x_next, lw_next, w_next, jnp.where(pending | diverged, identity, anc)


def moved_estimate(transition, mean, u, theta):
    """The estimate of a step whose weights carry no information: the last estimate ``mean``
    (nx,) moved by the model, f(mean, u, theta), or ``mean`` itself when that is not finite."""
    m_re = transition(mean, u, theta)
    return jnp.where(jnp.all(jnp.isfinite(m_re)), m_re, mean)


# -- init and step, composed ------------------------------------------------------------------


class _Config(NamedTuple):
    """What a bootstrap PF is built with, fixed before tracing (see :func:`bootstrap_pf`).

    Attributes:
        model: the vehjax model; f, h: its transition and observation, in the state's dtype.
        nx: state dimension; n: particles N; k_u: input-noise dimension (0 without).
        Q, LQ: (nx, nx) numpy process-noise covariance and its factor (chol(Q); for a
            semi-definite Q, :func:`vehjax.filters._model.chol_const`'s).
        R: (ny, ny) numpy measurement-noise covariance; r_diag: its diagonal (ny,) when R is
            diagonal, else None.
        Lu: (nu, k_u) input-noise factor or None.
        scheme, threshold: resampling scheme and ESS threshold; resample: the resampling
            function (:func:`vehjax.filters.smc.resample` or one with its signature).
        uniform_stream: the counter stream of the resampling uniforms.
    """

    model: Any
    f: Callable
    h: Callable
    nx: int
    n: int
    k_u: int
    Q: np.ndarray
    LQ: Any
    R: np.ndarray
    r_diag: np.ndarray | None
    Lu: Any
    scheme: str
    threshold: float
    resample: Callable
    uniform_stream: int


def _init(cfg: _Config, x0, P0, theta0=None, P_theta0=None, key=None) -> PFState:
    """N particles drawn from N(x0, P0) with equal weights (see :func:`bootstrap_pf`)."""
    del P_theta0  # state-only filter
    if key is None:
        raise ValueError("key: bootstrap_pf draws its particles at random; pass a PRNG key")
    nx, n = cfg.nx, cfg.n
    x0, P0 = prior(nx, x0, P0)
    dtype = x0.dtype
    theta = model_theta(cfg.model, theta0, dtype)
    k_init, k_run = jax.random.split(key)
    z = jax.random.normal(k_init, (nx, n), dtype)
    particles = x0[:, None] + jnp.linalg.cholesky(P0) @ z
    return PFState(
        particles=particles,
        log_weights=jnp.full((n,), -math.log(n), dtype),
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


def _step(cfg: _Config, state: PFState, y, u):
    """One bootstrap PF step (module docstring): propagate, weigh, moments, NIS, resample."""
    nx, n = cfg.nx, cfg.n
    log_n = math.log(n)
    dtype = state.particles.dtype
    y, u = jnp.asarray(y).astype(dtype), jnp.asarray(u).astype(dtype)
    Qd, LQ, Rd = _const(cfg.Q, dtype), _const(cfg.LQ, dtype), _const(cfg.R, dtype)
    theta = state.theta
    key_next, key_step = smc.split(state.key)
    z = smc.normals(key_step, nx + cfg.k_u, n, dtype)  # (nx + k, N): state, then input noise

    # propagate (a re-initialisation pending from the last step draws the particles around
    # its estimate instead: all from the mean, noise covariance P + Q)
    pending = state.pending_reinit
    L_re = reinit_factor(state.cov, Qd, LQ)
    start = jnp.where(pending, state.mean[:, None], state.particles)
    x = propagate(cfg.f, start, u, theta, jnp.where(pending, L_re, LQ), z[:nx], cfg.Lu, z[nx:])
    prior_lw = jnp.where(pending, -log_n, state.log_weights)
    prior_w = jnp.where(pending, 1.0 / n, state.weights)

    # weigh: Gaussian log-likelihood of the observed components; particles that are not
    # finite get weight zero
    obs, e, bad, x = residuals(cfg.h, x, y, u, theta)
    n_obs = jnp.sum(obs, dtype=jnp.int32)
    r_diag = None if cfg.r_diag is None else _const(cfg.r_diag, dtype)
    ll = measurement_logliks(e, obs, Rd, r_diag)
    rw = smc.reweight(prior_lw, jnp.where(bad, -jnp.inf, ll))
    diverged = rw.underflow

    # weighted moments of the updated particles; a cloud collapsed onto one particle (R far
    # below the data's noise) has a singular covariance: re-initialised like an underflow
    mean, cov = smc.moments(rw.w, x)
    collapsed = ~rw.underflow & ~is_pd(cov)
    nis = predicted_nis(e, prior_w, bad, Rd, obs)

    # resample for the next step; after an underflow, equal weights (re-drawn next step)
    u_res = smc.uniforms(key_step, cfg.scheme, n, dtype, stream=cfg.uniform_stream)
    x_next, lw_next, w_next, anc = resample_or_restart(
        cfg.resample, x, rw, u_res, cfg.scheme, cfg.threshold, pending, diverged)

    # divergence: the estimate moves on with the model, its covariance grows by Q, and the
    # next step re-draws the particles around it
    mean_out = jnp.where(diverged, moved_estimate(cfg.f, state.mean, u, theta), mean)
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


# -- the filter -------------------------------------------------------------------------------


def bootstrap_pf(
    model,
    Q,
    R,
    *,
    n_particles: int = 1000,
    resampling: smc.Resampling = smc.Resampling(),
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
        resampling: :class:`~vehjax.filters.Resampling`: the scheme, the ESS rule (resample
            when ESS < ess_threshold * N; 0 never resamples, 1 whenever the weights are not all
            equal) and the resampling function (``resample``, e.g.
            :func:`vehjax.filters.smc.resample_stop_gradient`: the same forward pass, the
            resampling's score in the gradient, what :mod:`vehjax.tune` differentiates).
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
            positive definite, n_particles < 2, a ``resampling`` that is not a
            :class:`~vehjax.filters.Resampling` (which checks its own fields when made).
    """
    nx, ny = check_model(model)
    n = smc.check_n_particles(n_particles)
    resampling = validation.record("resampling", resampling, smc.Resampling)
    scheme, thr, resample = resampling.scheme, resampling.ess_threshold, resampling.function()
    Qn, Rn = validation.cov("Q", Q, nx, allow_psd=True), validation.cov("R", R, ny)
    Lu = _inoise.input_factor(input_noise, model.input_names)
    k_u = 0 if Lu is None else Lu.shape[1]
    f = in_dtype(model.transition)
    cfg = _Config(
        model=model, f=f, h=in_dtype(model.observe), nx=nx, n=n, k_u=k_u, Q=Qn,
        LQ=chol_const(Qn), R=Rn, r_diag=np.diagonal(Rn).copy() if _is_diagonal(Rn) else None,
        Lu=Lu, scheme=scheme, threshold=thr, resample=resample,
        uniform_stream=(nx + k_u + 1) // 2,  # after the noise rows' counters
    )
    return Estimator(
        init=partial(_init, cfg),
        step=partial(_step, cfg),
        name="bootstrap_pf",
        dims=Dims(nx=nx, **model_dims(model)),
        params=ParamSpec(names=()),
        runtime=Runtime(needs_key=True, workload="particles"),
        backward=Backward(particle_transition=None if Lu is not None else ParticleTransition(f, _chol_or_none(Qn))),
    )
