"""What the marginalized PFs report from their weighted particles: the mixture's mean and
covariance over all model states (the particles and their Kalman filters) and the NIS of a
measurement under the mixture of the particles' predictives."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from .. import smc
from ...lib.entrywise import cholesky_observed
from ..sigma import solve_lower
from .setup import Setup

__all__ = ["mixture_moments", "mixture_nis"]


def mixture_moments(s: Setup, w_now, x, z, P):
    """Weighted mean and covariance over all model states (model order): the particles and the
    mixture of their Kalman filters, with a relative jitter of sqrt(eps) on the diagonal."""
    dtype = x.dtype
    Xp = jnp.concatenate([x, z])  # sampled then linear states
    mean_p, cov_p = smc.mixture(w_now, Xp, P if s.n_linear else None, s.n_states - s.n_kalman)
    jitter = jnp.sqrt(jnp.finfo(dtype).eps) * jnp.diagonal(cov_p) + jnp.sqrt(
        jnp.finfo(dtype).tiny)
    cov_p = cov_p + jnp.diag(jitter)
    return mean_p[s.model_order], cov_p[np.ix_(s.model_order, s.model_order)]


def mixture_nis(wp, mu_y, cov_y, y0, obs):
    """NIS of the observed components under the mixture of the particles' predictives (prior
    weights ``wp``)."""
    ybar = mu_y @ wp
    dyb = mu_y - ybar[:, None]
    Sy = jnp.einsum("ijn,n->ij", cov_y, wp) + (dyb * wp) @ dyb.T
    Ly = cholesky_observed(Sy, obs)
    a = solve_lower(Ly, jnp.where(obs, y0 - ybar, 0.0))
    return jnp.sum(a * a)
