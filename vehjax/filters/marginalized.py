"""The noise-adaptive marginalized particle filter of Berntorp & Di Cairano (paper 004, eq. 11-30,
Algorithm 1) as an :class:`Estimator`.

What it estimates
-----------------
One input of the model (``noisy_input``, the steering angle delta of eq. 4-5) is measured with an
error w ~ N(mu_w, sigma_w^2) of unknown mean (the steering offset) and variance; some outputs
(``sensors``, the inertial sensors ay, yaw rate, roll rate of eq. 7) carry noise e ~ N(b, R) of
unknown bias b and covariance R; other outputs (``known_std``, the bank angle phi_m and the
virtual yaw rate of eq. 10) have zero-mean noise of known std. Some states (``linear_states``, the
bank z = (phi, phi_dot, phi_ddot) of eq. 3) enter the model affinely and are Rao-Blackwellised:
a Kalman filter per particle. The other states x (vy, r) are particles. Per particle the filter
carries the sufficient statistics S = (gamma, mu_hat, Lambda_w, Lambda_e, nu) of a
Normal-inverse-Wishart (NiW) over the noise, and learns (mu_w, sigma_w, b, R) jointly with the
state. Without linear states and bank sensors it is the planar filter of Remark 2.

Time convention (vehjax's, see :mod:`vehjax.run`): step t takes the particles x_{t-1}, the input
u_t and the measurement y_t, where x_t = f(x_{t-1}, u_t + w_t) and y_t = h(x_t, u_t + w_t): the
same offset sample w_t drives the transition into x_t and enters y_t directly (eq. 6 and 8, where
the paper indexes the pre-transition state by k). One step is Algorithm 1 with its loops rotated
so that w_t is drawn given y_t (the paper's sec. 3.5 choice: eq. 30 conditions on the innovation):

1. predict the statistics with forgetting (eq. 20);
2. weight every particle by the Student-t predictive p(y_t | x_{0:t-1}, y_{0:t-1}) (eq. 26-27),
   which marginalises w_t, the sensor noise and its parameters, and the bank;
3. draw w_t from its Student-t conditional given y_t (eq. 30) and set
   x_t = f(x_{t-1}, u_t) + A_bar z_hat + g w_t (eq. 6);
4. Kalman-update the bank with y_t and the vehicle model (sec. 3.4);
5. update the statistics with the data (w_t, e_t) (eq. 18-19);
6. report the weighted estimates (eq. 23), then resample when the ESS is low (for the next step).

Reading of the paper (the transcription has gaps and typos; derived from the conjugate NiW
algebra, Murphy 2007 [25] sec. 9, Ozkan et al. 2013 [26], Saha & Gustafsson 2012 [20])
-------------------------------------------------------------------------------------------------
Conventions. NiW(gamma, mu_hat, Lambda, nu) is Murphy's NiW(mu_0, kappa, Lambda, nu) with
gamma = 1 / kappa: mu | Sigma ~ N(mu_hat, gamma Sigma), Sigma ~ IW(Lambda, nu) in dimension d.
Then eq. 18 is exactly Murphy's one-datum update (kappa + 1 = 1 / gamma_{k|k}, the weight
kappa / (kappa + 1) = 1 / (1 + gamma) on eta eta^T), so repeated with lambda = 1 it equals the
batch posterior (tests/test_marginalized.py checks it).

* Dependence structure, eq. 9 and 21. Write v = [w; e] (the offset and the sensor noise, which
  the model takes independent) and w_bar = [w; e_bar] = T v with e_bar = d w + e, T = [[1, 0],
  [d, I]]. A NiW on v with block-diagonal scale diag(Lambda_w, Lambda_e) maps to the NiW on
  w_bar with Lambda = T diag(Lambda_w, Lambda_e) T^T, which is eq. 21, and mean T mu_hat_v,
  which is eq. 9's (mu_w, d mu_w + b). So only mu_hat_v = (mu_w, b), Lambda_w (scalar) and
  Lambda_e (n_s x n_s) are propagated, as the paper says, and d may change with the state, the
  input and the particle (it is recomputed every step). Eq. 18d on v adds eta_v eta_v^T /
  (1 + gamma); its off-diagonal (w, e) block is dropped: w and e are independent by assumption.
  d = 1 + n_s is the dimension of v in every formula below.
* Degrees of freedom. The predictive of v (and of any linear map of it: e_bar, y) is
  St(mu_hat, (1 + gamma) / (nu - d + 1) Lambda, nu - d + 1) (sec. 3.2 and Murphy eq. 258): dof
  nu - d + 1, with the (1 + gamma) factor carried by every scale, including eq. 30's. The point
  estimate of the covariance is the inverse-Wishart mean Lambda / (nu - d - 1), so eq. 23's
  nu_tilde_{k|k} = nu - d - 1 (and sec. 3.4's "Lambda / (nu - d_y - 1)" is that mean, d_y a typo
  for d).
* Eq. 30 is the conditional of a multivariate t: for (a, b) ~ St(mu, Lambda, n) with
  dim b = d_y, a | b ~ St(mu_a + L_ab L_bb^-1 (b - mu_b), (n + q) / (n + d_y) (L_aa - L_ab
  L_bb^-1 L_ba), n + d_y), q = (b - mu_b)^T L_bb^-1 (b - mu_b). The print has the gain
  d Lambda_w Lambda_tilde^-1 where the cross scale is Lambda_tilde_w d^T (Lambda_w times
  (1 + gamma) / (nu - d + 1), like Lambda_tilde_e), and the denominator nu - d_y + 1 where it is
  n + d_y = nu - d + 1 + d_y (the printed nu* has it right). Here b is the whole observed
  measurement vector (the moment-matched Student-t of eq. 26), so d_y is the number of observed
  components, known-std ones included.
* Eq. 26-27, moment matching. The known-std measurements are Gaussian, independent of w and of
  the NiW; a Gaussian of covariance K is matched by a t of the same dof nu_t = nu - d + 1 and
  scale (nu_t - 2) / nu_t K (same covariance), which is Lambda_aug. The same is done for every
  other Gaussian contribution the paper leaves out: the bank's covariance P seen through the
  measurement (the RBPF likelihood of Schoen et al. 2005 [18] has C P C^T) and the bank's
  process noise. This needs nu_t > 2, i.e. lambda nu_{k-1|k-1} > d + 1 at every step; since nu
  runs monotonically from nu0 to its fixed point 1 / (1 - lambda) under eq. 18c/20c, the builder
  requires lambda min(nu0, 1 / (1 - lambda)) > d + 1 (at the paper's lambda = 0.995, nu -> 200).
* Eq. 19 and sec. 3.5. The data for the statistics are the drawn offset w_t (not a
  pseudo-inverse: x_t is built from it) and the sensor residual e_t = y_t - h(x_t, z_t, u_t +
  w_t) (not y - h - d mu_w as printed: with w_t drawn, e_t is the sensor noise itself). The bank
  z_t is not known: e_t uses its Kalman posterior mean, and the posterior covariance C P C^T is
  added to Lambda_e (the expected sufficient statistic, as in variational-Bayes adaptive Kalman
  filters), so the bank's uncertainty is not mistaken for small sensor noise. A sensor that is
  NaN at a step is imputed by its conditional mean given the observed ones and its conditional
  covariance is added likewise (the EM form of the conjugate update): with nothing observed the
  point estimates are unchanged. gamma and nu do not depend on data, so they are the same for
  every particle and are carried once.
* Eq. 20 (forgetting) is used as printed: gamma / lambda, lambda nu, lambda Lambda.
* Sec. 3.4, the bank filter. Given the particle's x_{t-1} and x_t, the vehicle model is a
  measurement of z_{t-1}: g^+ (x_t - f(x_{t-1}, 0, u_t)) = g^+ A_bar z_{t-1} + w_t, g^+ the
  pseudo-inverse of eq. 19/28 (the component of x_t - f along g; the component orthogonal to g
  has no noise in the model and is not used), with w_t ~ N(mu_w, sigma_w^2) the particle's point
  estimates. It shares w_t with the sensors (y = h(x_t) + C z_t + d w_t + e), so the Kalman step
  conditions the joint Gaussian of (z_{t-1}, w_t, z_t) on both: the scalar vehicle-model
  measurement on (z_{t-1}, w_t), the prediction of (w_t, z_t), then y_t (sequential
  conditioning, exact for that linear model: the test compares it with one batch Gaussian
  conditioning over a whole trajectory).
  The sensor noise covariance is the point estimate R_hat = Lambda_e / (nu - d - 1) and the
  bias b_hat. A_phi of eq. 3 is not the identity (see :mod:`vehjax.models.bank`); whatever the
  model's transition does to the linear states is read off by forward-mode differentiation.
* What sec. 3.4 leaves out, and ``kalman_states="all"``. Eq. 6 needs z_k; Algorithm 1 has
  only the bank's Kalman mean, so a particle's x_t = f + A_bar z_hat + g w_t leaves out
  A_bar (z_{t-1} - z_hat): the particle cloud carries no part of the bank's uncertainty in vy
  and r. On the consistency study's SingleTrackBank data with the noise statistics known
  (``vehjax reproduce consistency``, 100 runs x 3 s, N = 1000) the filter's errors are those of
  the exact Kalman filter of that linear-Gaussian model (within 1 % rms) but its reported vy
  variance is 0.92 of the exact one (vy's NEES 1.08 per state; NEES in the 95 % band on 0.887
  of the steps, the exact filter 0.943). Two exact repairs: (a) the RBPF of Schoen et al.
  2005 proper, x_t drawn with the bank marginalised and the bank then conditioned on all of
  x_t; its bank follows the particle's vy exactly (vy has no noise of its own across g), so
  the bank's uncertainty moves into the particle cloud and needs the bootstrap PF's numbers
  (bank mean off the exact filter's by 0.31 of its std at N = 1000, 0.16 at 4000; tried, not
  kept); (b) kept as ``kalman_states="all"``: given its offset draws w_{1:t} a particle's
  whole state is Gaussian (exact for affine models), so each particle carries the mean and
  covariance of (x, z). One step: the weight is the predictive of y_t (eq. 26-27 with the
  covariance of (x_{t-1}, z_{t-1}) seen through C [F_x, A_bar; F_zx, A_phi]); w_t drawn by
  eq. 30 as before; the Gaussian predicted through the Jacobians with w_t known and updated
  with y_t (:func:`_kf_joint_e`); the statistics updated with w_t and the sensor residual at
  the posterior mean, its covariance H P H^T added as above. No vehicle-model measurement is
  needed: w_t is known to the particle. Without linear states it is the planar filter
  unchanged. On the same data: NEES in band 0.943, per state 1.00 / 1.01 on vy / r, variances
  within 0.3 % of the exact filter's, means within 0.05 of its std. It costs 1.2-1.3x the
  time per step of "linear" (N = 500, one run and 100 runs).
* Eq. 23b as printed mixes the particles' covariance estimates with the spread of their means:
  R_hat = sum_i q_i (Lambda_e^i / (nu - d - 1) + (b^i - b_hat)(b^i - b_hat)^T), likewise
  sigma_w^2; the reported stds are the square roots of the diagonal. ``params_cov`` is the
  mixture of the per-particle posterior covariances of (mu_w, sigma_w, b, sigma_s): gamma Sigma_hat
  for the means (NiW), the inverse-Wishart covariance of the diagonal of Sigma (Press 1982)
  taken to the stds by the delta method (d sigma = d Sigma / (2 sigma)), with nu - d - 3
  floored at 1 where that variance does not exist, plus the spread of the particles' values
  about the reported estimate.

Linearisation. The model enters through forward-mode derivatives (``jax.jacfwd``) at each
particle: g = d f / d delta, A_bar = d f_x / d z, the bank transition, C = d h / d (x, z) and
d = d h / d delta. For models affine in the states, the linear states and the noisy input
(:class:`~vehjax.models.bank.SingleTrackBank` at a given speed) every formula is exact; for
others it is first order in the offset and the bank (an EKF-like step inside each particle).
Affinity in the linear states is checked numerically when the filter is built. Which entries
of these derivatives are constants, which depend on the input alone (computed once per step,
not per particle) and which on the particle is read off the traced model when the filter is
built (:func:`_entry_kinds`): for SingleTrackBank only the predicted x_t, z_t and y_t are
per particle.

Implementation. Particles are last in every leaf. The per-particle algebra is written entry by
entry (every matrix entry one (N,) vector, structural zeros skipped, the Cholesky and forward
substitutions of :mod:`vehjax.filters._linalg`), and its stages are materialised through a
trivial while loop (:func:`_barrier`) so that XLA does not recompute long elementwise chains in
every consumer; weights, resampling, moments and random numbers are the shared particle core
:mod:`vehjax.filters.smc`. Cholesky factors and triangular solves throughout, no inverses.

Random numbers: two standard-normal rows per step from the particle core (:mod:`smc`), one for
the t draw and one for its chi-square through the Wilson-Hilferty cube (Johnson, Kotz &
Balakrishnan 1994, eq. 18.25; its base floored at 0.1, which only touches dof < 10 beyond 3.4
sigma), and the resampling uniforms.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import gammaln

from .. import _hoist, _validate
from . import resampling as _rs
from . import smc
from .base import Estimator, StepOutput
from ._linalg import chol_entries, forward_entries
from .sigma import cholesky, solve_lower

__all__ = ["MPFState", "marginalized_pf"]


class MPFState(NamedTuple):
    """State of :func:`marginalized_pf` for one run; the particle axis N is last.

    Attributes:
        x: (n_x, N) sampled states (the model states not in ``linear_states``, model order);
            with ``kalman_states="all"`` the means of each particle's Gaussian over them.
        z: (n_z, N) Kalman means of the linear states (``linear_states`` order).
        P: (n_z, n_z, N) their covariances; with ``kalman_states="all"`` (n_x + n_z, n_x + n_z,
            N), the covariance of the particle's states and the linear states (that order).
        mu: (d, N) NiW means of v = (w, e): the offset mean, then one bias per sensor.
        lam_w: (N,) NiW scale of the offset, Lambda_w.
        lam_e: (n_s, n_s, N) NiW scale of the sensor noise, Lambda_e.
        gamma: scalar, the NiW gamma (1 / kappa), the same for all particles.
        nu: scalar, the NiW degrees of freedom, the same for all particles.
        log_weights, weights: (N,) normalised weights and their logs.
        key: (2,) uint32 raw Threefry key for the next step.
        ess: effective sample size after the last update, before resampling.
        flag_diverged: bool, the weights have underflowed at some step.
        n_reinit: int32, at how many steps they did.
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


# ---------------------------------------------------------------------------------------------
# The algebra, entry by entry
#
# Inside the filter every small matrix is a nested list of entries and every vector a list, each
# entry one (N,) array over the particles (or a scalar): XLA fuses the whole step into a few long
# vectorised loops, where vmapped matrix code keeps the particles first and materialises strided
# (N, k, k) intermediates (measured 2-3x slower on CPU). A Python float 0.0 is a structural zero
# and costs nothing. The functions without ``_e`` in their name take and return arrays: the
# same algebra on plain matrices, for the tests.


def _barrier(tree, start=None):
    """The array leaves of ``tree`` (structural constants pass through), materialised: they go
    through a while loop whose body multiplies by one and whose trip count (0 or 1) XLA cannot
    know at compile time. Without it XLA on CPU fuses long chains of elementwise producers into
    every consumer and recomputes them there (7x the operation count of the step);
    ``lax.optimization_barrier`` is removed before fusion on CPU and does not help.

    ``start``: an int32 scalar, 0 at run time but opaque to the compiler; best one that does not
    vary over the runs of a study (from the inputs), so that the loop stays a plain loop under
    ``vmap``. Default: from the first leaf.
    """
    leaves, treedef = jax.tree.flatten(tree)
    idx = [i for i, v in enumerate(leaves) if not _const(v)]
    if not idx:
        return tree
    arrs = [leaves[i] for i in idx]
    if start is None:
        probe = jnp.ravel(arrs[0])[0]
        start = (probe != probe).astype(jnp.int32)  # 0 unless NaN

    def body(c):
        one = (c[0] >= 0).astype(arrs[0].dtype)  # 1, but not known to the compiler
        return c[0] + 1, [a * one.astype(a.dtype) for a in c[1]]

    _, kept = jax.lax.while_loop(lambda c: c[0] < 1, body, (start, arrs))
    for i, v in zip(idx, kept):
        leaves[i] = v
    return jax.tree.unflatten(treedef, leaves)


def _zero(a) -> bool:
    return isinstance(a, float) and a == 0.0


def _const(a) -> bool:
    """A structural constant: a Python float (known when the step is traced)."""
    return isinstance(a, float)


def _add(a, b):
    if _zero(a):
        return b
    if _zero(b):
        return a
    return a + b


def _mul(a, b):
    if _zero(a) or _zero(b):
        return 0.0
    if isinstance(a, float) and a == 1.0:
        return b
    if isinstance(b, float) and b == 1.0:
        return a
    return a * b


def _sub(a, b):
    if _zero(b):
        return a
    if _zero(a):
        return -b
    return a - b


def _div(a, b):
    return 0.0 if _zero(a) else a / b


def _dot(a, b):
    """sum_k a_k b_k over lists, skipping structural zeros."""
    acc = 0.0
    for ak, bk in zip(a, b):
        acc = _add(acc, _mul(ak, bk))
    return acc


def _tr(A):
    return [list(col) for col in zip(*A)]


def _mv(A, x):
    return [_dot(row, x) for row in A]


def _mm(A, B):
    Bt = _tr(B)
    return [[_dot(row, col) for col in Bt] for row in A]


def _ent(a):
    """Entries of an array (k, ...) -> list, (m, k, ...) -> nested lists (leading axes)."""
    if a.ndim >= 2 and a.shape[0] * a.shape[1] == 0:
        return [[] for _ in range(a.shape[0])]
    return [_ent(a[i]) if a.ndim >= 3 else a[i] for i in range(a.shape[0])] if a.ndim >= 2 else [
        a[i] for i in range(a.shape[0])]


def _arr(E, like):
    """Nested lists back to an array (entries broadcast to ``like``'s shape)."""
    def one(v):
        return jnp.broadcast_to(jnp.asarray(v, like.dtype), like.shape)
    if E and isinstance(E[0], list):
        return jnp.stack([jnp.stack([one(v) for v in row]) if row else jnp.zeros((0,) + like.shape,
                                                                                 like.dtype)
                          for row in E])
    return jnp.stack([one(v) for v in E]) if E else jnp.zeros((0,) + like.shape, like.dtype)


def _masked(M, obs):
    """M (n, n) on the observed rows and columns, identity elsewhere."""
    both = obs[:, None] & obs[None, :]
    return jnp.where(both, M, jnp.eye(M.shape[-1], dtype=M.dtype))


def _chol_masked_e(S, obs):
    """Cholesky factor (nested lists) of S on the observed rows and columns, identity
    elsewhere; ``obs`` a list of booleans (scalars or arrays)."""
    def a(i, j):
        eye = 1.0 if i == j else 0.0
        return jnp.where(obs[i] & obs[j], S[i][j] if i == j else 0.5 * _add(S[i][j], S[j][i]), eye)
    return chol_entries(a, len(S))


def _st_logpdf_e(alpha, L, df, n_obs):
    """log St(r; 0, L L^T, df) from the whitened residual alpha = L^-1 r (zeros on the missing
    components, whose rows of L are the identity), n_obs observed components."""
    q = _dot(alpha, alpha)
    half_logdet = sum(jnp.log(L[i][i]) for i in range(len(L)))
    return (
        gammaln(0.5 * (df + n_obs)) - gammaln(0.5 * df) - 0.5 * n_obs * jnp.log(df * math.pi)
        - half_logdet - 0.5 * (df + n_obs) * jnp.log1p(q / df)
    )


def _t_weight_and_proposal_e(y, obs, mu_y, S, cross, sw, df):
    """Weight (eq. 27) and the offset's conditional (eq. 30) from the joint Student-t of (w, y).

    Args (lists over the measurement components):
        y, obs: measurement (anything where missing) and observed mask.
        mu_y, S: predictive mean and scale of y (eq. 26 with Lambda_aug).
        cross: cross scale of (w, y), Lambda_tilde_w D^T.
        sw: scale of w, Lambda_tilde_w.  df: degrees of freedom nu - d + 1.

    Returns:
        (loglik, shift of the conditional mean of w, its scale, its dof, innovation list).
    """
    n = len(y)
    eta = [jnp.where(obs[i], y[i] - mu_y[i], 0.0) for i in range(n)]
    L = _chol_masked_e(S, obs)
    alpha = forward_entries(L, eta)
    beta = forward_entries(L, [jnp.where(obs[i], cross[i], 0.0) for i in range(n)])
    n_obs = sum(jnp.asarray(o).astype(jnp.result_type(df)) for o in obs)
    ll = _st_logpdf_e(alpha, L, df, n_obs)
    q = _dot(alpha, alpha)
    s = (df + q) / (df + n_obs) * jnp.maximum(sw - _dot(beta, beta), 0.0)
    return ll, _dot(beta, alpha), s, df + n_obs, eta


def _impute_e(eta, sig, obs):
    """Missing sensor residuals: (eta with the missing entries replaced by their conditional
    mean given the observed ones, the conditional covariance on the missing block and zeros
    elsewhere), under the covariance ``sig`` (nested lists)."""
    n = len(eta)
    L = _chol_masked_e(sig, obs)
    a = forward_entries(L, [jnp.where(obs[i], eta[i], 0.0) for i in range(n)])
    B = [forward_entries(L, [jnp.where(obs[k], sig[k][i], 0.0) for k in range(n)])
         for i in range(n)]  # B[i] = L^-1 Sigma[o, i]
    full = [jnp.where(obs[i], eta[i], _dot(B[i], a)) for i in range(n)]
    V = [[jnp.where(~obs[i] & ~obs[j], sig[i][j] - _dot(B[i], B[j]), 0.0) for j in range(n)]
         for i in range(n)]
    return full, V


def _kf_e(lin, P, dx, y, obs, mu_w, b_y, sig_w2, R_y, Qz, start=None):
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
    gg = _dot(g, g)
    gp = [_div(gi, jnp.where(gg > 0, gg, 1.0)) for gi in g]
    a = [_dot(gp, [row[j] for row in lin.Ab]) for j in range(nz)]
    r1 = _dot(gp, dx) - mu_w
    Pa = _mv(P, a)
    S1 = _dot(a, Pa) + sig_w2
    kz = [_div(v, S1) for v in Pa]
    kw = sig_w2 / S1
    m1 = [_mul(k, r1) for k in kz]
    mw = kw * r1
    P1 = [[_sub(P[i][j], _mul(kz[i], Pa[j])) for j in range(nz)] for i in range(nz)]
    c1 = [_mul(k, -sig_w2) for k in kz]  # cov(s1, s2)
    v1 = sig_w2 - kw * sig_w2
    m1, mw, P1, c1, v1 = _barrier((m1, mw, P1, c1, v1), start)
    # predict (s2, s3)
    Ac = _mv(A, c1)
    mt = [_add(_dot(A[i], m1), _mul(gz[i], mw)) for i in range(nz)]
    czw = [_add(Ac[i], _mul(gz[i], v1)) for i in range(nz)]
    AP = _mm(A, P1)
    Czz = [[_add(_add(_add(_dot(AP[i], A[j]), _mul(Ac[i], gz[j])), _mul(gz[i], Ac[j])),
                 _add(_mul(_mul(gz[i], gz[j]), v1), Qz[i][j]))
            for j in range(nz)] for i in range(nz)]
    # state (s2, s3): mean, covariance
    mean = [mw] + mt
    cov = [[v1] + czw] + [[czw[i]] + Czz[i] for i in range(nz)]
    ny = len(y)
    H = [[d[i]] + list(Cz[i]) for i in range(ny)]
    o2 = [jnp.where(obs[i], _sub(_sub(_sub(y[i] - lin.yb[i], _dot(lin.Cx[i], dx)),
                                      _mul(_add(_dot(Cz[i], gz), d[i]), mu_w)), b_y[i]), 0.0)
          for i in range(ny)]
    mean, cov, o2 = _barrier((mean, cov, o2), start)
    post, C = _update_e(mean, cov, H, o2, R_y, obs, start)
    return post[1:], [row[1:] for row in C[1:]], o2, post[0]


def _update_e(mean, cov, H, r, R_y, obs, start=None):
    """Kalman update (entries): N(mean, cov) conditioned on the observed components of
    r = H s + noise(R_y). Returns the posterior mean and covariance (symmetrised)."""
    n, ny = len(mean), len(r)
    HS = _mm(H, cov)  # (ny, n)
    S2 = [[_add(_dot(HS[i], H[j]), R_y[i][j]) for j in range(ny)] for i in range(ny)]
    HS, S2 = _barrier((HS, S2), start)
    L = _chol_masked_e(S2, obs)
    alpha = forward_entries(L, [jnp.where(obs[i], _sub(r[i], _dot(H[i], mean)), 0.0)
                                for i in range(ny)])
    B = [forward_entries(L, [0.0 if _zero(HS[i][k]) else jnp.where(obs[i], HS[i][k], 0.0)
                             for i in range(ny)])
         for k in range(n)]  # B[k] = L^-1 (H cov)[:, k]
    post = [_add(mean[k], _dot(B[k], alpha)) for k in range(n)]
    C = [[_sub(cov[k][j], _dot(B[k], B[j])) for j in range(n)] for k in range(n)]
    return post, [[0.5 * _add(C[i][j], C[j][i]) for j in range(n)] for i in range(n)]


def _kf_joint_e(lin, P, w, y, obs, b_y, R_y, Qz, D, start=None):
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
    PhiP = _mm(Phi, P)
    Cp = [[_add(_dot(PhiP[i], Phi[j]), Qz[i - nxs][j - nxs] if (i >= nxs and j >= nxs) else 0.0)
           for j in range(n)] for i in range(n)]
    ny = len(y)
    H = [list(lin.Cx[i]) + list(lin.Cz[i]) for i in range(ny)]
    o = [jnp.where(obs[i], _sub(_sub(y[i] - lin.yb[i], _mul(D[i], w)), b_y[i]), 0.0)
         for i in range(ny)]
    Cp, o = _barrier((Cp, o), start)
    post, C = _update_e([0.0] * n, Cp, H, o, R_y, obs, start)
    return post, C, o


def _niw_predict(gamma, nu, lam_w, lam_e, forgetting):
    """Eq. 20: exponential forgetting of the statistics (mu_hat unchanged)."""
    return gamma / forgetting, forgetting * nu, forgetting * lam_w, forgetting * lam_e


def _niw_update(gamma, nu, mu, lam_w, lam_e, eta, extra_e=None):
    """Eq. 18 for one datum v with eta = v - mu: returns (gamma, nu, mu, lam_w, lam_e).

    Arrays with any trailing (particle) axes: eta, mu (d, ...), lam_w (...), lam_e
    (d - 1, d - 1, ...). Only the (w, w) and (e, e) blocks of Lambda are kept (eq. 21).
    ``extra_e`` is added to Lambda_e: the expected-statistic term for uncertain or missing
    sensor data.
    """
    g_post = gamma / (1.0 + gamma)
    s = 1.0 / (1.0 + gamma)
    ee = eta[1:]
    lam_e = lam_e + s * (ee[:, None] * ee[None, :])
    if extra_e is not None:
        lam_e = lam_e + extra_e
    return g_post, nu + 1.0, mu + g_post * eta, lam_w + s * eta[0] ** 2, lam_e


def _wilson_hilferty(z, dof):
    """chi^2_dof / dof from a standard normal z (Wilson-Hilferty cube, base floored at 0.1)."""
    c = 2.0 / (9.0 * dof)
    base = jnp.maximum(1.0 - c + z * jnp.sqrt(c), 0.1)
    return base * base * base


class _Lin(NamedTuple):
    """The model at one particle, to first order (exact for affine models).

    xb, zb, yb: x_t, z_t and y_t for w = 0 and z_{t-1} = its Kalman mean.
    g, gz: d x_t / d w, d z_t / d w.  Ab, A: d x_t / d z_{t-1}, d z_t / d z_{t-1}.
    Fx, Fzx: d x_t / d x_{t-1}, d z_t / d x_{t-1} (used with Gaussian particle states only).
    Cx, Cz, d: d y / d x, d y / d z at (xb, zb), and d y / d w directly (eq. 8's d).
    """

    xb: jnp.ndarray
    zb: jnp.ndarray
    yb: jnp.ndarray
    g: jnp.ndarray
    gz: jnp.ndarray
    Ab: jnp.ndarray
    A: jnp.ndarray
    Cx: jnp.ndarray
    Cz: jnp.ndarray
    d: jnp.ndarray
    Fx: jnp.ndarray
    Fzx: jnp.ndarray


def _linearise(f, h, x, m, u, theta, nl, li, i_in):
    """:class:`_Lin` of the model (f, h) at sampled states x, bank mean m, input u (one point).

    ``nl``, ``li``: indices of the sampled and linear states in the model's state vector;
    ``i_in``: index of the noisy input. Forward mode (``jax.linearize``), 1 + n_z directions
    through f and n_x + 1 through h.
    """
    nx = len(nl) + len(li)
    nz = len(li)
    inv = np.argsort(np.concatenate([nl, li]).astype(int))

    nxs = len(nl)

    def trans(p):  # p = (w, z deviation, x deviation)
        X = jnp.concatenate([x + p[1 + nz:], m + p[1:1 + nz]])[inv]
        return f(X, u.at[i_in].add(p[0]), theta)

    def obs(p):
        return h(p[:nx], u.at[i_in].add(p[nx]), theta)

    # jax.linearize and one tangent per direction rather than jacfwd: no inner vmap, so under
    # the filter's vmap over particles every derivative stays one vector over the particles
    # (directions whose derivatives are not used are compiled away)
    Xn, f_lin = jax.linearize(trans, jnp.zeros(1 + nz + nxs, x.dtype))
    eye = np.eye(1 + nz + nxs)
    J = jnp.stack([f_lin(jnp.asarray(eye[k], x.dtype)) for k in range(1 + nz + nxs)], axis=1)
    yb, h_lin = jax.linearize(obs, jnp.concatenate([Xn, jnp.zeros(1, x.dtype)]))
    eye = np.eye(nx + 1)
    JH = jnp.stack([h_lin(jnp.asarray(eye[k], x.dtype)) for k in range(nx + 1)], axis=1)
    zs, xs = slice(1, 1 + nz), slice(1 + nz, None)
    return _Lin(Xn[nl], Xn[li], yb, J[nl, 0], J[li, 0], J[nl, zs], J[li, zs], JH[:, nl],
                JH[:, li], JH[:, nx], J[nl, xs], J[li, xs])


def _lin_entries(lin):
    return _Lin(*(_ent(a) for a in lin))


def _entry_kinds(f, h, theta, nl, li, i_in, n_u, rows):
    """:class:`_Lin` of nested lists saying how each entry of the linearisation varies, found
    from the traced model (:func:`vehjax._hoist.dependence`); ``rows``: the output rows the
    filter uses. An entry is

    * a Python float: the same number at every particle, bank mean and input (a structural
      constant: the step's algebra skips zeros and ones and folds the rest);
    * ``"step"``: a function of the input alone, the same for every particle: computed once per
      step at one point and broadcast;
    * None: it depends on the particle (its sampled states or its bank mean).

    For SingleTrackBank 36 of the 60 Jacobian entries are constants (gz, A, most of Cx, Cz and
    d) and the other 24 depend on the speed only (the model is affine in (vy, r), the bank and
    the steering at a given speed): per particle only x_t, z_t and y_t at w = 0 remain."""
    probe = (jnp.zeros(len(nl)), jnp.zeros(len(li)), jnp.ones(n_u))

    def lin_one(x, m, u):
        lin = _linearise(f, h, x, m, u, theta, nl, li, i_in)
        return lin._replace(yb=lin.yb[rows], Cx=lin.Cx[rows], Cz=lin.Cz[rows], d=lin.d[rows])

    dep = _hoist.dependence(lin_one, probe)
    dep_particle = _hoist.dependence(lambda x, m: lin_one(x, m, probe[2]), probe[:2])
    val = _hoist.evaluate(lin_one, probe)

    def kinds(d, dp, v):
        if d.ndim == 2:
            return [kinds(di, dpi, vi) for di, dpi, vi in zip(d, dp, v)]
        return [None if dpi else ("step" if di else float(vi))
                for di, dpi, vi in zip(d, dp, np.asarray(v))]

    return _Lin(*(kinds(np.asarray(d), np.asarray(dp), v)
                  for d, dp, v in zip(dep, dep_particle, val)))


def _merge_entries(per_particle, per_step, kinds):
    """Entries of the linearisation: the constants of ``kinds`` (:func:`_entry_kinds`), the
    entries of ``per_step`` (one point) where the kind is "step", those of ``per_particle``
    elsewhere (all nested lists)."""
    def put(e, s, k):
        if isinstance(k, list):
            return [put(ei, si, ki) for ei, si, ki in zip(e, s, k)]
        return e if k is None else (s if k == "step" else k)
    return _Lin(*(put(e, s, k) for e, s, k in zip(per_particle, per_step, kinds)))


# -- the same on arrays, for the tests ----------------------------------------------------------


def _student_t_logpdf(x, loc, scale, df, observed=None):
    """log St(x; loc, scale, df) of a multivariate Student-t (scipy's ``multivariate_t``), over
    the ``observed`` components only (all when None): the marginal of a t is a t with the same
    dof and the sub-block of the scale."""
    x, loc, scale = jnp.asarray(x), jnp.asarray(loc), jnp.asarray(scale)
    n = x.shape[0]
    obs = jnp.ones(n, bool) if observed is None else jnp.asarray(observed)
    ob = [obs[i] for i in range(n)]
    L = _chol_masked_e(_ent(scale), ob)
    alpha = forward_entries(L, [jnp.where(ob[i], x[i] - loc[i], 0.0) for i in range(n)])
    n_obs = jnp.sum(obs).astype(x.dtype)
    return _st_logpdf_e(alpha, L, jnp.asarray(df, x.dtype), n_obs)


def _impute(eta, sig, obs):
    """:func:`_impute_e` on arrays: (eta (n,), V (n, n))."""
    n = eta.shape[0]
    full, V = _impute_e(_ent(eta), _ent(sig), [obs[i] for i in range(n)])
    return _arr(full, eta[0]), _arr(V, eta[0])


def _kf_step(lin, m, P, dx, y, obs, mu_w, b_y, sig_w2, R_y, Qz):
    """:func:`_kf_e` on arrays for one particle: (z_t mean, z_t covariance); ``lin`` from
    :func:`_linearise` at (x_{t-1}, m, u_t), dx = x_t - lin.xb."""
    n = y.shape[0]
    s3, P3, _, _ = _kf_e(_lin_entries(lin), _ent(P), _ent(dx), _ent(y), [obs[i] for i in range(n)],
                         mu_w, _ent(b_y), sig_w2, _ent(R_y), _ent(Qz))
    like = m[0]
    z = lin.zb + lin.gz * mu_w + _arr(s3, like)
    return z, _arr(P3, like)


# ---------------------------------------------------------------------------------------------
# validation


def _std_value(name, value):
    try:
        v = float(value)
    except (TypeError, ValueError):
        v = float("nan")
    if isinstance(value, (bool, np.bool_)) or not np.isfinite(v) or v <= 0.0:
        raise ValueError(f"{name}: expected a positive, finite standard deviation, got {value!r}")
    return v


def _std_dict(arg, value, required, allowed, unit_hint):
    if not isinstance(value, dict):
        raise ValueError(f"{arg}: expected a dict name -> std, got {value!r}")
    unknown = [k for k in value if k not in allowed]
    if unknown:
        raise ValueError(f"{arg}: unknown name(s) {unknown}; expected names from {tuple(allowed)}")
    missing = [k for k in required if k not in value]
    if missing:
        raise ValueError(f"{arg}: missing initial std for {missing} ({unit_hint})")
    return {k: _std_value(f"{arg}[{k!r}]", v) for k, v in value.items()}


def _affine_deviation(model, states, seed=0, n_points=4):
    """Largest relative deviation of transition and observe from an affine map in the given
    ``states`` over a few random points, extrapolating to 2.5 between two of them; None when no
    point gave finite values. All points in one jitted, vmapped evaluation."""
    rng = np.random.default_rng(seed)
    nx, nu = len(model.state_names), len(model.input_names)
    theta = jnp.asarray(model.theta, float)
    k = len(states)
    a = 2.5
    X = np.repeat(rng.normal(0.0, 0.1, (n_points, 1, nx)), 3, axis=1)
    U = np.repeat(1.0 + 0.1 * rng.normal(size=(n_points, 1, nu)), 3, axis=1)
    z1, z2 = rng.normal(0.0, 0.5, (n_points, k)), rng.normal(0.0, 0.5, (n_points, k))
    Z = np.stack([z1, z2, a * z1 + (1 - a) * z2], axis=1)  # (n_points, 3, k)
    X[:, :, states] = Z

    def both(x, u):
        return jnp.concatenate([jnp.ravel(model.transition(x, u, theta)),
                                jnp.ravel(model.observe(x, u, theta))])

    P = np.asarray(jax.jit(jax.vmap(both))(X.reshape(-1, nx), U.reshape(-1, nu)))
    P = P.reshape(n_points, 3, -1)
    ok = np.all(np.isfinite(P), axis=(1, 2))
    if not ok.any():
        return None
    p1, p2, p3 = P[ok, 0], P[ok, 1], P[ok, 2]
    err = np.abs(p3 - (a * p1 + (1 - a) * p2))
    return float(np.max(err / (1.0 + np.abs(p1) + np.abs(p2) + np.abs(p3))))


def _check_affine(model, li):
    """Raise ValueError naming ``linear_states`` unless transition and observe are affine in
    the linear states at a few random points."""
    if len(li) == 0:
        return
    dev = _affine_deviation(model, li)
    if dev is None:
        raise ValueError(
            "linear_states: could not check that the model is affine in them (transition and "
            "observe gave no finite values at the test points)"
        )
    if dev > 1e-6:
        names = tuple(model.state_names[i] for i in li)
        raise ValueError(
            f"linear_states: the model is not affine in {names} (transition or observe "
            f"deviates by {dev:.3g} relative from an affine map); only states that enter "
            f"linearly can be Rao-Blackwellised"
        )


# ---------------------------------------------------------------------------------------------
# the filter


def marginalized_pf(
    model,
    n_particles: int = 500,
    *,
    noisy_input: str = "delta",
    sensors=("ay", "r", "roll_rate"),
    known_std=None,
    linear_states=("phi", "phi_dot", "phi_ddot"),
    linear_noise_std=None,
    std0=None,
    mean0=None,
    forgetting: float = 0.995,
    gamma0: float = 1.0,
    nu0: float | None = None,
    ess_threshold: float = 0.5,
    resampling: str = "systematic",
    kalman_states: str = "linear",
) -> Estimator:
    """Noise-adaptive marginalized particle filter (Berntorp & Di Cairano 2018): the state, an
    unknown-mean unknown-variance input error and the biases and covariance of some sensors,
    with the affine substate in a Kalman filter per particle (see the module docstring).

    Args:
        model: a vehjax model, e.g. :class:`~vehjax.models.bank.SingleTrackBank`.
        n_particles: N >= 2.
        noisy_input: the input whose error w ~ N(mu_w, sigma_w^2) is learnt (eq. 4-5), in
            ``model.input_names``.
        sensors: outputs with noise N(b, R) of unknown bias and covariance (eq. 7-8), at least
            one, in ``model.output_names``.
        known_std: dict output -> std of zero-mean Gaussian noise known a priori (phi_m and the
            virtual yaw rate of eq. 10); outputs in neither are not used.
        linear_states: states entering transition and observe affinely (checked), estimated by
            a Kalman filter per particle (eq. 3, sec. 3.4); () for the planar filter. States
            that are neither linear states nor driven by ``noisy_input`` are particles without
            process noise: each particle keeps the value it drew from P0 (or its consequence).
            For the planar filter on a model with bank states (SingleTrackBank) give those
            states a negligible variance in P0 (e.g. 1e-20): with a 1e-3 rad/s^2 spread on
            phi_ddot each particle's bank grows by 1.8 rad a minute and the offset and ay bias
            drift to explain it.
        linear_noise_std: their process noise: for a model with ``bank_noise_gain()`` a scalar
            sigma_phi of eq. 3 [rad/s^3] (Q = sigma^2 B B^T on the linear states); otherwise,
            or given as one value per linear state, additive stds per step (Q diagonal).
            Required when there are linear states; >= 0.
        std0: dict of initial guesses of every unknown std: ``noisy_input`` and each sensor, in
            the input's and outputs' units (the paper uses about twice the true values).
        mean0: dict of initial offset / bias guesses, same keys (missing ones 0); default zeros.
        forgetting: lambda of eq. 20 in (0, 1]; lambda min(nu0, 1 / (1 - lambda)) must exceed
            d + 1 (d = 1 + len(sensors)) so that the Student-t stays of finite variance.
        gamma0: initial gamma (1 / kappa) > 0: the prior covariance of the offset and the biases
            is gamma0 times the noise covariance, so 1 says "the offset may be as large as the
            noise std".
        nu0: initial degrees of freedom, > d + 1; default d + 4 (a light prior, about three
            samples' worth of std0).
        ess_threshold: resample when ESS < ess_threshold * N, in [0, 1].
        resampling: "systematic", "stratified", "multinomial" or "residual".
        kalman_states: what each particle's Kalman filter covers. "linear" (the paper's
            Algorithm 1): the linear states; a particle's other states are a point, x_t built
            by eq. 6 from the bank's Kalman mean. "all": every state; a particle is a sequence
            of offset draws and carries the Gaussian of all states given them, so the bank's
            uncertainty reaches vy and r (with known noise statistics this is exact for models
            affine in the states: it matches the exact Kalman filter, where "linear" reports
            vy's variance about 8 % too small on SingleTrackBank; module docstring). 1.2-1.3x
            the time per step. No difference without linear states.

    Returns:
        ``Estimator`` (``needs_key=True``), ``nx`` = all model states, ``param_names`` =
        ``<noisy_input>_offset, <noisy_input>_std, <sensor>_bias..., <sensor>_std...`` in SI
        units. ``init(x0, P0, theta0=None, P_theta0=None, key)``: x0 (nx,), P0 over all model
        states (the bank's Kalman filters start from the Gaussian conditional of the linear
        states given each particle); ``theta0``, when given, replaces the guesses (offset, std,
        biases, stds) of ``mean0``/``std0`` (``P_theta0`` is ignored). ``step(state, y, u)``:
        StepOutput ``mean``/``cov`` the weighted mean and covariance over all model states
        (linear states from the mixture of the Kalman filters), ``params`` eq. 23's estimates,
        ``params_cov`` their mixture covariance, ``loglik`` log p(y_t | y_1:t-1) of the used
        components, ``nis`` and ``n_obs`` over them, ``reinit`` when every weight underflowed
        (the weights are then reset to equal, the particles kept).

    Raises:
        ValueError: naming the argument: unknown input, sensor, known-std output or state
            names, a name in both ``sensors`` and ``known_std``, a model not affine in the linear
            states, non-positive stds (negative ``linear_noise_std``), lambda outside (0, 1] or
            too small for nu0, gamma0 <= 0, nu0 <= d + 1, n_particles < 2, a bad resampling
            scheme, ess_threshold or kalman_states.
    """
    _validate.model(model)
    n = smc.check_n_particles(n_particles, low=2)
    scheme = _rs.check_scheme(resampling)
    thr = smc.check_ess_threshold(ess_threshold)
    state_names = tuple(model.state_names)
    input_names = tuple(model.input_names)
    output_names = tuple(model.output_names)
    if not isinstance(noisy_input, str) or noisy_input not in input_names:
        raise ValueError(f"noisy_input: expected one of the model's inputs {input_names}, got "
                         f"{noisy_input!r}")
    i_in = input_names.index(noisy_input)
    sensors = _validate.names("sensors", sensors, output_names)
    known = {} if known_std is None else _std_dict("known_std", known_std, (), output_names,
                                                  "output units")
    both = [k for k in known if k in sensors]
    if both:
        raise ValueError(f"known_std: {both} are also in sensors (unknown noise); name each "
                         f"output once")
    linear_states = _validate.names("linear_states", linear_states, state_names,
                                    allow_empty=True)
    li = np.array([state_names.index(s) for s in linear_states], dtype=int)
    nl = np.array([i for i in range(len(state_names)) if i not in set(li.tolist())], dtype=int)
    if len(nl) == 0:
        raise ValueError("linear_states: at least one state must remain a particle state")
    nz, nxs, nx = len(li), len(nl), len(state_names)
    ny, ns = len(output_names), len(sensors)
    d = 1 + ns

    # process noise of the linear states
    if nz:
        if linear_noise_std is None:
            raise ValueError(f"linear_noise_std: required with linear_states {linear_states} "
                             f"(sigma_phi of eq. 3)")
        try:
            sig = np.asarray(linear_noise_std, dtype=float)
        except (TypeError, ValueError):
            sig = np.array(np.nan)
        if isinstance(linear_noise_std, (bool, np.bool_)):
            sig = np.array(np.nan)
        if sig.ndim == 0 and np.isfinite(sig) and sig >= 0 and hasattr(model, "bank_noise_gain"):
            B = np.asarray(model.bank_noise_gain(), dtype=float)[li]
            Qz = float(sig) ** 2 * np.outer(B, B)
        elif sig.shape in ((), (nz,)) and np.all(np.isfinite(sig)) and np.all(sig >= 0):
            Qz = np.diag(np.broadcast_to(sig, (nz,)) ** 2)
        else:
            raise ValueError(f"linear_noise_std: expected a std >= 0 or {nz} of them, got "
                             f"{linear_noise_std!r}")
    else:
        Qz = np.zeros((0, 0))

    unknown_names = (noisy_input,) + sensors
    std0 = _std_dict("std0", {} if std0 is None else std0, unknown_names, unknown_names,
                     "input and output units")
    mean0 = _validate.keyed("mean0", mean0, unknown_names)
    mean0v = []
    for k in unknown_names:
        try:
            v = float(mean0.get(k, 0.0))
        except (TypeError, ValueError):
            v = float("nan")
        if not np.isfinite(v):
            raise ValueError(f"mean0[{k!r}]: expected a finite number, got {mean0.get(k)!r}")
        mean0v.append(v)
    lam = _validate.number("forgetting", forgetting, 0.0, 1.0, high_open=False)
    g0 = _validate.number("gamma0", gamma0, 0.0, np.inf)
    nu0 = float(d + 4) if nu0 is None else _validate.number("nu0", nu0, d + 1.0, np.inf)
    nu_low = nu0 if lam == 1.0 else min(nu0, 1.0 / (1.0 - lam))
    if not lam * nu_low > d + 1:
        raise ValueError(
            f"forgetting: lambda = {lam} with nu0 = {nu0} lets the degrees of freedom fall to "
            f"{lam * nu_low:.3g} <= d + 1 = {d + 1}, where the Student-t has no variance; use "
            f"lambda > {(d + 1) / (d + 2):.4g} (and nu0 > {(d + 1) / lam:.4g})"
        )
    if kalman_states not in ("linear", "all"):
        raise ValueError(f"kalman_states: expected 'linear' or 'all', got {kalman_states!r}")
    gauss = kalman_states == "all" and nz > 0
    nk = nx if gauss else nz  # dimension of each particle's Kalman filter
    _check_affine(model, li)

    # constants
    s_rows = np.array([output_names.index(s) for s in sensors], dtype=int)
    kv = np.zeros(ny)
    for k, v in known.items():
        kv[output_names.index(k)] = v * v
    used = np.zeros(ny, bool)
    used[s_rows] = True
    used[[output_names.index(k) for k in known]] = True
    param_names = (f"{noisy_input}_offset", f"{noisy_input}_std") + tuple(
        f"{s}_bias" for s in sensors) + tuple(f"{s}_std" for s in sensors)
    p = len(param_names)
    std0v = np.array([std0[k] for k in unknown_names])
    theta_prior = np.concatenate([[mean0v[0], std0v[0]], mean0v[1:], std0v[1:]])
    iw_var = 1.0 / (2.0 * max(nu0 - d - 3.0, 1.0))  # Var(sigma) / sigma^2 by the delta method
    P_prior = np.diag(np.concatenate([[g0 * std0v[0] ** 2, iw_var * std0v[0] ** 2],
                                      g0 * std0v[1:] ** 2, iw_var * std0v[1:] ** 2]))
    log_n = math.log(n)
    mth = jnp.asarray(model.theta)
    inv = np.argsort(np.concatenate([nl, li]).astype(int))

    def f(X, u, th):
        return jnp.asarray(model.transition(X, u, th)).astype(X.dtype)

    def h(X, u, th):
        return jnp.asarray(model.observe(X, u, th)).astype(X.dtype)

    def init(x0, P0, theta0=None, P_theta0=None, key=None):
        del P_theta0
        if key is None:
            raise ValueError("key: marginalized_pf draws its particles at random; pass a PRNG key")
        _validate.prior(nx, x0, P0)
        x0, P0 = jnp.asarray(x0), jnp.asarray(P0)
        dtype = jnp.result_type(x0.dtype, P0.dtype)
        if not jnp.issubdtype(dtype, jnp.floating):
            dtype = jnp.asarray(0.0).dtype
        x0 = x0.astype(dtype)
        P0 = (jnp.diag(P0) if P0.ndim == 1 else P0).astype(dtype)
        if theta0 is None:
            th = jnp.asarray(theta_prior, dtype)
        else:
            if np.shape(theta0) != (p,):
                raise ValueError(f"theta0: expected shape ({p},) for {param_names}, got "
                                 f"{np.shape(theta0)}")
            th = jnp.asarray(theta0).astype(dtype)
        mu0 = jnp.concatenate([th[:1], th[2:2 + ns]])
        sd0 = jnp.concatenate([th[1:2], th[2 + ns:]])
        k_init, k_run = jax.random.split(key)
        Pxx = P0[np.ix_(nl, nl)]
        Lx = jnp.linalg.cholesky(Pxx)
        xs = x0[nl][:, None] + Lx @ jax.random.normal(k_init, (nxs, n), dtype)
        if nz:
            Pzx = P0[np.ix_(li, nl)]
            G = jax.scipy.linalg.cho_solve((Lx, True), Pzx.T).T  # P_zx P_xx^-1
            zs = x0[li][:, None] + G @ (xs - x0[nl][:, None])
            Pz = P0[np.ix_(li, li)] - G @ Pzx.T
            Pz = 0.5 * (Pz + Pz.T)
        else:
            zs = jnp.zeros((0, n), dtype)
            Pz = jnp.zeros((0, 0), dtype)
        scale = nu0 - d - 1.0
        # with Gaussian particle states: zero covariance of the drawn states, the bank's after
        Pk = jnp.zeros((nk, nk), dtype).at[nk - nz:, nk - nz:].set(Pz)
        return MPFState(
            x=xs,
            z=zs,
            P=jnp.broadcast_to(Pk[:, :, None], (nk, nk, n)),
            mu=jnp.broadcast_to(mu0[:, None], (d, n)),
            lam_w=jnp.full((n,), scale, dtype) * sd0[0] ** 2,
            lam_e=jnp.broadcast_to((scale * jnp.diag(sd0[1:] ** 2))[:, :, None], (ns, ns, n)),
            gamma=jnp.asarray(g0, dtype),
            nu=jnp.asarray(nu0, dtype),
            log_weights=jnp.full((n,), -log_n, dtype),
            weights=jnp.full((n,), 1.0 / n, dtype),
            key=smc.raw_key(k_run),
            ess=jnp.asarray(float(n), dtype),
            flag_diverged=jnp.asarray(False),
            n_reinit=jnp.asarray(0, jnp.int32),
        )

    # rows of y the filter uses (sensors and known-std outputs, model order); sensor j's row
    u_idx = np.flatnonzero(used)
    nyu = len(u_idx)
    srow = [int(np.flatnonzero(u_idx == r)[0]) for r in s_rows]
    spos = {r: j for j, r in enumerate(srow)}  # used row -> sensor index
    kvu = [float(kv[r]) for r in u_idx]
    lin_all = jax.vmap(
        lambda x, m, u, theta: _linearise(f, h, x, m, u, theta, nl, li, i_in),
        in_axes=(-1, -1, None, None), out_axes=-1,
    )

    lin_kinds = _entry_kinds(f, h, mth, nl, li, i_in, len(input_names), u_idx)

    def particle_update(x, m, P, mu, lam_w, lam_e, z1, z2, y, obs, u, theta, gam, nu_p):
        """One step for all particles (entries over the last axis) before the weights are
        normalised: the log-likelihood, the draw, the Kalman step and the statistics update.
        The statistics come in predicted (eq. 20). y, obs: (n_yu,) used rows."""
        start = (u[0] != u[0]).astype(jnp.int32)  # 0 unless NaN, the same for every run
        dtype = x.dtype
        def used_rows(lin):
            return _lin_entries(lin._replace(yb=lin.yb[u_idx], Cx=lin.Cx[u_idx],
                                             Cz=lin.Cz[u_idx], d=lin.d[u_idx]))

        lin = used_rows(lin_all(x, m, u, theta))  # entries not used below are compiled away
        lin_step = used_rows(_linearise(f, h, jnp.zeros(nxs, dtype), jnp.zeros(nz, dtype), u,
                                        theta, nl, li, i_in))
        lin = _barrier(_merge_entries(lin, lin_step, lin_kinds), start)
        ye = [y[i] for i in range(nyu)]
        ob = [obs[i] for i in range(nyu)]
        Pe, lee = _ent(P), _ent(lam_e)
        Qe = [[float(Qz[i, j]) if Qz[i, j] == 0.0 else jnp.asarray(Qz[i, j], dtype)
               for j in range(nz)] for i in range(nz)]
        mu_w = mu[0]
        b = [mu[1 + j] for j in range(ns)]
        b_y = [b[spos[i]] if i in spos else 0.0 for i in range(nyu)]
        # predictive of y (eq. 26): w and the sensor noise through the NiW, the rest moment-matched
        D = [_add(_add(_dot(lin.Cx[i], lin.g), lin.d[i]), _dot(lin.Cz[i], lin.gz))
             for i in range(nyu)]
        df = nu_p - d + 1.0
        c = (1.0 + gam) / df
        sw = c * lam_w
        mm = (df - 2.0) / df
        M = [[_add(_dot(lin.Cx[i], [r[j] for r in lin.Ab]), _dot(lin.Cz[i], [r[j] for r in lin.A]))
              for j in range(nz)] for i in range(nyu)]
        if gauss:  # the particle's own states are uncertain too: y sees them through Fx, Fzx
            M = [[_add(_dot(lin.Cx[i], [r[j] for r in lin.Fx]),
                       _dot(lin.Cz[i], [r[j] for r in lin.Fzx])) for j in range(nxs)] + M[i]
                 for i in range(nyu)]
        D, M = _barrier((D, M), start)
        MP = _mm(M, Pe)
        CQ = _mm(lin.Cz, Qe)
        mu_y = [_add(_add(lin.yb[i], _mul(D[i], mu_w)), b_y[i]) for i in range(nyu)]
        S = [[None] * nyu for _ in range(nyu)]
        for i in range(nyu):
            for j in range(i + 1):
                K = _add(_dot(MP[i], M[j]), _dot(CQ[i], lin.Cz[j]))
                if i == j:
                    K = _add(K, kvu[i])
                v = _mul(sw, _mul(D[i], D[j]))
                if i in spos and j in spos:
                    v = _add(v, c * lee[spos[i]][spos[j]])
                S[i][j] = S[j][i] = _add(v, _mul(mm, K)) if not _zero(K) else v
        S, mu_y, D = _barrier((S, mu_y, D), start)
        ll, shift, sc, dfy, eta = _barrier(_t_weight_and_proposal_e(
            ye, ob, mu_y, S, [_mul(sw, v) for v in D], sw, df), start)
        # draw w_t from eq. 30 (Student-t via Wilson-Hilferty) and propagate (eq. 6)
        w = mu_w + shift + jnp.sqrt(sc) * z1 / jnp.sqrt(_wilson_hilferty(z2, dfy))
        dw = w - mu_w
        dx = [_mul(gk, w) for gk in lin.g]
        x_new = [_add(lin.xb[k], dx[k]) for k in range(nxs)]
        w, dw, dx, x_new = _barrier((w, dw, dx, x_new), start)
        # bank Kalman step and the sensor residuals, with the point estimates of eq. 23
        inv_den = 1.0 / (nu_p - d - 1.0)
        sig_w2 = lam_w * inv_den
        R_s = [[lee[i][j] * inv_den for j in range(ns)] for i in range(ns)]
        R_y = [[R_s[spos[i]][spos[j]] if (i in spos and j in spos) else (kvu[i] if i == j else 0.0)
                for j in range(nyu)] for i in range(nyu)]
        if gauss:
            xi, C, o2 = _barrier(_kf_joint_e(lin, Pe, w, ye, ob, b_y, R_y, Qe, D, start), start)
            x_new = [_add(x_new[k], xi[k]) for k in range(nxs)]
            z_new = [_add(_add(lin.zb[i], _mul(lin.gz[i], w)), xi[nxs + i]) for i in range(nz)]
            P3 = C
            Hs = [list(lin.Cx[r]) + list(lin.Cz[r]) for r in srow]
            eta_e = [_sub(o2[r], _dot(Hs[j], xi)) for j, r in enumerate(srow)]
            CP = _mm(Hs, C)
            V = [[_dot(CP[i], Hs[j]) for j in range(ns)] for i in range(ns)]
        elif nz:
            s3, P3, o2, _ = _barrier(_kf_e(lin, Pe, dx, ye, ob, mu_w, b_y, sig_w2, R_y, Qe, start),
                                     start)
            z_new = [_add(_add(lin.zb[i], _mul(lin.gz[i], mu_w)), s3[i]) for i in range(nz)]
            eta_e = [_sub(_sub(o2[r], _dot(lin.Cz[r], s3)), _mul(lin.d[r], dw)) for r in srow]
            CP = _mm([lin.Cz[r] for r in srow], P3)
            V = [[_dot(CP[i], lin.Cz[srow[j]]) for j in range(ns)] for i in range(ns)]
        else:
            z_new, P3 = [], []
            # o2 = y - yb - Cx dx - d mu_w - b_y = eta - Cx g (w - mu_w)
            eta_e = [_sub(_sub(eta[r], _mul(_dot(lin.Cx[r], lin.g), dw)), _mul(lin.d[r], dw))
                     for r in srow]
            V = [[0.0] * ns for _ in range(ns)]
        eta_e, V = _barrier((eta_e, V), start)
        ob_e = [ob[r] for r in srow]
        V = [[jnp.where(ob_e[i] & ob_e[j], V[i][j], 0.0) for j in range(ns)] for i in range(ns)]
        eta_e, V_miss = _barrier(_impute_e(eta_e, R_s, ob_e), start)
        like = x[0]
        eta_v = _arr([dw] + eta_e, like)
        extra = _arr([[_add(V[i][j], V_miss[i][j]) for j in range(ns)] for i in range(ns)], like)
        _, _, mu_new, lw_new, le_new = _niw_update(gam, nu_p, mu, lam_w, lam_e, eta_v, extra)
        x_new = _arr(x_new, like)
        z_new = _arr(z_new, like) if nz else m
        P_new = _arr(P3, like) if nz else P
        bad = ~(jnp.isfinite(ll) & jnp.all(jnp.isfinite(x_new), 0) & jnp.all(jnp.isfinite(z_new), 0)
                & jnp.all(jnp.isfinite(P_new), (0, 1)) & jnp.all(jnp.isfinite(mu_new), 0)
                & jnp.isfinite(lw_new) & jnp.all(jnp.isfinite(le_new), (0, 1)))
        ll = jnp.where(bad, -jnp.inf, ll)
        keep = lambda new, old: jnp.where(bad, old, new)  # noqa: E731
        cov_y = _arr(S, like) * (df / (df - 2.0))
        return (ll, keep(x_new, x), keep(z_new, m), keep(P_new, P), keep(mu_new, mu),
                keep(lw_new, lam_w), keep(le_new, lam_e), _arr(mu_y, like), cov_y)

    def estimates(w, mu, lam_w, lam_e, nu, gamma):
        """Eq. 23 and the mixture covariance of the parameter estimates."""
        dtype = w.dtype
        den = nu - d - 1.0
        sw2 = lam_w / den  # (N,)
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
        diag_lam = jnp.concatenate([lam_w[None], jnp.diagonal(lam_e, axis1=0, axis2=1).T])
        Lfull = jnp.zeros((d, d, lam_w.shape[0]), dtype).at[0, 0].set(lam_w).at[1:, 1:].set(lam_e)
        cov_diag = (2.0 * diag_lam[:, None, :] * diag_lam[None, :, :]
                    + 2.0 * (nu - pd - 1.0) * Lfull ** 2) / denom  # Cov(Sigma_ii, Sigma_jj)
        sd_i = jnp.concatenate([sd_w_i[None], sd_s_i])
        cov_sd = cov_diag / (4.0 * sd_i[:, None, :] * sd_i[None, :, :])
        cov_mu = gamma * jnp.zeros((d, d, lam_w.shape[0]), dtype).at[0, 0].set(sw2).at[
            1:, 1:].set(se)
        within_mu = jnp.einsum("ijn,n->ij", cov_mu, w)
        within_sd = jnp.einsum("ijn,n->ij", cov_sd, w)
        perm = np.concatenate([[0], np.arange(2, 2 + ns)])  # the mean entries in params order
        perm_sd = np.concatenate([[1], np.arange(2 + ns, 2 + 2 * ns)])
        pc = jnp.zeros((p, p), dtype)
        pc = pc.at[np.ix_(perm, perm)].set(within_mu).at[np.ix_(perm_sd, perm_sd)].set(within_sd)
        pc = pc + spread
        return params, 0.5 * (pc + pc.T)

    def step(state: MPFState, y, u):
        dtype = state.x.dtype
        y, u = jnp.asarray(y).astype(dtype), jnp.asarray(u).astype(dtype)
        theta = mth.astype(dtype)
        yu = y[u_idx]
        obs = ~jnp.isnan(yu)
        y0 = jnp.where(obs, yu, 0.0)
        n_obs = jnp.sum(obs, dtype=jnp.int32)
        gam_p, nu_p, lw_p, le_p = _niw_predict(state.gamma, state.nu, state.lam_w, state.lam_e,
                                                lam)
        key_next, key_step = smc.split(state.key)
        zn = _barrier(smc.normals(key_step, 2, n, dtype), (u[0] != u[0]).astype(jnp.int32))
        ll, x, z, P, mu, lam_w, lam_e, mu_y, cov_y = particle_update(
            state.x, state.z, state.P, state.mu, lw_p, le_p, zn[0], zn[1],
            y0, obs, u, theta, gam_p, nu_p)
        gamma = gam_p / (1.0 + gam_p)
        nu = nu_p + 1.0
        rw = smc.reweight(state.log_weights, ll)
        under = rw.underflow
        w_now = jnp.where(under, 1.0 / n, rw.w)
        lw_now = jnp.where(under, -log_n, rw.log_w)

        # estimates over all model states: particles and the mixture of the Kalman filters
        Xp = jnp.concatenate([x, z])  # sampled then linear states
        mean_p, cov_p = smc.moments(w_now, Xp)
        if nz:
            cov_p = cov_p.at[nx - nk:, nx - nk:].add(jnp.einsum("ijn,n->ij", P, w_now))
        jitter = jnp.sqrt(jnp.finfo(dtype).eps) * jnp.diagonal(cov_p) + jnp.sqrt(
            jnp.finfo(dtype).tiny)
        cov_p = cov_p + jnp.diag(jitter)
        mean = mean_p[inv]
        cov = cov_p[np.ix_(inv, inv)]
        params, params_cov = estimates(w_now, mu, lam_w, lam_e, nu, gamma)

        # NIS of the mixture predictive (prior weights)
        wp = state.weights
        ybar = mu_y @ wp
        dyb = mu_y - ybar[:, None]
        Sy = jnp.einsum("ijn,n->ij", cov_y, wp) + (dyb * wp) @ dyb.T
        Ly = cholesky(_masked(Sy, obs))
        a = solve_lower(Ly, jnp.where(obs, y0 - ybar, 0.0))
        nis = jnp.sum(a * a)

        # resample for the next step
        u_res = smc.uniforms(key_step, scheme, n, dtype, stream=1)
        parts = (x, mu, lam_w, lam_e) + ((z, P) if nz else ())  # no empty leaves
        parts, lw_next, w_next, _ = smc.resample(parts, w_now, lw_now, u_res, scheme, thr)
        x, mu, lam_w, lam_e = parts[:4]
        if nz:
            z, P = parts[4:]
        new_state = MPFState(
            x=x, z=z, P=P, mu=mu, lam_w=lam_w, lam_e=lam_e, gamma=gamma, nu=nu,
            log_weights=lw_next, weights=w_next, key=key_next,
            ess=jnp.where(under, 0.0, smc.ess(w_now)),
            flag_diverged=state.flag_diverged | under,
            n_reinit=state.n_reinit + under.astype(jnp.int32),
        )
        out = StepOutput(
            mean=mean,
            cov=cov,
            loglik=smc.step_loglik(rw),
            nis=nis,
            n_obs=n_obs,
            params=params,
            params_cov=params_cov,
            reinit=under,
        )
        return new_state, out

    return Estimator(
        init=init, step=step, nx=nx, param_names=param_names, name="marginalized_pf",
        needs_key=True, param_prior=(theta_prior, P_prior), ny=ny, nu=len(input_names),
        workload="small_dense",
    )
