"""Particle marginal Metropolis-Hastings (:func:`pmmh`), plain and correlated.

Andrieu, Doucet & Holenstein (2010), "Particle Markov chain Monte Carlo methods", JRSS B 72(3):
a Metropolis-Hastings chain over the unknown quantities phi whose acceptance ratio uses a particle
filter's estimate of the likelihood p(y_1:T | phi) in place of the exact one. The estimate is
unbiased, so the chain's stationary distribution is the exact posterior p(phi | y_1:T), whatever
the number of particles (fewer particles only make the chain stickier). The chain moves in the
priors' unconstrained coordinates (:mod:`vehjax.calibrate.priors`) with a Gaussian random walk,
adapted over the warm-up (:mod:`vehjax.calibrate.adaptation`).

Correlated pseudo-marginal (``pmmh(Correlated(bootstrap_pf, rho), ...)``, Deligiannidis,
Doucet & Pitt 2018): the chain carries the bootstrap PF's random numbers and moves them by a
Crank-Nicolson step with each proposal
(:func:`vehjax.calibrate.likelihood.cpm_log_likelihood_fn`, :mod:`vehjax.calibrate.correlated`),
so that the acceptance ratio compares two strongly correlated estimates.

Random streams: one ``key`` is split into one key per chain; iteration i of chain c draws its
proposal, its accept uniform and its particle filter's key from ``fold_in(key_c, i + 1)``
(the starting values' likelihood from ``fold_in(key_c, 0)``), so a run is reproducible and a
chain's draws do not depend on the number of chains. Chains are vmapped (one particle filter per
chain per iteration, all in one ``lax.scan``).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import validation
from .adaptation import adapt_init, adapt_step, chain_options, initial_factor
from .correlated import crank_nicolson
from .diagnostics import PMMHResult, result
from .likelihood import cpm_log_likelihood_fn, log_likelihood_fn
from .options import Chains, Correlated, RandomWalk
from .priors import check_priors, log_prior_unconstrained, starting_values, to_physical

__all__ = ["sampler", "pmmh"]


class _Chain(NamedTuple):
    z: jnp.ndarray          # (d,) unconstrained
    log_target: jnp.ndarray  # () log-lik estimate + log prior of z
    loglik: jnp.ndarray      # () the estimate held with z
    aux: object = None       # correlated estimates: the random numbers of that estimate


def _mh_iteration(loglik, priors, L_prop, key_chain, move=None):
    """One PMMH step of one chain: ``(chain, i) -> (chain, (z, loglik, accepted))``. Without
    ``move`` the estimate is drawn afresh from the iteration's key (``loglik(values, key)``);
    with it (correlated pseudo-marginal) the chain carries the estimate's random numbers and
    proposes ``move(aux, key)`` with z, accepted or rejected together (``loglik(values, aux)``)."""

    def step(chain: _Chain, i):
        k = jax.random.fold_in(key_chain, i + 1)
        k_prop, k_acc, k_pf = jax.random.split(k, 3)
        z_new = chain.z + L_prop @ jax.random.normal(k_prop, chain.z.shape, chain.z.dtype)
        if move is None:
            aux_new = None
            ll_new = loglik(to_physical(priors, z_new), k_pf)
        else:
            aux_new = move(chain.aux, k_pf)
            ll_new = loglik(to_physical(priors, z_new), aux_new)
        lt_new = ll_new + log_prior_unconstrained(priors, z_new)
        lt_new = jnp.where(jnp.isfinite(lt_new), lt_new, -jnp.inf)
        accept = jnp.log(jax.random.uniform(k_acc, (), chain.z.dtype)) < lt_new - chain.log_target
        aux = None if move is None else jax.tree_util.tree_map(
            lambda a, b: jnp.where(accept, a, b), aux_new, chain.aux)
        new = _Chain(jnp.where(accept, z_new, chain.z), jnp.where(accept, lt_new, chain.log_target),
                     jnp.where(accept, ll_new, chain.loglik), aux)
        return new, (new.z, new.loglik, accept)

    return step



def sampler(loglik, priors, n_iter: int, ends, target: float, prior_count: float,
             draw=None, move=None):
    """``(keys (C,), z0 (C, d), L0 (d, d)) -> (draws (C, n, d), logliks (C, n), accepted (C, n),
    L, starting log targets (C,))``: the starting values' likelihoods, then ``n_iter``
    iterations of every chain (one ``lax.scan`` over iterations, the chains vmapped inside it),
    the proposal re-estimated from the pooled draws after each iteration count in ``ends``
    (:func:`vehjax.calibrate.adaptation.adapt_step`; empty: never). Correlated estimates: ``draw(key) -> aux`` the
    starting random numbers (from ``fold_in(key_c, 0)``), ``move(aux, key) -> aux`` their
    proposal (:func:`_mh_iteration`)."""

    def first(key, z):
        if draw is None:
            ll = loglik(to_physical(priors, z), jax.random.fold_in(key, 0))
            return _Chain(z, ll + log_prior_unconstrained(priors, z), ll)
        aux = draw(jax.random.fold_in(key, 0))
        ll = loglik(to_physical(priors, z), aux)
        return _Chain(z, ll + log_prior_unconstrained(priors, z), ll, aux)

    def run(keys, z0, L0):
        chains = jax.vmap(first)(keys, z0)

        def body(carry, i):
            chains, ad = carry
            chains, out = jax.vmap(
                lambda k, c: _mh_iteration(loglik, priors, ad.L, k, move)(c, i))(keys, chains)
            ad = adapt_step(ad, i, out[0], out[2], ends, target, prior_count)
            return (chains, ad), out

        (_, ad), (zs, lls, acc) = jax.lax.scan(body, (chains, adapt_init(L0)),
                                               jnp.arange(n_iter))
        return (jnp.swapaxes(zs, 0, 1), jnp.swapaxes(lls, 0, 1), jnp.swapaxes(acc, 0, 1), ad.L,
                chains.log_target)

    return jax.jit(run)



def pmmh(builder, model, measurements, inputs=None, *, x0, P0, Q, R, priors, key,
         chains: Chains = Chains(), proposal: RandomWalk = RandomWalk()) -> PMMHResult:
    """Particle marginal Metropolis-Hastings over named quantities of a model and its noise.

    Args:
        builder: filter builder ``builder(model, Q, R)``, its options by ``functools.partial``:
            for PMMH ``partial(vehjax.filters.bootstrap_pf, n_particles=N)``, whose
            likelihood estimate is unbiased, or :func:`fixed_noise_mpf` (the marginalized PF
            with fixed noise statistics: unbiased, far less noisy for models affine in the
            states); a Kalman filter gives exact Metropolis-Hastings. Or a :class:`Correlated`
            (the bootstrap PF with its correlation rho): correlated pseudo-marginal
            (Deligiannidis, Doucet & Pitt 2018): the chain carries the bootstrap PF's random
            numbers aux (:func:`cpm_log_likelihood_fn`, :mod:`vehjax.calibrate.correlated`),
            each proposal moves them to rho aux + sqrt(1 - rho^2) eps with the random walk's
            step and both are accepted or rejected together; the acceptance ratio then sees
            the noise of a difference of two strongly correlated estimates
            (:func:`log_likelihood_difference_spread`) instead of two independent ones.
        model: a vehjax model; its ``theta`` holds the parameters that are not calibrated.
        measurements: (T, ny) one drive, NaN components missing; inputs (T, nu) or None.
        x0, P0: the prior of the state before the first step.
        Q, R: process / measurement noise, (n,) variances or (n, n); named stds replace their
            diagonal entries.
        priors: dict name -> :class:`Normal` / :class:`LogNormal` / :class:`Uniform` (module
            docstring for the names: ``"R[ay]"``, ``"Q[vy]"``, ``"bias[ay]"``,
            ``"input[delta]"`` standard deviations and biases, parameters by name).
        key: PRNG key; every random number of the run comes from it.
        chains: :class:`Chains` (number, draws kept, warm-up, starting values; default 4 x
            (500 + 1000) from the priors' centres; warm-up 500 unless given).
        proposal: :class:`RandomWalk`: the random walk's start (default 0.1 x each prior's
            scale) and its :class:`Adaptation` over the warm-up (module docstring).

    Returns:
        :class:`PMMHResult`.

    Raises:
        ValueError: naming the argument, for unknown names, bad priors or sizes, or a zero
            likelihood at the starting values (``chains.init``).
    """
    names, prs = check_priors(priors)
    chains, proposal, target, ends = chain_options(chains, proposal, len(prs), 500)
    draw = move = None
    if isinstance(builder, Correlated):
        loglik, draw = cpm_log_likelihood_fn(builder, model, measurements, inputs, x0=x0,
                                             P0=P0, Q=Q, R=R, names=names)
        rho = builder.correlation

        def move(aux, k):
            return crank_nicolson(aux, draw(k), rho)
    else:
        loglik = log_likelihood_fn(builder, model, measurements, inputs, x0=x0, P0=P0, Q=Q,
                                   R=R, names=names)
    L0 = initial_factor(prs, proposal)
    z0 = np.tile(starting_values(prs, chains.init, names, "chains.init"), (chains.n, 1))
    keys = validation.key(key, chains.n)
    run = sampler(loglik, prs, chains.warmup + chains.samples, ends, target, 5.0 * len(prs),
                  draw, move)
    zs, lls, acc, L, lt0 = run(keys, jnp.asarray(z0), jnp.asarray(L0))
    if not np.all(np.isfinite(np.asarray(lt0))):
        raise ValueError("chains.init: the likelihood estimate at the starting values is zero "
                         "(the filter diverged or the prior excludes them); give other "
                         "chains.init values or more particles")
    return result(names, prs, zs, lls, acc, L, chains.warmup)
