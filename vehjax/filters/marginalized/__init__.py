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

The paper as read (its transcription has gaps and typos; read from the conjugate NiW algebra,
Murphy 2007 sec. 9): gamma = 1 / kappa of Murphy's NiW, so eq. 18 is his one-datum update; the
NiW is on v = [w; e] with scale diag(Lambda_w, Lambda_e), mapped to eq. 21 by T = [[1, 0], [d, I]];
the predictive of v is St(mu_hat, (1 + gamma) / (nu - d + 1) Lambda, nu - d + 1) and eq. 23's
covariance estimate the inverse-Wishart mean Lambda / (nu - d - 1); eq. 30 is the conditional
of a multivariate t, with the cross scale Lambda_tilde_w d^T and the dof nu - d + 1 + d_y (the
print's gain and denominator are typos); eq. 26-27 moment-match every Gaussian contribution
(so the builder requires lambda min(nu0, 1 / (1 - lambda)) > d + 1); eq. 19's data are the drawn
offset w_t and the sensor residual at the bank's Kalman mean, its covariance added to Lambda_e;
eq. 20 as printed. ``kalman_states="all"`` carries each particle's mean and covariance of
(x, z) (the exact repair of what sec. 3.4 leaves out); ``"linear"`` is the paper's.

The grid filter (not the paper's): the paper's filter claims to know the learnt noise better
than it does, so the offset and the biases become Kalman states, the steering noise is process
noise (not drawn), each particle holds its own static sigma_w^2 on a fixed log-uniform grid that
is never resampled (the weights are the posterior over the grid, Jeffreys' prior by default) and
the sensor variances are learnt by Fisher scoring. Exact, given the sensor covariances, for
models affine in the states and the noisy input.

Linearisation: forward-mode derivatives (``jax.jacfwd``) at each particle; exact for models
affine in the states, the linear states and the noisy input (:class:`~vehjax.models.bank.
SingleTrackBank` at a given speed), first order otherwise. Particles are last in every leaf;
Cholesky factors and triangular solves throughout, no inverses.

Limits: the paper's filter under-reports vy's variance (0.92 of the exact filter's with
``kalman_states="linear"``) and is over-confident when it learns the noise; the grid filter's
approximations are R's scored variances, their forgetting and the grid's resolution.

See docs/marginalized.md for the whole reading of the paper (each equation, with its
derivation), what sec. 3.4 leaves out and the repairs tried, the grid filter's five changes with
their measurements, the linearisation and the implementation.
"""

from .contract import LinearStep, RBTransition
from .grid_filter import InputStdGrid, MeanStates, marginalized_pf_grid
from .paper import marginalized_pf
from .setup import NiW
from .state import MPFState

__all__ = ["marginalized_pf", "marginalized_pf_grid", "NiW", "MeanStates", "InputStdGrid",
           "MPFState", "RBTransition", "LinearStep"]
