"""The sensor variances of the consistent marginalized PF by Fisher scoring of its innovations,
weighted at the prior guess (:func:`~vehjax.filters.marginalized.marginalized_pf_grid`'s
default, ``sensor_variances="scored"``).

Why: the inverse-Wishart mean of the expected statistics T_t(R') = R' a a^T R' + R' - R' G R'
(the E-step of EM; S' = S_x + R' the predictive covariance of y_t, nu_t its innovation,
G = S'^-1, a = G nu_t) forgets its start only as n^-F, F_ij = ((R' G)_ij)^2 the fraction of the
complete-data information a step carries: small for a sensor seen beside other noise (ay beside
the steering noise: F about 0.04, +45 % after 300 steps from a guess twice the truth).

The estimate. Write the step's information about the sensor variances v = diag R in
innovations form (Gaussian predictive, S_x held fixed): the score s_t = 0.5 (a o a - diag G)
and the expected information W_t = 0.5 G o G (o: entrywise, on the sensors' rows), with
E[s_t] = W_t (v - r_t) at the variances r_t the step used. So z_t = r_t + W_t^-1 s_t is an
unbiased pseudo-observation of v, and any weights that do not look at the data keep it so. The
weights are the information at the prior guess v_0 (``std0``): W_bar_t, W_t's expression with
S_x + diag(v_0) in place of S' (the step's S_x, the guess for the sensors), and the prior counts
as nu0 - d - 1 complete observations at v_0 (the inverse-Wishart's weight):

    v = J^-1 h,  J = J_0 + sum_t W_bar_t,  h = J_0 v_0 + sum_t W_bar_t z_t,  J_0 = (nu0 - d - 1) / 2
        diag(v_0)^-2,

its covariance the sandwich J^-1 (J_0 + sum_t W_bar_t W_t^-1 W_bar_t) J^-1 (Var z_t = W_t^-1),
all sums forgotten like the statistics. For a sensor the step sees alone (S_x = 0) z_t is e_t^2
and W_bar_t the same at every step: v is the inverse-Wishart mean. A missing sensor has no row in
G: it adds nothing. (A toy comparison
with the alternatives: docs/sensor_scoring.md.)

Limits: s_t and W_t hold S_x fixed, so they leave out what later measurements say about e_t
through the dynamics: v is the fixed point of the filtered statistic, not the maximum-likelihood
estimate, and its interval, honest for it, is wider than the likelihood's. Only the variances
are estimated; the sensors' noises are taken as uncorrelated (the Kalman step plugs in diag(v)).
The steering std's reported variance gains the two-step estimator's term (Murphy & Topel 1985),
g C g^T with C the variances' covariance and g = I_theta_v / I_theta_theta, the cross
information from the ridge the grid points' variances lie on (:func:`ridge_sensitivity`). Cost:
about 1.7 times the inverse-Wishart mean's time per step.

See docs/sensor_scoring.md for the expected statistics' slope and the first-order correction
tried, the toy comparison, the steering std's interval and why the correlations were dropped,
and the coverage and errors measured against the inverse-Wishart mean (seeds, runs, commands).
"""

from __future__ import annotations

import jax.numpy as jnp

from ...lib.entrywise import backward_entries, chol_masked, chol_sym
from ...lib.linalg import forward_entries
from .staging import stage

__all__ = ["innovation_score", "scoring_terms", "prior_terms", "scored_variances",
           "ridge_sensitivity", "plug_in_variance"]


def _spd_inverse(A):
    """A^-1 (nested entries) of a small symmetric positive definite matrix, column by column
    from its Cholesky factor; NaN where it is not positive definite."""
    n = len(A)
    L = chol_sym(A)
    cols = [backward_entries(L, forward_entries(L, [1.0 if k == j else 0.0 for k in range(n)]))
            for j in range(n)]
    return [[cols[j][i] for j in range(n)] for i in range(n)]


def _inverse_rows(L, rows, ny):
    """The columns L^-1 e_j for j in ``rows`` (lists of ny entries)."""
    return [forward_entries(L, [1.0 if k == j else 0.0 for k in range(ny)]) for j in rows]


def innovation_score(S, nu, obs, rows):
    """The score s and expected information W of the sensor variances from one Gaussian
    predictive N(0, S) of the innovation ``nu``, S_x held fixed: s_i = 0.5 (a_i^2 - G_ii),
    W_ij = 0.5 G_ij^2, a = G nu, G = S^-1 on the observed components; zero rows where a sensor
    is missing.

    Args:
        S: (ny, ny) nested entries.  nu: (ny) entries.  obs: (ny) booleans.
        rows: the learnt sensors' rows in y (ns).

    Returns:
        (s (ns) entries, W (ns, ns) nested entries).
    """
    ny = len(S)
    L = stage(chol_masked(S, obs))
    a = backward_entries(L, forward_entries(L, [jnp.where(obs[k], nu[k], 0.0)
                                                for k in range(ny)]))
    E = _inverse_rows(L, rows, ny)
    G = stage([[sum(E[p][k] * E[q][k] for k in range(ny)) for q in range(len(rows))]
               for p in range(len(rows))])
    ob = [obs[i] for i in rows]
    s = [jnp.where(ob[p], 0.5 * (a[i] * a[i] - G[p][p]), 0.0) for p, i in enumerate(rows)]
    W = [[jnp.where(ob[p] & ob[q], 0.5 * G[p][q] * G[p][q], 0.0) for q in range(len(rows))]
         for p in range(len(rows))]
    return s, W


def scoring_terms(S, R_y, nu, obs, rows, v_ref):
    """One step's terms of the scored estimate (module docstring): (W_bar, W_bar z, W_bar W^-1
    W_bar) over the learnt sensors, nested entries (ns, ns), (ns), (ns, ns).

    Args:
        S: (ny, ny) nested entries, the step's predictive covariance of y (R_y in it).
        R_y: (ny, ny) nested entries, the noise covariance the step used.
        nu: (ny) entries, the innovation.  obs: (ny) booleans.
        rows: the learnt sensors' rows in y (ns).  v_ref: (ns) the prior guess's variances.
    """
    ns, ny = len(rows), len(S)
    s, W = innovation_score(S, nu, obs, rows)
    pos = {i: p for p, i in enumerate(rows)}
    Sb = [[S[i][j] if (i not in pos or j not in pos) else
           S[i][j] - R_y[i][j] + (v_ref[pos[i]] if i == j else 0.0) for j in range(ny)]
          for i in range(ny)]
    _, Wb = innovation_score(Sb, [0.0] * ny, obs, rows)
    ob = [obs[i] for i in rows]
    Winv = stage(_spd_inverse([[W[p][q] + (jnp.where(ob[p], 0.0, 1.0) if p == q else 0.0)
                                  for q in range(ns)] for p in range(ns)]))
    A = [[sum(Wb[p][k] * Winv[k][q] for k in range(ns)) for q in range(ns)] for p in range(ns)]
    r = [R_y[i][i] for i in rows]
    Wz = [sum(Wb[p][q] * r[q] + A[p][q] * s[q] for q in range(ns)) for p in range(ns)]
    H = [[sum(A[p][k] * Wb[k][q] for k in range(ns)) for q in range(ns)] for p in range(ns)]
    return Wb, Wz, H


def prior_terms(v_ref, count):
    """The prior as ``count`` complete observations at the guess: J_0 = count / 2 diag(v_ref)^-2
    (also the sandwich's prior term) and J_0 v_ref. ``v_ref``: (ns, ...) array."""
    j0 = 0.5 * count / v_ref ** 2
    eye = jnp.eye(v_ref.shape[0], dtype=v_ref.dtype).reshape(
        v_ref.shape[:1] * 2 + (1,) * (v_ref.ndim - 1))
    return eye * j0[None], j0 * v_ref


def scored_variances(J, h, H):
    """v = J^-1 h and its covariance J^-1 H J^-1; arrays (ns, ns, ...), (ns, ...), (ns, ns,
    ...). Where v is not positive or not finite, NaN (the caller falls back)."""
    ns = h.shape[0]
    Jinv = stage(_spd_inverse([[J[i, j] for j in range(ns)] for i in range(ns)]))
    v = jnp.stack([sum(Jinv[i][j] * h[j] for j in range(ns)) for i in range(ns)])
    JH = [[sum(Jinv[i][k] * H[k, j] for k in range(ns)) for j in range(ns)] for i in range(ns)]
    C = jnp.stack([jnp.stack([sum(JH[i][k] * Jinv[j][k] for k in range(ns)) for j in range(ns)])
                   for i in range(ns)])
    C = 0.5 * (C + jnp.swapaxes(C, 0, 1))
    ok = jnp.all(jnp.isfinite(v), axis=0) & jnp.all(v > 0.0, axis=0)
    return jnp.where(ok, v, jnp.nan), jnp.where(ok, C, jnp.nan)


def weighted_covariance(w, theta, v):
    """Cov_w(v, theta) over the grid: (ns,), from weights w (N,), the grid theta (N,) and
    each point's values v (ns, N)."""
    dt = theta - jnp.sum(w * theta)
    return (v - jnp.sum(w * v, axis=-1, keepdims=True)) @ (w * dt)


def ridge_sensitivity(w, theta, v, J, cov=None):
    """How far a grid parameter's estimate moves per unit error of the scored variances that
    each grid point plugs in: g = I_theta_v / I_theta_theta, with I_theta_theta = 1 /
    Var_w(theta), the grid's posterior, and the cross information from the ridge the grid
    points' variances lie on: each point's v is the root of its own score in v, so along the
    grid d/dtheta of that score vanishes, I_v_theta + I_vv dv/dtheta = 0, and g = J Cov_w(v,
    theta) (J the information of v, J Cov_w / Var_w times Var_w; signs drop out of g C g^T).

    Args:
        w: (N,) normalised weights.  theta: (N,) the grid.  v: (ns, N) each point's
            variances.  J: (ns, ns, N) their information (:func:`scoring_terms`' sums).
        cov: (ns,) or None: Cov(v, theta); None: :func:`weighted_covariance` (where the grid
            does not resolve the posterior, :func:`.grid.ridge_covariance`).

    Returns:
        (ns,) g.
    """
    if cov is None:
        cov = weighted_covariance(w, theta, v)
    return jnp.einsum("ijn,n,j->i", J, w, cov)


def plug_in_variance(g, C):
    """The variance a parameter estimated with the scored variances plugged in gains from
    their uncertainty (the two-step estimator's, Murphy & Topel 1985, its covariance term
    left out): g C g^T.

    Args:
        g: (ns,) the parameter's sensitivity (:func:`ridge_sensitivity`).
        C: (ns, ns, N) the variances' covariance at each grid point (:func:`scored_variances`;
            NaN where it fell back).

    Returns:
        (N,) the variance; 0 where not finite.
    """
    out = jnp.einsum("i,ijn,j->n", g, C, g)
    return jnp.where(jnp.isfinite(out), out, 0.0)
