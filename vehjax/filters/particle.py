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

Divergence. When every particle's likelihood underflows at a step (``loglik_t`` below
``log(finfo.tiny)``, about -708 in float64 and -87 in float32, or -inf/NaN because the model
returned nothing finite), the weights carry no information and the run is re-initialised around
its last estimate (m, P): that step outputs mean f(m, u_t, theta) and covariance P + Q, and the
next step draws all its particles afresh, from that mean propagated through the model plus noise
N(0, P + 2Q), with equal weights. ``state.flag_diverged`` is set and stays set (``vehjax.run``
reads it), ``state.n_reinit`` counts such steps, and the step's ``loglik`` is ``loglik_t`` when it
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
import operator
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from .. import _random
from . import resampling as _rs
from .base import Estimator, StepOutput
from .gaussian import _check_model, _prior, _theta, check_cov


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


# -- validation (before anything is traced) --------------------------------------------------


def _check_n_particles(n_particles) -> int:
    try:
        n = operator.index(n_particles)
    except TypeError:
        n = 0
    if isinstance(n_particles, (bool, np.bool_)) or n < 1:
        raise ValueError(f"n_particles: expected an int >= 1, got {n_particles!r}")
    if n > 2**30:
        raise ValueError(f"n_particles: expected at most 2**30 particles, got {n}")
    return n


def _check_ess_threshold(ess_threshold) -> float:
    try:
        thr = float(ess_threshold)
    except (TypeError, ValueError):
        thr = float("nan")
    if isinstance(ess_threshold, (bool, np.bool_)) or not 0.0 <= thr <= 1.0:
        raise ValueError(f"ess_threshold: expected a number in [0, 1], got {ess_threshold!r}")
    return thr


def _chol(A):
    """Lower Cholesky factor, in numpy for a constant, in jax for a traced matrix."""
    return np.linalg.cholesky(A) if isinstance(A, np.ndarray) else jnp.linalg.cholesky(A)


_UNROLL = 64  # matrices with at most this many entries are handled with unrolled scalar code


def _is_diagonal(A) -> bool:
    """Whether A is a constant (numpy) diagonal matrix."""
    return isinstance(A, np.ndarray) and A.ndim == 2 and A.shape[0] == A.shape[1] and not np.any(
        A - np.diag(np.diagonal(A))
    )


def _matmul(A, z):
    """``A @ z`` for a small A (m, k) and z (k, N): unrolled multiply-adds, which XLA on CPU
    fuses into one loop, several times cheaper than a batched dot at a vehicle model's sizes."""
    m, k = A.shape
    if k * m > _UNROLL:
        return A @ z
    acc = A[:, :1] * z[:1]
    for i in range(1, k):
        acc = acc + A[:, i : i + 1] * z[i : i + 1]
    return acc


def _add_noise(fx, L, z):
    """``fx + L @ z`` for fx (n, N), L (n, n) and normals z (n, N).

    The noise is a dot, so the normals are hashed once rather than once per use in a fused
    loop; for small n it is added row by row before the rows are stacked, which measured a few
    per cent faster on CPU than adding two stacked (n, N) arrays.
    """
    noise = L @ z
    n = fx.shape[0]
    if n * n > _UNROLL:
        return fx + noise
    return jnp.stack([fx[i] + noise[i] for i in range(n)])


def _moments(w, x):
    """Weighted mean (n,) and covariance (n, n) of the columns of x (n, N) with weights w (N,)
    summing to 1.

    For small n, row by row (full reductions, cheap on CPU); otherwise with dots.
    """
    n = x.shape[0]
    if n * n > _UNROLL:
        mean = x @ w
        d = x - mean[:, None]
        cov = (d * w) @ d.T
        return mean, 0.5 * (cov + cov.T)
    cols = [x[i] for i in range(n)]
    mean = jnp.stack([jnp.sum(w * c) for c in cols])
    d = [c - mean[i] for i, c in enumerate(cols)]
    wd = [w * di for di in d]
    entries = {}
    for i in range(n):
        for j in range(i, n):
            entries[i, j] = entries[j, i] = jnp.sum(wd[i] * d[j])
    cov = jnp.stack([jnp.stack([entries[i, j] for j in range(n)]) for i in range(n)])
    return mean, cov


def _cholesky(M):
    """Lower Cholesky factor of a small symmetric positive-definite M (NaN where it is not).

    Up to 8 x 8 in unrolled scalar code (no LAPACK call per run and step), else LAPACK.
    """
    n = M.shape[0]
    if n * n > _UNROLL:
        return jnp.linalg.cholesky(M)
    zero = jnp.zeros((), M.dtype)
    L = [[zero] * n for _ in range(n)]
    for j in range(n):
        L[j][j] = jnp.sqrt(M[j, j] - sum((L[j][k] ** 2 for k in range(j)), zero))
        for i in range(j + 1, n):
            L[i][j] = (M[i, j] - sum((L[i][k] * L[j][k] for k in range(j)), zero)) / L[j][j]
    return jnp.stack([jnp.stack(row) for row in L])


def _tril_inverse(L):
    """Inverse of a small lower-triangular L (unrolled forward substitution)."""
    n = L.shape[0]
    if n * n > _UNROLL:
        return jax.scipy.linalg.solve_triangular(L, jnp.eye(n, dtype=L.dtype), lower=True)
    zero = jnp.zeros((), L.dtype)
    X = [[zero] * n for _ in range(n)]
    for i in range(n):
        X[i][i] = 1.0 / L[i, i]
        for j in range(i):
            X[i][j] = -sum((L[i, k] * X[k][j] for k in range(j, i)), zero) / L[i, i]
    return jnp.stack([jnp.stack(row) for row in X])


def _whitened_norm2(L, r):
    """||L^-1 r||^2 for a small lower-triangular L and a vector r."""
    n = L.shape[0]
    if n * n > _UNROLL:
        return jnp.sum(jax.scipy.linalg.solve_triangular(L, r, lower=True) ** 2)
    v = []
    for i in range(n):
        v.append((r[i] - sum((L[i, k] * v[k] for k in range(i)), jnp.zeros((), r.dtype))) / L[i, i])
    return sum(vi**2 for vi in v)


def _const(A, dtype):
    """A matrix in the filter's dtype: numpy stays a numpy constant, a traced array is cast."""
    if isinstance(A, np.ndarray):
        return A.astype(np.dtype(dtype))
    return jnp.asarray(A).astype(dtype)


def _in_dtype(fn):
    """``fn`` with its output cast to the dtype of ``x`` (float32 filters stay float32)."""
    return lambda x, u, theta: jnp.asarray(fn(x, u, theta)).astype(x.dtype)


def _masked_chol(M, obs):
    """Cholesky factor of M restricted to the observed components, identity elsewhere."""
    both = obs[:, None] & obs[None, :]
    eye = jnp.eye(M.shape[0], dtype=M.dtype)
    return _cholesky(jnp.where(both, M, eye))


# -- the filter -------------------------------------------------------------------------------


def bootstrap_pf(
    model,
    Q,
    R,
    n_particles: int = 1000,
    resampling: str = "systematic",
    ess_threshold: float = 0.5,
) -> Estimator:
    """Bootstrap particle filter: propagate through the model plus Gaussian noise, weigh by the
    Gaussian measurement likelihood, resample when the effective sample size drops.

    Args:
        model: a vehjax model: ``transition(x, u, theta)``, ``observe(x, u, theta)``.
        Q: process-noise covariance, (nx, nx) or (nx,) variances, positive definite, in state
            units squared per step; the noise is added after the transition.
        R: measurement-noise covariance, (ny, ny) or (ny,) variances, positive definite, in
            output units squared.
        n_particles: number of particles N >= 1.
        resampling: "systematic", "stratified", "multinomial" or "residual"
            (see :mod:`vehjax.filters.resampling`).
        ess_threshold: resample when ESS < ess_threshold * N; 0 never resamples, 1 resamples
            whenever the weights are not all equal.

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
            positive definite, n_particles < 1, an unknown resampling scheme, an ess_threshold
            outside [0, 1].
    """
    nx, ny = _check_model(model)
    n = _check_n_particles(n_particles)
    scheme = _rs.check_scheme(resampling)
    thr = _check_ess_threshold(ess_threshold)
    Qn, Rn = check_cov("Q", Q, nx), check_cov("R", R, ny)
    LQn = _chol(Qn)
    r_diag = np.diagonal(Rn).copy() if _is_diagonal(Rn) else None
    resamples = thr > 0.0
    n_uniforms = _rs.uniforms_needed(scheme, n)
    uniform_stream = (nx + 1) // 2  # after the noise rows' counters
    log_n = math.log(n)
    log_2pi = math.log(2.0 * math.pi)
    f = _in_dtype(model.transition)
    h = _in_dtype(model.observe)
    f_all = jax.vmap(f, in_axes=(1, None, None), out_axes=1)
    h_all = jax.vmap(h, in_axes=(1, None, None), out_axes=1)

    def init(x0, P0, theta0=None, P_theta0=None, key=None):
        del P_theta0  # state-only filter
        if key is None:
            raise ValueError("key: bootstrap_pf draws its particles at random; pass a PRNG key")
        x0, P0 = _prior(nx, x0, P0)
        dtype = x0.dtype
        theta = _theta(model, theta0, dtype)
        k_init, k_run = jax.random.split(key)
        z = jax.random.normal(k_init, (nx, n), dtype)
        particles = x0[:, None] + _matmul(jnp.linalg.cholesky(P0), z)
        return PFState(
            particles=particles,
            log_weights=jnp.full((n,), -log_n, dtype),
            weights=jnp.full((n,), 1.0 / n, dtype),
            key=_random.raw_key(k_run),
            theta=theta,
            mean=x0,
            cov=P0,
            ess=jnp.asarray(float(n), dtype),
            pending_reinit=jnp.asarray(False),
            flag_diverged=jnp.asarray(False),
            n_reinit=jnp.asarray(0, jnp.int32),
        )

    def step(state: PFState, y, u):
        dtype = state.particles.dtype
        log_tiny = float(np.log(np.finfo(np.dtype(dtype)).tiny))
        y, u = jnp.asarray(y).astype(dtype), jnp.asarray(u).astype(dtype)
        Qd = _const(Qn, dtype)
        theta = state.theta
        key_next, key_step = _random.split(state.key)
        z = _random.std_normal_rows(key_step, nx, n, dtype)  # (nx, N)

        # propagate (a re-initialisation pending from the last step draws the particles
        # around its estimate instead: all from the mean, noise covariance P + Q)
        pending = state.pending_reinit
        L_re = _cholesky(state.cov + Qd)
        L_re = jnp.where(jnp.all(jnp.isfinite(L_re)), L_re, _const(LQn, dtype))
        start = jnp.where(pending, state.mean[:, None], state.particles)
        x = _add_noise(f_all(start, u, theta), jnp.where(pending, L_re, _const(LQn, dtype)), z)
        prior_lw = jnp.where(pending, -log_n, state.log_weights)
        prior_w = jnp.where(pending, 1.0 / n, state.weights)

        # predict the measurement; particles that are not finite get weight zero
        obs = ~jnp.isnan(y)
        n_obs = jnp.sum(obs, dtype=jnp.int32)
        e = jnp.where(obs[:, None], y[:, None] - h_all(x, u, theta), 0.0)  # (ny, N)
        bad = ~(jnp.all(jnp.isfinite(x), axis=0) & jnp.all(jnp.isfinite(e), axis=0))
        x = jnp.where(bad, 0.0, x)
        e = jnp.where(bad, 0.0, e)

        # weigh: Gaussian log-likelihood of the observed components
        if r_diag is not None:
            r = _const(r_diag, dtype)
            q = jnp.sum(e * e * (1.0 / r)[:, None], axis=0)
            half_logdet = 0.5 * jnp.sum(jnp.where(obs, jnp.log(r), 0.0))
        else:
            LR = _masked_chol(_const(Rn, dtype), obs)
            q = jnp.sum(_matmul(_tril_inverse(LR), e) ** 2, axis=0)
            half_logdet = jnp.sum(jnp.log(jnp.diagonal(LR)))
        ll = -0.5 * q - (0.5 * log_2pi * n_obs.astype(dtype) + half_logdet)
        lw_un = prior_lw + jnp.where(bad, -jnp.inf, ll)
        top = jnp.max(lw_un)
        w_un = jnp.exp(lw_un - top)
        total = jnp.sum(w_un)
        incr = top + jnp.log(total)
        diverged = ~(incr > log_tiny)
        w = w_un / total
        lw = lw_un - incr

        # weighted moments of the updated particles
        mean, cov = _moments(w, x)

        # NIS from the predicted measurement moments (prior weights, finite particles only)
        wp = jnp.where(bad, 0.0, prior_w)
        wp = wp / jnp.maximum(jnp.sum(wp), jnp.finfo(dtype).tiny)
        r_hat, S_h = _moments(wp, e)  # r_hat = y - y_hat on the observed components
        nis = _whitened_norm2(_masked_chol(S_h + _const(Rn, dtype), obs), r_hat)

        # resample for the next step
        ess = 1.0 / jnp.sum(w**2)
        if resamples:
            u_res = _random.uniforms(key_step, n_uniforms, dtype, stream=uniform_stream)
            idx = _rs.indices_from_uniforms(scheme, w, u_res, n)
            do = ess < thr * n
            x_next = jnp.where(do, jnp.stack([x[i][idx] for i in range(nx)]), x)
            lw_next = jnp.where(do | diverged, -log_n, lw)
            w_next = jnp.where(do | diverged, 1.0 / n, w)
        else:
            x_next = x
            lw_next = jnp.where(diverged, -log_n, lw)
            w_next = jnp.where(diverged, 1.0 / n, w)

        # divergence: the estimate moves on with the model, its covariance grows by Q, and the
        # next step re-draws the particles around it
        m_re = f(state.mean, u, theta)
        m_re = jnp.where(jnp.all(jnp.isfinite(m_re)), m_re, state.mean)
        mean_out = jnp.where(diverged, m_re, mean)
        cov_out = jnp.where(diverged, state.cov + Qd, cov)
        new_state = PFState(
            particles=x_next,
            log_weights=lw_next,
            weights=w_next,
            key=key_next,
            theta=theta,
            mean=mean_out,
            cov=cov_out,
            ess=jnp.where(diverged, 0.0, ess),
            pending_reinit=diverged,
            flag_diverged=state.flag_diverged | diverged,
            n_reinit=state.n_reinit + diverged.astype(jnp.int32),
        )
        out = StepOutput(
            mean=mean_out,
            cov=cov_out,
            loglik=jnp.where(jnp.isfinite(incr), incr, log_tiny),
            nis=nis,
            n_obs=n_obs,
            params=jnp.zeros((0,), dtype),
            params_cov=jnp.zeros((0, 0), dtype),
        )
        return new_state, out

    return Estimator(
        init=init, step=step, nx=nx, param_names=(), name="bootstrap_pf", needs_key=True
    )
