"""The marginalized PF's state (:class:`MPFState`, particles last in every leaf) and its start
from the prior (:func:`initial_state`): the particles drawn from P0, the Kalman filters from the
Gaussian conditional of the linear states given each particle, the NiW statistics from the
guesses."""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ... import validation
from .. import smc
from .setup import Setup

__all__ = ["MPFState", "initial_state", "prior_in_dtype"]


class MPFState(NamedTuple):
    """State of :func:`~vehjax.filters.marginalized.marginalized_pf` and
    :func:`~vehjax.filters.marginalized.marginalized_pf_grid` for one run; the particle axis N is
    last.

    Attributes:
        x: (n_x, N) sampled states (the model states not in ``linear_states``, model order);
            with ``kalman_states="all"`` the means of each particle's Gaussian over them.
        z: (n_z, N) Kalman means of the linear states (``linear_states`` order).
        P: (n_z, n_z, N) their covariances; with ``kalman_states="all"`` (n_x + n_z, n_x + n_z,
            N), the covariance of the particle's states and the linear states (that order).
        mu: (d, N) NiW means of v = (w, e): the offset mean, then one bias per sensor.
        lam_w: (N,) NiW scale of the offset, Lambda_w; in the grid filter each particle's own
            sigma_w^2 (static, a point of its grid).
        lam_e: (n_s, n_s, N) NiW scale of the sensor noise, Lambda_e.
        gamma: scalar, the NiW gamma (1 / kappa), the same for all particles.
        nu: scalar, the NiW degrees of freedom, the same for all particles.
        log_weights, weights: (N,) normalised weights and their logs.
        key: (2,) uint32 raw Threefry key for the next step.
        ess: effective sample size after the last update, before resampling.
        flag_diverged: bool, the weights have underflowed at some step.
        n_reinit: int32, at how many steps they did.
        offset: (N,) the offset w_t each particle drew at the last step (eq. 30); zeros after
            ``init``.
        ancestors: (N,) int32, each particle's index before the last step's resampling (its
            parent in the previous state; the identity when it did not resample).
        info: in the grid filter with Jeffreys' prior (N,), each grid point's Fisher information
            of log sigma_w^2 so far (covariance part, :mod:`.jeffreys`); else
            None.
        base_log_weights: in the grid filter with Jeffreys' prior (N,), the normalised log
            weights under equal prior weights (the likelihood alone); ``log_weights`` are them
            times Jeffreys' prior sqrt(info). Else None.
        var_info, var_stat, var_sand, var_ref, var_est: in the grid filter with scored sensor
            variances, the sensor variances' scoring sums (:mod:`.sensor_scoring`): J
            (n_s, n_s, N), h (n_s, N), the sandwich's middle (n_s, n_s, N), the prior guess v_0
            (n_s, N) and the scored variances J^-1 h (n_s, N; NaN where not positive); else
            None.
    """

    x: jnp.ndarray
    z: jnp.ndarray
    P: jnp.ndarray
    mu: jnp.ndarray
    lam_w: jnp.ndarray
    lam_e: jnp.ndarray
    gamma: jnp.ndarray
    nu: jnp.ndarray
    log_weights: jnp.ndarray
    weights: jnp.ndarray
    key: jnp.ndarray
    ess: jnp.ndarray
    flag_diverged: jnp.ndarray
    n_reinit: jnp.ndarray
    offset: jnp.ndarray
    ancestors: jnp.ndarray
    info: Any = None
    base_log_weights: Any = None
    var_info: Any = None
    var_stat: Any = None
    var_sand: Any = None
    var_ref: Any = None
    var_est: Any = None


def prior_in_dtype(s: Setup, x0, P0, theta0=None):
    """The checked prior in the filter's dtype (x0's and P0's, float when integer): x0, P0
    (a 1-D P0 as its diagonal), the noise parameters ``theta0`` (None: the guesses), dtype."""
    validation.prior(s.n_states, x0, P0)
    x0, P0 = jnp.asarray(x0), jnp.asarray(P0)
    dtype = jnp.result_type(x0.dtype, P0.dtype)
    if not jnp.issubdtype(dtype, jnp.floating):
        dtype = jnp.asarray(0.0).dtype
    x0 = x0.astype(dtype)
    P0 = (jnp.diag(P0) if P0.ndim == 1 else P0).astype(dtype)
    p = len(s.param_names)
    if theta0 is None:
        th = jnp.asarray(s.theta_prior, dtype)
    else:
        if np.shape(theta0) != (p,):
            raise ValueError(f"theta0: expected shape ({p},) for {s.param_names}, got "
                             f"{np.shape(theta0)}")
        th = jnp.asarray(theta0).astype(dtype)
    return x0, P0, th, dtype


def initial_state(s: Setup, x0, P0, theta0=None, P_theta0=None, key=None) -> MPFState:
    """The filter's ``init``: particles from the prior, Kalman filters from the Gaussian
    conditional of the linear states given each particle, the NiW statistics from the
    priors."""
    del P_theta0
    if key is None:
        raise ValueError("key: marginalized_pf draws its particles at random; pass a PRNG key")
    nl, li, nz, nk = s.sampled_idx, s.linear_idx, s.n_linear, s.n_kalman
    n, d, ns = s.n_particles, s.noise_dim, s.n_sensors
    x0, P0, th, dtype = prior_in_dtype(s, x0, P0, theta0)
    mu0 = jnp.concatenate([th[:1], th[2:2 + ns]])
    sd0 = jnp.concatenate([th[1:2], th[2 + ns:]])
    k_init, k_run = jax.random.split(key)
    Pxx = P0[np.ix_(nl, nl)]
    Lx = jnp.linalg.cholesky(Pxx)
    xs = x0[nl][:, None] + Lx @ jax.random.normal(k_init, (s.n_sampled, n), dtype)
    if nz:
        Pzx = P0[np.ix_(li, nl)]
        G = jax.scipy.linalg.cho_solve((Lx, True), Pzx.T).T  # P_zx P_xx^-1
        zs = x0[li][:, None] + G @ (xs - x0[nl][:, None])
        Pz = P0[np.ix_(li, li)] - G @ Pzx.T
        Pz = 0.5 * (Pz + Pz.T)
    else:
        zs = jnp.zeros((0, n), dtype)
        Pz = jnp.zeros((0, 0), dtype)
    scale = s.nu0 - d - 1.0
    # with Gaussian particle states: zero covariance of the drawn states, the bank's after
    Pk = jnp.zeros((nk, nk), dtype).at[nk - nz:, nk - nz:].set(Pz)
    lam_w = jnp.full((n,), scale, dtype) * sd0[0] ** 2
    log_w0 = jnp.full((n,), -math.log(n), dtype)
    return MPFState(
        x=xs,
        z=zs,
        P=jnp.broadcast_to(Pk[:, :, None], (nk, nk, n)),
        mu=jnp.broadcast_to(mu0[:, None], (d, n)),
        lam_w=lam_w,
        lam_e=jnp.broadcast_to((scale * jnp.diag(sd0[1:] ** 2))[:, :, None], (ns, ns, n)),
        gamma=jnp.asarray(s.gamma0, dtype),
        nu=jnp.asarray(s.nu0, dtype),
        log_weights=log_w0,
        weights=jnp.exp(log_w0),
        key=smc.raw_key(k_run),
        ess=jnp.asarray(float(n), dtype),
        flag_diverged=jnp.asarray(False),
        n_reinit=jnp.asarray(0, jnp.int32),
        offset=jnp.zeros((n,), dtype),
        ancestors=jnp.arange(n, dtype=jnp.int32),
    )
