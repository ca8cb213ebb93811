"""The Kalman filters of each particle of the marginalized PF (Berntorp & Di Cairano 2018,
sec. 3.4, and the Gaussian particle states of ``kalman_states="all"``), written entry by entry
over the particles (:mod:`vehjax.lib.entrywise`): every argument is a list or nested list
of (N,) arrays or structural constants, ``lin`` a :class:`~.linearise.Lin`
of entries. Sequential conditioning of joint Gaussians, Cholesky factors and forward
substitutions throughout (no inverses). The derivations are in
:mod:`vehjax.filters.marginalized`. The update itself is the one entry-form masked Kalman update,
:func:`vehjax.filters.kalman.condition_entries`, and the particles' log-likelihood the one Gaussian
log-density, :func:`vehjax.lib.gaussian.log_density_entries`.

Intermediate results are materialised by :func:`~vehjax.filters.marginalized.staging.stage`.
"""

from __future__ import annotations

import jax.numpy as jnp

from ...lib.entrywise import add, div, dot, matmul, matvec, mul, sub, transpose
from ...lib.gaussian import log_density_entries
from ..kalman import condition_entries
from .staging import stage

__all__ = ["bank_kalman_step", "kalman_update", "joint_kalman_step", "joint_prediction",
           "gaussian_loglik", "input_noise_kalman_step"]


def bank_kalman_step(lin, P, dx, y, obs, mu_w, b_y, sig_w2, R_y, Qz):
    """The bank's Kalman step (sec. 3.4) for x_t = lin.xb + dx, all arguments entries.

    Deviations s1 = z_{t-1} - m, s2 = w - mu_w, s3 = z_t - zb - gz mu_w (prior mean zero):
    first o1 = g^+ dx - mu_w = a^T s1 + s2 (the vehicle model along g, a = A_bar^T g^+^T; a
    scalar update of (s1, s2)), then the prediction of (s2, s3) by s3 = A s1 + gz s2 + zeta,
    then the observed components of o2 = y - yb - Cx dx - (Cz gz + d) mu_w - b_y = Cz s3 + d s2
    + noise(R_y). Sequential conditioning of the joint Gaussian: exact for that linear model.

    Returns:
        (posterior mean of s3, its covariance, o2 with zeros on missing, posterior mean of s2).
    """
    nz = len(lin.zb)
    g, A, gz, d, Cz = lin.g, lin.A, lin.gz, lin.d, lin.Cz
    gg = dot(g, g)
    gp = [div(gi, jnp.where(gg > 0, gg, 1.0)) for gi in g]
    a = [dot(gp, [row[j] for row in lin.Ab]) for j in range(nz)]
    r1 = dot(gp, dx) - mu_w
    Pa = matvec(P, a)
    S1 = dot(a, Pa) + sig_w2
    kz = [div(v, S1) for v in Pa]
    kw = sig_w2 / S1
    m1 = [mul(k, r1) for k in kz]
    mw = kw * r1
    P1 = [[sub(P[i][j], mul(kz[i], Pa[j])) for j in range(nz)] for i in range(nz)]
    c1 = [mul(k, -sig_w2) for k in kz]  # cov(s1, s2)
    v1 = sig_w2 - kw * sig_w2
    m1, mw, P1, c1, v1 = stage((m1, mw, P1, c1, v1))
    # predict (s2, s3)
    Ac = matvec(A, c1)
    mt = [add(dot(A[i], m1), mul(gz[i], mw)) for i in range(nz)]
    czw = [add(Ac[i], mul(gz[i], v1)) for i in range(nz)]
    AP = matmul(A, P1)
    Czz = [[add(add(add(dot(AP[i], A[j]), mul(Ac[i], gz[j])), mul(gz[i], Ac[j])),
                 add(mul(mul(gz[i], gz[j]), v1), Qz[i][j]))
            for j in range(nz)] for i in range(nz)]
    # state (s2, s3): mean, covariance
    mean = [mw] + mt
    cov = [[v1] + czw] + [[czw[i]] + Czz[i] for i in range(nz)]
    ny = len(y)
    H = [[d[i]] + list(Cz[i]) for i in range(ny)]
    o2 = [jnp.where(obs[i], sub(sub(sub(y[i] - lin.yb[i], dot(lin.Cx[i], dx)),
                                      mul(add(dot(Cz[i], gz), d[i]), mu_w)), b_y[i]), 0.0)
          for i in range(ny)]
    mean, cov, o2 = stage((mean, cov, o2))
    post, C = kalman_update(mean, cov, H, o2, R_y, obs)
    return post[1:], [row[1:] for row in C[1:]], o2, post[0]


def _update_parts(mean, cov, H, r, R_y, obs):
    """N(mean, cov) conditioned on the observed components of r = H s + noise(R_y), entries:
    the moments S = H cov H^T + R_y and Cov(s, r) = (H cov)^T staged, then
    :func:`vehjax.filters.kalman.condition_entries` (structural zeros of H cov cost nothing).
    Returns the posterior mean and covariance (symmetric), the whitened innovation alpha =
    L^-1 (r - H mean), the Cholesky factor L of S on the observed components (identity rows
    elsewhere) and S itself."""
    ny = len(r)
    HS = matmul(H, cov)  # (ny, n)
    S2 = [[add(dot(HS[i], H[j]), R_y[i][j]) for j in range(ny)] for i in range(ny)]
    HS, S2 = stage((HS, S2))
    e = [jnp.where(obs[i], sub(r[i], dot(H[i], mean)), 0.0) for i in range(ny)]
    post, C, alpha, L = condition_entries(mean, cov, e, S2, transpose(HS), obs)
    return post, C, alpha, L, S2


def kalman_update(mean, cov, H, r, R_y, obs):
    """Kalman update (entries): N(mean, cov) conditioned on the observed components of
    r = H s + noise(R_y). Returns the posterior mean and covariance (symmetric)."""
    return _update_parts(mean, cov, H, r, R_y, obs)[:2]


def gaussian_loglik(L, alpha, obs):
    """log N(r; H mean, S) of the observed components from :func:`_update_parts`' L and alpha
    (:func:`vehjax.lib.gaussian.log_density_entries`; L's identity rows add nothing)."""
    n_obs = sum(jnp.asarray(o).astype(jnp.int32) for o in obs)
    return log_density_entries(alpha, L, n_obs)[0]


def input_noise_kalman_step(lin, P, sig_w2, y, obs, b_y, R_y, Qz):
    """The Kalman step of Gaussian particle states with the noisy input's error w ~ N(0,
    sig_w2) as process noise (not drawn; ``marginalized_pf_grid``, where the offset is a
    state): the deviations xi = (x_{t-1} - x_hat, z_{t-1} - m) ~ N(0, P) and w predicted
    jointly, s_t = Phi xi + (g, gz) w (+ the linear states' noise Qz), then conditioned on the
    observed components of o = y - yb - b_y = H s_t + d w + noise(R_y), H = (Cx, Cz).

    Returns:
        (posterior mean of (dx_t, dz_t, w) (n + 1 entries), its covariance (nested lists),
        o with zeros on missing components, log N(o; 0, S) of the observed components (the
        particle's weight), S (ny, ny) the predictive covariance of y).
    """
    nxs, nz = len(lin.xb), len(lin.zb)
    n = nxs + nz
    Phi = ([list(lin.Fx[i]) + list(lin.Ab[i]) for i in range(nxs)]
           + [list(lin.Fzx[i]) + list(lin.A[i]) for i in range(nz)])
    gf = list(lin.g) + list(lin.gz)
    PhiP = matmul(Phi, P)
    cov = [[None] * (n + 1) for _ in range(n + 1)]
    for i in range(n):
        for j in range(i + 1):
            c = add(dot(PhiP[i], Phi[j]), mul(sig_w2, mul(gf[i], gf[j])))
            if i >= nxs and j >= nxs:
                c = add(c, Qz[i - nxs][j - nxs])
            cov[i][j] = cov[j][i] = c
        cov[i][n] = cov[n][i] = mul(sig_w2, gf[i])
    cov[n][n] = sig_w2
    ny = len(y)
    H = [list(lin.Cx[i]) + list(lin.Cz[i]) + [lin.d[i]] for i in range(ny)]
    o = [jnp.where(obs[i], sub(y[i] - lin.yb[i], b_y[i]), 0.0) for i in range(ny)]
    cov, o = stage((cov, o))
    post, C, alpha, L, S = _update_parts([0.0] * (n + 1), cov, H, o, R_y, obs)
    return post, C, o, gaussian_loglik(L, alpha, obs), S


def joint_kalman_step(lin, P, w, y, obs, b_y, R_y, Qz, D):
    """The Kalman step of Gaussian particle states: the deviations xi = (x_{t-1} - x_hat,
    z_{t-1} - m) ~ N(0, P) of one particle whose offset draw w is taken as known, predicted
    through the model's Jacobians (x_t = lin.xb + g w and z_t = lin.zb + gz w are the predicted
    means, the bank's process noise Qz on z), then updated with the observed components of
    y_t, o = y - yb - D w - b_y = Cx dx_t + Cz dz_t + noise(R_y), D = Cx g + Cz gz + d (the
    predictive's, eq. 26).

    Returns:
        (posterior mean of (dx_t, dz_t), their covariance (nested lists), o with zeros on
        missing components).
    """
    nxs, nz = len(lin.xb), len(lin.zb)
    n = nxs + nz
    Phi = ([list(lin.Fx[i]) + list(lin.Ab[i]) for i in range(nxs)]
           + [list(lin.Fzx[i]) + list(lin.A[i]) for i in range(nz)])
    PhiP = matmul(Phi, P)
    Cp = [[add(dot(PhiP[i], Phi[j]), Qz[i - nxs][j - nxs] if (i >= nxs and j >= nxs) else 0.0)
           for j in range(n)] for i in range(n)]
    ny = len(y)
    H = [list(lin.Cx[i]) + list(lin.Cz[i]) for i in range(ny)]
    o = [jnp.where(obs[i], sub(sub(y[i] - lin.yb[i], mul(D[i], w)), b_y[i]), 0.0)
         for i in range(ny)]
    Cp, o = stage((Cp, o))
    post, C = kalman_update([0.0] * n, Cp, H, o, R_y, obs)
    return post, C, o


def joint_prediction(lin, w, P, Qz):
    """The prediction of one particle's Gaussian over (x, z) with ``kalman_states="all"``, on
    arrays (one particle): given its offset draw w_t, x_t = xb + g w_t + Fx dx_{t-1} +
    A_bar dz_{t-1} and z_t = zb + gz w_t + Fzx dx_{t-1} + A dz_{t-1} + zeta_t, zeta ~ N(0, Qz),
    with (dx, dz)_{t-1} ~ N(0, P) the deviations from the particle's means (the prediction of
    :func:`joint_kalman_step`, before its update).

    Args:
        lin: :class:`~.linearise.Lin` of arrays at the particle's means and
            u_t.
        w: scalar, the offset draw w_t.  P: (n, n) covariance at t - 1, n = n_x + n_z.
        Qz: (n_z, n_z) process noise of the linear states.

    Returns:
        (m_pred (n,), P_pred (n, n), C (n, n)): the predicted mean and covariance of (x_t, z_t)
        and C = Cov((x, z)_{t-1}, (x, z)_t) = P Phi^T, Phi = [[Fx, A_bar], [Fzx, A]].
    """
    nxs = lin.xb.shape[0]
    Phi = jnp.concatenate([jnp.concatenate([lin.Fx, lin.Ab], 1),
                           jnp.concatenate([lin.Fzx, lin.A], 1)], 0)
    m_pred = jnp.concatenate([lin.xb + lin.g * w, lin.zb + lin.gz * w])
    C = P @ Phi.T
    P_pred = Phi @ C
    P_pred = P_pred.at[nxs:, nxs:].add(Qz)
    return m_pred, 0.5 * (P_pred + P_pred.T), C
