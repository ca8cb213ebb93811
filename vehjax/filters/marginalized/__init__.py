"""The noise-adaptive marginalized particle filter of Berntorp & Di Cairano (paper 004, eq. 11-30,
Algorithm 1), and a consistent variant over a fixed grid: two builders sharing the set-up, the
noise statistics, the particles' Kalman filters, the mixture and the scoring modules.

* :func:`marginalized_pf` (:mod:`.paper`): the paper's Algorithm 1.
* :func:`marginalized_pf_grid` (:mod:`.grid_filter`): the offset and the biases as Kalman states,
  each particle at its own steering-noise variance on a fixed grid (not the paper's; below).

Modules, one concept each: :mod:`.setup` (checks and constants, the model as the steps use it,
:class:`NiW`), :mod:`.state` (the state and its start), :mod:`.niw` (the NiW statistics, the
Student-t predictive, the eq. 30 draw, eq. 23's estimates), :mod:`.linearise`, :mod:`.kalman`
(the per-particle Kalman filters), :mod:`.parts` (per-particle pieces both steps share),
:mod:`.mixture` (the reported moments and NIS), :mod:`.means` (the grid filter's augmented model),
:mod:`.grid`, :mod:`.jeffreys`, :mod:`.sensor_scoring`, :mod:`.staging` (the one XLA tactic), and
:mod:`.contract` (what the smoother reads, :class:`RBTransition`).

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

Reading of the paper (the transcription has gaps and typos; derived from the conjugate NiW
algebra, Murphy 2007 [25] sec. 9, Ozkan et al. 2013 [26], Saha & Gustafsson 2012 [20])
-------------------------------------------------------------------------------------------------
Conventions. NiW(gamma, mu_hat, Lambda, nu) is Murphy's NiW(mu_0, kappa, Lambda, nu) with
gamma = 1 / kappa: mu | Sigma ~ N(mu_hat, gamma Sigma), Sigma ~ IW(Lambda, nu) in dimension d.
Then eq. 18 is exactly Murphy's one-datum update (kappa + 1 = 1 / gamma_{k|k}, the weight
kappa / (kappa + 1) = 1 / (1 + gamma) on eta eta^T), so repeated with lambda = 1 it equals the
batch posterior (tests/filters/marginalized/test_paper.py checks it).

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
  with y_t (:func:`.kalman.joint_kalman_step`); the statistics updated
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
* The consistent filter, :func:`marginalized_pf_grid` (not the paper's). The
  paper's filter says it knows the noise statistics better than it does when it learns them
  (``vehjax reproduce consistency``, 100 runs: NEES in the band on 0.17 of the steps with
  ``kalman_states="all"``, the roll-rate bias's spread over runs twice its reported std;
  ``vehjax reproduce noise-learning`` on paper 004's simulation: the NEES of (vy, r) about 4 per
  dof). Three causes, three changes (:mod:`.grid_filter`):
  (1) the particle's Kalman filter takes the NiW means as exact, and eq. 18 takes each
  residual as an exact observation of them, though the data tell some of them apart only
  slowly (the roll-rate bias from the bank rate; the ay bias from the steering offset, which
  ay sees as d mu_w): the steering offset and the sensor biases become constant states of each
  particle's Kalman filter (exact Gaussian posterior, correlated with the states and with each
  other; the model augmented by :func:`vehjax.models.with_output_biases` and
  :func:`vehjax.models.with_input_offset`), so the statistics are an inverse-Wishart of known
  zero mean over the covariances alone (``means_known`` in :func:`.niw.niw_update`);
  (2) with the offset a state, the input error w_t = the zero-mean steering noise is Gaussian
  given the covariances, so it is not drawn: each particle's Kalman step takes it as process
  noise through (g, gz) and conditions the joint of (x_t, z_t, w_t) on y_t
  (:func:`.kalman.input_noise_kalman_step`), and the statistics take the
  expected data: the posterior mean of w_t with its variance added to Lambda_w, the sensor
  residuals at the posterior mean with H C H^T added to Lambda_e. Drawn offsets made each
  particle's statistics those of its own path, which resampling shares among few particles;
  (3) what differs between the particles is then the steering noise's variance: each
  particle carries its own static sigma_w^2 on a fixed grid, log-uniform, runs its Kalman
  step with it and is weighted by that step's Gaussian predictive of y_t; the grid is never
  resampled, so the weights are the posterior over the grid (each particle is a Kalman filter
  given its sigma_w^2: a multiple-model filter over it);
  (4) the prior over that grid is Jeffreys' by default (:class:`InputStdGrid`,
  :mod:`.jeffreys`): each point weighted by the square root of the Fisher
  information the data so far carry about sigma_w there. The steering noise reaches the
  sensors beside their own noise, so the likelihood is flat below the true std and steep
  above it (paper 004's simulation, 20 runs x 180 s, everything else known: 0.5x the truth
  costs 2.7 nats per run, 2x costs 33; ``python benchmarks/mpf_consistent_steering.py profile
  20 180``). A prior equal in log sigma_w then leaves mass far below the truth and the
  states' covariance, which scales with sigma_w^2, too small; the inverse-Wishart prior of
  the paper's guess (twice the truth) holds the posterior above it. Jeffreys' prior weighs
  the flat end down by how little the data can say there (its one-parameter coverage is
  right to first order, Welch & Peers 1963). The other two priors stay as options: the
  inverse-Wishart prior's marginal, weighted by it (:func:`.niw.static_prior_grid`), and
  equal weights over ``input_std_range``;
  (5) the sensor variances are learnt per particle by Fisher scoring of the innovations weighted
  at the guess (``sensor_variances="scored"``, the default;
  :mod:`.sensor_scoring`), with their sandwich covariance, the sensors' noises
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
  that separates them. On paper 004's simulation that statistic ended far above the true
  steering std, and static values moved by Liu & West's kernel collapsed the cloud (the
  experiments: benchmarks/results/notes_marginalized.md).
  Exact, given the sensor covariances, for models affine in the states and the noisy input:
  with R known the weights are the exact posterior over the grid
  (tests/filters/marginalized/test_grid_filter.py, against numpy Kalman likelihoods), and with
  every covariance known it is the Kalman filter of the augmented model. Approximate: R's
  scored variances (filtered, not the whole data's likelihood; or the inverse-Wishart
  statistics, a variational-Bayes style update) and their forgetting, the grid's
  resolution. With forgetting < 1 the inverse-Wishart statistics' own noise (about 200
  steps' worth at lambda = 0.995) makes the predictive favour a larger sigma_w (paper 004's
  simulation, 10 runs x 180 s: +22 % at 0.995, +12 % at 1; ``python benchmarks/
  mpf_consistent_steering.py learn 10 180 25 iw 0.995 inverse-wishart``). The prior of the
  offset and the biases is N(mean0, gamma0 std0^2) as the paper's NiW unless
  ``MeanStates.mean_std0`` gives their size: a prior tied to the noise std (0.04 deg for a 0.28
  deg offset in paper 004's simulation) holds the offset state several stds from the truth for
  long and makes the filter over-confident meanwhile. Measured on the consistency study and
  paper 004's simulation: ``vehjax reproduce consistency --filters MPF-K`` and ``vehjax
  reproduce noise-learning`` (their docstrings have the numbers).

Linearisation. The model enters through forward-mode derivatives (``jax.jacfwd``) at each
particle: g = d f / d delta, A_bar = d f_x / d z, the bank transition, C = d h / d (x, z) and
d = d h / d delta. For models affine in the states, the linear states and the noisy input
(:class:`~vehjax.models.bank.SingleTrackBank` at a given speed) every formula is exact; for
others it is first order in the offset and the bank (an EKF-like step inside each particle).
Affinity in the linear states is checked numerically when the filter is built. Which entries
of these derivatives are constants, which depend on the input alone (computed once per step,
not per particle) and which on the particle is read off the traced model when the filter is
built (:func:`.linearise.entry_kinds`): for SingleTrackBank only the
predicted x_t, z_t and y_t are per particle.

Implementation. The mathematics is in module-level functions, each documented and tested on
its own (the modules above); the two step modules compose them. Particles are last in every
leaf. The per-particle algebra is written entry by entry (every matrix entry one (N,) vector,
structural zeros skipped: :mod:`vehjax.lib.entrywise`, shared with the runs-last Gaussian
steps), and its stages are materialised by :func:`.staging.stage` so that XLA does not recompute
long elementwise chains in every consumer; weights, moments and random numbers are the shared
particle core :mod:`vehjax.filters.smc`. Cholesky factors and triangular solves throughout, no
inverses.
"""

from .contract import LinearStep, RBTransition
from .grid_filter import InputStdGrid, MeanStates, marginalized_pf_grid
from .paper import marginalized_pf
from .setup import NiW
from .state import MPFState

__all__ = ["marginalized_pf", "marginalized_pf_grid", "NiW", "MeanStates", "InputStdGrid",
           "MPFState", "RBTransition", "LinearStep"]
