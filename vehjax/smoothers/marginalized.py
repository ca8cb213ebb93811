"""Smoothing one run with the marginalized PF (:func:`vehjax.filters.marginalized_pf`):
M trajectories of the particles' sampled part, by ancestor tracing (``method="ancestor"``, the
default, both ``kalman_states``) or by Rao-Blackwellised backward simulation
(``method="ffbsi"``, the paper's ``kalman_states="linear"``), each with its linear states
smoothed by a per-trajectory RTS and its noise statistics.

The forward pass is the filter itself, its own ``init`` and ``step`` in a ``lax.scan``, keeping
after every step each particle's Gaussian over the states (means ``x``, ``z``, covariance
``P``), its NiW statistics, the offset w_t it drew (eq. 30) and the resampling genealogy
(:class:`vehjax.filters.marginalized.MPFState`). Then:

1. **Paths** (``method="ancestor"``): M indices drawn from the final weights, each one's
   genealogy followed back (``MPFState.ancestors``): the path-space (Kitagawa 1996) smoother.
2. **States, given a path.** ``kalman_states="all"``: the Rauch-Tung-Striebel recursion on the
   path's own filtered moments, for t = T-1, ..., 1 with s = (x, z),
   ``G = C_t P_t|t-1^+``, ``m_t-1|T = m_t-1 + G (m_t|T - m_t|t-1)``,
   ``P_t-1|T = P_t-1 + G (P_t|T - P_t|t-1) G^T``, ``Cov(s_t-1, s_t | .) = G P_t|T``, ``^+`` the
   pseudo-inverse on the range of ``P_t|t-1`` (:func:`psd_right_solve`).
   ``kalman_states="linear"``: the path's sampled states are the trajectory itself and its
   linear states are smoothed by the backward recursion on the joint Gaussian of
   (z_t-1, z_t) given x_0:t, y_0:t, ``G = P_ab P_bb^+``, ``m_t-1|T = m_a + G (m_t|T - m_t)``,
   ``P_t-1|T = P_aa + G (P_t|T - P_t) G^T``, ``Cov(z_t-1, z_t | .) = G P_t|T``, each step's
   Kalman update recomputed along the path with z_t-1 kept (:func:`linear_step_joint`,
   :func:`linear_path_rts`).
3. **Moments**: the equally weighted mixture of the M per-path Gaussians
   (:func:`vehjax.filters.smc.mixture`), the lag-one covariance likewise.
4. **Noise statistics**: eq. 23's estimates over the M paths' particles at each t
   (:func:`vehjax.filters.marginalized.niw.noise_estimates`, equal weights).

``method="ffbsi"`` (``kalman_states="linear"`` only) is the Rao-Blackwellised backward
simulation of Fong, Godsill, Doucet & West (2002) in the form of Särkkä, Bunch & Godsill (2012)
over the vehicle states x_t: each trajectory draws particle j at t with probability proportional
to W_t^j p(x_t+1^m, y_t+1 | x_0:t^j, y_0:t) (:func:`backward_logdens`; the measurement y_t+1 is
in it, since it depends on the pair through the offset w_t+1), then re-runs its linear states'
Kalman filter and NiW statistics along it (:func:`linear_path_forward`) and smooths them by
:func:`linear_path_rts`. The covariance's x block is regularised by ``BACKWARD_JITTER``;
``backward_ess`` and ``n_distinct`` report per time how far the draws spread.

Exact: given a path (or an FFBSi trajectory) its Rao-Blackwellised part, for a model affine in
the (linear) states and the noisy input, with the plug-in noise of each step. Consistent, with
Monte-Carlo error: the ancestral paths, whose genealogies coalesce at early times
(``n_unique``). Limits: FFBSi's backward weights leave out what the data after t + 1 say about
the linear states (no backward information filter, Lindsten & Schön 2013), so its trajectories
are not draws of p(x_0:T-1 | y_0:T-1) even as N grows; backward simulation falls back to
ancestor tracing where the bank covariance across g is small or absent (the planar filter); the
noise statistics at t condition on y_{1:t} along a path (with ``forgetting=1`` the last row is
their smoothed estimate); ``kalman_states="all"`` has no FFBSi.

See docs/marginalized_smoother.md for each step's recursion and why it is exact, the backward
weights and the weights tried (with their errors against the exact RTS), the near-degeneracy,
and what is exact and what is approximate, with the measurements.

Time convention of :func:`vehjax.filter`: x0/P0 describe the state before the first step and
time t is the state after step t (0 .. T-1). NaN measurement components are missing (the
filter skips them, and so do the backward weights of ``"ffbsi"``). Divergence: a step that
re-initialised (every weight underflowed) or gave a non-finite output flags the run
``diverged``; its moments are still finite.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import validation
from ..engine import output_ok
from ..filters.marginalized.linearise import linearise
from ..filters.marginalized.niw import impute_missing, niw_predict, niw_update, noise_estimates
from ..filters import smc
from ..filters.base import Estimator
from ..lib.linalg import sym
from .linear import rts_apply
from .particle import count_unique, ffbsi_indices

__all__ = [
    "MPFSmootherResult", "MPFForward", "smooth", "forward", "backward", "METHODS",
    "trace_ancestors", "psd_right_solve", "psd_part", "rts_step",
    "linear_step_joint", "linear_path_rts", "linear_path_step", "linear_path_forward",
    "backward_logdens", "backward_ess",
]

#: The smoother's methods (module docstring).
METHODS = ("ancestor", "ffbsi")

#: Relative regularisation of the backward density's covariance (module docstring, FFBSi):
#: ``S + BACKWARD_JITTER tr(S) / n I``.
BACKWARD_JITTER = 1e-9


class MPFSmootherResult(NamedTuple):
    """The marginalized PF's smoothing of one run of T steps (a leading runs axis under
    ``vmap``); model state order, p noise statistics as the filter's ``param_names``.

    Attributes:
        states: (T, nx) smoothed means.
        covariances: (T, nx, nx) smoothed covariances (mixture of the per-path Gaussians).
        cross_covariances: (T - 1, nx, nx), entry t the lag-one Cov(x_t, x_t+1 | y).
        path_states: (M, T, nx) each path's smoothed mean (Rao-Blackwellised trajectories).
        params: (T, p) eq. 23's noise statistics over the M paths at each time (module
            docstring: with ``forgetting=1`` the last row is the smoothed estimate).
        params_cov: (T, p, p) their mixture covariance.
        loglik: (T,) the filter's log p(y_t | y_0:t-1), as :func:`vehjax.filter` gives with
            the same key.
        n_unique: (T,) int32, how many distinct particle slots the M paths pass through.
        diverged: bool scalar, the filter re-initialised or gave a bad output at some step.
        n_distinct: (T,) int32, how many distinct particles by value: slots that hold copies
            of one particle (the same resampled parent) count once.
        backward_ess: (T,) the effective sample size of the backward weights at t, averaged
            over the M trajectories (``"ffbsi"``; at T - 1 that of the final filter weights);
            1 with ``"ancestor"`` (each path has one parent).
        path_indices: (M, T) int32, the filter particle each path or trajectory passes
            through at every time (an index into the filter's N particles after that step's
            resampling, as in ``MPFState.ancestors``): which particles the smoother followed,
            without comparing floating-point states.
    """

    states: jnp.ndarray
    covariances: jnp.ndarray
    cross_covariances: jnp.ndarray
    path_states: jnp.ndarray
    params: jnp.ndarray
    params_cov: jnp.ndarray
    loglik: jnp.ndarray
    n_unique: jnp.ndarray
    diverged: jnp.ndarray
    n_distinct: jnp.ndarray
    backward_ess: jnp.ndarray
    path_indices: jnp.ndarray


# ----------------------------------------------------------------------------------------------
# The mathematics


def trace_ancestors(ancestors, idx_last):
    """The particle indices of paths followed back through a genealogy.

    Args:
        ancestors: (T, N) int, ``ancestors[t, i]`` the index at t - 1 of particle i's parent
            (row 0 unused).
        idx_last: (M,) int, the paths' particles at T - 1.

    Returns:
        (T, M) int32: the paths' particle at every time.
    """
    def body(idx_next, anc_next):
        idx = anc_next[idx_next].astype(jnp.int32)
        return idx, idx

    idx_last = jnp.asarray(idx_last, jnp.int32)
    _, idx = jax.lax.scan(body, idx_last, ancestors[1:], reverse=True)
    return jnp.concatenate([idx, idx_last[None]], axis=0)


def psd_right_solve(C, S, rtol: float | None = None):
    """C S^+ for a symmetric positive semi-definite S (n, n) and C (k, n): S = V diag(l) V^T by
    ``eigh`` and S^+ = V diag(1 / l) V^T over the eigenvalues l > rtol max(l) (the rest,
    rounding noise about the null space, dropped). Where the rows of C lie in the range of S
    (C = P Phi^T and S = Phi P Phi^T + Q in a Kalman prediction), this is the exact solution of
    G S = C on that range; for a positive definite S it is C S^-1.

    ``rtol``: default 1e3 n eps of the dtype."""
    n = S.shape[-1]
    if rtol is None:
        rtol = 1e3 * n * float(jnp.finfo(S.dtype).eps)
    lam, V = jnp.linalg.eigh(0.5 * (S + S.T))
    keep = lam > rtol * jnp.max(lam)
    inv = jnp.where(keep, 1.0 / jnp.where(keep, lam, 1.0), 0.0)
    return ((C @ V) * inv) @ V.T


def psd_part(S):
    """The positive semi-definite part of a symmetric (n, n) S: S = V diag(l) V^T by ``eigh``,
    returned as V diag(max(l, 0)) V^T, symmetrised.

    A smoothed covariance is PSD in exact arithmetic, and singular where the exact answer has
    zero variance in some direction (a particle's sampled states start as a point, so at t = 0
    a path's covariance has a zero block). The RTS form ``P + G (P_next - P_pred) G^T``
    subtracts nearly equal matrices there, and rounding leaves eigenvalues of order
    -eps ||S|| (seen: -7.8e-21 against 8e-5 on SingleTrackBank). This removes them, so each
    backward step starts from a PSD matrix and the errors do not grow along the recursion; a
    positive definite S changes only by rounding."""
    lam, V = jnp.linalg.eigh(0.5 * (S + S.T))
    out = (V * jnp.maximum(lam, 0.0)) @ V.T
    return 0.5 * (out + out.T)


def rts_step(m, P, m_pred, P_pred, C, m_next, P_next):
    """One backward step of the Rauch-Tung-Striebel smoother.

    Args:
        m, P: (n,), (n, n) filtered moments at t - 1.
        m_pred, P_pred: (n,), (n, n) the prediction of t from them.
        C: (n, n) Cov(s_t-1, s_t) of that prediction (P Phi^T for a linear model).
        m_next, P_next: smoothed moments at t.

    Returns:
        (m_s, P_s, cross): smoothed moments at t - 1 and Cov(s_t-1, s_t | all data) = G P_next,
        G = C P_pred^+ (:func:`psd_right_solve`); P_s symmetric positive semi-definite
        (:func:`psd_part`). The recursion is :func:`vehjax.smoothers.linear.rts_apply`'s with
        this gain (a pseudo-inverse: a path's predicted covariance may be singular).
    """
    m_s, P_s, cross = rts_apply(psd_right_solve(C, P_pred), m, P, m_pred, P_pred, m_next,
                                P_next)
    return m_s, psd_part(P_s), cross


def _mixture_cross(m0, m1, cross):
    """Lag-one covariance of the mixture: mean(cross_i) + mean((m0_i - m0)(m1_i - m1)^T)."""
    d0, d1 = m0 - jnp.mean(m0, axis=0), m1 - jnp.mean(m1, axis=0)
    return jnp.mean(cross, axis=0) + jnp.einsum("mi,mj->ij", d0, d1) / m0.shape[0]


def linear_step_joint(rb, theta, x_prev, z_prev, P_prev, mu, lam_w, lam_e, nu, x_new, y, u):
    """Step t of one particle's Kalman filter of the linear states (``kalman_states="linear"``,
    sec. 3.4 as :func:`vehjax.filters.marginalized.kalman.bank_kalman_step` does it) recomputed with
    z_t-1 kept: the joint Gaussian of (z_t-1, z_t) given the particle's path x_0:t and y_0:t.

    With s1 = z_t-1 - m, s2 = w_t - mu_w, zeta_t the linear states' process noise (prior
    N(0, blockdiag(P, sigma_w^2, Qz))), the linearisation at (x_t-1, m, u_t) and the point
    estimates of eq. 23 after eq. 20's forgetting (the filter's, from the particle's statistics
    at t - 1): the vehicle model along g, r1 = g^+ (x_t - xb) - mu_w = a^T s1 + s2 exactly
    (a = A_bar^T g^+^T), and the observed components of y_t, o2 = y - yb - Cx (x_t - xb)
    - (Cz gz + d) mu_w - b = Cz (A s1 + gz s2 + zeta) + d s2 + e, e ~ N(0, R_y), condition the
    Gaussian of (s1, s2, zeta); then z_t-1 = m + s1 and z_t = zb + gz mu_w + A s1 + gz s2 +
    zeta. The z_t block is the filter's posterior at t (to rounding).

    Args:
        rb: the filter's :class:`~vehjax.filters.marginalized.RBTransition`.
        theta: model parameters.  x_prev (n_xs,), z_prev (n_z,), P_prev (n_z, n_z): the
            particle at t - 1.  mu (d,), lam_w (), lam_e (n_s, n_s), nu (): its NiW statistics
            at t - 1.  x_new (n_xs,): its sampled states at t.  y (ny,), u (nu,): at t.

    Returns:
        (mean (2 n_z,), cov (2 n_z, 2 n_z)) of (z_t-1, z_t).
    """
    s = rb.linear
    dtype = x_prev.dtype
    nz, rows = rb.nz, np.asarray(s.used_rows)
    srow = np.asarray(s.sensor_rows, int)
    lin = linearise(s.transition, s.observe, x_prev, z_prev, u, theta, s.sampled_idx,
                    s.linear_idx, s.input_idx)
    yb, Cx, Cz, d = lin.yb[rows], lin.Cx[rows], lin.Cz[rows], lin.d[rows]
    yu = y[rows]
    obs = ~jnp.isnan(yu)
    # the point estimates the filter's step uses (eq. 20, 23)
    nu_p = s.forgetting * nu
    inv_den = 1.0 / (nu_p - s.noise_dim - 1.0)
    sig_w2 = s.forgetting * lam_w * inv_den
    mu_w = mu[0]
    b_y = jnp.zeros(len(rows), dtype).at[srow].set(mu[1:])
    R_y = jnp.diag(jnp.asarray(s.known_variances, dtype)).at[np.ix_(srow, srow)].set(
        s.forgetting * lam_e * inv_den)
    g = lin.g
    gg = g @ g
    gp = g / jnp.where(gg > 0, gg, 1.0)
    a = lin.Ab.T @ gp
    dx = x_new - lin.xb
    r1 = gp @ dx - mu_w
    o2 = jnp.where(obs, yu - yb - Cx @ dx - (Cz @ lin.gz + d) * mu_w - b_y, 0.0)
    Qz = jnp.asarray(s.linear_noise, dtype)
    n = 2 * nz + 1
    Sv = jnp.zeros((n, n), dtype).at[:nz, :nz].set(P_prev).at[nz, nz].set(sig_w2)
    Sv = Sv.at[nz + 1:, nz + 1:].set(Qz)
    H = jnp.concatenate([
        jnp.concatenate([a, jnp.ones(1, dtype), jnp.zeros(nz, dtype)])[None],
        jnp.concatenate([Cz @ lin.A, (Cz @ lin.gz + d)[:, None], Cz], axis=1)], axis=0)
    ob = jnp.concatenate([jnp.ones(1, bool), obs])
    H = jnp.where(ob[:, None], H, 0.0)
    R = jnp.zeros((len(ob), len(ob)), dtype).at[1:, 1:].set(R_y)
    R = jnp.where(ob[:, None] & ob[None, :], R, jnp.eye(len(ob), dtype=dtype))
    r = jnp.concatenate([r1[None], o2])
    HS = H @ Sv
    S = HS @ H.T + R
    L = jnp.linalg.cholesky(0.5 * (S + S.T))
    B = jax.scipy.linalg.solve_triangular(L, HS, lower=True)  # L^-1 H Sv
    alpha = jax.scipy.linalg.solve_triangular(L, r, lower=True)
    mv = B.T @ alpha
    Cv = Sv - B.T @ B
    J = jnp.zeros((2 * nz, n), dtype).at[:nz, :nz].set(jnp.eye(nz, dtype=dtype))
    J = J.at[nz:, :nz].set(lin.A).at[nz:, nz].set(lin.gz).at[nz:, nz + 1:].set(
        jnp.eye(nz, dtype=dtype))
    mean = jnp.concatenate([z_prev, lin.zb + lin.gz * mu_w]) + J @ mv
    cov = J @ Cv @ J.T
    return mean, 0.5 * (cov + cov.T)


def linear_path_step(rb, theta, x_prev, z_prev, P_prev, mu, lam_w, lam_e, gamma, nu, x_new, y,
                     u):
    """Step t of the paper's filter (``kalman_states="linear"``) along a given path of sampled
    states: one particle's Kalman step of the linear states and its NiW update, as the filter
    does them for a particle at x_t-1 that moved to x_t (:func:`vehjax.filters.marginalized`
    steps 4-5), for a path stitched by backward simulation (whose x_t was drawn by another
    particle). The Kalman step is the z_t block of :func:`linear_step_joint`. The statistics:
    eq. 20's forgetting, then eq. 18 with the datum v = (w_t - mu_w, e_t): the offset
    w_t = g^+ (x_t - xb) (the filter's draw when x_t is the particle's own), the sensor residual
    e_t = y - yb - Cx (x_t - xb) - Cz (z_t - zb) - d w_t - b at the posterior mean z_t, with
    Cz P_t Cz^T on the observed sensor pairs and the conditional covariance of missing sensors
    (:func:`vehjax.filters.marginalized.niw.impute_missing`) added to Lambda_e.

    Args:
        rb: the filter's :class:`~vehjax.filters.marginalized.RBTransition`.
        theta: model parameters.  x_prev (n_xs,), z_prev (n_z,), P_prev (n_z, n_z): the path
            at t - 1 (its sampled states, Kalman mean and covariance).  mu (d,), lam_w (),
            lam_e (n_s, n_s): its NiW statistics at t - 1.  gamma (), nu (): the shared NiW
            gamma and dof at t - 1.  x_new (n_xs,): the path's sampled states at t.  y (ny,),
            u (nu,): at t.

    Returns:
        (z_t (n_z,), P_t (n_z, n_z), mu (d,), lam_w (), lam_e (n_s, n_s)) after step t.
    """
    s = rb.linear
    nz, rows = rb.nz, np.asarray(s.used_rows)
    srow = np.asarray(s.sensor_rows, int)
    ns = len(srow)
    if nz:
        mj, Cj = linear_step_joint(rb, theta, x_prev, z_prev, P_prev, mu, lam_w, lam_e, nu,
                                   x_new, y, u)
        z_new, P_new = mj[nz:], Cj[nz:, nz:]
    else:
        z_new, P_new = z_prev, P_prev
    lin = linearise(s.transition, s.observe, x_prev, z_prev, u, theta, s.sampled_idx,
                    s.linear_idx, s.input_idx)
    gam_p, nu_p, lw_p, le_p = niw_predict(gamma, nu, lam_w, lam_e, s.forgetting)
    g = lin.g
    gg = g @ g
    dx = x_new - lin.xb
    w = (g / jnp.where(gg > 0, gg, 1.0)) @ dx
    yu = y[rows][srow]
    obs = ~jnp.isnan(yu)
    Cz = lin.Cz[rows][srow]
    pred = (lin.yb[rows][srow] + lin.Cx[rows][srow] @ dx + Cz @ (z_new - lin.zb)
            + lin.d[rows][srow] * w)
    eta = jnp.where(obs, yu - pred - mu[1:], 0.0)
    V = jnp.where(obs[:, None] & obs[None, :], Cz @ P_new @ Cz.T, 0.0)
    R_s = le_p / (nu_p - s.noise_dim - 1.0)
    ob = [obs[i] for i in range(ns)]
    eta_l, V_miss = impute_missing([eta[i] for i in range(ns)],
                                   [[R_s[i, j] for j in range(ns)] for i in range(ns)], ob)
    eta_v = jnp.stack([w - mu[0]] + list(eta_l))
    extra = V + jnp.asarray([[V_miss[i][j] + jnp.zeros((), V.dtype) for j in range(ns)]
                             for i in range(ns)]).reshape(ns, ns)
    _, _, mu_new, lw_new, le_new = niw_update(gam_p, nu_p, mu, lw_p, le_p, eta_v, extra)
    return z_new, P_new, mu_new, lw_new, le_new


def backward_logdens(rb, theta, x, z, P, mu, lam_w, lam_e, gamma, nu, u_next, y_next, x_next,
                     jitter: float = BACKWARD_JITTER):
    """The backward density of the Rao-Blackwellised backward simulation with
    ``kalman_states="linear"`` (module docstring): for every trajectory m and particle j at t,
    log p(x_t+1^m, y_t+1 | x_0:t^j, y_0:t) up to a constant common to all pairs, the next
    sampled states and the next measurement with particle j's linear states z_t, the offset
    w = w_t+1 and the linear states' noise zeta marginalised under its own filtered moments and
    statistics (linearised at (x_j, z_j, u_t+1) as the filter does: exact for models affine in
    the states and the noisy input). With s1 = z_t - z_j ~ N(0, P_j), w ~ N(mu_w_j, var_w_j),
    zeta ~ N(0, Qz) and e ~ N(0, R_j):
    x_t+1 = xb + A_bar s1 + g w, z_t+1 = zb + A s1 + gz w + zeta and the used, observed rows
    of y_t+1 = yb + Cx (x_t+1 - xb) + Cz (z_t+1 - zb) + d w + b_j + e: one Gaussian of
    (x_t+1, y_t+1) per particle, its x block regularised by ``jitter`` tr / n_xs on the
    diagonal (the filter's x_t+1 has noise along g only). The noise statistics enter as the
    moment-matched Gaussian of the NiW's Student-t predictive after eq. 20's forgetting
    (primes): var_w = (1 + gamma') Lambda_w' / (nu' - d - 1), R = (1 + gamma') Lambda_e' /
    (nu' - d - 1) on the sensor rows, the known variances on the others, means mu_w and b.

    Args:
        rb: the filter's :class:`~vehjax.filters.marginalized.RBTransition`.
        theta: model parameters.  x (n_xs, N), z (n_z, N), P (n_z, n_z, N), mu (d, N),
            lam_w (N,), lam_e (n_s, n_s, N): the filter's particles at t.  gamma, nu: scalars
            at t.  u_next (nu,), y_next (ny,): the input and measurement at t + 1 (NaN
            missing).  x_next: (n_xs, M) the trajectories at t + 1.
        jitter: relative regularisation of the x block.

    Returns:
        (M, N) log densities, each -|L_j^-1 r_mj|^2 / 2 - log det L_j (finite).
    """
    s = rb.linear
    nxs, nz = x.shape[0], rb.nz
    rows = np.asarray(s.used_rows)
    srow = np.asarray(s.sensor_rows, int)
    dtype = x.dtype
    lin = jax.vmap(lambda xj, zj: linearise(s.transition, s.observe, xj, zj, u_next, theta,
                                            s.sampled_idx, s.linear_idx, s.input_idx),
                   in_axes=(1, 1))(x, z)
    gam_p, nu_p = gamma / s.forgetting, s.forgetting * nu
    c = (1.0 + gam_p) * s.forgetting / (nu_p - s.noise_dim - 1.0)
    var_w = c * lam_w  # (N,)
    yu = y_next[rows]
    obs = ~jnp.isnan(yu)
    nyu = len(rows)
    R = jnp.broadcast_to(jnp.diag(jnp.asarray(s.known_variances, dtype)), (x.shape[1], nyu, nyu))
    R = R.at[:, srow[:, None], srow[None, :]].set(c * jnp.moveaxis(lam_e, -1, 0))
    b_y = jnp.zeros((x.shape[1], nyu), dtype).at[:, srow].set(mu[1:].T)
    # V = (s1, w, zeta): x_t+1 - xb = Jx V, z_t+1 - zb = Jz V, y - yb - b - e = Jy V
    N = x.shape[1]
    Jx = jnp.concatenate([lin.Ab, lin.g[:, :, None], jnp.zeros((N, nxs, nz), dtype)], axis=2)
    Jz = jnp.concatenate([lin.A, lin.gz[:, :, None],
                          jnp.broadcast_to(jnp.eye(nz, dtype=dtype), (N, nz, nz))], axis=2)
    Cx, Cz, d = lin.Cx[:, rows], lin.Cz[:, rows], lin.d[:, rows]
    Jy = Cx @ Jx + Cz @ Jz
    Jy = Jy.at[:, :, nz].add(d)
    nv = 2 * nz + 1
    Sv = jnp.zeros((N, nv, nv), dtype).at[:, :nz, :nz].set(jnp.moveaxis(P, -1, 0))
    Sv = Sv.at[:, nz, nz].set(var_w).at[:, nz + 1:, nz + 1:].set(jnp.asarray(s.linear_noise, dtype))
    J = jnp.concatenate([Jx, Jy], axis=1)  # (N, n_xs + n_yu, nv)
    S = J @ Sv @ jnp.swapaxes(J, 1, 2)
    S = S.at[:, nxs:, nxs:].add(R)
    S = 0.5 * (S + jnp.swapaxes(S, 1, 2))
    ob = jnp.concatenate([jnp.ones(nxs, bool), obs])
    S = jnp.where(ob[:, None] & ob[None, :], S, jnp.eye(nxs + nyu, dtype=dtype))
    tr = jnp.trace(S[:, :nxs, :nxs], axis1=1, axis2=2)
    S = S.at[:, :nxs, :nxs].add(((jitter * tr / nxs + jnp.finfo(dtype).tiny)[:, None, None])
                                * jnp.eye(nxs, dtype=dtype))
    L = jnp.linalg.cholesky(S)  # (N, n, n)
    mean_x = lin.xb + lin.g * mu[0][:, None]  # (N, n_xs)
    mean_y = lin.yb[:, rows] + Jy[:, :, nz] * mu[0][:, None] + b_y  # (N, n_yu)
    ry = jnp.where(obs[None], jnp.where(obs, yu, 0.0)[None] - mean_y, 0.0)  # (N, n_yu)
    rx = x_next.T[:, None, :] - mean_x[None]  # (M, N, n_xs)
    r = jnp.concatenate([rx, jnp.broadcast_to(ry[None], rx.shape[:2] + (nyu,))], axis=2)
    # one triangular solve per particle with the M trajectories as right-hand sides
    a = jax.scipy.linalg.solve_triangular(L, jnp.transpose(r, (1, 2, 0)), lower=True)  # (N, n, M)
    logdet = jnp.sum(jnp.log(jnp.diagonal(L, axis1=1, axis2=2)), axis=1)
    return -0.5 * jnp.sum(a * a, axis=1).T - logdet[None, :]


def backward_ess(log_w, logdens):
    """Effective sample size 1 / sum_j p_mj^2 of each trajectory's normalised backward weights
    p_mj ~ W_j exp(logdens_mj), log_w (N,), logdens (M, N), averaged over the M trajectories
    (rows with no finite entry fall back to the filter weights, as the draw does)."""
    logits = log_w[None, :] + logdens
    top = jnp.max(logits, axis=1, keepdims=True)
    logits = jnp.where(jnp.isfinite(top), logits, log_w[None, :])
    p = jax.nn.softmax(logits, axis=1)
    return jnp.mean(1.0 / jnp.sum(p * p, axis=1))


# ----------------------------------------------------------------------------------------------
# The passes


class MPFForward(NamedTuple):
    """The filter's forward pass over one run of T steps, kept for the backward pass
    (:func:`forward`): after every step, each of the N particles' Gaussian over the states
    (sampled states ``x``, linear states ``z``, covariance ``P``), its NiW statistics, the offset
    it drew, the genealogy and weights, and per step the log-likelihood and a bad-step flag.
    Shapes are in the comments (N last, as in :class:`vehjax.filters.marginalized.MPFState`)."""

    x: jnp.ndarray  # (T, nxs, N)
    z: jnp.ndarray  # (T, nz, N)
    P: jnp.ndarray  # (T, nk, nk, N)
    mu: jnp.ndarray  # (T, d, N)
    lam_w: jnp.ndarray  # (T, N)
    lam_e: jnp.ndarray  # (T, ns, ns, N)
    gamma: jnp.ndarray  # (T,)
    nu: jnp.ndarray  # (T,)
    offset: jnp.ndarray  # (T, N)
    ancestors: jnp.ndarray  # (T, N)
    log_weights: jnp.ndarray  # (T, N)
    loglik: jnp.ndarray  # (T,)
    bad: jnp.ndarray  # (T,)


def forward(estimator: Estimator, ys, us, x0, P0, theta0, key) -> MPFForward:
    """The filter over the run, keeping what the backward pass needs after every step.

    Args:
        estimator: a :func:`~vehjax.filters.marginalized_pf` estimator.
        ys: (T, ny) measurements (NaN missing); us: (T, nu) inputs.
        x0, P0: (nx,), (nx, nx) the prior; theta0: the filter's initial noise guesses or None.
        key: PRNG key (the filter's own, as :func:`vehjax.filter` uses it).

    Returns:
        :class:`MPFForward`, which :func:`backward` smooths: the backward pass reads the very
        particles this pass made (its ``path_indices`` index them).
    """
    state0 = estimator.init(x0, P0, theta0, None, key)
    p = len(estimator.param_names)

    def body(state, yu):
        state, out = estimator.step(state, *yu)
        bad = jnp.asarray(out.reinit, bool) | ~output_ok(out, p)
        keep = (state.x, state.z, state.P, state.mu, state.lam_w, state.lam_e, state.gamma,
                state.nu, state.offset, state.ancestors, state.log_weights)
        return state, keep + (out.loglik, bad)

    _, per = jax.lax.scan(body, state0, (ys, us))
    return MPFForward(*per)


def _path_rts(rb, us, theta, xs, zs, Ps, ws):
    """RTS along one path: its filtered moments s_t = (x_t, z_t), P_t (T, ...) and draws w_t;
    returns smoothed means (T, n), covariances (T, n, n) and lag-one covariances (T - 1, n, n)
    in (sampled, linear) order."""
    s = jnp.concatenate([xs, zs], axis=1)

    def body(carry, k):
        m_next, P_next = carry
        x_prev, z_prev, P_prev, w, u = k
        m_pred, P_pred, C = rb.predict(x_prev, z_prev, P_prev, w, u, theta)
        m_s, P_s, cross = rts_step(jnp.concatenate([x_prev, z_prev]), P_prev, m_pred, P_pred,
                                   C, m_next, P_next)
        return (m_s, P_s), (m_s, P_s, cross)

    ks = (xs[:-1], zs[:-1], Ps[:-1], ws[1:], us[1:])
    _, (m, P, cross) = jax.lax.scan(body, (s[-1], Ps[-1]), ks, reverse=True)
    return (jnp.concatenate([m, s[-1:]]), jnp.concatenate([P, Ps[-1:]]), cross)


def linear_path_rts(rb, theta, ys, us, nus, xs, zs, Ps, mu, lam_w, lam_e):
    """RTS of the linear states along one path with ``kalman_states="linear"``: the path's
    sampled states xs (T, n_xs), its filtered moments zs (T, n_z), Ps (T, n_z, n_z) and NiW
    statistics mu (T, d), lam_w (T,), lam_e (T, n_s, n_s) after each step; nus (T,) the shared
    dof; ys (T, ny), us (T, nu) the data. Each step's joint of (z_t-1, z_t) given the
    data up to t (:func:`linear_step_joint`, recomputed inside the backward scan so that no
    (T, ...) intermediates are kept), and the backward recursion with it. Returns smoothed
    means (T, n_z), covariances (T, n_z, n_z), lag-one covariances (T - 1, n_z, n_z)."""
    nz = zs.shape[-1]

    def body(carry, k):
        m_next, P_next = carry
        mj, Cj = linear_step_joint(rb, theta, *k)
        m_s, P_s, cross = rts_step(mj[:nz], Cj[:nz, :nz], mj[nz:], Cj[nz:, nz:], Cj[:nz, nz:],
                                   m_next, P_next)
        return (m_s, P_s), (m_s, P_s, cross)

    ks = (xs[:-1], zs[:-1], Ps[:-1], mu[:-1], lam_w[:-1], lam_e[:-1], nus[:-1], xs[1:], ys[1:],
          us[1:])
    _, (m, P, cross) = jax.lax.scan(body, (zs[-1], Ps[-1]), ks, reverse=True)
    return jnp.concatenate([m, zs[-1:]]), jnp.concatenate([P, Ps[-1:]]), cross


def linear_path_forward(rb, theta, ys, us, gammas, nus, xs, z0, P0, mu0, lam_w0, lam_e0):
    """The paper's filter's Kalman filter of the linear states and its NiW statistics re-run
    along one path of sampled states xs (T, n_xs) (:func:`linear_path_step` at t = 1 .. T-1),
    from the moments and statistics at t = 0 of the path's particle there: z0 (n_z,),
    P0 (n_z, n_z), mu0 (d,), lam_w0 (), lam_e0 (n_s, n_s). gammas, nus (T,) the shared NiW
    gamma and dof after each step; ys (T, ny), us (T, nu) the data. Along an ancestral path of
    the filter this reproduces the filter's own values.

    Returns:
        (zs (T, n_z), Ps (T, n_z, n_z), mu (T, d), lam_w (T,), lam_e (T, n_s, n_s)) after each
        step.
    """
    def body(carry, k):
        out = linear_path_step(rb, theta, k[0], *carry, *k[1:])
        return out, out

    init = (z0, P0, mu0, lam_w0, lam_e0)
    ks = (xs[:-1], gammas[:-1], nus[:-1], xs[1:], ys[1:], us[1:])
    _, per = jax.lax.scan(body, init, ks)
    return tuple(jnp.concatenate([a[None], b]) for a, b in zip(init, per))


def _ffbsi(rb, theta, fwd: MPFForward, ys, us, m: int, key):
    """Backward simulation over the filter's particles (module docstring, FFBSi): the
    trajectories' particle indices (T, M) and the backward ESS (T,)."""
    T, _, n = fwd.x.shape
    k_last, k_back = jax.random.split(key)
    lw_last = fwd.log_weights[-1]
    idx_last = jax.random.categorical(k_last, jnp.broadcast_to(lw_last, (m, n)),
                                      axis=1).astype(jnp.int32)
    w_last = jax.nn.softmax(lw_last)

    def body(idx_next, k):
        x, z, P, mu, lam_w, lam_e, gamma, nu, log_w, x_next_all, u_next, y_next, key = k
        logdens = backward_logdens(rb, theta, x, z, P, mu, lam_w, lam_e, gamma, nu, u_next,
                                   y_next, x_next_all[:, idx_next])
        idx = ffbsi_indices(key, log_w, logdens)
        return idx, (idx, backward_ess(log_w, logdens))

    keys = jax.random.split(k_back, max(T - 1, 1))[: T - 1]
    ks = (fwd.x[:-1], fwd.z[:-1], fwd.P[:-1], fwd.mu[:-1], fwd.lam_w[:-1], fwd.lam_e[:-1],
          fwd.gamma[:-1], fwd.nu[:-1], fwd.log_weights[:-1], fwd.x[1:], us[1:], ys[1:], keys)
    _, (idx, ess) = jax.lax.scan(body, idx_last, ks, reverse=True)
    return (jnp.concatenate([idx, idx_last[None]]),
            jnp.concatenate([ess, (1.0 / jnp.sum(w_last * w_last))[None]]))


def _check(estimator, method, n_trajectories):
    """Validation particular to this smoother (before anything is traced)."""
    rb = estimator.rao_blackwell if isinstance(estimator, Estimator) else None
    if rb is None:
        name = getattr(estimator, "name", type(estimator).__name__)
        raise ValueError(f"estimator: the marginalized-PF smoother needs a marginalized_pf "
                         f"estimator, got {name!r}")
    if rb.nz and not rb.gauss and rb.linear is None:
        raise ValueError(
            "estimator: this marginalized_pf with kalman_states='linear' does not declare its "
            "linear step (RBTransition.linear), which the smoother needs")
    method = "ancestor" if method is None else validation.choice("method", method, METHODS)
    if method == "ffbsi" and (rb.gauss or rb.linear is None):
        raise ValueError(
            "method: 'ffbsi' needs the paper's filter (kalman_states='linear', whose particles "
            "sample the vehicle states): with kalman_states='all' the particles sample only "
            "the offsets, which one-step backward weights do not tie together (module "
            "docstring); use method='ancestor'")
    return method, validation.integer("n_trajectories", n_trajectories, 1, 2**24)


def smooth(estimator: Estimator, measurements, inputs=None, *, x0, P0, key, method=None,
           n_trajectories: int = 100, theta0=None) -> MPFSmootherResult:
    """Smooth one run with the marginalized PF (module docstring).

    Pure and traceable (``jax.jit`` with the options static, ``jax.vmap`` over runs or keys).
    The filter runs with ``key`` itself (``loglik`` equals :func:`vehjax.filter`'s with the
    same key), the ancestral paths are drawn with ``jax.random.fold_in(key, 1)``, the FFBSi
    trajectories with ``jax.random.fold_in(key, 2)``. Memory O(T N) for the forward pass and
    O(T M) per trajectory quantity; time: the filter, then with ``"ffbsi"`` one linearisation
    per particle and step and an (M, N) density per step, and two Kalman steps per trajectory
    and step (the forward re-run and the RTS).

    Args:
        estimator: a :func:`~vehjax.filters.marginalized_pf` estimator (either
            ``kalman_states``, with or without linear states).
        measurements: (T, ny); NaN components are missing.
        inputs: (T, nu).
        x0, P0: state before the first step, (nx,), and its covariance (nx, nx) or (nx,).
        key: PRNG key.
        method: None or "ancestor" (ancestral paths, both ``kalman_states``), or "ffbsi"
            (Rao-Blackwellised backward simulation; ``kalman_states="linear"`` only).
        n_trajectories: M >= 1 paths / trajectories.
        theta0: the filter's initial noise guesses (p,) (``marginalized_pf``'s ``init``).

    Returns:
        :class:`MPFSmootherResult`.

    Raises:
        ValueError: naming the argument: an estimator that is not such a marginalized PF,
            ``n_trajectories`` < 1, an unknown method or "ffbsi" with ``kalman_states="all"``
            (``method``), a missing key, shapes that do not fit.
    """
    method, m = _check(estimator, method, n_trajectories)
    if key is None:
        raise ValueError("key: the marginalized PF draws random numbers; pass "
                         "key=jax.random.key(...)")
    ys = jnp.asarray(measurements)
    if ys.ndim != 2 or np.shape(inputs)[:1] != ys.shape[:1]:
        raise ValueError(f"measurements: expected (T, ny) with inputs (T, nu), got "
                         f"{ys.shape} and {np.shape(inputs)}")
    P0 = jnp.asarray(P0)
    P0 = jnp.diag(P0) if P0.ndim == 1 else P0
    fwd = forward(estimator, ys, jnp.asarray(inputs), jnp.asarray(x0), P0, theta0, key)
    return backward(estimator, fwd, ys, inputs, key=key, method=method, n_trajectories=m)


def backward(estimator: Estimator, fwd: MPFForward, measurements, inputs, *, key,
             method=None, n_trajectories: int = 100) -> MPFSmootherResult:
    """The backward pass of :func:`smooth` over a forward pass ``fwd`` (:func:`forward` of the
    same estimator, data and key): ``smooth(...)`` is ``backward(estimator, forward(...), ...)``.
    Arguments as :func:`smooth`'s; ``key`` draws the paths (``fold_in(key, 1)``) or the FFBSi
    trajectories (``fold_in(key, 2)``). Pure and traceable."""
    method, m = _check(estimator, method, n_trajectories)
    rb = estimator.rao_blackwell
    ys = jnp.asarray(measurements)
    dtype = fwd.x.dtype
    us = jnp.asarray(inputs).astype(dtype)
    T = ys.shape[0]
    n = fwd.x.shape[-1]
    theta = jnp.asarray(rb.theta).astype(dtype)
    ys_d = ys.astype(dtype)
    if method == "ffbsi":
        idx, b_ess = _ffbsi(rb, theta, fwd, ys_d, us, m, jax.random.fold_in(key, 2))
    else:
        idx_last = jax.random.categorical(jax.random.fold_in(key, 1),
                                          jnp.broadcast_to(fwd.log_weights[-1], (m, n)), axis=1)
        idx = trace_ancestors(fwd.ancestors, idx_last)  # (T, M)
        b_ess = jnp.ones((T,), dtype)

    def take(a):  # (T, ..., N) -> (M, T, ...)
        got = jnp.take_along_axis(a, idx.reshape((T,) + (1,) * (a.ndim - 2) + (m,)), axis=-1)
        return jnp.moveaxis(got, -1, 0)

    xs, zs, Ps, ws = take(fwd.x), take(fwd.z), take(fwd.P), take(fwd.offset)
    stats = (take(fwd.mu), take(fwd.lam_w), take(fwd.lam_e))
    if method == "ffbsi" and T > 1:  # the linear states and statistics re-run along each path
        zs, Ps, *stats = jax.vmap(
            lambda x, *a: linear_path_forward(rb, theta, ys_d, us, fwd.gamma, fwd.nu, x, *a))(
            xs, zs[:, 0], Ps[:, 0], *(a[:, 0] for a in stats))
    nxs, nz = xs.shape[-1], rb.nz
    nk = nxs + nz
    if rb.gauss and T > 1:
        ms, Pss, cross = jax.vmap(lambda a, b, c, d: _path_rts(rb, us, theta, a, b, c, d))(
            xs, zs, Ps, ws)
    elif nz and T > 1:  # kalman_states="linear": the path's x, an RTS of its linear states
        zsm, Pz, cz = jax.vmap(
            lambda *a: linear_path_rts(rb, theta, ys_d, us, fwd.nu, *a))(
            xs, zs, Ps, *stats)
        ms = jnp.concatenate([xs, zsm], axis=2)
        Pss = jnp.zeros(ms.shape + (nk,), dtype).at[..., nxs:, nxs:].set(Pz)
        cross = jnp.zeros((m, T - 1, nk, nk), dtype).at[..., nxs:, nxs:].set(cz)
    else:  # the path is the trajectory (planar filter), or one step: the filtered moments
        ms = jnp.concatenate([xs, zs], axis=2)
        Pss = Ps if rb.gauss else jnp.zeros(ms.shape + (nk,), dtype).at[
            ..., nxs:, nxs:].set(Ps)
        cross = jnp.zeros((m, max(T - 1, 0), nk, nk), dtype)
    inv = np.asarray(rb.order)
    ms, Pss, cross = ms[..., inv], Pss[..., inv, :][..., inv], cross[..., inv, :][..., inv]
    w_eq = jnp.full((m,), 1.0 / m, dtype)  # the paths, equally weighted
    mean, cov = jax.vmap(lambda mt, Pt: smc.mixture(w_eq, mt.T, jnp.moveaxis(Pt, 0, -1)),
                         in_axes=(1, 1))(ms, Pss)
    cov = sym(cov)
    cr = jax.vmap(_mixture_cross, in_axes=(1, 1, 1))(ms[:, :-1], ms[:, 1:], cross)
    params, params_cov = jax.vmap(
        lambda mu, lw, le, nu, g: noise_estimates(w_eq, mu, lw, le, nu, g))(
        stats[0].transpose(1, 2, 0), stats[1].T, stats[2].transpose(1, 2, 3, 0),
        fwd.nu, fwd.gamma)
    copies = jnp.take_along_axis(fwd.ancestors, idx, axis=1)  # the resampled parent of each slot
    return MPFSmootherResult(
        states=mean, covariances=cov, cross_covariances=cr, path_states=ms, params=params,
        params_cov=params_cov, loglik=fwd.loglik, n_unique=jax.vmap(count_unique)(idx),
        diverged=jnp.any(fwd.bad), n_distinct=jax.vmap(count_unique)(copies),
        backward_ess=b_ess, path_indices=idx.T,
    )
