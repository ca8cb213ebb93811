"""Iterated smoothers: the whole forward-backward pass iterated to a fixed point.

* IEKS, the iterated extended Kalman smoother (Bell 1994; Tronarp, García-Fernández & Särkkä
  2018): linearise the transition and the measurement by their Jacobians about the last
  smoothed means, run the Kalman filter and RTS smoother on that affine model, repeat. It is
  Gauss-Newton on the negative log posterior of the whole trajectory, so its fixed point is the
  maximum a posteriori trajectory.
* IPLS, the iterated posterior-linearisation smoother (García-Fernández, Svensson & Särkkä 2017;
  Tronarp et al. 2018): the same with statistical linear regression by the filter's sigma
  points about the last smoothed Gaussians N(m^s_t, P^s_t).

Both are one map Phi: trajectory (M (T+1, n), P (T+1, n, n)) -> the smoothed moments of the
model linearised about it (:func:`vehjax.smoothers.gaussian.linearize`; with them the pass's
cross-covariances and log-likelihood, which Phi does not read), iterated from a start
until the largest change of a mean, in units of its smoothed standard deviation, is at most
``tol`` or ``max_iter`` passes have run; each pass sequential or parallel in time
(:mod:`vehjax.smoothers.parallel`).

Gradients (:func:`fixed_point`): not by unrolling the iterations. The fixed point z* = Phi(z*,
p) (p: everything the model, the noise and the prior depend on) is differentiated implicitly,
dz*/dp = (I - dPhi/dz)^-1 dPhi/dp: the reverse pass solves w = zbar + (dPhi/dz)^T w by the same
kind of iteration (as in JAX's documented fixed-point example) and returns (dPhi/dp)^T w. The
smoothed log-likelihood, that of the Kalman filter on the model linearised about z*, is then
differentiated through z* and directly in p: the exact derivative of the reported number. (The
envelope shortcut, stopping the gradient at z*, would drop the dependence of the linearisation
on z*; exact only for affine models.)
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp

from . import linear, parallel as _parallel

__all__ = ["linear_pass", "change", "fixed_point"]


def linear_pass(model: linear.Affine, ys, parallel):
    """Kalman filter then RTS smoother on an affine model, sequential (``parallel`` False) or
    parallel in time (True or "associative": ``jax.lax.associative_scan``; "doubling":
    :func:`vehjax.smoothers.parallel.doubling_scan`).

    Returns:
        (smoothed means (T+1, n), covariances (T+1, n, n), cross-covariances (T, n, n),
        log-likelihood per step (T+1,)).
    """
    if not parallel:
        ms, Ps, ll = linear.kalman_filter(model, ys)
        m_s, P_s, cross = linear.rts_smoother(model, ms, Ps)
    else:
        scan = "associative" if parallel is True else parallel
        ms, Ps, ll = _parallel.kalman_filter(model, ys, scan)
        m_s, P_s, cross = _parallel.rts_smoother(model, ms, Ps, scan)
    return m_s, P_s, cross, ll


def change(z_new, z_old):
    """Largest change of a mean between two trajectories (M, P, ...), in units of the new
    smoothed standard deviations: max |M_new - M_old| / sqrt(diag P_new). NaN when either is
    NaN."""
    M1, P1 = z_new[0], z_new[1]
    M0 = z_old[0]
    sd = jnp.sqrt(jnp.maximum(jnp.diagonal(P1, axis1=-2, axis2=-1), jnp.finfo(M1.dtype).tiny))
    return jnp.max(jnp.abs(M1 - M0) / sd)


def _iterate(fn, tol, max_iter, z0, params):
    """``z <- fn(z, params)`` until :func:`change` <= tol or max_iter passes; (z, passes, last
    change). A NaN change stops the loop (the caller flags the run)."""

    def cond(carry):
        _, k, delta = carry
        return (k < max_iter) & (delta > tol)

    def body(carry):
        z, k, _ = carry
        z_new = fn(z, params)
        return z_new, k + 1, change(z_new, z)

    inf = jnp.asarray(jnp.inf, z0[0].dtype)
    return jax.lax.while_loop(cond, body, (z0, jnp.zeros((), jnp.int32), inf))


@partial(jax.custom_vjp, nondiff_argnums=(0, 1, 2))
def _fixed_point(fn, tol, max_iter, z0, params):
    return _iterate(fn, tol, max_iter, z0, params)


def _fixed_point_fwd(fn, tol, max_iter, z0, params):
    out = _iterate(fn, tol, max_iter, z0, params)
    return out, (out[0], params, z0)


def _fixed_point_bwd(fn, tol, max_iter, res, cts):
    z, params, z0 = res
    zbar = cts[0]
    _, vjp_z = jax.vjp(lambda zz: fn(zz, params), z)
    leaves = jax.tree_util.tree_leaves

    def size(w):
        return jnp.max(jnp.stack([jnp.max(jnp.abs(a)) for a in leaves(w)]))

    def cond(carry):
        w, k, delta = carry
        return (k < 4 * max_iter) & (delta > tol * (1.0 + size(w)))

    def body(carry):
        w, k, _ = carry
        w_new = jax.tree_util.tree_map(jnp.add, zbar, vjp_z(w)[0])
        delta = size(jax.tree_util.tree_map(jnp.subtract, w_new, w))
        return w_new, k + 1, delta

    inf = jnp.asarray(jnp.inf, z[0].dtype)
    w, _, _ = jax.lax.while_loop(cond, body, (zbar, jnp.zeros((), jnp.int32), inf))
    _, vjp_p = jax.vjp(lambda p: fn(z, p), params)
    return jax.tree_util.tree_map(jnp.zeros_like, z0), vjp_p(w)[0]


_fixed_point.defvjp(_fixed_point_fwd, _fixed_point_bwd)


def fixed_point(phi, z0, args, tol: float, max_iter: int):
    """Iterate ``z <- phi(z, args)`` from z0 to its fixed point, implicitly differentiable.

    Args:
        phi: ``phi(z, args) -> z``, pure; may close over traced values (they are hoisted with
            ``jax.closure_convert`` and differentiated too).
        z0: start, a pytree (M, P, ...) of (T+1, n), (T+1, n, n) and anything else phi
            returns (not read by phi).
        args: pytree of arrays phi depends on (differentiated).
        tol: stop when :func:`change` <= tol (smoothed standard deviations).
        max_iter: at most this many passes.

    Returns:
        (z*, passes run (int32), last change): z* carries the implicit derivative of module
        docstring; the other two are diagnostics (not differentiated).
    """
    closed, consts = jax.closure_convert(phi, z0, args)

    def fn(z, params):
        a, c = params
        return closed(z, a, *c)

    z, k, delta = _fixed_point(fn, float(tol), int(max_iter), z0, (args, list(consts)))
    return z, jax.lax.stop_gradient(k), jax.lax.stop_gradient(delta)
