"""The sensor variances of the consistent marginalized PF by Fisher scoring of its innovations,
weighted at the prior guess (:func:`~vehjax.filters.marginalized.marginalized_pf_grid`'s
default, ``sensor_variances="scored"``).

What was wrong with the expected statistics alone. Each particle's Kalman step with the sensor
covariance R' (its estimate so far) gives the posterior of the sensor noise e_t given y_1:t,
and the inverse-Wishart statistics add its second moment T_t(R') = E[e_t e_t^T | y_1:t; R'] (the
E-step of EM, or a variational-Bayes adaptive Kalman filter). In innovations form, with S' =
S_x + R' the predictive covariance of y_t, nu_t its innovation, G = S'^-1 and a = G nu_t,

    T_t(R') = R' a a^T R' + R' - R' G R'.

At the true R its mean is R (the tower property; on the consistency study's data, R' held at
the truth: 0.999 of ay's variance over 100 runs x 300 steps). The numbers of this docstring
come from ``python benchmarks/mpf_k_sensor_variances.py`` (``statistic``, ``guess``,
``profile``, ``toy``) and ``benchmarks/mpf_k_param_bias.py``. But its slope in R'_jj is
delta_ij - F_ij, F_ij = ((R' G)_ij)^2, the fraction of the complete-data information that y_t
carries: 1 for a sensor that the step sees alone, small for one seen beside other noise. The
average of T_t (the inverse-Wishart mean) is then a stochastic approximation of gain 1 / n and
slope -F, which forgets its start as n^-F. On the consistency study's data the steering noise
reaches ay directly through the front tyres (d sigma_w about 0.35 m/s^2 beside ay's 0.2), F about
0.04: started at twice the truth the ay std was still +45 % after 300 steps, its interval
holding the truth in no run; started at the truth, the light prior's early fluctuations left it
-3 % for good. Taking each T_t to first order in the estimate (a Newton, missing-information
correction, Louis 1982) removes the slope but weighs step t by F_t, which grows with the
estimate r_t of that time: runs whose estimate fell early weigh the later, correcting steps
less (in the toy below it ends 7.6 % low in variance).

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
G: it adds nothing. In a toy of y_t = x_t + e_t with x_t independent N(0, 3 R) (ay's case), 300
steps, 20,000 runs: started at the truth, this estimate ends at 0.997 R, the first-order
corrected average at 0.924 R, Fisher scoring weighted at the current estimate at 1.027 R.

What it does not use. s_t and W_t hold S_x fixed: they leave out what later measurements say
about e_t through the dynamics (the steering noise moves vy and r, which the sensors see over
the following steps), so v is the fixed point of the filtered statistic, not the maximum-
likelihood estimate, and its interval, honest for it, is wider than the likelihood's (on the
consistency data, sensor noise and steering std known, the exact likelihood gives the ay std a
std of about 11 % per run of 300 steps). Only the variances are estimated; the sensors'
noises are taken as uncorrelated (below).

The steering std's interval. Each grid point of sigma_w plugs in its own scored variances, and
the grid's posterior is conditional on them: with the variances now as uncertain as the data
leave them (the ay std about 20 % per run of 300 steps), the steering std's spread over runs
was 1.17-1.27 times its reported std. Its reported variance gains the two-step estimator's
term (Murphy & Topel 1985), g C g^T with C the variances' covariance and g the shift of its
estimate per unit error of the variances, g = I_theta_v / I_theta_theta. I_theta_theta is the
grid's posterior precision; the cross information comes from the ridge the grid points'
variances lie on (each point's v the root of its own score, so I_v_theta = -I_vv dv/dtheta
along the grid, :func:`ridge_sensitivity`). The covariance-part cross information (the
innovations' 0.5 (S^-1 dS S^-1)_jj) gave half of what the spread needed.

The sensors' noises are taken as uncorrelated: the Kalman step plugs in diag(v). It first
kept the inverse-Wishart statistics' correlations beside the scored variances; those come from
the same slowly forgetting statistics, the filter with them was suboptimal, and its gyro
innovations exceeded its predictive covariance: the scored r and roll-rate stds ended 1.1-1.4 %
above the oracle's (each run's sample std of its true noise, states and bias known; the
script below prints it), also with the Kalman step's plug-in held at the truth (an experiment
not kept; benchmarks/results/notes_marginalized.md). Numpy's exact Kalman filter on the same data,
every noise known, gives scores that average -0.3 % of r's variance (the script's last line,
seed 0).

Measured (``python benchmarks/mpf_k_param_bias.py SEED 1000 jeffreys 1 [inverse-wishart]``,
100 runs x
300 steps, the consistency study's data, the guesses at the truth; seeds 0 / 1 / 2), the 95 %
intervals' coverage with the mean relative error:

    ==============  ==========================  ====================================
    std             scored (the default)        inverse-Wishart mean
    ==============  ==========================  ====================================
    ay              1.00 / 0.99 / 0.97,         0.86 / 0.89 / 0.84 (seed 0 at N =
                    -0.4 / +1.6 / +1.0 %        1000; -3.3 / -2.5 / -2.9 %)
    steering        0.94 / 0.93 / 0.94,         0.92-0.97
                    -0.1 / +0.1 / -0.5 %
    r               0.98 / 0.97 / 0.92,         0.91 at seed 2
                    -0.2 / -0.1 / +0.5 %
                    (oracle -0.2 / -0.2 / +0.6)
    roll rate       0.95 / 0.96 / 0.92,
                    -0.3 / -0.5 / -1.0 %
                    (oracle -0.3 / -0.4 / -0.8)
    ==============  ==========================  ====================================

At seed 2 the data's own r noise is dispersed: the oracle's spread is 1.18 times its
theoretical std and its coverage 0.92 (0.94-1.01 and 0.97-0.98 at seeds 0, 1, 3).

Started at twice the truth (steering std known, seed 0; ``python
benchmarks/mpf_k_sensor_variances.py guess 2 300 scored``): ay +2.0 % (the inverse-Wishart mean:
+45 %), coverage 0.99 (0.00), the NEES in the band on 0.93 of the steps (0.83). Cost: about 1.7
times the inverse-Wishart mean's time per step (``python benchmarks/mpf_consistent_steering.py
time 20 30``; the dated timings: benchmarks/results/notes_marginalized.md).

What it costs where the sensors are seen alone. On paper 004's simulation (sensors seen nearly
alone, guesses twice the truth) each grid point's scored variances fit its own sigma_w: early
on, the points above the true sigma_w explain the ay residuals by the steering noise and score
ay's variance down (ay std 0.92 of the truth at 0.5 s, against 1.15 with the inverse-Wishart
mean, 50 runs; ``python benchmarks/mpf_consistent_steering.py early 50``), so they keep their
weight longer (sigma_w 4.1 times the truth at 0.5 s against 2.9, 1.85 against 1.61 at 5 s) and
the states' covariance is wider for longer: NEES of (vy, r) in the band on 0.85 of the steps
against 0.86 (100 runs x 180 s, ``vehjax reproduce noise-learning``, rows MPF (consistent) and
MPF (inverse-Wishart)). It is the default all the same: that 0.01 against the inverse-Wishart
mean's ay interval holding the truth in 0.84-0.89 of the consistency study's runs (and +45 %
from a guess twice the truth where a sensor is seen beside other noise).
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
