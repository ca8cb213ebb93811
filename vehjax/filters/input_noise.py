"""Noise that enters through the inputs: ``x' = f(x, u + w_u, theta) + w``, ``w_u ~ N(0, Sigma_u)``.

A vehicle's measured inputs (the steering angle, the speed) carry sensor noise, and the model's
error is often best described as an error of its input: a road-wheel angle that is not what the
steering sensor says. Every filter of :mod:`vehjax.filters` that takes ``input_noise=`` treats
it with the mathematics here, one small function per idea:

* :func:`input_factor` - the user's description (stds by input name, or an (nu, nu) covariance)
  as a factor ``Lu`` (nu, k) with ``Sigma_u = Lu Lu^T``; k is the number of noisy directions, so
  inputs without noise add no dimension.
* :func:`linearized_input_noise` - the EKF's term ``G Sigma_u G^T``, ``G = df/du`` at (x, u) by
  ``jax.jacfwd``: the step's process noise is ``Q + G Sigma_u G^T``.
* :func:`augmented_points`, :func:`sigma_predict`, :func:`sqrt_sigma_predict` - the sigma-point
  filters augment the state with the standardised input noise ``e ~ N(0, I_k)``:
  ``a = [x; e] ~ N([x; 0], blockdiag(P, I_k))``, each point goes through
  ``f(a_x, u + Lu a_e)``, and the moments of the images are the prediction (plus Q). On a model
  linear in x and u that is exactly ``A P A^T + B Sigma_u B^T + Q``.
* :func:`perturbed_inputs` - the particle filters draw one input per particle,
  ``u_i = u + Lu z_i``.

Units: ``input_noise`` stds are in the units of each input (``model.input_units``: rad for a
steering angle, m/s for a speed), a covariance in those units squared; ``Q`` stays in state units
squared per step. With input noise ``Q`` may be zero or tiny: the noise then enters only through
the inputs (the prediction covariance is still positive definite where ``G Sigma_u G^T`` reaches
every state the data need).
"""

from __future__ import annotations

from typing import Mapping

import jax
import jax.numpy as jnp
import numpy as np

from .. import validation
from ..lib.linalg import cholesky, sym
from .sigma import SigmaRule, sigma_points, sqrt_unscented_transform, unscented_transform

__all__ = ["input_factor", "input_covariance", "linearized_input_noise", "augmented_points",
           "through_inputs", "sigma_predict", "sqrt_sigma_predict", "perturbed_inputs"]


def _std_entries(input_noise: Mapping, input_names) -> tuple[np.ndarray, list]:
    """(indices of the named inputs, their stds) from a dict name -> std; ValueError naming
    ``input_noise``."""
    names = tuple(input_names)
    bad = [k for k in input_noise if k not in names]
    if bad:
        raise ValueError(f"input_noise: unknown input name(s) {bad}; expected names from {names}")
    if not input_noise:
        raise ValueError("input_noise: expected at least one input name -> std, got an empty dict")
    idx, stds = [], []
    for k in names:
        if k not in input_noise:
            continue
        s = input_noise[k]
        if not validation.is_tracer(s):
            if isinstance(s, (bool, np.bool_)) or np.ndim(s) != 0:
                raise ValueError(f"input_noise: expected a number (std) for {k!r}, got {s!r}")
            try:
                v = float(s)
            except (TypeError, ValueError):  # complex, text
                v = float("nan")
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"input_noise: the std of {k!r} must be finite and > 0 (in the "
                                 f"input's units), got {s!r}")
        idx.append(names.index(k))
        stds.append(s)
    return np.array(idx, dtype=int), stds


def input_factor(input_noise, input_names):
    """A factor ``Lu`` (nu, k) with ``Lu Lu^T = Sigma_u``, the covariance of the input noise.

    Args:
        input_noise: None (no input noise); a dict ``{input name: std}`` with stds > 0 in the
            input's units (the other inputs are noise-free; k = number of names), values may
            be traced (fitting them); or an (nu, nu) covariance in input units squared,
            positive semi-definite (k = its rank when concrete; a traced one must be positive
            definite, k = nu).
        input_names: the model's input names (nu of them).

    Returns:
        None, a numpy array when ``input_noise`` is concrete, else a jax array.

    Raises:
        ValueError: naming ``input_noise``: unknown names, stds not > 0, a wrong shape, a
            covariance that is not symmetric positive semi-definite or is zero, a model without
            inputs.
    """
    if input_noise is None:
        return None
    names = tuple(input_names)
    nu = len(names)
    if nu == 0:
        raise ValueError("input_noise: the model has no inputs")
    if isinstance(input_noise, Mapping):
        idx, stds = _std_entries(input_noise, names)
        k = len(idx)
        if not any(validation.is_tracer(s) for s in stds):
            Lu = np.zeros((nu, k))
            Lu[idx, np.arange(k)] = np.asarray(stds, dtype=float)
            return Lu
        return jnp.zeros((nu, k)).at[idx, np.arange(k)].set(jnp.stack(
            [jnp.asarray(s) for s in stds]))
    if validation.is_tracer(input_noise):
        S = validation.cov("input_noise", input_noise, nu, allow_diag=False)
        return jnp.linalg.cholesky(S)
    S = validation.cov("input_noise", input_noise, nu, allow_diag=False, allow_psd=True)
    w, V = np.linalg.eigh(S)
    keep = w > 1e-12 * max(float(w.max()), np.finfo(float).tiny)
    if not np.any(keep):
        raise ValueError("input_noise: the covariance is zero; pass None for no input noise")
    if np.all(keep):
        return np.linalg.cholesky(S)
    return V[:, keep] * np.sqrt(w[keep])[None, :]


def input_covariance(Lu):
    """``Sigma_u = Lu Lu^T`` (nu, nu), input units squared."""
    return Lu @ Lu.T


def linearized_input_noise(f, x, u, Lu):
    """The EKF's process noise from the inputs, ``G Sigma_u G^T`` (nx, nx) in state units
    squared, with ``G = df/du`` (nx, nu) at (x, u) by ``jax.jacfwd``.

    Args:
        f: ``f(x, u) -> x'`` (nx,), the transition at fixed parameters.
        x: (nx,) the point of linearisation (the filtered mean).
        u: (nu,) the input.
        Lu: (nu, k) factor of Sigma_u (:func:`input_factor`).
    """
    Lu = jnp.asarray(Lu, x.dtype)
    Gw = jax.jacfwd(lambda e: f(x, u + Lu @ e))(jnp.zeros((Lu.shape[1],), x.dtype))  # G Lu
    return sym(Gw @ Gw.T)


def augmented_points(rule: SigmaRule, x, L, k: int):
    """Sigma points (m, nx + k) of N([x; 0], blockdiag(L L^T, I_k)), ``rule`` in nx + k
    dimensions (the state and the standardised input noise)."""
    nx = x.shape[0]
    dt = x.dtype
    La = jnp.zeros((nx + k, nx + k), dt).at[:nx, :nx].set(L).at[nx:, nx:].set(jnp.eye(k, dtype=dt))
    return sigma_points(jnp.concatenate([x, jnp.zeros((k,), dt)]), La, rule)


def through_inputs(f, u, Lu, A, nx: int):
    """Rows a of ``A`` (m, nx + k) through ``f(a[:nx], u + Lu a[nx:])``: (m, nx')."""
    Lu = jnp.asarray(Lu, A.dtype)
    return jax.vmap(lambda a: jnp.asarray(f(a[:nx], u + Lu @ a[nx:])).astype(A.dtype))(A)


def sigma_predict(rule: SigmaRule, x, P, f, u, Lu, Q=None):
    """Sigma-point prediction with input noise: points of N([x; 0], blockdiag(P, I_k)) through
    ``f(x, u + Lu e)``, their weighted mean (nx,) and covariance (nx, nx), plus ``Q`` when
    given. ``rule`` is in nx + k dimensions. Returns (x-, P-)."""
    nx, k = x.shape[0], Lu.shape[1]
    Xf = through_inputs(f, u, Lu, augmented_points(rule, x, cholesky(P), k), nx)
    return unscented_transform(Xf, rule, Q)


def sqrt_sigma_predict(rule: SigmaRule, x, L, f, u, Lu, LQ):
    """Square-root :func:`sigma_predict`: (x-, L-) with L- L-^T = P-, from the factor L of P
    and a square root LQ of Q (zeros for Q = 0)."""
    nx, k = x.shape[0], Lu.shape[1]
    Xf = through_inputs(f, u, Lu, augmented_points(rule, x, L, k), nx)
    return sqrt_unscented_transform(Xf, rule, LQ)


def perturbed_inputs(u, Lu, z):
    """One input per particle, ``u + Lu z`` (nu, N), from standard normals z (k, N)."""
    return u[:, None] + jnp.asarray(Lu, z.dtype) @ z
