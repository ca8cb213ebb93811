"""Liu-West particle filter for the parameters + UKF for the state (Dutta et al. 2019, Alg. 3).

The parameters named in ``estimate`` are carried as M weighted particles, drawn at ``init`` from a
uniform prior on the box [theta_low, theta_high]. Each particle lives in the domain of the
parameters, ``bounds`` (default: (0, inf) for a box with theta_low > 0, the log coordinate, else
the prior box itself), and is carried in the unconstrained
coordinate s_i of that domain (:mod:`vehjax.lib.transforms`, unit scale: ``theta = s``
unbounded, ``low + exp(s)`` / ``high - exp(s)`` one-sided, ``low + (high - low) sigmoid(s)`` for a
box), theta_i = g(s_i). The state is estimated by a UKF (:func:`vehjax.filters.gaussian.ukf`)
that runs the model at the weighted parameter mean. One step, with (mu, P) the UKF's filtered
state from the last step and W_i the carried weights::

    y_i   = h(f(mu + D (theta_i - theta_bar'), u_t, theta_i), u_t, theta_i)  (one-step prediction)
    log W_i <- log W_i + log N(y_t; y_i, S)  then normalised                (weigh, log space)
    mean, V = weighted mean and covariance of the s_i
    resample when ESS = 1 / sum W_i^2 < ess_threshold * M                   (vehjax resampling)
    if resampled (every step with move="every"):                           (Liu-West kernel)
        m_i = a s_i + (1 - a) mean,  s_i <- N(m_i, h^2 V),  h^2 = 1 - a^2
    theta_bar = sum_i W_i g(s_i)                                            (StepOutput.params)
    W_i <- gamma W_i + (1 - gamma) / M                                      (residual weight)
    UKF predict + update with theta_bar, D <- d mu / d theta_bar through that step

(theta_bar' the estimate the UKF ran with at the last step, D = 0 with ``recurrent=False``.)

When the kernel moves the particles (``move``): Liu and West (2001) and Dutta et al.'s
Algorithm 3 move them at every step (``move="every"``); vehjax moves them only at the steps that
resample (``move="resampled"``, the default), where the kernel has duplicates to spread. Against
the exact posterior mean of the same likelihood (``vehjax bench liu_west_bias``) moving at every
step pulls the cloud towards a Gaussian and the estimate settles near the mode of a skewed
posterior (about 0.3-1 % low on Dynamic3DOF); moved after resampling only, the weights carry the
likelihood's shape. The parameters are carried in the log coordinate of (0, inf), not the logit
of the box, which biased them by about 4-5 % (the kernel keeps the moments of s, not of theta).

The kernel keeps the weighted mean and covariance of the cloud of s_i: E[sum W_i m_i] = mean and
the mixture covariance is a^2 V + h^2 V = V (Liu & West 2001), so it restores diversity without
the over-dispersion of plain jittering. Acting on s, it can never move a particle out of the
domain (with ``bounds={}``, s = theta and this is Liu and West's kernel on theta itself, which
can). The reported estimate is in physical units: ``params`` the weighted mean of the mapped
particles g(s_i), ``params_cov`` their weighted covariance (both inside the domain's convex
hull; no delta method is needed for a particle cloud).

Where the transcription of Algorithm 3 is unclear: the likelihood covariance S is the UKF's
innovation covariance of the one-step prediction (``likelihood="predictive"``, the default;
``"measurement"`` is the paper's S = R); gamma is read as W_i <- gamma W_i + (1 - gamma) / M
(gamma = 1 is Liu and West's filter); V is the particles' weighted covariance plus
1e3 * eps * w^2 on its diagonal (w the prior box's width, in s for the kernel); a particle whose
prediction is not finite gets weight zero; the prior is the box (``run`` and ``filter`` report its
centre and covariance diag((high - low)^2 / 12) for a run that diverges at its first step).

Limits: with few particles the parameter covariance is over-confident, more so with
``move="resampled"``; use M >= 1000 (the default).

See docs/liu_west.md for the measurements behind ``move`` (the exact reference, two excitations,
a skewed scalar model, the few-particle calibration, the diagnosis), the bias of the first
build and the two causes that removed it with their before/after figures, and each reading of
the transcription in full.

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

import dataclasses
import math
from functools import partial
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import validation
from ..runtime import prng
from . import sigma, smc
from ..lib.entrywise import cholesky_observed
from ..lib.transforms import Transform
from .bounds import check_inside, parse as _parse_bounds
from .base import Dims, Estimator, ParamSpec, Runtime, check_estimate
from ._model import check_model, in_dtype, model_dims, prior
from .gaussian import GaussianState, ukf

__all__ = ["LiuWestState", "liu_west_ukf", "full_theta", "box_jitter", "predict_particles",
           "likelihood_factor", "weigh", "liu_west_move", "residual_weight",
           "ukf_with_derivative"]

_LIKELIHOODS = ("predictive", "measurement")
_MOVES = ("resampled", "every")


@dataclasses.dataclass(frozen=True)
class LiuWestKernel:
    """How :func:`liu_west_ukf` weighs and moves its parameter particles (its option ``kernel``).

    Attributes:
        a: Liu-West shrinkage in (0, 1); the kernel variance is h^2 V with h^2 = 1 - a^2.
            Liu and West's discount factor delta in [0.95, 0.99] gives a = (3 delta - 1) /
            (2 delta) in [0.974, 0.995].
        gamma: residual weight factor in (0, 1]: the fraction of each particle's weight carried
            to the next step, the rest spread evenly (module docstring). 1 is plain Liu-West.
        move: when the kernel moves the particles: "resampled" (default) at the steps that
            resample, "every" at every step with a measurement (Liu and West's, the paper's).
            "every" biases a skewed posterior's mean (module docstring).
        likelihood: what the particles are weighed by: "predictive" (S = the UKF's one-step
            innovation covariance) or "measurement" (S = R, as in the paper); module docstring.
    """

    a: float = 0.98
    gamma: float = 1.0
    move: str = "resampled"
    likelihood: str = "predictive"

    def __post_init__(self):
        object.__setattr__(self, "a", validation.number("a", self.a, 0.0, 1.0))
        object.__setattr__(self, "gamma", validation.number("gamma", self.gamma, 0.0, 1.0,
                                                            high_open=False))
        validation.choice("move", self.move, _MOVES)
        validation.choice("likelihood", self.likelihood, _LIKELIHOODS)


class LiuWestState(NamedTuple):
    """State of :func:`liu_west_ukf` for one run (``run`` adds a leading runs axis).

    Attributes:
        x: (nx,) the UKF's filtered state mean (x0 before the first step).
        P: (nx, nx) its covariance.
        particles: (p, M) parameter particles (particle axis last) after the last step's kernel,
            in the unconstrained coordinates s of the parameter domains (module docstring;
            physical units for an unbounded parameter). ``vehjax.lib.transforms.Transform(
            *estimator.bounds).to_physical(particles, axis=0)`` gives them in physical units.
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
        D: (nx, p) recurrent derivative d x / d theta of the UKF's filtered state in the
            parameter estimate it ran with, physical units (zeros when ``recurrent=False``).
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
    D: jnp.ndarray


# -- validation (before anything is traced) --------------------------------------------------


def _check_box(theta_low, theta_high, names) -> tuple[np.ndarray, np.ndarray]:
    """The prior box (low, high), each (p,) float64, for the parameters ``names``: ValueError
    naming ``theta_low`` / ``theta_high`` for values that are not real (complex, strings), not
    finite, of the wrong shape, or not low < high."""
    p = len(names)
    out = []
    for arg, v in (("theta_low", theta_low), ("theta_high", theta_high)):
        a = np.asarray(validation.array(arg, v), dtype=float)  # real and finite, else refused
        a = a.reshape(-1) if a.ndim <= 1 else a
        if a.shape != (p,):
            raise ValueError(
                f"{arg}: expected shape ({p},), one bound per estimated parameter {names}, "
                f"got shape {np.shape(v)}"
            )
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


def _draw_box(u, low, high):
    """Uniform draws from the box, (p, n), from uniforms u (p, n) in [0, 1)."""
    return low[:, None] + (high - low)[:, None] * u


def _domain(low_n, high_n, bounds, names, nominal) -> tuple[np.ndarray, np.ndarray]:
    """The parameters' domains (low, high), each (p,) with +-inf for open ends: with ``bounds``
    None, (0, inf) where the prior box is positive (low_n > 0, the log coordinate), else the box
    [low_n, high_n] itself; else :func:`vehjax.filters.bounds.parse` of ``bounds`` (nominal
    values ``nominal`` (p,)), which must contain the box (ValueError naming ``bounds``)."""
    if bounds is None:
        pos = low_n > 0
        return np.where(pos, 0.0, low_n), np.where(pos, np.inf, high_n)
    dom_lo, dom_hi = _parse_bounds(bounds, names, nominal)
    outside = (low_n < dom_lo) | (high_n > dom_hi)
    if np.any(outside):
        bad = [n for n, o in zip(names, outside) if o]
        raise ValueError(
            f"bounds: each domain must contain the prior box [theta_low, theta_high]; not so "
            f"for {bad} (domain low {dom_lo}, high {dom_hi}; box {low_n}, {high_n})"
        )
    return dom_lo, dom_hi


def full_theta(base, idx, values):
    """Model parameter vector(s): ``base`` (np,) with the entries ``idx`` (p,) int set to
    ``values`` (..., p); returns (..., np)."""
    shape = values.shape[:-1] + base.shape
    return jnp.broadcast_to(base, shape).at[..., idx].set(values)


def box_jitter(dtype, width):
    """diag(1e3 eps width^2) (p, p) in ``dtype`` (eps its machine epsilon): what keeps a
    collapsed cloud's covariance positive definite, for a box of widths ``width`` (p,)."""
    eps = float(np.finfo(np.dtype(dtype)).eps)
    return jnp.asarray(np.diag(1e3 * eps * width**2), dtype)


def predict_particles(f, h, x, u, base, idx, theta_i, D=None, theta_mean=None):
    """One-step predicted measurement of every parameter particle, y_i = h(f(x_i, u, th_i),
    u, th_i), from the state x (nx,): x_i = x, or with the recurrent derivative D (nx, p),
    x_i = x + D (th_i - theta_mean) (the state the UKF would have filtered with th_i, to first
    order). theta_i (p, M) physical parameters; base (np,) and idx (p,) as for
    :func:`full_theta`. Returns (M, ny)."""
    if D is not None:

        def one(th):
            full = full_theta(base, idx, th)
            return h(f(x + D @ (th - theta_mean), u, full), u, full)

        return jax.vmap(one)(theta_i.T)
    return jax.vmap(lambda th: h(f(x, u, th), u, th))(full_theta(base, idx, theta_i.T))


def likelihood_factor(rule, f, h, x, P, u, theta, Q, R, obs, predictive: bool):
    """Cholesky factor of the particles' likelihood covariance S restricted to the observed
    components ``obs`` (ny,) (:func:`vehjax.lib.entrywise.cholesky_observed`): with ``predictive`` the
    unscented one-step innovation covariance Cov[h(f(x))] + R from N(x (nx,), P (nx, nx)) at
    the full parameter vector ``theta`` (np,) with process noise Q (the sigma-point ``rule``),
    else R (ny, ny); R's factor when S's is not finite."""
    if predictive:
        x_pred, P_pred = sigma.predict(rule, x, P, lambda v: f(v, u, theta), Q)
        S = sigma.measure(rule, x_pred, P_pred, lambda v: h(v, u, theta), R).S
    else:
        S = R
    L = cholesky_observed(S, obs)
    return jnp.where(jnp.all(jnp.isfinite(L)), L, cholesky_observed(R, obs))  # broken S: R


def weigh(log_w, y_i, y, obs, L) -> smc.Reweighted:
    """The particles' weights updated with log N(y; y_i, S) over the observed components:
    log_w (M,) normalised, y_i (M, ny) predictions, y (ny,), obs (ny,) bool, L the factor of S
    (:func:`likelihood_factor`). A particle whose residual is not finite gets weight zero."""
    e = jnp.where(obs, y[None, :] - y_i, 0.0)
    bad = ~jnp.all(jnp.isfinite(e), axis=1)
    e = jnp.where(bad[:, None], 0.0, e)
    ll = smc.gaussian_logliks(e.T, obs, L=L)
    return smc.reweight(log_w, jnp.where(bad, -jnp.inf, ll))


def liu_west_move(resample, particles, w, log_w, u_res, scheme, threshold, z, jitter, a,
                  keep, every: bool):
    """Resample when the weights degenerate, then shrink towards the mean and jitter
    (:func:`vehjax.filters.smc.shrink_move`) at the steps that resample, or at every step with
    ``every``.

    Args:
        resample: resampling function (:func:`vehjax.filters.smc.resample`'s signature).
        particles: (p, M) in the unconstrained coordinates; w, log_w: (M,) their weights.
        u_res: resampling uniforms; scheme, threshold: as for ``resample``.
        z: (p, M) standard normals; jitter: (p, p) added to the cloud's covariance V;
        a: shrinkage in (0, 1); keep: bool, leave everything as it is (a step without
        information or one that diverged).

    Returns:
        (particles (p, M), log_w (M,)) after the move, or as given where not moved.
    """
    mean, V = smc.moments(w, particles)
    parts, lw_k, _, resampled = resample(particles, w, log_w, u_res, scheme, threshold)
    moved = smc.shrink_move(z, parts, mean, V + jitter, a)
    do_move = ~keep & jnp.all(jnp.isfinite(moved))
    if not every:
        do_move = do_move & resampled
    return jnp.where(do_move, moved, particles), jnp.where(do_move, lw_k, log_w)


def residual_weight(log_w, gamma: float):
    """W_i <- gamma W_i + (1 - gamma) / M in log space, log_w (M,) normalised; gamma in (0, 1]
    (1 returns ``log_w`` itself)."""
    if gamma >= 1.0:
        return log_w
    log_n = math.log(log_w.shape[-1])
    return jnp.logaddexp(math.log(gamma) + log_w, math.log1p(-gamma) - log_n)


def ukf_with_derivative(ukf_step, x, P, D, base, idx, theta_bar, y, u, recurrent: bool):
    """The UKF's step at the parameter estimate theta_bar (p,) from N(x, P), and with
    ``recurrent`` its recurrent derivative D' = d x' / d theta_bar (nx, p) (``jax.jacfwd`` of
    the step from x(th) = x + D (th - theta_bar) at th; zeros where not finite); D itself
    without. ``ukf_step`` is :func:`vehjax.filters.gaussian.ukf`'s step. Returns (D', UKF
    state, StepOutput)."""

    def step_at(th):
        st, o = ukf_step(GaussianState(x + D @ (th - theta_bar), P, full_theta(base, idx, th)),
                         y, u)
        return st.x, (st, o)

    if recurrent:
        D_next, (st, out) = jax.jacfwd(step_at, has_aux=True)(theta_bar)
        return jnp.where(jnp.all(jnp.isfinite(D_next)), D_next, 0.0), st, out
    st, out = step_at(theta_bar)[1]
    return D, st, out


# -- init and step, composed ------------------------------------------------------------------


class _Config(NamedTuple):
    """What a Liu-West PF + UKF is built with, fixed before tracing (see
    :func:`liu_west_ukf`): the model's functions f, h (in the state's dtype) and nominal
    parameters ``theta`` (np,), the estimated parameters ``names`` at ``idx`` (p,) int32,
    particles n = M, the prior box (low, high) and the domains (dom_lo, dom_hi) (numpy (p,)),
    the transform ``tf`` to the unconstrained coordinates, the box's width there ``width_s``,
    the kernel's a, gamma, resampling (scheme, threshold, resample), the likelihood
    (``predictive``), ``every`` (move="every"), ``recurrent``, the UKF's sigma-point ``rule``
    and step ``ukf_step``, Q and R (numpy), and the counter stream ``s_box`` of the box draws
    (the resampling uniforms use the next one)."""

    f: Callable
    h: Callable
    theta: np.ndarray
    names: tuple
    idx: np.ndarray
    nx: int
    n: int
    low: np.ndarray
    high: np.ndarray
    dom_lo: np.ndarray
    dom_hi: np.ndarray
    tf: Transform
    width_s: np.ndarray
    a: float
    gamma: float
    scheme: str
    threshold: float
    resample: Callable
    predictive: bool
    every: bool
    recurrent: bool
    rule: Any
    ukf_step: Callable
    Q: np.ndarray
    R: np.ndarray
    s_box: int


def _draw(cfg: _Config, u, low, high):
    """M draws from the uniform prior box, in s: (p, M), from uniforms u (p, M)."""
    return cfg.tf.to_unconstrained(_draw_box(u, low, high), axis=0)


def _check_init(cfg: _Config, theta0, P_theta0, key) -> None:
    """ValueError naming theta0 / P_theta0 / key: wrong shapes, theta0 outside the domains,
    no key."""
    p, names = len(cfg.names), cfg.names
    if theta0 is not None and np.shape(theta0) != (p,):
        raise ValueError(
            f"theta0: expected shape ({p},) for parameters {names} or None (the prior is "
            f"the box), got shape {np.shape(theta0)}"
        )
    if theta0 is not None:
        check_inside("theta0", theta0, cfg.dom_lo, cfg.dom_hi, names)
    if P_theta0 is not None and np.shape(P_theta0) != (p, p):
        raise ValueError(
            f"P_theta0: expected shape ({p}, {p}) for parameters {names} or None, "
            f"got shape {np.shape(P_theta0)}"
        )
    if key is None:
        raise ValueError("key: liu_west_ukf draws random numbers; pass key=jax.random.key(...)")


def _init(cfg: _Config, x0, P0, theta0=None, P_theta0=None, key=None) -> LiuWestState:
    """The UKF's prior and M draws from the box with equal weights (see :func:`liu_west_ukf`)."""
    x0, P0 = prior(cfg.nx, x0, P0)
    dtype = x0.dtype
    _check_init(cfg, theta0, P_theta0, key)
    p, n = len(cfg.names), cfg.n
    low, high = jnp.asarray(cfg.low, dtype), jnp.asarray(cfg.high, dtype)
    k_run, k_draw = smc.split(smc.raw_key(key))
    return LiuWestState(
        x=x0,
        P=P0,
        particles=_draw(cfg, prng.uniforms(k_draw, p * n, dtype).reshape(p, n), low, high),
        log_weights=jnp.full((n,), -math.log(n), dtype),
        key=k_run,
        theta_mean=0.5 * (low + high),
        theta_cov=jnp.diag((high - low) ** 2 / 12.0),
        ess=jnp.asarray(float(n), dtype),
        flag_diverged=jnp.asarray(False),
        n_reinit=jnp.asarray(0, jnp.int32),
        D=jnp.zeros((cfg.nx, p), dtype),
    )


def _step(cfg: _Config, state: LiuWestState, y, u):
    """One step (module docstring): weigh the particles by their one-step predictions, the
    Liu-West move, the parameter estimate, the residual weight, the UKF at the estimate."""
    p, n = len(cfg.names), cfg.n
    dtype = state.x.dtype
    y, u = jnp.asarray(y).astype(dtype), jnp.asarray(u).astype(dtype)
    base = jnp.asarray(cfg.theta).astype(dtype)
    low, high = jnp.asarray(cfg.low, dtype), jnp.asarray(cfg.high, dtype)
    Rd = jnp.asarray(cfg.R, dtype)
    k_next, k_step = smc.split(state.key)
    # the step's random numbers, each from its own counter stream of the particle core:
    # kernel normals (p, M), uniforms for a fresh box draw (p, M) and for resampling
    z = smc.normals(k_step, p, n, dtype)
    u_box = prng.uniforms(k_step, p * n, dtype, stream=cfg.s_box).reshape(p, n)
    u_res = smc.uniforms(k_step, cfg.scheme, n, dtype, stream=cfg.s_box + 1)
    obs = jnp.isfinite(y)
    has_obs = jnp.any(obs)
    theta_prev = full_theta(base, cfg.idx, state.theta_mean)

    # weigh: one-step prediction of every particle from the UKF's filtered mean
    theta_i = cfg.tf.to_physical(state.particles, axis=0)  # (p, M) inside the domains
    rec = (state.D, state.theta_mean) if cfg.recurrent else (None, None)
    y_i = predict_particles(cfg.f, cfg.h, state.x, u, base, cfg.idx, theta_i, *rec)
    L = likelihood_factor(cfg.rule, cfg.f, cfg.h, state.x, state.P, u, theta_prev,
                          jnp.asarray(cfg.Q, dtype), Rd, obs, cfg.predictive)
    rw = weigh(state.log_weights, y_i, y, obs, L)
    diverged = has_obs & rw.underflow
    keep = diverged | ~has_obs
    lw = jnp.where(keep, state.log_weights, rw.log_w)
    w = jnp.exp(lw)

    # Liu-West: resample when the weights degenerate, then (at the steps that resample, or
    # at every step with move="every") shrink towards the mean and jitter
    ess = smc.ess(w)
    parts, lw_k = liu_west_move(cfg.resample, state.particles, w, lw, u_res, cfg.scheme,
                                cfg.threshold, z, box_jitter(dtype, cfg.width_s), cfg.a, keep,
                                cfg.every)

    # parameter estimate: weighted moments of the moved cloud, in physical units
    theta_bar, cov_bar = smc.moments(jnp.exp(lw_k), cfg.tf.to_physical(parts, axis=0))
    cov_bar = cov_bar + box_jitter(dtype, cfg.high - cfg.low)

    # residual weight (a fraction gamma of each weight goes on, the rest evenly); divergence:
    # the next step starts from fresh draws from the prior box
    lw_next = jnp.where(keep, lw_k, residual_weight(lw_k, cfg.gamma))
    parts_next, lw_next, _ = smc.reinitialise(diverged, _draw(cfg, u_box, low, high), parts,
                                              lw_next, jnp.exp(lw_next))

    # state: UKF at the parameter estimate
    D_next, ukf_state, out = ukf_with_derivative(cfg.ukf_step, state.x, state.P, state.D, base,
                                                 cfg.idx, theta_bar, y, u, cfg.recurrent)
    new_state = LiuWestState(
        x=ukf_state.x,
        P=ukf_state.P,
        particles=parts_next,
        log_weights=lw_next,
        key=k_next,
        theta_mean=theta_bar,
        theta_cov=cov_bar,
        ess=jnp.where(diverged, 0.0, jnp.where(has_obs, ess, state.ess)),
        flag_diverged=state.flag_diverged | diverged,
        n_reinit=state.n_reinit + diverged.astype(jnp.int32),
        D=D_next,
    )
    return new_state, out._replace(params=theta_bar, params_cov=cov_bar, reinit=diverged)


# -- the filter -------------------------------------------------------------------------------


def liu_west_ukf(
    model,
    Q,
    R,
    *,
    n_particles: int = 1000,
    estimate=None,
    theta_low=None,
    theta_high=None,
    kernel: LiuWestKernel = LiuWestKernel(),
    resampling: smc.Resampling = smc.Resampling(),
    points: sigma.SigmaPoints = sigma.SigmaPoints(),
    bounds=None,
    recurrent: bool = True,
) -> Estimator:
    """Liu-West particle filter for the parameters ``estimate`` plus a UKF for the state.

    Args:
        model: a vehjax model: ``transition(x, u, theta)``, ``observe(x, u, theta)``.
        Q: process-noise covariance of the state, (nx, nx) or (nx,) variances, state units
            squared per step (the paper's R_s).
        R: measurement-noise covariance, (ny, ny) or (ny,) variances, output units squared (the
            paper's Q).
        n_particles: number of parameter particles M >= 2.
        estimate: names of the estimated parameters, a subset of ``model.param_names`` (p of
            them); the others stay at ``model.theta``.
        theta_low, theta_high: (p,) bounds of the uniform prior, physical units, low < high.
        kernel: :class:`LiuWestKernel`: the shrinkage a, the residual weight gamma, when the
            kernel moves the particles and the likelihood they are weighed by.
        resampling: :class:`~vehjax.filters.Resampling`: the scheme, the ESS rule (resample
            when ESS < ess_threshold * M; 1 resamples every step whose weights are not all
            equal, 0 never, and with ``move="resampled"`` the kernel then never moves the
            particles either) and the resampling function (``resample``, e.g.
            :func:`vehjax.filters.smc.resample_stop_gradient`).
        points: the UKF's sigma-point scaling, :class:`~vehjax.filters.SigmaPoints`
            (:func:`vehjax.filters.sigma.unscented_rule`).
        bounds: ``{name: (low, high)}`` domains of the estimated parameters in physical units,
            None for an open end; the particles never leave them (the kernel acts on the
            unconstrained coordinate, module docstring). Default (None): (0, inf) for a
            parameter whose prior box has theta_low > 0, else the prior box
            [theta_low, theta_high] itself (the logit of a box biases the estimate, module
            docstring). A dict is the whole specification: parameters it
            does not name are unbounded, so ``bounds={}`` is the kernel on theta itself (Liu and
            West's, whose particles can leave the box). Each domain must contain its prior box.
        recurrent: True (default): predict each particle from the UKF's state moved to first
            order to its own parameters, mu + D (theta_i - theta_bar), D = d mu / d theta_bar
            carried through the UKF's recursion (``jax.jacfwd`` of its step); False: from mu
            (module docstring).

    Returns:
        ``Estimator`` with ``needs_key=True`` and ``param_names = estimate``:

        ``init(x0, P0, theta0=None, P_theta0=None, key=None) -> LiuWestState``: x0 (nx,), P0
        (nx, nx) or (nx,) variances: the UKF's prior (their dtype sets the filter's). The
        parameter prior is the uniform box, M draws with equal weights; ``theta0`` (p,) and
        ``P_theta0`` (p, p) are only checked (shapes, theta0 inside the domains) and otherwise
        not used (``vehjax.run``
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
            positive definite, n_particles < 2, unknown or empty ``estimate``, theta_low /
            theta_high of the wrong length or not low < high, ``bounds`` naming other
            parameters, not pairs with low < high, or not containing the prior box, a
            ``kernel``, ``resampling`` or ``points`` that is not its record (the records refuse
            a outside (0, 1), gamma outside (0, 1], an unknown likelihood, move or resampling
            scheme, ess_threshold outside [0, 1] and a ``resample`` that is not callable when
            made).
    """
    nx, ny = check_model(model)
    names, idx = check_estimate(model, estimate)
    if theta_low is None or theta_high is None:
        raise ValueError(
            "theta_low, theta_high: required, the bounds of the uniform prior of " f"{names}"
        )
    low_n, high_n = _check_box(theta_low, theta_high, names)
    n = smc.check_n_particles(n_particles)
    kernel = validation.record("kernel", kernel, LiuWestKernel)
    a, gamma, likelihood, move = kernel.a, kernel.gamma, kernel.likelihood, kernel.move
    resampling = validation.record("resampling", resampling, smc.Resampling)
    scheme, thr, resample = resampling.scheme, resampling.ess_threshold, resampling.function()
    recurrent = validation.flag("recurrent", recurrent)
    points = validation.record("points", points, sigma.SigmaPoints)
    rule = points.rule(nx)  # checks n + kappa
    Qn, Rn = validation.cov("Q", Q, nx, allow_psd=True), validation.cov("R", R, ny)
    dom_lo, dom_hi = _domain(low_n, high_n, bounds, names,
                             np.asarray(model.theta, float)[list(idx)])
    tf = Transform(dom_lo, dom_hi)
    # the prior box's width in s (delta method at its centre), for the kernel's jitter
    centre = 0.5 * (low_n + high_n)
    width_s = (high_n - low_n) / np.abs(np.asarray(tf.jacobian(tf.to_unconstrained(centre))))
    cfg = _Config(
        f=in_dtype(model.transition), h=in_dtype(model.observe), theta=model.theta, names=names,
        idx=np.asarray(idx, np.int32),  # int32: valid with x64 off too (float32 studies)
        nx=nx, n=n, low=low_n, high=high_n, dom_lo=dom_lo, dom_hi=dom_hi, tf=tf,
        width_s=width_s, a=a, gamma=gamma, scheme=scheme, threshold=thr, resample=resample,
        predictive=likelihood == "predictive", every=move == "every", recurrent=recurrent,
        rule=rule,
        ukf_step=ukf(model, Qn, Rn, points=points).step,
        Q=Qn, R=Rn, s_box=(len(names) + 1) // 2,  # counter streams: normals, box, resampling
    )
    box = (0.5 * (low_n + high_n), np.diag((high_n - low_n) ** 2 / 12.0))
    return Estimator(
        init=partial(_init, cfg),
        step=partial(_step, cfg),
        name="liu_west_ukf",
        dims=Dims(nx=nx, **model_dims(model)),
        params=ParamSpec(names=names, prior=box, bounds=tf.bounds),
        runtime=Runtime(needs_key=True, workload="small_dense"),
    )
