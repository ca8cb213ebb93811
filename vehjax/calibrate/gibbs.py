"""Particle Gibbs with ancestor sampling (:func:`particle_gibbs`).

Lindsten, Jordan & Schon (2014), "Particle Gibbs with ancestor sampling", JMLR 15 (paper 004's
[29]): alternates a conditional particle filter with ancestor sampling (:func:`conditional_pf_as`),
which draws a state trajectory given the current values and the previous trajectory, with
Metropolis-Hastings moves of the values given the trajectory on the exact joint density
p(x_0:T, y | values) (:func:`log_joint`). It needs the transition density, so the process noise
must be additive Gaussian with Q positive definite; it mixes with a few tens of particles where
PMMH needs the likelihood estimate's variance near 1.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from .. import validation
from ..filters import resampling as _rs
from ..filters import smc
from .adaptation import adapt_init, adapt_step, chain_options, initial_factor
from .diagnostics import PMMHResult, result
from .likelihood import targets
from .options import Chains, RandomWalk, Sweep
from .priors import check_priors, log_prior_unconstrained, starting_values, to_physical

__all__ = ["conditional_pf_as", "log_joint", "particle_gibbs"]

#: the resampling scheme of the conditional PF: multinomial, each non-reference ancestor drawn
#: independently from the weights (Lindsten, Jordan & Schon 2014, Algorithm 2)
_SCHEME = "multinomial"


def _gaussian_cols(e, L):
    """log N(e_j; 0, L L^T) of the columns of e (n, M), L a lower Cholesky factor: (M,)
    (:func:`vehjax.filters.smc.gaussian_logliks`, every component observed)."""
    return smc.gaussian_logliks(e, jnp.ones(e.shape[0], bool), L=L)


def _measurement_cols(y, yhat, r_var):
    """log N(y; yhat_j, diag(r_var)) over the observed (finite) components of y (ny,), for the
    columns yhat (ny, M): (M,)."""
    obs = jnp.isfinite(y)
    e = jnp.where(obs[:, None], y[:, None] - yhat, 0.0)
    return smc.gaussian_logliks(e, obs, var=r_var)


def _weights(log_w, log_lik):
    """Normalised weights (N,) of ``log_w + log_lik`` (:func:`vehjax.filters.smc.reweight`),
    equal ones where every weight vanished."""
    r = smc.reweight(log_w, log_lik)
    return jnp.where(r.underflow, 1.0 / log_w.shape[0], r.w), jnp.where(
        r.underflow, -jnp.log(float(log_w.shape[0])), r.log_w)


def _draw(w, key, n: int, stream: int):
    """n ancestor indices drawn independently from the weights w (N,) (multinomial, the
    particle core's :func:`vehjax.filters.resampling.indices_from_uniforms`)."""
    u = smc.uniforms(key, _SCHEME, n, w.dtype, stream=stream)
    return _rs.indices_from_uniforms(_SCHEME, w, u, n)


def _pg_parts(model, tg, theta_base, Q, R, values):
    """(theta, chol(Q), R's diagonal, bias (ny,)) with the named quantities set to ``values``."""
    theta = theta_base
    for i, j in tg.params:
        theta = theta.at[j].set(values[i])
    for i, j in tg.q_std:
        Q = Q.at[j, j].set(values[i] ** 2)
    r_var = jnp.diag(R)
    for i, j in tg.r_std:
        r_var = r_var.at[j].set(values[i] ** 2)
    bias = jnp.zeros(model.ny)
    for i, j in tg.bias:
        bias = bias.at[j].set(values[i])
    return theta, jnp.linalg.cholesky(Q), r_var, bias


def conditional_pf_as(model, key, ref, theta, LQ, r_var, bias, ys, us, x0, LP0, n: int):
    """One sweep of the conditional particle filter with ancestor sampling (Lindsten, Jordan &
    Schon 2014, Algorithm 2): a new state trajectory (T + 1, nx) given the reference ``ref``.

    Model: x_0 ~ N(x0, LP0 LP0^T), x_t = f(x_{t-1}, u_t) + N(0, LQ LQ^T),
    y_t = h(x_t, u_t) + bias + N(0, diag(r_var)) (NaN components of y_t missing). Particle n - 1
    is the reference; its ancestor at each step is drawn with weights w_{t-1}^j
    p(ref_t | x_{t-1}^j); the others resample multinomially and propagate; one trajectory is
    drawn by its final weight and traced back through the ancestors.

    Built on the particle core (:mod:`vehjax.filters.smc`): particles (nx, N) with the particle
    axis last, weights by :func:`~vehjax.filters.smc.reweight` of
    :func:`~vehjax.filters.smc.gaussian_logliks`, random numbers hashed from a raw key
    (:func:`~vehjax.filters.smc.normals`, :func:`~vehjax.filters.smc.uniforms`; ``key`` any
    JAX key), ancestors by :func:`vehjax.filters.resampling.indices_from_uniforms`.
    """
    f = jax.vmap(model.transition, in_axes=(1, None, None), out_axes=1)
    h = jax.vmap(model.observe, in_axes=(1, None, None), out_axes=1)
    nx = LQ.shape[0]
    dtype = jnp.result_type(x0, LQ)
    s_u = (nx + 1) // 2  # the first counter stream after the normals' rows
    key, k0 = smc.split(smc.raw_key(key))
    X0 = (x0[:, None] + LP0 @ smc.normals(k0, nx, n, dtype)).at[:, n - 1].set(ref[0])

    def step(carry, inp):
        X, log_w, key = carry
        y, u, xref = inp
        key, k = smc.split(key)
        FX = f(X, u, theta)
        anc = _draw(jnp.exp(log_w), k, n, s_u)
        w_ref, _ = _weights(log_w, _gaussian_cols(xref[:, None] - FX, LQ))
        anc = anc.at[n - 1].set(_draw(w_ref, k, 1, s_u + 1)[0])
        Xn = (FX[:, anc] + LQ @ smc.normals(k, nx, n, dtype)).at[:, n - 1].set(xref)
        _, log_w = _weights(jnp.full(n, -math.log(n), dtype),
                            _measurement_cols(y, h(Xn, u, theta) + bias[:, None], r_var))
        return (Xn, log_w, key), (Xn, anc)

    log_w0 = jnp.full(n, -math.log(n), dtype)
    (_, log_w, key), (Xs, ancs) = jax.lax.scan(step, (X0, log_w0, key), (ys, us, ref[1:]))
    k = _draw(jnp.exp(log_w), smc.split(key)[1], 1, 0)[0]

    def back(k, inp):
        X, anc = inp
        return anc[k], X[:, k]

    k0, traj = jax.lax.scan(back, k, (Xs, ancs), reverse=True)
    return jnp.concatenate([X0[:, k0][None], traj])


def log_joint(model, traj, theta, LQ, r_var, bias, ys, us, x0, LP0):
    """log p(x_0:T, y_1:T | theta) of a trajectory (T + 1, nx) under the model of
    :func:`conditional_pf_as`: ()."""
    fx = jax.vmap(model.transition, in_axes=(0, 0, None))(traj[:-1], us, theta)
    yhat = jax.vmap(model.observe, in_axes=(0, 0, None))(traj[1:], us, theta) + bias
    obs = jax.vmap(lambda y, yh: _measurement_cols(y, yh[:, None], r_var)[0])(ys, yhat)
    return (_gaussian_cols((traj[0] - x0)[:, None], LP0)[0]
            + jnp.sum(_gaussian_cols((traj[1:] - fx).T, LQ)) + jnp.sum(obs))


def particle_gibbs(model, measurements, inputs=None, *, x0, P0, Q, R, priors, key,
                   sweep: Sweep = Sweep(), chains: Chains = Chains(),
                   proposal: RandomWalk = RandomWalk()) -> PMMHResult:
    """Particle Gibbs with ancestor sampling (Lindsten, Jordan & Schon 2014) over named
    quantities (model parameters, ``"R[<output>]"``, ``"Q[<state>]"``, ``"bias[<output>]"`` as
    in :func:`pmmh`; no input noise).

    Each sweep draws a state trajectory from :func:`conditional_pf_as` given the current
    values, then makes ``sweep.moves`` random-walk Metropolis-Hastings moves of the values (in
    the priors' unconstrained coordinates) on log p(x_0:T, y | values) + log prior
    (:func:`log_joint`). Few particles suffice (ancestor sampling keeps the trajectory mixing).
    The model's process noise must be additive and Q positive definite; R is diagonal
    ((ny,) variances or a diagonal matrix).

    Args:
        model, measurements (T, ny), inputs (T, nu) or None, x0, P0, Q, R, priors, key: as in
            :func:`pmmh`.
        sweep: :class:`Sweep`: the conditional PF's particles (default 20) and the moves of
            the values per sweep (default 3).
        chains: :class:`Chains` as in :func:`pmmh`; warm-up 200 unless given.
        proposal: :class:`RandomWalk` as in :func:`pmmh`; the adaptation tunes the moves of
            the values given the trajectory (pooled over chains, the acceptance averaged over
            the sweep's moves).

    Returns:
        :class:`PMMHResult` (``loglik``: log p(x_0:T, y | values) of each draw with its
        trajectory).
    """
    names, prs = check_priors(priors)
    tg = targets(model, names)
    if tg.inputs:
        raise ValueError("priors: particle_gibbs does not calibrate input noise ('input[...]')")
    chains, proposal, acceptance_target, ends = chain_options(chains, proposal, len(prs), 200)
    sweep = validation.record("sweep", sweep, Sweep)
    n, mh_steps = sweep.n_particles, sweep.moves
    warmup, samples = chains.warmup, chains.samples
    ys, us = validation.data(measurements, inputs, model.ny, model.nu, "one")
    ys, us = jnp.asarray(ys, float), jnp.asarray(us, float)
    x0a, P0a = validation.prior(model.nx, x0, P0)
    x0a, LP0 = jnp.asarray(x0a, float), jnp.asarray(np.linalg.cholesky(np.asarray(P0a, float)))
    Qm = jnp.asarray(validation.cov("Q", Q, model.nx))
    Rm = np.asarray(validation.cov("R", R, model.ny))
    if not np.allclose(Rm, np.diag(np.diag(Rm))):
        raise ValueError("R: particle_gibbs needs a diagonal measurement covariance")
    Rm = jnp.asarray(Rm)
    L = jnp.asarray(initial_factor(prs, proposal))
    z0 = jnp.tile(starting_values(prs, chains.init, names, "chains.init"), (chains.n, 1))
    keys = validation.key(key, chains.n)
    theta_base = jnp.asarray(model.theta, float)
    T = ys.shape[0]

    def parts(z):
        return _pg_parts(model, tg, theta_base, Qm, Rm, to_physical(prs, z))

    def target(z, traj):
        return log_joint(model, traj, *parts(z), ys, us, x0a, LP0) + log_prior_unconstrained(prs, z)

    def one_sweep(key_c, z, traj, i, L):
        """One sweep of one chain: (z, traj) -> (z, traj, log joint, acceptance rate)."""
        k_pf, k_mh = jax.random.split(jax.random.fold_in(key_c, i))
        traj = conditional_pf_as(model, k_pf, traj, *parts(z), ys, us, x0a, LP0, n)

        def mh(zc, k):
            kp, ku = jax.random.split(k)
            zn = zc + L @ jax.random.normal(kp, zc.shape)
            d = target(zn, traj) - target(zc, traj)
            ok = jnp.log(jax.random.uniform(ku)) < jnp.where(jnp.isfinite(d), d, -jnp.inf)
            return jnp.where(ok, zn, zc), ok

        z, acc = jax.lax.scan(mh, z, jax.random.split(k_mh, mh_steps))
        return z, traj, log_joint(model, traj, *parts(z), ys, us, x0a, LP0), jnp.mean(acc)

    def run(keys, z0, L0):
        def body(carry, i):
            z, traj, ad = carry
            z, traj, lj, acc = jax.vmap(lambda k, zc, tc: one_sweep(k, zc, tc, i, ad.L))(
                keys, z, traj)
            ad = adapt_step(ad, i, z, acc, ends, acceptance_target, 5.0 * len(prs))
            return (z, traj, ad), (z, lj, acc)

        traj0 = jnp.tile(x0a, (z0.shape[0], T + 1, 1))
        (_, _, ad), (zs, ljs, acc) = jax.lax.scan(body, (z0, traj0, adapt_init(L0)),
                                                  jnp.arange(warmup + samples))
        return (jnp.swapaxes(zs, 0, 1), jnp.swapaxes(ljs, 0, 1), jnp.swapaxes(acc, 0, 1), ad.L)

    zs, ljs, acc, L = jax.jit(run)(keys, z0, L)
    return result(names, prs, zs, ljs, acc, L, warmup)
