"""The random walk's adaptation over the warm-up of a particle MCMC chain.

The random-walk covariance starts as ``(0.1 * prior scale)^2`` per coordinate (unconstrained
units) unless a proposal is given (:func:`initial_factor`; :class:`~vehjax.calibrate.RandomWalk`).
With an :class:`~vehjax.calibrate.Adaptation` (the default) the warm-up is cut
into windows of doubling length (:func:`adaptation_windows`; the first 80 % of it); after each
the proposal becomes s^2 (2.38^2 / d) C (Roberts & Rosenthal 2001's scaling) with C the
covariance of that window's draws pooled over chains, shrunk toward the previous estimate
(:func:`adapted_covariance`), and s a scale tuned toward a target acceptance rate
(:func:`scale_update`; :func:`target_acceptance`: 0.44 for d = 1 to 0.234 for an exact
likelihood, lower for a noisy estimate). Later windows are longer, so the estimate settles as
the chains reach the posterior; strongly correlated quantities get a proposal along their
correlation. The proposal is fixed after the last window, so the draws kept after warm-up come
from a plain Metropolis-Hastings chain. :class:`Adapt` is the state a sampler carries
(:func:`adapt_init`, :func:`adapt_step`).
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import validation
from .options import Chains, RandomWalk

__all__ = ["RW_SCALE", "RW_ACCEPTANCE", "target_acceptance", "adaptation_windows",
           "adapted_covariance", "scale_update", "proposal_factor", "initial_factor", "Adapt",
           "adapt_init", "adapt_step"]


#: Roberts, Gelman & Gilks (1997): the random walk's optimal scale on a d-dimensional Gaussian
#: target is 2.38 / sqrt(d) times the target's covariance, where the acceptance is 0.234
RW_SCALE, RW_ACCEPTANCE = 2.38, 0.234


#: the optimal random walk's acceptance rate on a d-dimensional Gaussian target, d = 1..10
#: (Gelman, Roberts & Gilks 1996, Bayesian Statistics 5, table 1); 0.234 beyond
_RW_ACCEPTANCE_D = (0.441, 0.352, 0.316, 0.279, 0.275, 0.266, 0.261, 0.255, 0.25, 0.247)


def target_acceptance(d: int, loglik_std=0.0):
    """The acceptance rate to tune a random walk toward in d dimensions when the log-likelihood
    is estimated with Gaussian noise of std ``loglik_std`` [nats]: the exact-likelihood optimum
    a_d (Gelman, Roberts & Gilks 1996: 0.44 for d = 1 down to 0.234 for large d) times the
    factor the noise takes off it at the large-d optimal scale l = 2.38 (Sherlock, Thiery,
    Roberts & Rosenthal 2015, Ann. Statist. 43(1): acceptance 2 Phi(-sqrt(l^2 + 2 sigma^2) / 2),
    0.234 at sigma = 0, 0.144 at 1.2, 0.11 at 1.5). Dimensionless, in (0, 1)."""
    d = validation.integer("d", d, 1)
    s = validation.number("loglik_std", loglik_std, 0.0, low_open=False)
    a_d = _RW_ACCEPTANCE_D[d - 1] if d <= len(_RW_ACCEPTANCE_D) else RW_ACCEPTANCE
    noisy = math.erfc(0.5 * math.sqrt(RW_SCALE**2 + 2.0 * s * s) / math.sqrt(2.0))
    return a_d * noisy / math.erfc(0.5 * RW_SCALE / math.sqrt(2.0))


def chain_options(chains, proposal, d: int, warmup: int):
    """The chains and the random walk every sampler takes, checked the same way: (the
    :class:`~vehjax.calibrate.Chains` (``Chains()`` for None) with its warm-up set, ``warmup``
    (the sampler's default) where None; the :class:`~vehjax.calibrate.RandomWalk`
    (``RandomWalk()`` for None); the acceptance target (the adaptation's, default
    :func:`target_acceptance` of the d quantities); the iterations after which the proposal is
    re-estimated (:func:`adaptation_windows`; empty without adaptation)). ValueError naming the
    argument (``chains.warmup`` >= 2 with adaptation)."""
    chains = validation.record("chains", chains, Chains)
    if chains.warmup is None:
        chains = dataclasses.replace(chains, warmup=warmup)
    proposal = validation.record("proposal", proposal, RandomWalk)
    ad = proposal.adaptation
    if ad is None:
        return chains, proposal, target_acceptance(d), np.zeros(0, int)
    validation.integer("chains.warmup", chains.warmup, 2)
    target = target_acceptance(d) if ad.acceptance is None else ad.acceptance
    return chains, proposal, target, adaptation_windows(chains.warmup, ad.windows)


def adaptation_windows(warmup: int, windows: int) -> np.ndarray:
    """The iterations (1-based counts) after which the warm-up re-estimates the proposal:
    ``windows`` windows whose lengths double (1, 2, 4, ...) and fill the first 80 % of the
    warm-up; the last 20 % runs with the final proposal. (k,) ints, strictly increasing, k <=
    windows (windows shorter than 4 iterations merged into the next); empty for 0 windows."""
    if windows <= 0 or warmup < 2:
        return np.zeros(0, int)
    span = max(1, int(0.8 * warmup))
    w = 2.0 ** np.arange(windows)
    ends = np.unique(np.round(span * np.cumsum(w) / w.sum()).astype(int))
    keep = np.diff(np.concatenate([[0], ends])) >= 4
    keep[-1] = True
    ends = ends[keep]
    return ends[ends >= 1]


def adapted_covariance(s1, s2, count, cov_prev, prior_count):
    """The target's covariance estimated from one window's draws pooled over chains, shrunk
    toward the previous estimate: (count C + prior_count cov_prev) / (count + prior_count), C the
    draws' covariance (ddof 1) from their sums s1 = sum z (d,), s2 = sum z z^T (d, d) over
    ``count`` draws (unconstrained units). The shrinkage keeps a short window whose chains
    barely moved from collapsing the proposal. (d, d), symmetric."""
    mean = s1 / count
    cov = (s2 - count * jnp.outer(mean, mean)) / (count - 1)
    cov = (count * cov + prior_count * cov_prev) / (count + prior_count)
    return 0.5 * (cov + cov.T)


def scale_update(log_scale, acceptance, target):
    """The random walk's log scale after a window with acceptance rate ``acceptance``, toward
    ``target``: for a random walk of scale l (in units of the target's std) on a Gaussian target
    the acceptance is 2 Phi(-l / 2) (Roberts, Gelman & Gilks 1997), so the scale that gives
    ``target`` is the current one times Phi^-1(target / 2) / Phi^-1(acceptance / 2). The
    acceptance is clipped to [0.005, 0.95] and the factor to [1/4, 4] (one window's estimate).
    Scalars in, scalar out (log of a dimensionless factor)."""
    a = jnp.clip(acceptance, 0.005, 0.95)
    ratio = jax.scipy.stats.norm.ppf(0.5 * target) / jax.scipy.stats.norm.ppf(0.5 * a)
    return log_scale + jnp.log(jnp.clip(ratio, 0.25, 4.0))


def proposal_factor(cov, log_scale, L_prev):
    """The random walk's Cholesky factor exp(log_scale) chol((2.38^2 / d) cov) (plus a 1e-10
    relative jitter), or ``L_prev`` when that is not positive definite. (d, d) lower."""
    d = cov.shape[0]
    cov = cov + 1e-10 * jnp.maximum(1.0, jnp.max(jnp.diag(cov))) * jnp.eye(d)
    L = jnp.exp(log_scale) * jnp.linalg.cholesky((RW_SCALE**2 / d) * cov)
    return jnp.where(jnp.all(jnp.isfinite(L)), L, L_prev)


class Adapt(NamedTuple):
    """The warm-up's adaptation state: the target's covariance estimate and the proposal's log
    scale, the proposal factor they give, and the current window's sums."""
    cov: jnp.ndarray        # (d, d) unconstrained
    log_scale: jnp.ndarray  # ()
    L: jnp.ndarray          # (d, d) proposal factor in use
    s1: jnp.ndarray         # (d,) window sums
    s2: jnp.ndarray         # (d, d)
    n: jnp.ndarray          # () draws in the window (over chains)
    acc: jnp.ndarray        # () accepted moves in the window


def adapt_init(L0):
    """Adaptation state whose proposal is L0: cov = L0 L0^T d / 2.38^2, scale 1."""
    d = L0.shape[0]
    z = jnp.zeros((), L0.dtype)
    return Adapt(L0 @ L0.T * d / RW_SCALE**2, z, L0, jnp.zeros(d, L0.dtype),
                  jnp.zeros((d, d), L0.dtype), z, z)


def adapt_step(ad: Adapt, i, z, accepted, ends, target, prior_count):
    """After iteration i (0-based) with draws z (C, d) and acceptances (C,) (or rates): add
    them to the window; at a window's end (i + 1 in ``ends``) re-estimate the covariance
    (:func:`adapted_covariance`) and the scale (:func:`scale_update`), set the proposal
    (:func:`proposal_factor`) and start a new window."""
    s1, s2 = ad.s1 + z.sum(axis=0), ad.s2 + z.T @ z
    n, acc = ad.n + z.shape[0], ad.acc + jnp.sum(accepted)
    ad = ad._replace(s1=s1, s2=s2, n=n, acc=acc)
    if len(ends) == 0:
        return ad

    def update(ad):
        cov = adapted_covariance(ad.s1, ad.s2, ad.n, ad.cov, prior_count)
        cov = jnp.where(jnp.all(jnp.isfinite(cov)), cov, ad.cov)
        ls = scale_update(ad.log_scale, ad.acc / ad.n, target)
        zero = jnp.zeros_like(ad.n)
        return Adapt(cov, ls, proposal_factor(cov, ls, ad.L), 0.0 * ad.s1, 0.0 * ad.s2, zero,
                     zero)

    # only at a window's end (a branch, not a select: the rest of the time costs nothing)
    return jax.lax.cond(jnp.any(i + 1 == jnp.asarray(ends)), update, lambda ad: ad, ad)


def initial_factor(priors, proposal):
    """The random walk's starting Cholesky factor (d, d), unconstrained units, of a
    :class:`~vehjax.calibrate.RandomWalk`: of its ``cov`` when given, else diag(``std``), else
    diag(0.1 x each prior's scale). ValueError naming the field for a size other than d."""
    d = len(priors)
    if proposal.cov is not None:
        C = np.asarray(proposal.cov, float)
        L = np.linalg.cholesky(C) if C.shape == (d, d) and np.all(np.isfinite(C)) \
            and np.allclose(C, C.T) and np.all(np.linalg.eigvalsh(C) > 0) else None
        if L is None:
            raise ValueError(f"proposal.cov: expected a symmetric positive definite ({d}, {d}) "
                             f"matrix (unconstrained units), got {proposal.cov!r}")
        return L
    if proposal.std is None:
        return np.diag([0.1 * p.scale for p in priors])
    s = np.asarray(proposal.std, float) if np.ndim(proposal.std) <= 1 else None
    s = None if s is None or s.shape not in ((), (1,), (d,)) else np.broadcast_to(s, (d,))
    if s is None or not np.all(np.isfinite(s)) or np.any(s <= 0):
        raise ValueError(f"proposal.std: expected a positive number or {d} positive numbers "
                         f"(unconstrained units), got {proposal.std!r}")
    return np.diag(s)
