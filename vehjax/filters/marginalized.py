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
  with y_t (:func:`vehjax.filters._mpf_kalman.joint_kalman_step`); the statistics updated
  with w_t and the sensor residual at
  the posterior mean, its covariance H P H^T added as above. No vehicle-model measurement is
  needed: w_t is known to the particle. Without linear states it is the planar filter
  unchanged. On the same data: NEES in band 0.943, per state 1.00 / 1.01 on vy / r, variances
  within 0.3 % of the exact filter's, means within 0.05 of its std. It costs more per step
  than "linear": each particle carries the covariance of every state, not only the bank's.
* Eq. 23b as printed mixes the particles' covariance estimates with the spread of their means:
  R_hat = sum_i q_i (Lambda_e^i / (nu - d - 1) + (b^i - b_hat)(b^i - b_hat)^T), likewise
  sigma_w^2; the reported stds are the square roots of the diagonal. ``params_cov`` is the
  mixture of the per-particle posterior covariances of (mu_w, sigma_w, b, sigma_s): gamma Sigma_hat
  for the means (NiW), the inverse-Wishart covariance of the diagonal of Sigma (Press 1982)
  taken to the stds by the delta method (d sigma = d Sigma / (2 sigma)), with nu - d - 3
  floored at 1 where that variance does not exist, plus the spread of the particles' values
  about the reported estimate.
* ``noise_means="kalman"`` (not the paper's; issue #33 item 2). The paper's filter says it
  knows the noise statistics better than it does when it learns them (``vehjax reproduce
  consistency``, 100 runs: NEES in the band on 0.17 of the steps with ``kalman_states="all"``,
  the roll-rate bias's spread over runs twice its reported std; ``vehjax reproduce
  noise-learning`` on paper 004's simulation: the NEES of (vy, r) about 4 per dof). Three
  causes, three changes (:func:`_kalman_means_update`):
  (1) the particle's Kalman filter takes the NiW means as exact, and eq. 18 takes each
  residual as an exact observation of them, though the data tell some of them apart only
  slowly (the roll-rate bias from the bank rate; the ay bias from the steering offset, which
  ay sees as d mu_w): the steering offset and the sensor biases become constant states of each
  particle's Kalman filter (exact Gaussian posterior, correlated with the states and with each
  other; the model augmented by :func:`vehjax.models.with_output_biases` and
  :func:`vehjax.models.with_input_offset`), so the statistics are an inverse-Wishart of known
  zero mean over the covariances alone (``means_known`` in :func:`vehjax.filters._niw.
  niw_update`);
  (2) with the offset a state, the input error w_t = the zero-mean steering noise is Gaussian
  given the covariances, so it is not drawn: each particle's Kalman step takes it as process
  noise through (g, gz) and conditions the joint of (x_t, z_t, w_t) on y_t
  (:func:`vehjax.filters._mpf_kalman.input_noise_kalman_step`), and the statistics take the
  expected data: the posterior mean of w_t with its variance added to Lambda_w, the sensor
  residuals at the posterior mean with H C H^T added to Lambda_e. Drawn offsets made each
  particle's statistics those of its own path, which resampling shares among few particles;
  (3) what differs between the particles is then the steering noise's variance: each
  particle carries its own static sigma_w^2 on a fixed grid, log-uniform, runs its Kalman
  step with it and is weighted by that step's Gaussian predictive of y_t; the grid is never
  resampled, so the weights are the posterior over the grid (each particle is a Kalman filter
  given its sigma_w^2: a multiple-model filter over it);
  (4) the prior over that grid is Jeffreys' by default (``input_std_prior``,
  :mod:`vehjax.filters._jeffreys`): each point weighted by the square root of the Fisher
  information the data so far carry about sigma_w there. The steering noise reaches the
  sensors beside their own noise, so the likelihood is flat below the true std and steep
  above it (paper 004's simulation, 20 runs x 180 s, everything else known: 0.5x the truth
  costs 2.7 nats per run, 2x costs 33; ``python benchmarks/mpf_consistent_steering.py profile
  20 180``). A prior equal in log sigma_w then leaves mass far below the truth and the
  states' covariance, which scales with sigma_w^2, too small; the inverse-Wishart prior of
  the paper's guess (twice the truth) holds the posterior above it. Jeffreys' prior weighs
  the flat end down by how little the data can say there (its one-parameter coverage is
  right to first order, Welch & Peers 1963). The other two priors stay as options: the
  inverse-Wishart prior's marginal, weighted by it (:func:`vehjax.filters._niw.
  static_prior_grid`), and equal weights over ``input_std_range``;
  (5) the sensor variances are learnt per particle by Fisher scoring of the innovations weighted
  at the guess (``sensor_variances="scored"``, the default;
  :mod:`vehjax.filters._sensor_scoring`), with their sandwich covariance, the sensors' noises
  taken as uncorrelated, in the Kalman step and the report; sigma_w's reported variance gains
  what their plug-in adds (Murphy & Topel's two-step correction, the cross information from the
  ridge the grid points' variances lie on). The first build learnt R from the expected
  statistics (the inverse-Wishart over the residuals, its mean in the Kalman step; kept as
  ``sensor_variances="inverse-wishart"``, 0.6 times the time per step). That mean forgets its
  start as n^-F, F the fraction of a complete observation's information a step carries about a
  variance: about 0.04 for ay on the consistency study's data, where the steering noise reaches
  ay directly beside ay's own (started at twice the truth the ay std stayed +45 % over 300
  steps; scored: +2.0 %), and its ay std's interval held the truth in 0.84-0.89 of the
  consistency study's runs (scored: 0.97-1.00). Why a grid: the data tell sigma_w apart mostly
  through the dynamics (the steering noise moves vy and r, which the sensors see over the
  following steps), which only the predictive likelihood carries; the expected statistic of w_t
  given y_1:t sees only the direct term d w_t in ay, beside ay's own noise, and learns nothing
  that separates them. On paper 004's simulation that statistic (with covariances drawn per
  particle, Storvik's filter, as first built here: ``vehjax reproduce noise-learning`` at
  3108ace) ended at 3.8 times the true steering std; drawing static values and moving them by
  Liu & West's kernel collapsed the cloud (an experiment not kept: commit c9ee043's message).
  Exact, given the sensor covariances, for models affine in the states and the noisy input:
  with R known the weights are the exact posterior over the grid
  (tests/test_mpf_consistent.py, against numpy Kalman likelihoods), and with
  every covariance known it is the Kalman filter of the augmented model. Approximate: R's
  scored variances (filtered, not the whole data's likelihood; or the inverse-Wishart
  statistics, a variational-Bayes style update) and their forgetting, the grid's
  resolution. With forgetting < 1 the inverse-Wishart statistics' own noise (about 200
  steps' worth at lambda = 0.995) makes the predictive favour a larger sigma_w (paper 004's
  simulation, 10 runs x 180 s: +22 % at 0.995, +12 % at 1; ``python benchmarks/
  mpf_consistent_steering.py learn 10 180 25 iw 0.995 inverse-wishart``). The prior of the
  offset and the biases is N(mean0, gamma0 std0^2) as the paper's NiW unless ``mean_std0``
  gives their size: a prior tied to the noise std (0.04 deg for a 0.28 deg offset in paper
  004's simulation) holds the offset state several stds from the truth for long and makes the
  filter over-confident meanwhile. Measured on the consistency study and paper 004's
  simulation: ``vehjax reproduce consistency --filters MPF-K`` and ``vehjax reproduce
  noise-learning`` (their docstrings have the numbers).

Linearisation. The model enters through forward-mode derivatives (``jax.jacfwd``) at each
particle: g = d f / d delta, A_bar = d f_x / d z, the bank transition, C = d h / d (x, z) and
d = d h / d delta. For models affine in the states, the linear states and the noisy input
(:class:`~vehjax.models.bank.SingleTrackBank` at a given speed) every formula is exact; for
others it is first order in the offset and the bank (an EKF-like step inside each particle).
Affinity in the linear states is checked numerically when the filter is built. Which entries
of these derivatives are constants, which depend on the input alone (computed once per step,
not per particle) and which on the particle is read off the traced model when the filter is
built (:func:`vehjax.filters._mpf_linearise.entry_kinds`): for SingleTrackBank only the
predicted x_t, z_t and y_t are per particle.

Implementation. The mathematics is in module-level functions, each documented and tested on
its own: the NiW recursion, the Student-t predictive and weight, the eq. 30 draw, the imputation
and eq. 23's estimates in :mod:`vehjax.filters._niw`; the per-particle Kalman filters in
:mod:`vehjax.filters._mpf_kalman`; the linearisation and which of its entries are constants in
:mod:`vehjax.filters._mpf_linearise`; with ``noise_means="kalman"`` the sensor variances'
scoring in :mod:`vehjax.filters._sensor_scoring`, Jeffreys' prior in
:mod:`vehjax.filters._jeffreys` and the steering std's report where the grid does not resolve
its posterior in :mod:`vehjax.filters._grid`. This module holds the state, the validation
(:func:`_configure`) and the builder that composes them. Particles are last in every leaf. The
per-particle algebra is written entry by entry (every matrix entry one (N,) vector, structural
zeros skipped: :mod:`vehjax.lib.entrywise`, shared with the runs-last Gaussian steps), and
its stages are materialised through a trivial while loop
(:func:`vehjax.lib.entrywise.barrier`) so that XLA does not recompute long elementwise
chains in every consumer; weights, moments and random numbers are the shared particle core
:mod:`vehjax.filters.smc`, and resampling is ``smc.resample`` unless the caller passes another
function (``resample=``). Cholesky factors and triangular solves throughout, no inverses.

Random numbers: two standard-normal rows per step from the particle core (:mod:`smc`), one for
the t draw and one for its chi-square through the Wilson-Hilferty cube (Johnson, Kotz &
Balakrishnan 1994, eq. 18.25; its base floored at 0.1, which only touches dof < 10 beyond 3.4
sigma), and the resampling uniforms.
"""

from __future__ import annotations

import functools
import math
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import validation
from . import _mpf_means
from . import resampling as _rs
from . import smc
from ..lib.entrywise import add, barrier, dot, entries, matmul, mul, stack, sub
from ._mpf_kalman import (bank_kalman_step, input_noise_kalman_step, joint_kalman_step,
                          joint_prediction)
from ._mpf_linearise import entry_kinds, lin_entries, linearise, merge_entries
from ._jeffreys import covariance_information, grid_derivative
from ._jeffreys import log_prior as jeffreys_log_prior
from ._grid import grid_posterior, ridge_covariance, with_resolved_std
from ._sensor_scoring import (plug_in_variance, prior_terms, ridge_sensitivity, scored_variances,
                              scoring_terms, weighted_covariance)
from ._niw import (draw_offset, impute_missing, niw_predict, niw_update,
                   noise_estimates, static_prior_grid, t_predictive,
                   t_weight_and_proposal)
from .base import Estimator, StepOutput
from .sigma import cholesky, solve_lower

__all__ = ["MPFState", "RBTransition", "marginalized_pf"]


class MPFState(NamedTuple):
    """State of :func:`marginalized_pf` for one run; the particle axis N is last.

    Attributes:
        x: (n_x, N) sampled states (the model states not in ``linear_states``, model order);
            with ``kalman_states="all"`` the means of each particle's Gaussian over them.
        z: (n_z, N) Kalman means of the linear states (``linear_states`` order).
        P: (n_z, n_z, N) their covariances; with ``kalman_states="all"`` (n_x + n_z, n_x + n_z,
            N), the covariance of the particle's states and the linear states (that order).
        mu: (d, N) NiW means of v = (w, e): the offset mean, then one bias per sensor.
        lam_w: (N,) NiW scale of the offset, Lambda_w; with ``noise_means="kalman"`` each
            particle's own sigma_w^2 (static, a point of its grid).
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
        info: with ``input_std_prior="jeffreys"`` (N,), each grid point's Fisher information
            of log sigma_w^2 so far (covariance part, :mod:`vehjax.filters._jeffreys`); else
            None.
        base_log_weights: with ``input_std_prior="jeffreys"`` (N,), the normalised log
            weights under equal prior weights (the likelihood alone); ``log_weights`` are them
            times Jeffreys' prior sqrt(info). Else None.
        var_info, var_stat, var_sand, var_ref, var_est: with ``sensor_variances="scored"``,
            the sensor variances' scoring sums (:mod:`vehjax.filters._sensor_scoring`): J
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


class RBTransition(NamedTuple):
    """What the marginalized PF declares for smoothing over its particles
    (``Estimator.rao_blackwell``, :mod:`vehjax.smoothers.marginalized`).

    Attributes:
        predict: ``predict(x, z, P, w, u, theta) -> (m_pred, P_pred, C)``: one particle's
            Gaussian prediction over (sampled, linear) states from its means x (n_xs,), z
            (n_z,), covariance P (n_k, n_k) and offset draw w with input u
            (:func:`vehjax.filters._mpf_kalman.joint_prediction`); meaningful when ``gauss``.
        theta: the model parameters the filter runs with.
        order: (nx,) index array, (sampled, linear) order -> model order.
        nz: number of linear states.
        gauss: the particles carry a Gaussian over all states (``kalman_states="all"`` with
            linear states).
        setup, model: the filter's constants (``_Setup``) and model functions (``_Model``),
            from which the smoother recomputes a step's Kalman filter of the linear states
            with ``kalman_states="linear"``.
    """

    predict: Callable
    theta: Any
    order: np.ndarray
    nz: int
    gauss: bool
    setup: Any = None
    model: Any = None


def _masked(M, obs):
    """M (n, n) on the observed rows and columns, identity elsewhere."""
    both = obs[:, None] & obs[None, :]
    return jnp.where(both, M, jnp.eye(M.shape[-1], dtype=M.dtype))


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


class _Setup(NamedTuple):
    """Everything :func:`marginalized_pf` fixes when it is built (numpy and Python values,
    static under ``jit``); see :func:`_configure`."""

    n: int  # particles
    scheme: str  # resampling scheme
    thr: float  # ESS threshold
    lam: float  # forgetting lambda
    g0: float  # gamma0
    nu0: float
    d: int  # dimension of v = (w, e)
    ns: int  # sensors
    nz: int  # linear states
    nxs: int  # sampled states
    nx: int  # model states
    nk: int  # dimension of each particle's Kalman filter
    gauss: bool  # kalman_states == "all" with linear states
    nl: np.ndarray  # indices of the sampled states in the model's state vector
    li: np.ndarray  # indices of the linear states
    inv: np.ndarray  # (sampled, linear) order -> model order
    i_in: int  # index of the noisy input
    Qz: np.ndarray  # (nz, nz) process noise of the linear states
    u_idx: np.ndarray  # output rows the filter uses (sensors and known-std outputs)
    srow: list  # sensor j's row among the used rows
    spos: dict  # used row -> sensor index
    kvu: list  # known variance of each used row (0.0 for sensors)
    param_names: tuple
    theta_prior: np.ndarray
    P_prior: np.ndarray
    n_inputs: int
    ny: int
    resample: Callable  # smc.resample or the caller's
    # noise_means="kalman": the offset and the sensor means known (zero, Kalman states), w as
    # process noise at each particle's static sigma_w^2 on a grid (_kalman_means_update)
    means_known: bool = False
    # noise_means="kalman": the (low, high) stds of the noisy input's log-uniform grid, or None
    # for a decade either side of the guess (Jeffreys) or the grid over the inverse-Wishart
    # prior (_niw.static_prior_grid)
    w_range: Any = None
    # noise_means="kalman": the grid's weights are Jeffreys' prior (_jeffreys), not equal
    jeffreys: bool = False
    # noise_means="kalman": the sensor variances scored (_sensor_scoring, the default), not
    # the inverse-Wishart mean alone
    scored: bool = False


def _linear_noise(model, linear_noise_std, li, linear_states) -> np.ndarray:
    """Q of the linear states from ``linear_noise_std`` (the builder's docstring)."""
    nz = len(li)
    if not nz:
        return np.zeros((0, 0))
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
        return float(sig) ** 2 * np.outer(B, B)
    if sig.shape in ((), (nz,)) and np.all(np.isfinite(sig)) and np.all(sig >= 0):
        return np.diag(np.broadcast_to(sig, (nz,)) ** 2)
    raise ValueError(f"linear_noise_std: expected a std >= 0 or {nz} of them, got "
                     f"{linear_noise_std!r}")


def _std_range(value):
    """Checked ``input_std_range``: None or (low, high) with 0 < low < high, finite."""
    if value is None:
        return None
    try:
        lo, hi = (float(v) for v in value)
    except (TypeError, ValueError):
        lo = hi = float("nan")
    if not (0.0 < lo < hi < math.inf) or isinstance(value, str):
        raise ValueError(f"input_std_range: expected (low, high) with 0 < low < high, got "
                         f"{value!r}")
    return lo, hi


INPUT_STD_PRIORS = ("jeffreys", "inverse-wishart", "log-uniform")
SENSOR_VARIANCES = ("inverse-wishart", "scored")


def _sensor_variances(value) -> bool:
    """Whether ``sensor_variances`` asks for the scored variances (None: scored, the
    default)."""
    if value is None:
        return True
    if value not in SENSOR_VARIANCES:
        raise ValueError(f"sensor_variances: expected one of {SENSOR_VARIANCES}, got {value!r}")
    return value == "scored"


def _input_std_prior(prior, std_range) -> bool:
    """Checked ``input_std_prior`` against ``input_std_range``: True for Jeffreys' prior."""
    if prior is None:
        prior = "jeffreys"
    if prior not in INPUT_STD_PRIORS:
        raise ValueError(f"input_std_prior: expected one of {INPUT_STD_PRIORS}, got {prior!r}")
    if prior == "log-uniform" and std_range is None:
        raise ValueError("input_std_prior: 'log-uniform' needs input_std_range=(low, high)")
    if prior == "inverse-wishart" and std_range is not None:
        raise ValueError("input_std_prior: 'inverse-wishart' spans its own grid; give no "
                         "input_std_range")
    return prior == "jeffreys"


def _noise_prior(unknown_names, std0, mean0, d):
    """Checked (std0 values, mean0 values, lambda-free priors) of the unknown noise."""
    std0 = _std_dict("std0", {} if std0 is None else std0, unknown_names, unknown_names,
                     "input and output units")
    mean0 = validation.keyed("mean0", mean0, unknown_names)
    mean0v = []
    for k in unknown_names:
        try:
            v = float(mean0.get(k, 0.0))
        except (TypeError, ValueError):
            v = float("nan")
        if not np.isfinite(v):
            raise ValueError(f"mean0[{k!r}]: expected a finite number, got {mean0.get(k)!r}")
        mean0v.append(v)
    return np.array([std0[k] for k in unknown_names]), mean0v


def _forgetting(forgetting, gamma0, nu0, d):
    """Checked (lambda, gamma0, nu0): lambda min(nu0, 1 / (1 - lambda)) > d + 1."""
    lam = validation.number("forgetting", forgetting, 0.0, 1.0, high_open=False)
    g0 = validation.number("gamma0", gamma0, 0.0, np.inf)
    nu0 = float(d + 4) if nu0 is None else validation.number("nu0", nu0, d + 1.0, np.inf)
    nu_low = nu0 if lam == 1.0 else min(nu0, 1.0 / (1.0 - lam))
    if not lam * nu_low > d + 1:
        raise ValueError(
            f"forgetting: lambda = {lam} with nu0 = {nu0} lets the degrees of freedom fall to "
            f"{lam * nu_low:.3g} <= d + 1 = {d + 1}, where the Student-t has no variance; use "
            f"lambda > {(d + 1) / (d + 2):.4g} (and nu0 > {(d + 1) / lam:.4g})"
        )
    return lam, g0, nu0


def _configure(model, n_particles, noisy_input, sensors, known_std, linear_states,
               linear_noise_std, std0, mean0, forgetting, gamma0, nu0, ess_threshold,
               resampling, kalman_states, resample) -> _Setup:
    """Every check of :func:`marginalized_pf`'s arguments (ValueError naming the argument) and
    the constants the filter is built from."""
    validation.model(model)
    n = smc.check_n_particles(n_particles, low=2)
    scheme = _rs.check_scheme(resampling)
    thr = smc.check_ess_threshold(ess_threshold)
    resample = smc.check_resample(resample)
    state_names = tuple(model.state_names)
    input_names = tuple(model.input_names)
    output_names = tuple(model.output_names)
    if not isinstance(noisy_input, str) or noisy_input not in input_names:
        raise ValueError(f"noisy_input: expected one of the model's inputs {input_names}, got "
                         f"{noisy_input!r}")
    sensors = validation.names("sensors", sensors, output_names)
    known = {} if known_std is None else _std_dict("known_std", known_std, (), output_names,
                                                  "output units")
    both = [k for k in known if k in sensors]
    if both:
        raise ValueError(f"known_std: {both} are also in sensors (unknown noise); name each "
                         f"output once")
    linear_states = validation.names("linear_states", linear_states, state_names,
                                    allow_empty=True)
    li = np.array([state_names.index(s) for s in linear_states], dtype=int)
    nl = np.array([i for i in range(len(state_names)) if i not in set(li.tolist())], dtype=int)
    if len(nl) == 0:
        raise ValueError("linear_states: at least one state must remain a particle state")
    nz, nx, ny, ns = len(li), len(state_names), len(output_names), len(sensors)
    d = 1 + ns
    Qz = _linear_noise(model, linear_noise_std, li, linear_states)
    unknown_names = (noisy_input,) + sensors
    std0v, mean0v = _noise_prior(unknown_names, std0, mean0, d)
    lam, g0, nu0 = _forgetting(forgetting, gamma0, nu0, d)
    if kalman_states not in ("linear", "all"):
        raise ValueError(f"kalman_states: expected 'linear' or 'all', got {kalman_states!r}")
    gauss = kalman_states == "all" and nz > 0
    _check_affine(model, li)

    s_rows = np.array([output_names.index(s) for s in sensors], dtype=int)
    kv = np.zeros(ny)
    for k, v in known.items():
        kv[output_names.index(k)] = v * v
    used = np.zeros(ny, bool)
    used[s_rows] = True
    used[[output_names.index(k) for k in known]] = True
    u_idx = np.flatnonzero(used)
    srow = [int(np.flatnonzero(u_idx == r)[0]) for r in s_rows]
    param_names = (f"{noisy_input}_offset", f"{noisy_input}_std") + tuple(
        f"{s}_bias" for s in sensors) + tuple(f"{s}_std" for s in sensors)
    theta_prior = np.concatenate([[mean0v[0], std0v[0]], mean0v[1:], std0v[1:]])
    iw_var = 1.0 / (2.0 * max(nu0 - d - 3.0, 1.0))  # Var(sigma) / sigma^2 by the delta method
    P_prior = np.diag(np.concatenate([[g0 * std0v[0] ** 2, iw_var * std0v[0] ** 2],
                                      g0 * std0v[1:] ** 2, iw_var * std0v[1:] ** 2]))
    return _Setup(
        n=n, scheme=scheme, thr=thr, lam=lam, g0=g0, nu0=nu0, d=d, ns=ns, nz=nz, nxs=len(nl),
        nx=nx, nk=nx if gauss else nz, gauss=gauss, nl=nl, li=li,
        inv=np.argsort(np.concatenate([nl, li]).astype(int)),
        i_in=input_names.index(noisy_input), Qz=Qz, u_idx=u_idx, srow=srow,
        spos={r: j for j, r in enumerate(srow)}, kvu=[float(kv[r]) for r in u_idx],
        param_names=param_names, theta_prior=theta_prior, P_prior=P_prior,
        n_inputs=len(input_names), ny=ny, resample=resample,
    )


# ---------------------------------------------------------------------------------------------
# the filter, composed


class _Model(NamedTuple):
    """The model as the step uses it: f, h (x's dtype), the linearisation at every particle
    (vmapped over the last axis) and the kinds of its entries (:func:`entry_kinds`)."""

    f: Callable
    h: Callable
    lin_all: Callable
    kinds: Any
    theta: Any


def _model_fns(model, s: _Setup) -> _Model:
    def f(X, u, th):
        return jnp.asarray(model.transition(X, u, th)).astype(X.dtype)

    def h(X, u, th):
        return jnp.asarray(model.observe(X, u, th)).astype(X.dtype)

    lin_all = jax.vmap(
        lambda x, m, u, theta: linearise(f, h, x, m, u, theta, s.nl, s.li, s.i_in),
        in_axes=(-1, -1, None, None), out_axes=-1,
    )
    mth = jnp.asarray(model.theta)
    kinds = entry_kinds(f, h, mth, s.nl, s.li, s.i_in, s.n_inputs, s.u_idx)
    return _Model(f, h, lin_all, kinds, mth)


def _init(s: _Setup, x0, P0, theta0=None, P_theta0=None, key=None) -> MPFState:
    """The filter's ``init``: particles from the prior, Kalman filters from the Gaussian
    conditional of the linear states given each particle, the NiW statistics from the
    priors."""
    del P_theta0
    if key is None:
        raise ValueError("key: marginalized_pf draws its particles at random; pass a PRNG key")
    nl, li, nz, nk, n, d, ns = s.nl, s.li, s.nz, s.nk, s.n, s.d, s.ns
    validation.prior(s.nx, x0, P0)
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
    mu0 = jnp.concatenate([th[:1], th[2:2 + ns]])
    sd0 = jnp.concatenate([th[1:2], th[2 + ns:]])
    k_init, k_run = jax.random.split(key)
    Pxx = P0[np.ix_(nl, nl)]
    Lx = jnp.linalg.cholesky(Pxx)
    xs = x0[nl][:, None] + Lx @ jax.random.normal(k_init, (s.nxs, n), dtype)
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
    if s.means_known:  # every particle starts as the prior (sampled, linear order), its own
        order = np.concatenate([nl, li]).astype(int)  # sigma_w^2 a point of the grid
        xs = jnp.broadcast_to(x0[nl][:, None], (s.nxs, n))
        zs = jnp.broadcast_to(x0[li][:, None], (nz, n))
        Pk = P0[np.ix_(order, order)]
        if s.w_range is None and not s.jeffreys:
            lam_w, log_w0 = static_prior_grid(lam_w[0], s.nu0 - d + 1.0, n)
        else:  # log-uniform over the range, by default a decade either side of the guess
            lo, hi = s.w_range or (sd0[0] * 0.1, sd0[0] * 10.0)
            lam_w = jnp.exp(jnp.linspace(2.0 * jnp.log(lo), 2.0 * jnp.log(hi), n, dtype=dtype))
    jeff = {}
    if s.jeffreys:  # no information yet: equal weights
        jeff = dict(info=jnp.zeros((n,), dtype), base_log_weights=log_w0)
    if s.scored:  # the sensor variances' scoring sums: the prior alone
        v_ref = jnp.broadcast_to((sd0[1:] ** 2)[:, None], (ns, n))
        J0, h0 = prior_terms(v_ref, scale)
        jeff.update(var_info=J0, var_stat=h0, var_sand=J0, var_ref=v_ref, var_est=v_ref)
    return MPFState(
        x=xs,
        z=zs,
        P=jnp.broadcast_to(Pk[:, :, None], (nk, nk, n)),
        mu=jnp.broadcast_to(mu0[:, None], (d, n)),
        lam_w=lam_w,
        lam_e=jnp.broadcast_to((scale * jnp.diag(sd0[1:] ** 2))[:, :, None], (ns, ns, n)),
        gamma=jnp.asarray(s.g0, dtype),
        nu=jnp.asarray(s.nu0, dtype),
        log_weights=log_w0,
        weights=jnp.exp(log_w0),
        key=smc.raw_key(k_run),
        ess=jnp.asarray(float(n), dtype),
        flag_diverged=jnp.asarray(False),
        n_reinit=jnp.asarray(0, jnp.int32),
        offset=jnp.zeros((n,), dtype),
        ancestors=jnp.arange(n, dtype=jnp.int32),
        **jeff,
    )


def _linearisation(s: _Setup, mdl: _Model, x, m, u, theta, start):
    """The linearisation's entries at every particle (used output rows only): constants as
    numbers, the entries that depend on the input alone computed once at one point."""
    dtype = x.dtype
    u_idx = s.u_idx

    def used_rows(lin):
        return lin_entries(lin._replace(yb=lin.yb[u_idx], Cx=lin.Cx[u_idx], Cz=lin.Cz[u_idx],
                                        d=lin.d[u_idx]))

    lin = used_rows(mdl.lin_all(x, m, u, theta))  # entries not used below are compiled away
    lin_step = used_rows(linearise(mdl.f, mdl.h, jnp.zeros(s.nxs, dtype),
                                   jnp.zeros(s.nz, dtype), u, theta, s.nl, s.li, s.i_in))
    return barrier(merge_entries(lin, lin_step, mdl.kinds), start)


def _kalman_stage(s: _Setup, lin, Pe, Qe, w, dw, dx, x_new, ye, ob, eta, mu_w, b_y, sig_w2,
                  R_y, D, start):
    """The particles' Kalman step after the draw of w_t and the sensor residuals for the
    statistics: (x_t, z_t entries, P_t entries, sensor residuals, their covariance from the
    Kalman posterior)."""
    nxs, nz, srow = s.nxs, s.nz, s.srow
    ns = len(srow)
    if s.gauss:
        xi, C, o2 = barrier(joint_kalman_step(lin, Pe, w, ye, ob, b_y, R_y, Qe, D, start), start)
        x_new = [add(x_new[k], xi[k]) for k in range(nxs)]
        z_new = [add(add(lin.zb[i], mul(lin.gz[i], w)), xi[nxs + i]) for i in range(nz)]
        Hs = [list(lin.Cx[r]) + list(lin.Cz[r]) for r in srow]
        eta_e = [sub(o2[r], dot(Hs[j], xi)) for j, r in enumerate(srow)]
        CP = matmul(Hs, C)
        V = [[dot(CP[i], Hs[j]) for j in range(ns)] for i in range(ns)]
        return x_new, z_new, C, eta_e, V
    if nz:
        s3, P3, o2, _ = barrier(bank_kalman_step(lin, Pe, dx, ye, ob, mu_w, b_y, sig_w2, R_y, Qe,
                                                 start), start)
        z_new = [add(add(lin.zb[i], mul(lin.gz[i], mu_w)), s3[i]) for i in range(nz)]
        eta_e = [sub(sub(o2[r], dot(lin.Cz[r], s3)), mul(lin.d[r], dw)) for r in srow]
        CP = matmul([lin.Cz[r] for r in srow], P3)
        V = [[dot(CP[i], lin.Cz[srow[j]]) for j in range(ns)] for i in range(ns)]
        return x_new, z_new, P3, eta_e, V
    # o2 = y - yb - Cx dx - d mu_w - b_y = eta - Cx g (w - mu_w)
    eta_e = [sub(sub(eta[r], mul(dot(lin.Cx[r], lin.g), dw)), mul(lin.d[r], dw)) for r in srow]
    return x_new, [], [], eta_e, [[0.0] * ns for _ in range(ns)]


def _q_entries(s: _Setup, dtype):
    """The linear states' process noise as entries: structural zeros as 0.0."""
    return [[float(s.Qz[i, j]) if s.Qz[i, j] == 0.0 else jnp.asarray(s.Qz[i, j], dtype)
             for j in range(s.nz)] for i in range(s.nz)]


def _used_noise(s: _Setup, R_s):
    """The noise covariance of the used output rows (entries): the sensors' ``R_s``, the known
    variances on the diagonal elsewhere."""
    spos, kvu = s.spos, s.kvu
    nyu = len(s.u_idx)
    return [[R_s[spos[i]][spos[j]] if (i in spos and j in spos) else (kvu[i] if i == j else 0.0)
             for j in range(nyu)] for i in range(nyu)]


def _sensor_data(s: _Setup, eta_e, V, ob, R_s, start):
    """The sensor part of the statistics' datum: the residuals ``eta_e`` with missing ones
    imputed from ``R_s`` (the point estimate) and the covariance added to Lambda_e (``V`` on
    the observed pairs plus the imputation's). Returns (eta_e list, extra (ns, ns) entries)."""
    ns = s.ns
    ob_e = [ob[r] for r in s.srow]
    V = [[jnp.where(ob_e[i] & ob_e[j], V[i][j], 0.0) for j in range(ns)] for i in range(ns)]
    eta_e, V_miss = barrier(impute_missing(eta_e, R_s, ob_e), start)
    return eta_e, [[add(V[i][j], V_miss[i][j]) for j in range(ns)] for i in range(ns)]


def _finite_or_old(ll, news, olds):
    """Per particle: where the log-likelihood or any new value is not finite, the weight zero
    (-inf) and the old values kept. ``news``, ``olds``: arrays with particles last."""
    ok = jnp.isfinite(ll)
    for a in news:
        ok = ok & jnp.all(jnp.isfinite(a), axis=tuple(range(a.ndim - 1)))
    return jnp.where(ok, ll, -jnp.inf), [jnp.where(ok, n, o) for n, o in zip(news, olds)]


def _particle_update(s: _Setup, mdl: _Model, x, m, P, mu, lam_w, lam_e, z1, z2, y, obs, u,
                     theta, gam, nu_p):
    """One step for all particles (entries over the last axis) before the weights are
    normalised: the Student-t weight (eq. 26-27), the draw of w_t (eq. 30, eq. 6), the Kalman
    step and the statistics update (eq. 18-19). The statistics come in predicted (eq. 20).
    y, obs: (n_yu,) the used rows. Returns (log-likelihoods (N,), x, z, P, mu, lam_w, lam_e,
    predictive means (n_yu, N), predictive covariances (n_yu, n_yu, N), offset draws (N,))."""
    start = (u[0] != u[0]).astype(jnp.int32)  # 0 unless NaN, the same for every run
    dtype = x.dtype
    nxs, nz, ns, spos, kvu = s.nxs, s.nz, s.ns, s.spos, s.kvu
    nyu = len(s.u_idx)
    lin = _linearisation(s, mdl, x, m, u, theta, start)
    ye = [y[i] for i in range(nyu)]
    ob = [obs[i] for i in range(nyu)]
    Pe, lee = entries(P), entries(lam_e)
    Qe = _q_entries(s, dtype)
    mu_w = mu[0]
    b = [mu[1 + j] for j in range(ns)]
    b_y = [b[spos[i]] if i in spos else 0.0 for i in range(nyu)]
    # predictive of y (eq. 26): w and the sensor noise through the NiW, the rest moment-matched
    mu_y, S, D, sw, df = t_predictive(lin, Pe, Qe, lam_w, lee, mu_w, b_y, gam, nu_p, s.d, kvu,
                                      spos, nxs if s.gauss else 0, start)
    ll, shift, sc, dfy, eta = barrier(t_weight_and_proposal(
        ye, ob, mu_y, S, [mul(sw, v) for v in D], sw, df), start)
    # draw w_t from eq. 30 (Student-t via Wilson-Hilferty) and propagate (eq. 6)
    w = draw_offset(mu_w, shift, sc, dfy, z1, z2)
    dw = w - mu_w
    dx = [mul(gk, w) for gk in lin.g]
    x_new = [add(lin.xb[k], dx[k]) for k in range(nxs)]
    w, dw, dx, x_new = barrier((w, dw, dx, x_new), start)
    # bank Kalman step and the sensor residuals, with the point estimates of eq. 23
    inv_den = 1.0 / (nu_p - s.d - 1.0)
    sig_w2 = lam_w * inv_den
    R_s = [[lee[i][j] * inv_den for j in range(ns)] for i in range(ns)]
    R_y = _used_noise(s, R_s)
    x_new, z_new, P3, eta_e, V = _kalman_stage(s, lin, Pe, Qe, w, dw, dx, x_new, ye, ob, eta,
                                               mu_w, b_y, sig_w2, R_y, D, start)
    eta_e, V = barrier((eta_e, V), start)
    eta_e, extra = _sensor_data(s, eta_e, V, ob, R_s, start)
    like = x[0]
    _, _, mu_new, lw_new, le_new = niw_update(gam, nu_p, mu, lam_w, lam_e,
                                             stack([dw] + eta_e, like), stack(extra, like))
    x_new = stack(x_new, like)
    z_new = stack(z_new, like) if nz else m
    P_new = stack(P3, like) if nz else P
    ll, kept = _finite_or_old(ll, (x_new, z_new, P_new, mu_new, lw_new, le_new),
                              (x, m, P, mu, lam_w, lam_e))
    cov_y = stack(S, like) * (df / (df - 2.0))
    return (ll, *kept, stack(mu_y, like), cov_y, w)


def _scored_scale(s: _Setup, lam_e, nu, v):
    """The sensor covariance's scale with the scored variances ``v`` (n_s, N)
    (:mod:`vehjax.filters._sensor_scoring`): diagonal, (nu - d - 1) v; where v is NaN (not
    positive), Lambda_e's diagonal. The sensors' noises are taken as uncorrelated: Lambda_e's
    correlations come from the same slowly forgetting statistics, and kept they made the
    filter suboptimal (the r and roll-rate stds ended 1.1-1.4 % above the oracle's on the
    consistency study's data; ``_sensor_scoring``'s docstring). Also returns the variances
    it gives, (n_s, N)."""
    den = nu - s.d - 1.0
    lam_diag = jnp.diagonal(lam_e, axis1=0, axis2=1).T  # (ns, N)
    used = jnp.where(jnp.isnan(v), lam_diag / den, v)
    eye = jnp.eye(lam_e.shape[0], dtype=lam_e.dtype)[:, :, None]
    return eye * (den * used)[None], used


def _kalman_means_update(s: _Setup, mdl: _Model, x, m, P, lam_w, lam_e, y, obs, u, theta,
                         nu_p, J, h, H, v_ref, v_est):
    """One step of every particle with ``noise_means="kalman"`` (module docstring): the Kalman
    step with the noisy input's error as process noise at the particle's own sigma_w^2
    (``lam_w``, static) and its sensor covariance (the inverse-Wishart statistics' mean; with
    ``sensor_variances="scored"`` its variances the last step's scored ``v_est``, the scoring
    sums ``J``, ``h``, ``H`` updated with the prior guess ``v_ref``), the Gaussian predictive
    of y_t as the weight, the sensor statistics updated with the expected data (and the
    innovations' scoring terms). Returns what
    :func:`_particle_update` returns (the posterior mean of w_t in place of a draw), then J,
    h, H after the step (None unless scored)."""
    start = (u[0] != u[0]).astype(jnp.int32)
    nxs, nz, ns, srow = s.nxs, s.nz, s.ns, s.srow
    nk = s.nk
    nyu = len(s.u_idx)
    lin = _linearisation(s, mdl, x, m, u, theta, start)
    ye = [y[i] for i in range(nyu)]
    ob = [obs[i] for i in range(nyu)]
    lam_use = lam_e
    if s.scored:
        lam_use = barrier(_scored_scale(s, lam_e, nu_p, v_est)[0], start)
    Pe, lee = entries(P), entries(lam_use)
    Qe = _q_entries(s, x.dtype)
    inv_den = 1.0 / (nu_p - s.d - 1.0)
    R_s = [[lee[i][j] * inv_den for j in range(ns)] for i in range(ns)]
    sig_w2, R_y = barrier((lam_w, _used_noise(s, R_s)), start)
    post, C, o, ll, S = barrier(input_noise_kalman_step(lin, Pe, sig_w2, ye, ob, [0.0] * nyu,
                                                        R_y, Qe, start), start)
    x_new = [add(lin.xb[k], post[k]) for k in range(nxs)]
    z_new = [add(lin.zb[i], post[nxs + i]) for i in range(nz)]
    P_new = [row[:nk] for row in C[:nk]]
    # the statistics' data: w's and the sensor residuals' posterior means and covariances
    Hs = [list(lin.Cx[r]) + list(lin.Cz[r]) + [lin.d[r]] for r in srow]
    eta_e = [sub(o[r], dot(Hs[j], post)) for j, r in enumerate(srow)]
    CH = matmul(Hs, C)
    V = [[dot(CH[i], Hs[j]) for j in range(ns)] for i in range(ns)]
    eta_e, extra = _sensor_data(s, eta_e, V, ob, R_s, start)
    like = x[0]
    eta_v = stack([post[nk]] + eta_e, like)
    _, _, _, _, le_new = niw_update(0.0, nu_p, jnp.zeros_like(eta_v), lam_w, lam_e, eta_v,
                                    stack(extra, like), means_known=True)
    x_new, z_new, P_new = stack(x_new, like), stack(z_new, like), stack(P_new, like)
    if s.scored:
        Wb, Wz, Hs_t = barrier(scoring_terms(S, R_y, o, ob, srow, entries(v_ref), start), start)
        J_new, h_new, H_new = J + stack(Wb, like), h + stack(Wz, like), H + stack(Hs_t, like)
        ll, (x_new, z_new, P_new, le_new, J_new, h_new, H_new) = _finite_or_old(
            ll, (x_new, z_new, P_new, le_new, J_new, h_new, H_new), (x, m, P, lam_e, J, h, H))
    else:
        J_new = h_new = H_new = None
        ll, (x_new, z_new, P_new, le_new) = _finite_or_old(
            ll, (x_new, z_new, P_new, le_new), (x, m, P, lam_e))
    mu_y = stack([lin.yb[i] for i in range(nyu)], like)
    # lam_w (the particle's sigma_w^2) is static: returned as it came
    return (ll, x_new, z_new, P_new, None, lam_w, le_new, mu_y, stack(S, like),
            post[nk] + 0.0 * like, J_new, h_new, H_new)


def _mixture_moments(s: _Setup, w_now, x, z, P):
    """Weighted mean and covariance over all model states (model order): the particles and the
    mixture of their Kalman filters, with a relative jitter of sqrt(eps) on the diagonal."""
    dtype = x.dtype
    Xp = jnp.concatenate([x, z])  # sampled then linear states
    mean_p, cov_p = smc.moments(w_now, Xp)
    if s.nz:
        cov_p = cov_p.at[s.nx - s.nk:, s.nx - s.nk:].add(jnp.einsum("ijn,n->ij", P, w_now))
    jitter = jnp.sqrt(jnp.finfo(dtype).eps) * jnp.diagonal(cov_p) + jnp.sqrt(
        jnp.finfo(dtype).tiny)
    cov_p = cov_p + jnp.diag(jitter)
    return mean_p[s.inv], cov_p[np.ix_(s.inv, s.inv)]


def _mixture_nis(wp, mu_y, cov_y, y0, obs):
    """NIS of the observed components under the mixture of the particles' predictives (prior
    weights ``wp``)."""
    ybar = mu_y @ wp
    dyb = mu_y - ybar[:, None]
    Sy = jnp.einsum("ijn,n->ij", cov_y, wp) + (dyb * wp) @ dyb.T
    Ly = cholesky(_masked(Sy, obs))
    a = solve_lower(Ly, jnp.where(obs, y0 - ybar, 0.0))
    return jnp.sum(a * a)


def _rb_predict(s: _Setup, mdl: _Model, x, z, P, w, u, theta):
    """:attr:`RBTransition.predict`: the linearisation at the particle's means and
    :func:`joint_prediction` with its draw w."""
    lin = linearise(mdl.f, mdl.h, x, z, u, theta, s.nl, s.li, s.i_in)
    return joint_prediction(lin, w, P, jnp.asarray(s.Qz, x.dtype))


def _step(s: _Setup, mdl: _Model, state: MPFState, y, u):
    """The filter's ``step`` (module docstring, steps 1-6)."""
    n = s.n
    dtype = state.x.dtype
    y, u = jnp.asarray(y).astype(dtype), jnp.asarray(u).astype(dtype)
    theta = mdl.theta.astype(dtype)
    yu = y[s.u_idx]
    obs = ~jnp.isnan(yu)
    y0 = jnp.where(obs, yu, 0.0)
    n_obs = jnp.sum(obs, dtype=jnp.int32)
    gam_p, nu_p, lw_p, le_p = niw_predict(state.gamma, state.nu, state.lam_w, state.lam_e, s.lam)
    key_next, key_step = smc.split(state.key)
    miss, var_cov = {}, None
    if s.means_known:  # nothing drawn; sigma_w^2 is the particle's static value, not forgotten
        ll, x, z, P, _, lam_w, lam_e, mu_y, cov_y, w_draw, J, h, H = _kalman_means_update(
            s, mdl, state.x, state.z, state.P, state.lam_w, le_p, y0, obs, u, theta, nu_p,
            *((s.lam * state.var_info, s.lam * state.var_stat, s.lam * state.var_sand,
               state.var_ref, state.var_est) if s.scored else (None,) * 5))
        mu = state.mu
        if s.scored:  # the scored variances (J^-1 h does not see the forgetting)
            st0 = (u[0] != u[0]).astype(jnp.int32)
            v_est, var_cov = scored_variances(J, h, H, st0)
            J, h, H, v_est, var_cov = barrier((J, h, H, v_est, var_cov), st0)
            miss = dict(var_info=J, var_stat=h, var_sand=H, var_ref=state.var_ref, var_est=v_est)
    else:
        zn = barrier(smc.normals(key_step, 2, n, dtype), (u[0] != u[0]).astype(jnp.int32))
        ll, x, z, P, mu, lam_w, lam_e, mu_y, cov_y, w_draw = _particle_update(
            s, mdl, state.x, state.z, state.P, state.mu, lw_p, le_p, zn[0], zn[1],
            y0, obs, u, theta, gam_p, nu_p)
    gamma = gam_p / (1.0 + gam_p)
    nu = nu_p + 1.0
    rw = smc.reweight(state.log_weights, ll)  # the step's predictive and its underflow
    under = rw.underflow
    jeff = {}
    if s.jeffreys:  # the likelihood so far times Jeffreys' prior of the information so far
        info = state.info + covariance_information(
            cov_y, grid_derivative(cov_y, jnp.log(lam_w)), obs)
        base = smc.reweight(state.base_log_weights, ll)
        under = under | base.underflow
        rj = smc.reweight(base.log_w, jeffreys_log_prior(info))
        base_lw = jnp.where(under, -math.log(n), base.log_w)
        jeff = dict(info=info, base_log_weights=base_lw)
        rw_w, rw_lw = rj.w, rj.log_w
    else:
        rw_w, rw_lw = rw.w, rw.log_w
    w_now = jnp.where(under, 1.0 / n, rw_w)
    lw_now = jnp.where(under, -math.log(n), rw_lw)

    mean, cov = _mixture_moments(s, w_now, x, z, P)
    lam_rep, w_extra = lam_e, None
    if s.means_known:  # the grid's posterior of log sigma_w^2, where the grid is too coarse
        t = jnp.log(lam_w)
        post = grid_posterior(lw_now, t)
    if s.scored:  # the scored sensor variances, and what their plug-in adds to sigma_w's
        lam_rep, v_used = _scored_scale(s, lam_e, nu, v_est)
        cov_vt = jnp.where(post.narrow, ridge_covariance(post, t, v_used),
                           weighted_covariance(w_now, t, v_used))
        g = ridge_sensitivity(w_now, t, v_used, J, cov_vt)
        w_extra = 0.25 * lam_w * plug_in_variance(g, var_cov)
    params, params_cov = noise_estimates(w_now, mu, lam_w, lam_rep, nu, gamma,
                                        means_known=s.means_known, var_cov=var_cov,
                                        input_var_extra=w_extra)
    if s.means_known:
        within = 0.0 if w_extra is None else jnp.sum(w_now * w_extra)
        params, params_cov = with_resolved_std(params, params_cov, 1, post, within)
    nis = _mixture_nis(state.weights, mu_y, cov_y, y0, obs)

    # resample for the next step
    # the draws and the particles' own indices ride along: the genealogy for smoothing
    parts = (x, mu, lam_w, lam_e, w_draw, jnp.arange(n, dtype=jnp.int32)) + (
        (z, P) if s.nz else ())  # no empty leaves
    if s.means_known:  # a fixed grid of sigma_w^2: never resampled
        lw_next, w_next = lw_now, w_now
    else:
        u_res = smc.uniforms(key_step, s.scheme, n, dtype, stream=1)
        parts, lw_next, w_next, _ = s.resample(parts, w_now, lw_now, u_res, s.scheme, s.thr)
    x, mu, lam_w, lam_e, w_draw, anc = parts[:6]
    if s.nz:
        z, P = parts[6:]
    new_state = MPFState(
        x=x, z=z, P=P, mu=mu, lam_w=lam_w, lam_e=lam_e, gamma=gamma, nu=nu,
        log_weights=lw_next, weights=w_next, key=key_next,
        ess=jnp.where(under, 0.0, smc.ess(w_now)),
        flag_diverged=state.flag_diverged | under,
        n_reinit=state.n_reinit + under.astype(jnp.int32),
        offset=w_draw, ancestors=anc, **jeff, **miss,
    )
    out = StepOutput(mean=mean, cov=cov, loglik=smc.step_loglik(rw), nis=nis, n_obs=n_obs,
                     params=params, params_cov=params_cov, reinit=under)
    return new_state, out


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
    kalman_states: str | None = None,
    resample=None,
    noise_means: str = "niw",
    bias_walk=None,
    mean_std0=None,
    input_std_range=None,
    input_std_prior: str | None = None,
    sensor_variances: str | None = None,
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
        ess_threshold: resample when ESS < ess_threshold * N, in [0, 1] (with
            ``noise_means="kalman"`` unused, as ``resampling`` and ``resample``: its grid is
            never resampled).
        resampling: "systematic", "stratified", "multinomial" or "residual".
        kalman_states: what each particle's Kalman filter covers. "linear" (the paper's
            Algorithm 1): the linear states; a particle's other states are a point, x_t built
            by eq. 6 from the bank's Kalman mean. "all": every state; a particle is a sequence
            of offset draws and carries the Gaussian of all states given them, so the bank's
            uncertainty reaches vy and r (with known noise statistics this is exact for models
            affine in the states: it matches the exact Kalman filter, where "linear" reports
            vy's variance about 8 % too small on SingleTrackBank; module docstring). 1.2-1.3x
            the time per step. No difference without linear states. Default (None): "linear"
            with ``noise_means="niw"``, "all" with ``noise_means="kalman"``.
        resample: the resampling function, ``resample(particles, w, log_w, u, scheme,
            threshold) -> (particles, log_w, w, resampled)`` with the signature and meaning of
            :func:`vehjax.filters.smc.resample` (which None means), e.g.
            :func:`vehjax.filters.smc.resample_stop_gradient` (what :mod:`vehjax.tune` builds
            the filter with to differentiate its log-likelihood).
        noise_means: where the offset mean and the sensor biases are learnt. "niw" (the
            paper's Algorithm 1): in the NiW statistics of each particle (eq. 18), the Kalman
            filters taking them as exact. "kalman" (not the paper's): as constant states of
            each particle's Kalman filter (exact Gaussian posterior, correlated with the
            states and each other; prior N(mean0, gamma0 std0^2) or ``mean_std0``), the input
            error as process noise (not drawn), each particle a Kalman filter at its own
            steering variance on a fixed grid (never resampled: the weights are the posterior
            over it), the sensor variances learnt by scoring (``sensor_variances``; module
            docstring). Needs ``kalman_states="all"``; the model
            must be affine in ``noisy_input`` (checked with the linear states). The
            estimator declares no Rao-Blackwell structure (``vehjax.smooth`` does not smooth
            it). Its cost per step against the paper's: ``vehjax reproduce noise-learning``
            measures both.
        bias_walk: with ``noise_means="kalman"`` only: dict sensor -> std per step of a
            random walk of its bias (sensor units; missing sensors 0: constant biases), the
            process noise of the bias states.
        mean_std0: with ``noise_means="kalman"`` only: dict of the prior stds of the offset
            (key ``noisy_input``) and the biases (sensor names), the input's and outputs'
            units; missing names sqrt(gamma0) std0 (the paper's NiW prior). A Kalman state's
            prior need not be tied to the noise std: give the size the offset and biases may
            have.
        input_std_range: with ``noise_means="kalman"`` only: (low, high), 0 < low < high, the
            range of the noisy input's std (input units) over which the N particles' grid is
            log-uniform; its weights are ``input_std_prior``'s. Default None: a decade either
            side of the ``std0`` guess (Jeffreys' prior). The grid's spacing is
            log(high / low) / (N - 1) in log std (0.19 for 25 points over a decade either
            side). Where the data pin the std more narrowly than that, its estimate and
            interval come from the Laplace approximation on the grid
            (:mod:`vehjax.filters._grid`); the states still mix the grid's Kalman filters,
            each at its own std, so a finer grid still serves them better.
        input_std_prior: with ``noise_means="kalman"`` only: the prior over the grid of the
            noisy input's std. "jeffreys" (default): Jeffreys' prior, each grid point weighted
            by the square root of the Fisher information the data so far carry about the std
            there (the covariance part, from the particles' predictive covariances;
            :mod:`vehjax.filters._jeffreys`). "log-uniform": equal weights over
            ``input_std_range`` (required). "inverse-wishart": the grid over the inverse-Wishart
            prior's marginal of sigma_w^2 (``std0`` and ``nu0``; no ``input_std_range``),
            weighted by that prior (at the default nu0 it spans 0.35 to 7.6 times the guess,
            99 % of the prior between 0.42 and 2.7 times). A std that the data see only beside
            other noise has a likelihood flat below the truth; Jeffreys' prior takes the weight
            off that flat end, where equal weights leave the states' covariance too small and
            a prior at a guess above the truth too large (paper 004's simulation, guess twice
            the truth: NEES of (vy, r) 1.01 per dof with Jeffreys' prior, 0.83 with the
            inverse-Wishart grid, 100 runs x 180 s; 1.33 with equal weights over a tenth to
            ten times the guess, 20 runs; ``benchmarks/mpf_consistent_steering.py``). With
            Jeffreys' prior the reported ``loglik`` is each step's predictive under the prior
            at that step (the prior moves as information comes), not a marginal likelihood.
        sensor_variances: with ``noise_means="kalman"`` only: how the sensor variances are
            learnt. "scored" (default, None): Fisher scoring of the innovations weighted at
            the ``std0`` guess, with a sandwich covariance, the sensors' noises taken as
            uncorrelated, and sigma_w's reported variance widened by their plug-in
            (:mod:`vehjax.filters._sensor_scoring`). "inverse-wishart": the mean of the
            inverse-Wishart statistics (sensor correlations included), which a sensor seen
            beside other noise (ay beside the steering noise's direct term) forgets its start
            only slowly from (its ay std's 95 % interval held the truth in 0.84-0.89 of the
            consistency study's runs); 0.6 times the scored option's time per step.

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
            scheme, ess_threshold, kalman_states, noise_means, input_std_range,
            input_std_prior or sensor_variances, or a ``resample`` that is not callable.
    """
    if noise_means not in ("niw", "kalman"):
        raise ValueError(f"noise_means: expected 'niw' or 'kalman', got {noise_means!r}")
    if kalman_states is None:
        kalman_states = "all" if noise_means == "kalman" else "linear"
    if noise_means == "kalman":
        if kalman_states != "all":
            raise ValueError(f"kalman_states: noise_means='kalman' needs 'all' (every state "
                             f"Gaussian in each particle), got {kalman_states!r}")
        return _kalman_means_pf(model, n_particles, noisy_input, sensors, known_std,
                                linear_states, linear_noise_std, std0, mean0, forgetting,
                                gamma0, nu0, ess_threshold, resampling, kalman_states, resample,
                                bias_walk, mean_std0, input_std_range, input_std_prior,
                                sensor_variances)
    learns_std = "the paper's filter learns the input's std in its NiW statistics"
    for name, value, why in (
            ("input_std_prior", input_std_prior, learns_std),
            ("input_std_range", input_std_range, learns_std),
            ("mean_std0", mean_std0, "the paper's NiW ties the means' prior to gamma0 std0^2"),
            ("bias_walk", bias_walk, "the paper's filter tracks drifting biases by forgetting"),
            ("sensor_variances", sensor_variances, "the paper's NiW learns them")):
        if value is not None:
            raise ValueError(f"{name}: only with noise_means='kalman' ({why})")
    s = _configure(model, n_particles, noisy_input, sensors, known_std, linear_states,
                   linear_noise_std, std0, mean0, forgetting, gamma0, nu0, ess_threshold,
                   resampling, kalman_states, resample)
    mdl = _model_fns(model, s)
    rb = RBTransition(predict=functools.partial(_rb_predict, s, mdl), theta=mdl.theta,
                      order=s.inv, nz=s.nz, gauss=s.gauss, setup=s, model=mdl)
    return Estimator(
        init=functools.partial(_init, s), step=functools.partial(_step, s, mdl), nx=s.nx,
        param_names=s.param_names, name="marginalized_pf", needs_key=True,
        param_prior=(s.theta_prior, s.P_prior), ny=s.ny, nu=s.n_inputs, workload="small_dense",
        rao_blackwell=rb,
    )


def _kalman_means_pf(model, n_particles, noisy_input, sensors, known_std, linear_states,
                     linear_noise_std, std0, mean0, forgetting, gamma0, nu0, ess_threshold,
                     resampling, kalman_states, resample, bias_walk=None,
                     mean_std0=None, input_std_range=None, input_std_prior=None,
                     sensor_variances=None) -> Estimator:
    """:func:`marginalized_pf` with ``noise_means="kalman"``: the filter on the model with the
    sensor biases as constant linear states (:func:`_mpf_means.with_noise_means`), its NiW
    pinned at mean zero (``means_known``), and an estimator over the model's own
    states and the paper's parameters around it."""
    validation.model(model)
    sensors = validation.names("sensors", sensors, tuple(model.output_names))
    linear_states = validation.names("linear_states", linear_states, tuple(model.state_names),
                                    allow_empty=True)
    if not isinstance(noisy_input, str) or noisy_input not in tuple(model.input_names):
        raise ValueError(f"noisy_input: expected one of the model's inputs "
                         f"{tuple(model.input_names)}, got {noisy_input!r}")
    extra = _mpf_means.mean_state_names(sensors, noisy_input)
    clash = [n for n in extra if n in tuple(model.state_names)]
    if clash:
        raise ValueError(f"noise_means: the model already has states named {clash}")
    aug = _mpf_means.with_noise_means(model, sensors, noisy_input)
    linear_noise_std = _mpf_means.pad_linear_noise(
        linear_noise_std, len(linear_states), len(extra), hasattr(model, "bank_noise_gain"))
    s_user = _configure(aug, n_particles, noisy_input, sensors, known_std,
                        tuple(linear_states) + extra, linear_noise_std, std0, mean0,
                        forgetting, gamma0, nu0, ess_threshold, resampling, kalman_states,
                        resample)
    ns, nx = s_user.ns, len(model.state_names)
    names = (noisy_input,) + tuple(sensors)
    msd = _std_dict("mean_std0", {} if mean_std0 is None else mean_std0, (), names,
                    "input and output units")
    # prior stds of the added states (biases, then the offset); NaN: sqrt(gamma0) std0
    mean_sd = np.array([msd.get(k, np.nan) for k in tuple(sensors) + (noisy_input,)])
    mi = np.concatenate([[0], np.arange(2, 2 + ns)])  # offset and biases in params order
    walk = _mpf_means.bias_walk_stds(bias_walk, sensors)
    Qz = np.array(s_user.Qz)
    Qz[-ns - 1:-1, -ns - 1:-1] = np.diag(walk ** 2)
    # the filter's own NiW: the offset's and the sensors' means zero and known
    prior = np.where(np.isin(np.arange(2 + 2 * ns), mi), 0.0, s_user.theta_prior)
    s = s_user._replace(means_known=True, Qz=Qz, theta_prior=prior,
                        w_range=_std_range(input_std_range),
                        jeffreys=_input_std_prior(input_std_prior, input_std_range),
                        scored=_sensor_variances(sensor_variances))
    mdl = _model_fns(aug, s)

    def init(x0, P0, theta0=None, P_theta0=None, key=None):
        del P_theta0
        validation.prior(nx, x0, P0)
        p = len(s.param_names)
        if theta0 is not None and np.shape(theta0) != (p,):
            raise ValueError(f"theta0: expected shape ({p},) for {s.param_names}, got "
                             f"{np.shape(theta0)}")
        th = jnp.asarray(s_user.theta_prior if theta0 is None else theta0)
        th = th.astype(jnp.result_type(th.dtype, jnp.asarray(x0).dtype, float))
        xa, Pa = _mpf_means.augment_prior(x0, P0, th, s_user.g0, ns, mean_sd)
        return _init(s, xa, Pa, th.at[mi].set(0.0), None, key)

    def step(state, y, u):
        state, out = _step(s, mdl, state, y, u)
        params, params_cov = _mpf_means.map_estimates(out.mean, out.cov, out.params,
                                                      out.params_cov, nx, ns)
        return state, out._replace(mean=out.mean[:nx], cov=out.cov[:nx, :nx], params=params,
                                   params_cov=params_cov)

    return Estimator(
        init=init, step=step, nx=nx, param_names=s.param_names, name="marginalized_pf",
        needs_key=True, param_prior=(s_user.theta_prior, s_user.P_prior), ny=s.ny,
        nu=s.n_inputs, workload="small_dense")
