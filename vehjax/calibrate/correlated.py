"""The bootstrap particle filter's likelihood as a function of its random numbers, for the
correlated pseudo-marginal method (Deligiannidis, Doucet & Pitt 2018, "The correlated
pseudo-marginal method", JRSS B 80(5); Dahlin, Lindsten, Kronander & Schon 2015).

Model (the one :func:`vehjax.filters.bootstrap_pf` filters)::

    x_0 ~ N(x0, P0)
    x_t = f(x_{t-1}, u_t + Lu w_t, theta) + LQ v_t,      w_t ~ N(0, I_k), v_t ~ N(0, I_nx)
    y_t = h(x_t, u_t, theta) + bias + e_t,              e_t ~ N(0, R), NaN components missing

The filter here consumes explicit auxiliary random numbers ``aux`` (:class:`Aux`), all standard
normal: ``x0`` (N, nx) for the initial particles, ``noise`` (T, N, nx + k) for each step's
propagation (process noise, then input noise) and ``resample`` (T,) for each step's systematic
resampling, mapped to one uniform by the normal CDF. :func:`log_likelihood` is then a
deterministic function of (theta, aux); its exponential is the usual unbiased estimate of
p(y_1:T | theta) for aux ~ N(0, I) (Del Moral 2004), whatever the order the particles are put in
before resampling.

Continuity in aux. PMMH with correlated estimates moves aux by a small Crank-Nicolson step
(:func:`crank_nicolson`) together with theta; the log-likelihood difference between the two is
small only if the estimate is continuous in aux. Plain resampling is not: a small change of the
particles reorders them, and the uniform then picks different ancestors. Sorting the particles
along one scalar key before systematic resampling (a monotone map from one uniform to ancestor
ranks) makes the estimate continuous except where two particles swap places in the key.

The key (:func:`sort_order`). One dimension (nx = 1): the state itself; sorted systematic
resampling is then continuous up to swaps of neighbours, which are close in the state, and the
correlation of successive estimates holds (Deligiannidis et al., sec. 4). Several dimensions: no
ordering keeps all neighbours close, so every swap of two particles' places moves a slot's
ancestor (and the noise it is then propagated with) by the distance between order-neighbours.
Default ``"hilbert"``, the choice of Deligiannidis et al. for d > 1: the particles mapped into
the unit cube by the normal CDF of their standardised coordinates (the weighted mean and std per
component, so units do not matter), cut into a 2^bits grid per axis and ordered along the
Hilbert curve (:func:`hilbert_index`), which keeps order-neighbours within about N^(-1/nx) of
the cloud's size (a 1-D projection keeps them close along one direction only). Alternative
``"projection"``: the projection on the first principal direction of the standardised weighted
cloud (:func:`sort_direction`; power iteration from (1, ..., 1) / sqrt(nx), so the direction is
continuous in the particles and its sign fixed), one argsort: as good where the cloud is
elongated along one direction. Either way the correlation that survives in nx >= 2 falls with
the number of swaps, which grows with N^2 T times the Crank-Nicolson step: it is measured, not
assumed (:func:`vehjax.calibrate.log_likelihood_difference_spread`).

Resampling happens at every step (no ESS threshold: a threshold switch is a discontinuity).
Shapes: N particles, nx states, k input-noise directions, T steps, ny outputs.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from ..filters import resampling as _rs
from ..filters.particle import measurement_logliks

__all__ = ["Aux", "draw_aux", "crank_nicolson", "sort_direction", "hilbert_index", "sort_order",
           "systematic_ancestors", "log_likelihood"]

#: power-iteration steps of :func:`sort_direction`
POWER_STEPS = 20
#: grid cells per axis of the Hilbert sort: 2^HILBERT_BITS (fewer when nx * bits > 64)
HILBERT_BITS = 16


class Aux(NamedTuple):
    """The filter's random numbers, all standard normal (a pytree).

    Attributes:
        x0: (N, nx) for the initial particles x0 + L0 x0_i.
        noise: (T, N, nx + k) step t's process noise (first nx) and input noise (last k).
        resample: (T,) step t's systematic-resampling uniform is Phi(resample[t]).
    """

    x0: jnp.ndarray
    noise: jnp.ndarray
    resample: jnp.ndarray


def draw_aux(key, T: int, n: int, nx: int, k: int = 0) -> Aux:
    """Independent standard normals of :class:`Aux`'s shapes (float64 under x64)."""
    k0, k1, k2 = jax.random.split(key, 3)
    return Aux(jax.random.normal(k0, (n, nx)), jax.random.normal(k1, (T, n, nx + k)),
               jax.random.normal(k2, (T,)))


def crank_nicolson(aux, eps, rho):
    """The Crank-Nicolson move rho aux + sqrt(1 - rho^2) eps of every leaf (aux, eps: pytrees of
    the same shapes, eps standard normal; rho in (0, 1)): it leaves N(0, I) invariant and is
    reversible with respect to it, so the pair (theta, aux) can be proposed jointly with
    acceptance ratio the ratio of the estimates (Deligiannidis et al. 2018, eq. 8)."""
    c = math.sqrt(1.0 - rho * rho) if isinstance(rho, float) else jnp.sqrt(1.0 - rho * rho)
    return jax.tree_util.tree_map(lambda a, e: rho * a + c * e, aux, eps)


def sort_direction(x, w, steps: int = POWER_STEPS):
    """The sorting key's direction (module docstring): the first principal direction of the
    particles x (N, nx) with normalised weights w (N,) in standardised coordinates, by ``steps``
    power iterations from (1, ..., 1) / sqrt(nx). Returns (a (nx,), m (nx,), s (nx,)): the key
    of a particle is ((x - m) / s) . a, with m the weighted mean and s the weighted std (plus a
    1e-300 floor) per component."""
    m = w @ x
    xc = x - m
    s = jnp.sqrt(w @ (xc * xc)) + 1e-300
    zs = xc / s
    C = (zs * w[:, None]).T @ zs                       # weighted correlation (nx, nx)
    nx = x.shape[1]

    def power(a, _):
        b = C @ a
        return b / (jnp.linalg.norm(b) + 1e-300), None

    a, _ = jax.lax.scan(power, jnp.full((nx,), 1.0 / math.sqrt(nx), x.dtype), None,
                        length=steps)
    return a, m, s


def hilbert_index(q, bits: int):
    """Hilbert-curve index of integer points: q (N, d) uint64 with entries < 2^bits, d * bits
    <= 64. Skilling (2004, "Programming the Hilbert curve", AIP Conf. Proc. 707): the axes are
    turned into the curve's "transpose" (undo the excess work, then Gray-encode), whose bits
    interleaved (most significant first, axis 0 first) are the index along the curve. Returns
    (N,) uint64; points adjacent on the curve are adjacent cells of the 2^bits grid."""
    d = q.shape[1]
    X = [q[:, i] for i in range(d)]
    one = jnp.uint64(1)
    Q = 1 << (bits - 1)
    while Q > 1:
        P, Qu = jnp.uint64(Q - 1), jnp.uint64(Q)
        for i in range(d):
            hit = (X[i] & Qu) != 0
            if i == 0:
                X[0] = jnp.where(hit, X[0] ^ P, X[0])
            else:
                t = (X[0] ^ X[i]) & P
                X0 = jnp.where(hit, X[0] ^ P, X[0] ^ t)
                X[i] = jnp.where(hit, X[i], X[i] ^ t)
                X[0] = X0
        Q >>= 1
    for i in range(1, d):
        X[i] = X[i] ^ X[i - 1]
    t = jnp.zeros_like(X[0])
    Q = 1 << (bits - 1)
    while Q > 1:
        t = jnp.where((X[d - 1] & jnp.uint64(Q)) != 0, t ^ jnp.uint64(Q - 1), t)
        Q >>= 1
    X = [xi ^ t for xi in X]
    h = jnp.zeros_like(X[0])
    for b in range(bits - 1, -1, -1):
        for i in range(d):
            h = (h << one) | ((X[i] >> jnp.uint64(b)) & one)
    return h


def sort_order(x, w, method: str = "hilbert"):
    """Indices (N,) that sort the particles x (N, nx) with normalised weights w (N,): by x
    itself for nx = 1; else ``"hilbert"``: by the Hilbert index (:func:`hilbert_index`) of
    Phi((x - m) / s) on a grid of 2^bits cells per axis (m, s the weighted mean and std per
    component, Phi the normal CDF: the cloud mapped into the unit cube), or ``"projection"``:
    by the key of :func:`sort_direction`."""
    if x.shape[1] == 1:
        return jnp.argsort(x[:, 0])
    if method == "projection":
        a, m, s = sort_direction(x, w)
        return jnp.argsort(((x - m) / s) @ a)
    nx = x.shape[1]
    bits = min(HILBERT_BITS, 64 // nx)
    m = w @ x
    s = jnp.sqrt(w @ ((x - m) ** 2)) + 1e-300
    cell = jnp.floor(jax.scipy.stats.norm.cdf((x - m) / s) * 2.0**bits)
    q = jnp.clip(cell, 0, 2.0**bits - 1).astype(jnp.uint64)
    return jnp.argsort(hilbert_index(q, bits))


def systematic_ancestors(w, uniform):
    """Systematic resampling: ancestor indices (N,) int, non-decreasing, of the positions
    (i + uniform) / N, i = 0..N-1, in the cumulative weights of w (N,) normalised; uniform in
    [0, 1). Monotone in the position, so sorted particles keep their order (the particle
    core's :func:`vehjax.filters.resampling.indices_from_uniforms`)."""
    return _rs.indices_from_uniforms("systematic", w, uniform, w.shape[0])


def log_likelihood(f, h, ys, us, theta, x0, L0, LQ, R, bias, aux: Aux, Lu=None,
                   sort: str = "hilbert"):
    """log of the bootstrap PF's likelihood estimate of y_1:T with random numbers ``aux``.

    Args:
        f, h: ``f(x, u, theta) -> x'``, ``h(x, u, theta) -> y`` of one point.
        ys: (T, ny) measurements, NaN missing; us: (T, nu) inputs; theta: (np,).
        x0: (nx,) prior mean; L0: (nx, nx) its covariance's factor.
        LQ: (nx, nx) process-noise factor (LQ LQ^T = Q, state units per step).
        R: (ny, ny) measurement-noise covariance [output units^2]; bias: (ny,) added to h.
        aux: :class:`Aux` for N particles, T steps, k = Lu's columns.
        Lu: (nu, k) input-noise factor or None (k = 0).

    Returns:
        () sum_t log(mean_i p(y_t | x_t^i)); -inf when every particle's weight vanishes at a
        step (or a value is not finite).
    """
    nx = L0.shape[0]
    n = aux.x0.shape[0]
    log_n = math.log(n)
    fv = jax.vmap(f, in_axes=(0, 0 if Lu is not None else None, None))
    hv = jax.vmap(h, in_axes=(0, None, None))
    X = x0 + aux.x0 @ L0.T

    def step(X, inp):
        y, u, z, r = inp
        uu = u if Lu is None else u + z[:, nx:] @ Lu.T
        X = fv(X, uu, theta) + z[:, :nx] @ LQ.T
        obs = jnp.isfinite(y)
        e = jnp.where(obs, y - hv(X, u, theta) - bias, 0.0)
        ll = measurement_logliks(e.T, obs, R)  # the bootstrap PF's, particles in columns
        ll = jnp.where(jnp.all(jnp.isfinite(X), axis=1) & jnp.isfinite(ll), ll, -jnp.inf)
        inc = jax.scipy.special.logsumexp(ll) - log_n
        w = jnp.exp(ll - jnp.max(ll))
        w = w / jnp.sum(w)
        w = jnp.where(jnp.isfinite(w), w, 1.0 / n)         # after a vanished step (inc -inf)
        order = sort_order(jnp.where(jnp.isfinite(X), X, 0.0), w, sort)
        anc = systematic_ancestors(w[order], jax.scipy.stats.norm.cdf(r))
        return X[order[anc]], inc

    _, incs = jax.lax.scan(step, X, (ys, us, aux.noise, aux.resample))
    total = jnp.sum(incs)
    return jnp.where(jnp.isfinite(total), total, -jnp.inf)
