"""The marginalized PF with the noise means as Kalman states (``marginalized_pf(...,
noise_means="kalman")``): the model seen by that filter, and its priors and estimates mapped
to and from the paper's parameters.

Why. In the paper's filter (eq. 18) each particle's NiW statistics take the particle's
residuals as exact observations of the sensor noise, and the particle's Kalman filter takes the
NiW bias means as exact. A sensor whose bias the data separate from a state only slowly (the
roll-rate bias from the bank rate: only the bank-angle sensor, through the integral, tells them
apart) then gets a bias posterior far narrower than the data support (``vehjax reproduce
consistency``: its spread over runs about twice its reported std). The offset mean mu_w and the
biases b enter the model linearly (x_t = f(x, u + mu_w + w~) ~ affine in mu_w for a model affine
in the noisy input; y = h(...) + b + e~), so each particle's Kalman filter can carry them as
constant states with their exact Gaussian posterior and their correlation with the states, and
only the covariances (sigma_w^2, R) remain for the conjugate statistics: an inverse-Wishart on
v~ = (w~, e~) of known mean zero, i.e. the NiW with gamma = 0 (kappa = infinity: eq. 18 with
gamma = 0 adds eta eta^T to Lambda and leaves the mean; the predictive of eq. 26 keeps its dof
nu - d + 1 with the factor 1 + gamma = 1). The residual the statistics take is then at the
Kalman posterior mean of all states, offset and biases included, with H P H^T added (the
expected sufficient statistic, :mod:`vehjax.filters.marginalized`), so the uncertainty of the
biases reaches the covariance statistics too.

Prior. The paper's NiW gives the offset and the biases the prior N(mean0, gamma0 Sigma_0),
Sigma_0 = diag(std0^2); the Kalman states get the same Gaussian (independent of the model's
states).

Estimates. Offset and biases: the weighted mean and covariance of the particles' Kalman
posteriors (the mixture moments of those states); stds and their covariance: eq. 23 on the
inverse-Wishart statistics. The cross-covariance between the two groups is not computed (zero).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ..models.base import Model
from ..models.biases import _BiasedBank, with_output_biases

__all__ = ["with_noise_means", "mean_state_names", "pad_linear_noise", "bias_walk_stds",
           "augment_prior", "map_estimates"]


def mean_state_names(sensors):
    """Names of the added states: ``<sensor>_bias`` per sensor (those of
    :func:`vehjax.models.with_output_biases`)."""
    return tuple(f"{s}_bias" for s in sensors)


def with_noise_means(model, sensors) -> Model:
    """``model`` with the bias of each sensor as a constant state after the model's own:
    :func:`vehjax.models.with_output_biases` (observe adds it to the sensor's row; a model
    with ``bank_noise_gain()`` keeps it, zeros on the biases)."""
    return with_output_biases(model, sensors)


def pad_linear_noise(linear_noise_std, n_linear, n_extra, bank_gain):
    """``linear_noise_std`` of the user's linear states extended to the added (constant) mean
    states: None with no linear states -> zeros; per-state stds -> zeros appended; a scalar on
    a model without ``bank_noise_gain`` -> that std on each linear state, zeros after (with
    the gain the scalar is sigma_phi and the gain is zero on the added states). Anything else
    is returned as given, for ``marginalized_pf``'s own check to name."""
    if linear_noise_std is None:
        return np.zeros(n_extra) if n_linear == 0 else None
    if isinstance(linear_noise_std, (bool, np.bool_)):
        return linear_noise_std
    try:
        sig = np.asarray(linear_noise_std, dtype=float)
    except (TypeError, ValueError):
        return linear_noise_std
    if sig.ndim == 1 and sig.shape[0] == n_linear:
        return np.r_[sig, np.zeros(n_extra)]
    if sig.ndim == 0 and not bank_gain:
        return np.r_[np.full(n_linear, float(sig)), np.zeros(n_extra)]
    return linear_noise_std


def bias_walk_stds(bias_walk, sensors):
    """Checked random-walk stds (ns,) of the bias states from ``bias_walk`` (None or a dict
    sensor -> std per step >= 0, missing sensors 0). Raises ValueError naming ``bias_walk``."""
    if bias_walk is None:
        return np.zeros(len(sensors))
    if not isinstance(bias_walk, dict) or any(k not in sensors for k in bias_walk):
        raise ValueError(f"bias_walk: expected a dict sensor -> std with sensors from "
                         f"{tuple(sensors)}, got {bias_walk!r}")
    out = []
    for k in sensors:
        v = bias_walk.get(k, 0.0)
        try:
            f = float(v)
        except (TypeError, ValueError):
            f = float("nan")
        if isinstance(v, (bool, np.bool_)) or not np.isfinite(f) or f < 0.0:
            raise ValueError(f"bias_walk[{k!r}]: expected a finite std >= 0, got {v!r}")
        out.append(f)
    return np.array(out)


def augment_prior(x0, P0, theta, gamma0, ns):
    """The prior of the model with the bias states: x0 (nx,), P0 (nx,) or (nx, nx) of the
    model's states, ``theta`` (2 + 2 ns,) the paper's parameters (offset, its std, biases,
    stds). Returns (x0 (nx + ns,), P0 (nx + ns, nx + ns)): the biases appended with variance
    gamma0 * std^2, independent of the model's states (the paper's NiW prior of the biases)."""
    x0 = jnp.asarray(x0)
    P0 = jnp.asarray(P0)
    P0 = jnp.diag(P0) if P0.ndim == 1 else P0
    nx = x0.shape[0]
    dtype = jnp.result_type(x0.dtype, P0.dtype, theta.dtype)
    Pa = jnp.zeros((nx + ns, nx + ns), dtype).at[:nx, :nx].set(P0).at[nx:, nx:].set(
        jnp.diag(gamma0 * theta[2 + ns:] ** 2))
    return jnp.concatenate([x0.astype(dtype), theta[2:2 + ns].astype(dtype)]), Pa


def map_estimates(mean, cov, params, params_cov, nx, ns):
    """The paper's parameters from the filter on the model with bias states: the biases from
    the mixture mean ``mean`` (nx + ns,) and covariance ``cov`` of the states (model order, the
    biases last), the offset and the stds from the statistics' ``params`` (2 + 2 ns,) and
    ``params_cov``. Returns (params, params_cov) in the order offset, offset std, biases,
    stds; zero covariance between the biases and the rest."""
    bi = np.arange(2, 2 + ns)  # the biases in params order
    oi = np.concatenate([[0, 1], np.arange(2 + ns, 2 + 2 * ns)])
    p = params.at[bi].set(mean[nx:])
    pc = jnp.zeros_like(params_cov).at[np.ix_(bi, bi)].set(cov[nx:, nx:]).at[
        np.ix_(oi, oi)].set(params_cov[np.ix_(oi, oi)])
    return p, pc
