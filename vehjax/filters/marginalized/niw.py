"""The noise statistics of the marginalized PF (Berntorp & Di Cairano 2018, eq. 18-30): the
Normal-inverse-Wishart (NiW) recursion, the Student-t predictive weight and the offset's
conditional (eq. 30), the imputation of missing sensor residuals and the point estimates of
eq. 23. The reading of the paper behind each formula is in :mod:`vehjax.filters.marginalized`.

Conventions. NiW(gamma, mu_hat, Lambda, nu) is Murphy's (2007) NiW(mu_0, kappa, Lambda, nu)
with gamma = 1 / kappa, over v = (w, e) of dimension d = 1 + n_s: the offset w of the noisy
input and the sensor noise e. Only the (w, w) block ``lam_w`` (scalar) and the (e, e) block
``lam_e`` (n_s, n_s) of Lambda are kept (eq. 21). Arrays may carry trailing particle axes
(``mu`` (d, N), ``lam_w`` (N,), ``lam_e`` (n_s, n_s, N)); gamma and nu are the same for all
particles. The functions whose arguments are "entries" take the nested lists of
:mod:`vehjax.lib.entrywise` (each entry an (N,) array over the particles or a constant).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import gammaln

from ...lib.entrywise import add, chol_masked, dot, is_zero, matmul, mul
from ...lib.linalg import forward_entries
from .staging import stage

__all__ = [
    "niw_predict", "niw_update", "st_logpdf_whitened", "t_weight_and_proposal", "impute_missing",
    "wilson_hilferty", "draw_offset", "noise_estimates", "t_predictive",
    "static_prior_grid",
]


def niw_predict(gamma, nu, lam_w, lam_e, forgetting):
    """Eq. 20, exponential forgetting of the statistics: (gamma / lambda, lambda nu,
    lambda Lambda_w, lambda Lambda_e); mu_hat is unchanged. ``forgetting`` lambda in (0, 1]."""
    return gamma / forgetting, forgetting * nu, forgetting * lam_w, forgetting * lam_e


def niw_update(gamma, nu, mu, lam_w, lam_e, eta, extra_e=None, means_known=False):
    """Eq. 18, the conjugate update with one datum v, given as ``eta = v - mu`` (d, ...):
    gamma / (1 + gamma), nu + 1, mu + gamma / (1 + gamma) eta, and Lambda + eta eta^T /
    (1 + gamma) on the (w, w) and (e, e) blocks (Murphy 2007, one datum with kappa = 1 / gamma).

    Args:
        gamma, nu: scalars.  mu: (d, ...).  lam_w: (...).  lam_e: (d - 1, d - 1, ...).
        eta: (d, ...) the datum minus mu.
        extra_e: (d - 1, d - 1, ...) added to Lambda_e, or None: the expected-statistic term for
            uncertain or missing sensor data (docs/marginalized.md, eq. 19).
        means_known: the noise's mean is known (zero; the grid filter's, where the
            offset and the biases are Kalman states): the NiW is an inverse-Wishart, gamma = 0
            (kappa = infinity), so the means stay and Lambda gains eta eta^T on both blocks.

    Returns:
        (gamma, nu, mu, lam_w, lam_e) after the datum.
    """
    g_post = gamma / (1.0 + gamma)
    s = 1.0 if means_known else 1.0 / (1.0 + gamma)
    ee = eta[1:]
    lam_e = lam_e + s * (ee[:, None] * ee[None, :])
    mu_new = mu if means_known else mu + g_post * eta
    if extra_e is not None:
        lam_e = lam_e + extra_e
    lam_w = lam_w + s * eta[0] ** 2
    return g_post, nu + 1.0, mu_new, lam_w, lam_e


def st_logpdf_whitened(alpha, L, df, n_obs):
    """log St(r; 0, L L^T, df), the multivariate Student-t density, from the whitened residual
    alpha = L^-1 r (entries; zeros on the missing components, whose rows of L are the
    identity) with ``n_obs`` observed components:
    log Gamma((df + n) / 2) - log Gamma(df / 2) - n/2 log(df pi) - log det L
    - (df + n)/2 log(1 + |alpha|^2 / df)."""
    q = dot(alpha, alpha)
    half_logdet = sum(jnp.log(L[i][i]) for i in range(len(L)))
    return (
        gammaln(0.5 * (df + n_obs)) - gammaln(0.5 * df) - 0.5 * n_obs * jnp.log(df * math.pi)
        - half_logdet - 0.5 * (df + n_obs) * jnp.log1p(q / df)
    )


def t_weight_and_proposal(y, obs, mu_y, S, cross, sw, df):
    """The particle weight (eq. 27) and the offset's conditional (eq. 30) from the joint
    Student-t of (w, y) with dof ``df``, location (mu_w, mu_y) and scale
    [[sw, cross^T], [cross, S]], over the observed components of y.

    The weight is the marginal log St(y_o; mu_y, S_oo, df) (the marginal of a t is a t with
    the same dof and the sub-block of the scale). The conditional of w given y_o is
    St(mu_w + c^T S^-1 eta, (df + q) / (df + n) (sw - c^T S^-1 c), df + n), eta = y - mu_y,
    q = eta^T S^-1 eta, n the number of observed components (all on the observed block).

    Args (entries, lists over the measurement components):
        y, obs: measurement (anything where missing) and the observed mask.
        mu_y, S: predictive location and scale of y (eq. 26 with Lambda_aug).
        cross: cross scale of (y, w), Lambda_tilde_w D.
        sw: scale of w, Lambda_tilde_w.
        df: degrees of freedom nu - d + 1.

    Returns:
        (log weight, shift of the conditional location of w, its scale, its dof, the innovation
        list eta with zeros on the missing components).
    """
    n = len(y)
    eta = [jnp.where(obs[i], y[i] - mu_y[i], 0.0) for i in range(n)]
    L = chol_masked(S, obs)
    alpha = forward_entries(L, eta)
    beta = forward_entries(L, [jnp.where(obs[i], cross[i], 0.0) for i in range(n)])
    n_obs = sum(jnp.asarray(o).astype(jnp.result_type(df)) for o in obs)
    ll = st_logpdf_whitened(alpha, L, df, n_obs)
    q = dot(alpha, alpha)
    s = (df + q) / (df + n_obs) * jnp.maximum(sw - dot(beta, beta), 0.0)
    return ll, dot(beta, alpha), s, df + n_obs, eta


def impute_missing(eta, sig, obs):
    """Missing sensor residuals under the Gaussian N(0, sig) (entries): eta with the missing
    components replaced by their conditional mean given the observed ones,
    Sigma_mo Sigma_oo^-1 eta_o, and the conditional covariance Sigma_mm - Sigma_mo Sigma_oo^-1
    Sigma_om on the missing block (zeros elsewhere).

    Returns:
        (eta list (n,), covariance nested lists (n, n)).
    """
    n = len(eta)
    L = chol_masked(sig, obs)
    a = forward_entries(L, [jnp.where(obs[i], eta[i], 0.0) for i in range(n)])
    B = [forward_entries(L, [jnp.where(obs[k], sig[k][i], 0.0) for k in range(n)])
         for i in range(n)]  # B[i] = L^-1 Sigma[o, i]
    full = [jnp.where(obs[i], eta[i], dot(B[i], a)) for i in range(n)]
    V = [[jnp.where(~obs[i] & ~obs[j], sig[i][j] - dot(B[i], B[j]), 0.0) for j in range(n)]
         for i in range(n)]
    return full, V


def wilson_hilferty(z, dof):
    """chi^2_dof / dof from a standard normal z by the Wilson-Hilferty cube (Johnson, Kotz &
    Balakrishnan 1994, eq. 18.25): (1 - c + z sqrt(c))^3, c = 2 / (9 dof), the base floored at
    0.1 (which only touches dof < 10 beyond 3.4 sigma)."""
    c = 2.0 / (9.0 * dof)
    base = jnp.maximum(1.0 - c + z * jnp.sqrt(c), 0.1)
    return base * base * base


#: how far into the tails of its prior :func:`static_prior_grid` reaches, in standard normal
#: quantiles of the chi-square (Wilson-Hilferty): 3.5 leaves about 2e-4 of the prior outside
GRID_Z = 3.5


def static_prior_grid(lam_w, dof, n: int):
    """A grid of n variances over the inverse-Wishart prior's marginal Lambda_w / chi^2_dof and
    their prior log weights: each particle's own static sigma_w^2 (``marginalized_pf_grid``).

    The grid is uniform in log sigma^2 between the chi-square's Wilson-Hilferty quantiles at
    -+ :data:`GRID_Z` (Johnson, Kotz & Balakrishnan 1994, eq. 18.25; lower base floored at 1e-3
    of the mean); the weights are the prior density of log sigma^2 there (that of log c for
    c = Lambda_w / sigma^2 ~ chi^2_dof: (dof / 2) log c - c / 2), normalised.

    Args:
        lam_w: scalar Lambda_w (> 0); dof: nu0 - d + 1 (> 0); n: grid size >= 2.

    Returns:
        (variances (n,), log weights (n,) summing to 1 in exp).
    """
    c = 2.0 / (9.0 * dof)
    q = lambda z: dof * max(1.0 - c + z * math.sqrt(c), 1e-1) ** 3  # noqa: E731
    lo, hi = math.log(q(-GRID_Z)), math.log(q(GRID_Z))
    log_c = jnp.linspace(hi, lo, n)  # sigma^2 from small to large
    lw = 0.5 * dof * log_c - 0.5 * jnp.exp(log_c)
    lw = lw - jax.scipy.special.logsumexp(lw)
    return lam_w / jnp.exp(log_c), lw


def noise_estimates(w, mu, lam_w, lam_e, nu, gamma, means_known=False, var_cov=None,
                    input_var_extra=None):
    """Eq. 23, the weighted estimates of the noise statistics, and their mixture covariance.

    The offset mean and the biases are the weighted NiW means; the variances mix the particles'
    inverse-Wishart means Lambda / (nu - d - 1) with the spread of their means (eq. 23b); the
    reported stds are the square roots of their diagonals. The covariance of
    (mu_w, sigma_w, b, sigma_s) is the mixture of the per-particle posterior covariances
    (gamma Sigma_hat for the means; the inverse-Wishart covariance of diag(Sigma) (Press 1982)
    taken to the stds by the delta method, nu - d - 3 floored at 1) plus the spread of the
    particles' values about the estimate.

    Args:
        w: (N,) normalised weights.  mu: (d, N).  lam_w: (N,).  lam_e: (d - 1, d - 1, N).
        nu, gamma: scalars, after the update.
        means_known: the noise's mean is known (gamma = 0, :func:`niw_update`): no
            within-particle covariance of the offset and the biases; ``lam_w`` is then each
            particle's sigma_w^2 itself (a static parameter of the particle, not a statistic:
            ``marginalized_pf_grid``), so sigma_w has no within-particle variance either.
        var_cov: (d - 1, d - 1, N) or None: each particle's covariance of its sensor
            variances in place of the inverse-Wishart's (where finite; the scored variances of
            :mod:`vehjax.filters.marginalized.sensor_scoring`).
        input_var_extra: (N,) or None: a within-particle variance of sigma_w (its std) to add
            (with ``means_known``: the plug-in of the scored sensor variances,
            :func:`vehjax.filters.marginalized.sensor_scoring.plug_in_variance`).

    Returns:
        (params (p,), params_cov (p, p)), p = 2 d, in the order offset mean, offset std,
        the d - 1 biases, the d - 1 sensor stds.
    """
    dtype = w.dtype
    d = mu.shape[0]
    ns = d - 1
    p = 2 * d
    den = nu - d - 1.0
    sw2 = lam_w if means_known else lam_w / den  # (N,)
    se = lam_e / den  # (ns, ns, N)
    m_w = jnp.sum(w * mu[0])
    b = mu[1:] @ w
    db = mu[1:] - b[:, None]
    var_w = jnp.sum(w * (sw2 + (mu[0] - m_w) ** 2))
    R = jnp.einsum("ijn,n->ij", se, w) + (db * w) @ db.T
    std_w = jnp.sqrt(var_w)
    std_s = jnp.sqrt(jnp.diagonal(R))
    params = jnp.concatenate([m_w[None], std_w[None], b, std_s])
    # per-particle values and within-particle covariances
    sd_w_i = jnp.sqrt(sw2)
    sd_s_i = jnp.sqrt(jnp.diagonal(se, axis1=0, axis2=1).T)  # (ns, N)
    theta_i = jnp.concatenate([mu[:1], sd_w_i[None], mu[1:], sd_s_i])  # (p, N)
    dev = theta_i - params[:, None]
    spread = (dev * w) @ dev.T
    # inverse-Wishart covariance of diag(Sigma) (dimension d), delta method to the stds
    pd = float(d)
    iw = jnp.maximum(nu - pd - 3.0, 1.0)
    denom = (nu - pd) * (nu - pd - 1.0) ** 2 * iw
    lw_stat = jnp.zeros_like(lam_w) if means_known else lam_w
    diag_lam = jnp.concatenate([lw_stat[None], jnp.diagonal(lam_e, axis1=0, axis2=1).T])
    Lfull = jnp.zeros((d, d, lam_w.shape[0]), dtype).at[0, 0].set(lw_stat).at[1:, 1:].set(lam_e)
    cov_diag = (2.0 * diag_lam[:, None, :] * diag_lam[None, :, :]
                + 2.0 * (nu - pd - 1.0) * Lfull ** 2) / denom  # Cov(Sigma_ii, Sigma_jj)
    sd_i = jnp.concatenate([sd_w_i[None], sd_s_i])
    cov_sd = cov_diag / (4.0 * sd_i[:, None, :] * sd_i[None, :, :])
    if var_cov is not None:
        cs = var_cov / (4.0 * sd_s_i[:, None, :] * sd_s_i[None, :, :])
        cov_sd = cov_sd.at[1:, 1:].set(jnp.where(jnp.isfinite(cs), cs, cov_sd[1:, 1:]))
    if input_var_extra is not None:
        cov_sd = cov_sd.at[0, 0].add(input_var_extra)
    cov_mu = (0.0 if means_known else gamma) * jnp.zeros((d, d, lam_w.shape[0]), dtype).at[
        0, 0].set(sw2).at[1:, 1:].set(se)
    within_mu = jnp.einsum("ijn,n->ij", cov_mu, w)
    within_sd = jnp.einsum("ijn,n->ij", cov_sd, w)
    perm = np.concatenate([[0], np.arange(2, 2 + ns)])  # the mean entries in params order
    perm_sd = np.concatenate([[1], np.arange(2 + ns, 2 + 2 * ns)])
    pc = jnp.zeros((p, p), dtype)
    pc = pc.at[np.ix_(perm, perm)].set(within_mu).at[np.ix_(perm_sd, perm_sd)].set(within_sd)
    pc = pc + spread
    return params, 0.5 * (pc + pc.T)


def draw_offset(mu_w, shift, scale, dof, z1, z2):
    """A draw of the offset w_t from its Student-t conditional (eq. 30),
    St(mu_w + shift, scale, dof), from two standard normals: w = mu_w + shift +
    sqrt(scale) z1 / sqrt(chi^2_dof / dof), the chi-square by :func:`wilson_hilferty` of z2."""
    return mu_w + shift + jnp.sqrt(scale) * z1 / jnp.sqrt(wilson_hilferty(z2, dof))


def t_predictive(lin, P, Qz, lam_w, lam_e, mu_w, b_y, gamma, nu, dim, known_var, sensor_pos,
                 n_sampled):
    """The moment-matched Student-t predictive of y_t of one step (eq. 26-27), entries over
    the particles.

    The offset w and the sensor noise enter through the NiW: y = yb + D w + b + e + ..., with
    D = Cx g + Cz gz + d (the noisy input through the sampled states, the linear states and
    directly), so the scale is Lambda_tilde_w D D^T + Lambda_tilde_e on the sensor block, where
    Lambda_tilde = (1 + gamma) / df Lambda and df = nu - dim + 1. Every Gaussian contribution
    (the known-std outputs' variances, the Kalman covariance P seen through
    M = [Cx Fx + Cz Fzx,] Cx A_bar + Cz A, the linear states' process noise Cz Qz Cz^T) is
    matched by a t of the same dof and covariance: scale (df - 2) / df K.

    Args:
        lin: :class:`~vehjax.filters.marginalized.linearise.Lin` of entries, the used output rows.
        P: (n_k, n_k) entries, the particles' Kalman covariances.
        Qz: (n_z, n_z) entries, the linear states' process noise.
        lam_w, lam_e: Lambda_w (N,) and Lambda_e entries (n_s, n_s), predicted (eq. 20).
        mu_w: (N,) the NiW offset means.  b_y: the bias of each used output (0.0 if none).
        gamma, nu: predicted NiW scalars.  dim: d = 1 + n_s.
        known_var: variance of each used output's known noise (0.0 for sensors).
        sensor_pos: dict used output row -> sensor index.
        n_sampled: how many sampled states are Gaussian too (``kalman_states="all"``), else 0.

    Returns:
        (mu_y, S, D, sw, df): the predictive location (list) and scale (nested lists), D,
        Lambda_tilde_w (N,) and the dof.
    """
    nyu, nz = len(lin.yb), len(lin.zb)
    D = [add(add(dot(lin.Cx[i], lin.g), lin.d[i]), dot(lin.Cz[i], lin.gz)) for i in range(nyu)]
    df = nu - dim + 1.0
    c = (1.0 + gamma) / df
    sw = c * lam_w
    mm = (df - 2.0) / df
    M = [[add(dot(lin.Cx[i], [r[j] for r in lin.Ab]), dot(lin.Cz[i], [r[j] for r in lin.A]))
          for j in range(nz)] for i in range(nyu)]
    if n_sampled:  # the particle's own states are uncertain too: y sees them through Fx, Fzx
        M = [[add(dot(lin.Cx[i], [r[j] for r in lin.Fx]),
                  dot(lin.Cz[i], [r[j] for r in lin.Fzx])) for j in range(n_sampled)] + M[i]
             for i in range(nyu)]
    D, M = stage((D, M))
    MP = matmul(M, P)
    CQ = matmul(lin.Cz, Qz)
    mu_y = [add(add(lin.yb[i], mul(D[i], mu_w)), b_y[i]) for i in range(nyu)]
    S = [[None] * nyu for _ in range(nyu)]
    for i in range(nyu):
        for j in range(i + 1):
            K = add(dot(MP[i], M[j]), dot(CQ[i], lin.Cz[j]))
            if i == j:
                K = add(K, known_var[i])
            v = mul(sw, mul(D[i], D[j]))
            if i in sensor_pos and j in sensor_pos:
                v = add(v, c * lam_e[sensor_pos[i]][sensor_pos[j]])
            S[i][j] = S[j][i] = add(v, mul(mm, K)) if not is_zero(K) else v
    S, mu_y, D = stage((S, mu_y, D))
    return mu_y, S, D, sw, df
