"""The marginalized PF with the noise means as Kalman states
(:func:`~vehjax.filters.marginalized.marginalized_pf_grid`): the model seen by that filter, and its
priors and estimates mapped to and from the paper's parameters.

Why. In the paper's filter (eq. 18) each particle's NiW statistics take the particle's
residuals as exact observations of the noise means, and the particle's Kalman filter takes the
NiW means as exact. A mean that the data separate from a state or another mean only slowly
(the roll-rate bias from the bank rate: only the bank-angle sensor, through the integral,
tells them apart; the ay bias from the steering offset, which ay sees as d mu_w) then gets a
posterior far narrower than the data support (``vehjax reproduce consistency``: the roll-rate
bias's spread over runs about twice its reported std). The offset mu_w and the biases b enter
the model linearly (x_t = f(x, u + mu_w + w~), affine in mu_w for a model affine in the noisy
input; y = h(...) + b + e~), so each particle's Kalman filter carries them as constant states
(:func:`vehjax.models.with_output_biases`, :func:`vehjax.models.with_input_offset`) with
their exact Gaussian posterior and their correlations, and only the covariances (sigma_w^2,
R) remain for the conjugate statistics: an inverse-Wishart on v~ = (w~, e~) of known mean
zero (the NiW with gamma = 0). How the filter then learns the covariances (sigma_w^2 on a
fixed grid of particles, R from expected statistics) is in :mod:`vehjax.filters.marginalized`.

Prior. The paper's NiW gives the offset and the biases the prior N(mean0, gamma0 Sigma_0),
Sigma_0 = diag(std0^2); the Kalman states get that Gaussian, or the stds the caller gives
(``mean_std0``), independent of the model's states and of each other.

Estimates. Offset and biases: the weighted mean and covariance of the particles' Kalman
posteriors (the mixture moments of those states, their correlations included); stds and their
covariance: eq. 23 on the inverse-Wishart statistics. The cross-covariance between the two
groups is not computed (zero).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ... import validation
from ...models.base import Model
from ...models.biases import with_input_offset, with_output_biases

__all__ = ["with_noise_means", "mean_state_names", "pad_linear_noise", "bias_walk_stds",
           "augment_prior", "map_estimates"]


def mean_state_names(sensors, noisy_input):
    """Names of the added states: ``<sensor>_bias`` per sensor (those of
    :func:`vehjax.models.with_output_biases`), then ``<noisy_input>_offset`` (that of
    :func:`vehjax.models.with_input_offset`)."""
    return tuple(f"{s}_bias" for s in sensors) + (f"{noisy_input}_offset",)


def with_noise_means(model, sensors, noisy_input) -> Model:
    """``model`` with the bias of each sensor and the offset of ``noisy_input`` as constant
    states after the model's own: :func:`vehjax.models.with_output_biases` (observe adds each
    bias to its sensor's row), then :func:`vehjax.models.with_input_offset` (the model driven
    by the input plus the offset). A model with ``bank_noise_gain()`` keeps it, zeros on the
    added states."""
    return with_input_offset(with_output_biases(model, sensors), noisy_input)


def pad_linear_noise(Q, n_linear, n_extra, bank_gain):
    """``Q`` (process covariance) of the user's linear states extended to the added (constant)
    mean states: None with no linear states -> zeros; per-state variances -> zeros appended; an
    (n_linear, n_linear) covariance -> zero rows and columns appended; a scalar on a model
    without ``bank_noise_gain`` -> that variance on each linear state, zeros after (with the
    gain the scalar is sigma_phi^2 and the gain is zero on the added states). Anything else is
    returned as given, for ``marginalized_pf``'s own check to name."""
    if Q is None:
        return np.zeros(n_extra) if n_linear == 0 else None
    try:
        q = validation.array("Q", Q, allow_nan=True)
    except ValueError:  # a bool, a string: marginalized_pf's own check names it
        return Q
    if q.ndim == 1 and q.shape[0] == n_linear:
        return np.r_[q, np.zeros(n_extra)]
    if q.ndim == 2 and q.shape == (n_linear, n_linear):
        out = np.zeros((n_linear + n_extra, n_linear + n_extra))
        out[:n_linear, :n_linear] = q
        return out
    if q.ndim == 0 and not bank_gain:
        return np.r_[np.full(n_linear, float(q)), np.zeros(n_extra)]
    return Q


def bias_walk_stds(bias_walk, sensors):
    """Checked random-walk stds (ns,) of the bias states from ``bias_walk`` (None or a dict
    sensor -> std per step >= 0, missing sensors 0). Raises ValueError naming ``bias_walk``."""
    if bias_walk is None:
        return np.zeros(len(sensors))
    if not isinstance(bias_walk, dict) or any(k not in sensors for k in bias_walk):
        raise ValueError(f"bias_walk: expected a dict sensor -> std with sensors from "
                         f"{tuple(sensors)}, got {bias_walk!r}")
    return np.array([validation.number(f"bias_walk[{k!r}]", bias_walk.get(k, 0.0), 0.0,
                                       low_open=False, what="a finite std >= 0")
                     for k in sensors])


def augment_prior(x0, P0, theta, gamma0, ns, mean_sd=None):
    """The prior of the model with the mean states: x0 (nx,), P0 (nx,) or (nx, nx) of the
    model's states, ``theta`` (2 + 2 ns,) the paper's parameters (offset, its std, biases,
    stds). Returns (x0 (nx + ns + 1,), P0 (nx + ns + 1, nx + ns + 1)): the biases then the
    offset appended with variance gamma0 * std^2 (the paper's NiW prior of the means) or
    ``mean_sd``^2 where given ((ns + 1,) in that order, NaN for "not given"), independent of
    each other and of the model's states."""
    x0 = jnp.asarray(x0)
    P0 = jnp.asarray(P0)
    P0 = jnp.diag(P0) if P0.ndim == 1 else P0
    nx = x0.shape[0]
    dtype = jnp.result_type(x0.dtype, P0.dtype, theta.dtype)
    means = jnp.concatenate([theta[2:2 + ns], theta[:1]])
    stds = jnp.concatenate([theta[2 + ns:], theta[1:2]])
    var = gamma0 * stds ** 2
    if mean_sd is not None:
        var = jnp.where(np.isnan(mean_sd), var, np.nan_to_num(np.asarray(mean_sd)) ** 2)
    Pa = jnp.zeros((nx + ns + 1, nx + ns + 1), dtype).at[:nx, :nx].set(P0).at[nx:, nx:].set(
        jnp.diag(var))
    return jnp.concatenate([x0.astype(dtype), means.astype(dtype)]), Pa


def map_estimates(mean, cov, params, params_cov, nx, ns):
    """The paper's parameters from the filter on the model with mean states: the biases and
    the offset from the mixture mean ``mean`` (nx + ns + 1,) and covariance ``cov`` of the
    states (model order, the biases then the offset last), the offset's std and the sensor stds
    from the statistics' ``params`` (2 + 2 ns,) and ``params_cov``. Returns (params,
    params_cov) in the order offset, offset std, biases, stds; the means' covariance (offset
    and biases, with their correlation) from the states, zero covariance between the means and
    the stds."""
    mi = np.concatenate([[0], np.arange(2, 2 + ns)])  # offset, biases in params order
    si = np.concatenate([[nx + ns], np.arange(nx, nx + ns)])  # the same among the states
    oi = np.concatenate([[1], np.arange(2 + ns, 2 + 2 * ns)])  # the stds
    p = params.at[mi].set(mean[si])
    pc = jnp.zeros_like(params_cov).at[np.ix_(mi, mi)].set(cov[np.ix_(si, si)]).at[
        np.ix_(oi, oi)].set(params_cov[np.ix_(oi, oi)])
    return p, pc
