"""Particle smoothing of one run by backward simulation over a particle filter's particles.

The forward pass is the filter itself: its own ``init`` and ``step`` in a ``lax.scan``, keeping
each step's particles x_t^i (nx, N), their normalised log weights log W_t^i and the resampling
genealogy (:class:`vehjax.filters.particle.PFState`). The filtered set after step t is the
particle approximation sum_i W_t^i delta(x - x_t^i) of p(x_t | y_0:t) (after a resampling the
resampled, equally weighted set). The model's transition density, in the filter's time
convention (step t + 1 predicts with u_{t+1})::

    p(x_{t+1} | x_t) = N(x_{t+1}; f(x_t, u_{t+1}, theta), Q),   Q = L L^T

comes from ``Estimator.particle_transition`` (:class:`vehjax.filters.base.ParticleTransition`).

Methods, each giving M trajectories x_{0:T-1}^m, m = 1..M:

``"ffbsi"``  forward-filtering backward-simulation (Godsill, Doucet & West 2004): draw the last
    state from the final filter weights, then for t = T-2, ..., 0 draw index i for each
    trajectory with probability proportional to the backward weight::

        W_t^i N(x_{t+1}^m; f(x_t^i, u_{t+1}), Q)            (normalised over i)

    O(N M) per step. As N grows the trajectories are draws from p(x_0:T-1 | y_0:T-1): their
    moments converge to the smoothed ones (for a linear-Gaussian model, the RTS smoother's).

``"rejection"``  the same draws by rejection sampling (Douc, Garivier, Moulines & Olsson 2011;
    Taghavi, Lindsten, Svensson & Schon 2013): propose i from the filter weights W_t^i and accept
    with probability N(x_{t+1}^m; f(x_t^i), Q) / N(0; 0, Q) = exp(-|L^-1(x_{t+1}^m - f(x_t^i))|^2
    / 2) <= 1. Each trajectory tries at most ``max_tries`` proposals; those still not accepted
    are drawn exactly as in ``"ffbsi"`` (the fallback, counted in ``fallbacks``). The draws
    have exactly FFBSi's distribution. O(N + M tries) per step when the fallback is not needed
    (one run under ``jit``); under ``vmap`` the fallback branch is evaluated for every run (a
    ``lax.cond`` becomes a select), so that the cost is FFBSi's plus the tries. For a filter
    cloud about N(m, P) and a model with Jacobian A the acceptance probability is at most
    about sqrt(det Q / det(Q + A P A^T)): small when the process noise is small against the
    filter's spread, and then most trajectories fall back (measured: 60 % of them after 4
    tries on the linear model of tests/smoothers/test_particle_smoothing.py).

``"ancestor"``  ancestor tracing: draw M of the filter's final particles by their weights and
    follow each one's genealogy back (``PFState.ancestors``). The cheapest (no transition
    density at all), but degenerate: resampling makes the genealogies coalesce, so at early
    times the M trajectories run through a handful of distinct particles (``n_unique``), and
    the early smoothed moments rest on those few points, whatever M: their Monte-Carlo error
    is large (measured on the linear test model, T = 40, N = M = 100, resampling every step:
    4-7 distinct particles at t = 0, and a covariance there between 0.1 and 2.4 times the
    RTS's over 16 keys). It is the path-space smoother of Kitagawa 1996.

Time convention: as :func:`vehjax.filter`, x0/P0 describe the state before the first step, and
trajectory time t is the state after step t (0 .. T-1). NaN measurement components are
missing: the filter skips them and so does the smoother (the transition density involves no
measurement).

Divergence: a filter step that re-initialised (its weights underflowed) draws the next
particles afresh around its estimate; the transition density then does not link the particles
across that step, and the result is flagged ``diverged`` (its trajectories are still finite:
a backward step whose weights are all zero or not finite falls back to the filter weights).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from .. import validation
import numpy as np

from ..engine import output_ok
from ..lib.linalg import solve_lower
from ..filters.base import Estimator

__all__ = [
    "ParticleSmootherResult", "smooth", "METHODS", "transition_logdens", "ffbsi_indices",
    "rejection_indices", "ancestor_indices", "trajectory_moments", "count_unique",
]

#: The backward-simulation methods of :func:`smooth`.
METHODS = ("ffbsi", "rejection", "ancestor")


class ParticleSmootherResult(NamedTuple):
    """Particle smoothing of one run of T steps (a leading runs axis under ``vmap``).

    Attributes:
        trajectories: (M, T, nx) the M smoothed trajectories, equally weighted.
        states: (T, nx) their mean, the smoothed state estimate.
        covariances: (T, nx, nx) their sample covariance (divisor M - 1; zeros when M = 1).
        cross_covariances: (T - 1, nx, nx), entry t the lag-one sample covariance
            Cov(x_t, x_{t+1} | y_0:T-1) (for a linear-Gaussian model the RTS smoother's
            P_{t,t+1|T} = G_t P_{t+1|T}); divisor M - 1.
        loglik: (T,) the filter's log p(y_t | y_0:t-1), as :func:`vehjax.filter` gives with
            the same key (its sum is the run's log-likelihood estimate).
        n_unique: (T,) int32, how many distinct filter particles the M trajectories pass
            through at each time (the degeneracy of ancestor tracing shows here).
        fallbacks: (T,) int32, how many trajectories the rejection sampler drew exactly after
            ``max_tries`` rejections at each time; zeros for the other methods.
        diverged: bool scalar, the filter re-initialised or gave a bad output at some step
            (module docstring).
    """

    trajectories: jnp.ndarray
    states: jnp.ndarray
    covariances: jnp.ndarray
    cross_covariances: jnp.ndarray
    loglik: jnp.ndarray
    n_unique: jnp.ndarray
    fallbacks: jnp.ndarray
    diverged: jnp.ndarray


# ----------------------------------------------------------------------------------------------
# The mathematics, one function each


def transition_logdens(L, fx, x_next):
    """Log transition densities up to their common constant: for every pair (m, i),
    ``-|L^-1 (x_next[:, m] - fx[:, i])|^2 / 2``, which is log N(x_next_m; fx_i, L L^T) +
    log((2 pi)^(nx/2) det L) and at most 0.

    Args:
        L: (nx, nx) lower Cholesky factor of Q.
        fx: (nx, N) the filter particles moved by the model, f(x_t^i, u_{t+1}, theta).
        x_next: (nx, M) the trajectories' states at t + 1.

    Returns:
        (M, N).
    """
    a = solve_lower(L, x_next)  # (nx, M)
    b = solve_lower(L, fx)  # (nx, N)
    d = a[:, :, None] - b[:, None, :]
    return -0.5 * jnp.sum(d * d, axis=0)


def _safe_logits(log_w, logdens):
    """Backward log weights (M, N) = log W (N,) + logdens (M, N); a row with no finite entry
    (no particle can lead to that trajectory's next state, e.g. across a re-initialisation)
    falls back to the filter weights alone."""
    logits = log_w[None, :] + logdens
    top = jnp.max(logits, axis=1, keepdims=True)
    return jnp.where(jnp.isfinite(top), logits, log_w[None, :])


def _cumsum(a, axis: int):
    """Cumulative sum by an associative scan: O(N log N), where ``jnp.cumsum`` lowers on CPU to
    a reduce-window of O(N^2) (measured 0.13 s against 0.014 s for a (512, 512) array)."""
    return jax.lax.associative_scan(jnp.add, a, axis=axis)


def ffbsi_indices(key, log_w, logdens):
    """One backward step of FFBSi: for each trajectory m an index i drawn with probability
    proportional to ``W_i p(x_{t+1}^m | x_t^i)``, by the inverse CDF of each row (one uniform
    per trajectory, not N Gumbel draws).

    Args:
        key: PRNG key.
        log_w: (N,) filter log weights at t (-inf for zero weight).
        logdens: (M, N) :func:`transition_logdens`.

    Returns:
        (M,) int32 indices into the filter particles at t.
    """
    logits = _safe_logits(log_w, logdens)
    w = jnp.exp(logits - jnp.max(logits, axis=1, keepdims=True))
    cdf = _cumsum(jnp.where(jnp.isfinite(w), w, 0.0), axis=1)  # (M, N), last entry >= 1
    u = jax.random.uniform(key, (cdf.shape[0], 1), cdf.dtype) * cdf[:, -1:]
    idx = jnp.sum(cdf <= u, axis=1)  # first i with cdf_i > u
    return jnp.minimum(idx, cdf.shape[1] - 1).astype(jnp.int32)


def _inverse_cdf(cdf, u):
    """Indices i with cdf[i-1] <= u * cdf[-1] < cdf[i], for uniforms u (M,) in [0, 1)."""
    idx = jnp.searchsorted(cdf, u * cdf[-1], side="right")
    return jnp.minimum(idx, cdf.shape[0] - 1).astype(jnp.int32)


def rejection_indices(key, log_w, a, b, max_tries: int):
    """One backward step by rejection sampling, with the exact draw as fallback.

    Each pending trajectory m proposes i ~ W (inverse CDF, O(log N)) and accepts it with
    probability ``exp(-|a_m - b_i|^2 / 2)``, the transition density over its maximum; after
    ``max_tries`` rounds the trajectories still pending are drawn by :func:`ffbsi_indices`
    (computed only when some are pending, for one run under ``jit``).

    Args:
        key: PRNG key.
        log_w: (N,) filter log weights at t.
        a: (nx, M) ``L^-1 x_{t+1}^m``.
        b: (nx, N) ``L^-1 f(x_t^i, u_{t+1})``.
        max_tries: proposals per trajectory before the fallback, >= 1.

    Returns:
        (indices (M,) int32, number of trajectories that fell back, int32 scalar).
    """
    a, b, log_w = jnp.asarray(a), jnp.asarray(b), jnp.asarray(log_w)
    m = a.shape[1]
    w = jnp.exp(log_w - jnp.max(log_w))
    cdf = _cumsum(jnp.where(jnp.isfinite(w), w, 0.0), axis=0)
    k_try, k_exact = jax.random.split(key)

    def cond(carry):
        k, _, pending = carry
        return (k < max_tries) & jnp.any(pending)

    def body(carry):
        k, idx, pending = carry
        ku, ka = jax.random.split(jax.random.fold_in(k_try, k))
        prop = _inverse_cdf(cdf, jax.random.uniform(ku, (m,), a.dtype))
        d = a - b[:, prop]
        log_acc = -0.5 * jnp.sum(d * d, axis=0)
        accept = pending & (jnp.log(jax.random.uniform(ka, (m,), a.dtype)) <= log_acc)
        return k + 1, jnp.where(accept, prop, idx), pending & ~accept

    init = (jnp.zeros((), jnp.int32), jnp.zeros((m,), jnp.int32), jnp.ones((m,), bool))
    _, idx, pending = jax.lax.while_loop(cond, body, init)

    def exact(_):
        d = a[:, :, None] - b[:, None, :]
        return ffbsi_indices(k_exact, log_w, -0.5 * jnp.sum(d * d, axis=0))

    drawn = jax.lax.cond(jnp.any(pending), exact, lambda _: idx, None)
    return jnp.where(pending, drawn, idx), jnp.sum(pending, dtype=jnp.int32)


def ancestor_indices(ancestors_next, idx_next):
    """One step of ancestor tracing: the parents ``ancestors_next[idx_next]`` (M,) at t of the
    particles ``idx_next`` (M,) at t + 1; ``ancestors_next`` (N,) is the filter's genealogy
    at t + 1."""
    return ancestors_next[idx_next]


def trajectory_moments(traj):
    """Sample moments of equally weighted trajectories (M, T, nx), divisor M - 1.

    Returns:
        (mean (T, nx), covariance (T, nx, nx) symmetric, lag-one covariance (T - 1, nx, nx)
        with entry t = Cov(x_t, x_{t+1})); covariances zero when M = 1.
    """
    m = traj.shape[0]
    mean = jnp.mean(traj, axis=0)
    d = traj - mean[None]
    scale = 1.0 / max(m - 1, 1)
    cov = scale * jnp.einsum("mti,mtj->tij", d, d)
    cross = scale * jnp.einsum("mti,mtj->tij", d[:, :-1], d[:, 1:])
    return mean, 0.5 * (cov + jnp.swapaxes(cov, -1, -2)), cross


def count_unique(idx):
    """Number of distinct values in an int vector (M,), as int32."""
    s = jnp.sort(idx)
    return (1 + jnp.sum(s[1:] != s[:-1])).astype(jnp.int32)


# ----------------------------------------------------------------------------------------------
# The passes


class _Forward(NamedTuple):
    particles: jnp.ndarray  # (T, nx, N)
    log_weights: jnp.ndarray  # (T, N)
    ancestors: jnp.ndarray  # (T, N)
    loglik: jnp.ndarray  # (T,)
    bad: jnp.ndarray  # (T,) bool: re-initialised or a bad output
    theta: jnp.ndarray  # (np,)


def _forward(estimator: Estimator, ys, us, x0, P0, theta0, key) -> _Forward:
    """The filter over the run, keeping its particles, log weights and genealogy per step."""
    state0 = estimator.init(x0, P0, theta0, None, key)

    def body(state, yu):
        state, out = estimator.step(state, *yu)
        bad = jnp.asarray(out.reinit, bool) | ~output_ok(out, 0)
        return state, (state.particles, state.log_weights, state.ancestors, out.loglik, bad)

    _, per = jax.lax.scan(body, state0, (ys, us))
    return _Forward(*per, theta=state0.theta)


def _backward(fwd: _Forward, us, trans, method: str, m: int, max_tries: int, key):
    """Indices (T, M) of the M trajectories into the filter particles, and fallbacks (T,)."""
    T, _, n = fwd.particles.shape
    dtype = fwd.particles.dtype
    L = jnp.asarray(trans.chol_Q).astype(dtype)
    f_all = jax.vmap(trans.transition, in_axes=(1, None, None), out_axes=1)
    k_last, k_back = jax.random.split(key)
    idx_last = jax.random.categorical(k_last, jnp.broadcast_to(fwd.log_weights[-1], (m, n)),
                                      axis=1).astype(jnp.int32)

    def step(idx_next, xs):
        x_t, lw_t, x_next_all, anc_next, u_next, k = xs
        if method == "ancestor":
            return ancestor_indices(anc_next, idx_next), jnp.zeros((), jnp.int32)
        fx = f_all(x_t, u_next, fwd.theta)
        x_next = x_next_all[:, idx_next]
        if method == "ffbsi":
            idx = ffbsi_indices(k, lw_t, transition_logdens(L, fx, x_next))
            return idx, jnp.zeros((), jnp.int32)
        return rejection_indices(k, lw_t, solve_lower(L, x_next), solve_lower(L, fx), max_tries)

    def body(idx_next, xs):
        idx, n_fb = step(idx_next, xs)
        return idx, (idx, n_fb)

    keys = jax.random.split(k_back, max(T - 1, 1))[: T - 1]
    xs = (fwd.particles[:-1], fwd.log_weights[:-1], fwd.particles[1:], fwd.ancestors[1:],
          us[1:], keys)
    _, (idx, fb) = jax.lax.scan(body, idx_last, xs, reverse=True)
    idx = jnp.concatenate([idx, idx_last[None]], axis=0)
    fb = jnp.concatenate([fb, jnp.zeros((1,), jnp.int32)])
    return idx, fb


def _check_data(estimator: Estimator, ys, us, x0, P0, key):
    """Shapes of one run's data and prior (concrete or traced), the key's presence."""
    nx, ny, nu = estimator.nx, estimator.ny, estimator.nu
    shape = np.shape(ys)
    if len(shape) != 2 or shape[0] == 0 or (ny is not None and shape[1] != ny):
        raise ValueError(f"measurements: expected shape (T, {ny if ny is not None else 'ny'}) "
                         f"with T >= 1 for one run, got {shape}")
    T = shape[0]
    if us is None:
        if nu:
            raise ValueError(f"inputs: required, shape ({T}, {nu}) for this model's inputs")
    elif np.ndim(us) != 2 or np.shape(us)[0] != T or (nu is not None and np.shape(us)[1] != nu):
        raise ValueError(f"inputs: expected shape ({T}, {nu if nu is not None else 'nu'}) to "
                         f"match measurements {shape}, got {np.shape(us)}")
    if np.shape(x0) != (nx,):
        raise ValueError(f"x0: expected shape ({nx},), got {np.shape(x0)}")
    if np.shape(P0) not in ((nx, nx), (nx,)):
        raise ValueError(f"P0: expected shape ({nx}, {nx}) or ({nx},) variances, got "
                         f"{np.shape(P0)}")
    if key is None:
        raise ValueError("key: particle smoothing draws random numbers; pass "
                         "key=jax.random.key(...)")


def _check(estimator, method, n_trajectories, max_tries):
    """Validation of what is particular to particle smoothing (before anything is traced)."""
    if not isinstance(estimator, Estimator) or estimator.particle_transition is None:
        name = getattr(estimator, "name", type(estimator).__name__)
        raise ValueError(
            f"estimator: particle smoothing needs a particle filter that declares its "
            f"transition density (Estimator.particle_transition: bootstrap_pf without input "
            f"noise), got {name!r}")
    if estimator.particle_transition.chol_Q is None:
        raise ValueError(
            f"estimator: {estimator.name!r} has a process noise Q that is only positive "
            f"semi-definite; backward simulation needs a transition density (Q positive definite)")
    method = validation.choice("method", method, METHODS)
    m = validation.integer("n_trajectories", n_trajectories, 1, 2**24)
    tries = validation.integer("max_tries", max_tries, 1, 2**16)
    return method, m, tries


def smooth(estimator: Estimator, measurements, inputs=None, *, x0, P0, key,
           method: str = "ffbsi", n_trajectories: int = 100, theta0=None,
           max_tries: int = 10) -> ParticleSmootherResult:
    """Smooth one run with a particle filter and backward simulation (module docstring).

    Pure and traceable (``jax.jit`` with the keyword arguments static where they are Python
    values, ``jax.vmap`` over runs or keys); every random number comes from ``key``: the
    filter runs with ``key`` itself (so ``loglik`` equals :func:`vehjax.filter`'s with the same
    key) and the backward pass with ``jax.random.fold_in(key, 1)``.

    Args:
        estimator: a particle filter with ``particle_transition`` (``bootstrap_pf``).
        measurements: (T, ny); NaN (or +-inf) components are missing.
        inputs: (T, nu); None when the model has no inputs.
        x0: state before the first step, (nx,).
        P0: its covariance, (nx, nx) or (nx,) variances.
        key: PRNG key (``jax.random.key``).
        method: "ffbsi", "rejection" or "ancestor".
        n_trajectories: M >= 1 trajectories to draw.
        theta0: (np,) model parameters for the filter (the model's nominal ones when None).
        max_tries: "rejection" only: proposals per trajectory and step before the exact
            fallback, >= 1.

    Returns:
        :class:`ParticleSmootherResult`.

    Raises:
        ValueError: naming the argument: an estimator that is not such a particle filter (or
            whose Q is singular), an unknown method, n_trajectories or max_tries < 1, shapes
            that do not fit, a missing key.
    """
    method, m, tries = _check(estimator, method, n_trajectories, max_tries)
    _check_data(estimator, measurements, inputs, x0, P0, key)
    ys = jnp.asarray(measurements)
    T = ys.shape[0]
    us = jnp.zeros((T, 0), ys.dtype) if inputs is None else jnp.asarray(inputs)
    P0 = jnp.asarray(P0)
    P0 = jnp.diag(P0) if P0.ndim == 1 else P0
    fwd = _forward(estimator, ys, us, jnp.asarray(x0), P0, theta0, key)
    idx, fb = _backward(fwd, us.astype(fwd.particles.dtype), estimator.particle_transition,
                        method, m, tries, jax.random.fold_in(key, 1))
    # trajectories (M, T, nx): particle idx[t, m] of step t
    traj = jnp.take_along_axis(fwd.particles, idx[:, None, :], axis=2).transpose(2, 0, 1)
    mean, cov, cross = trajectory_moments(traj)
    return ParticleSmootherResult(
        trajectories=traj, states=mean, covariances=cov, cross_covariances=cross,
        loglik=fwd.loglik, n_unique=jax.vmap(count_unique)(idx), fallbacks=fb,
        diverged=jnp.any(fwd.bad),
    )
