"""Offline calibration by particle MCMC: particle marginal Metropolis-Hastings (:func:`pmmh`,
plain or correlated) and particle Gibbs with ancestor sampling (:func:`particle_gibbs`).

Andrieu, Doucet & Holenstein (2010), "Particle Markov chain Monte Carlo methods", JRSS B 72(3):
a Metropolis-Hastings chain over the unknown quantities phi whose acceptance ratio uses a particle
filter's estimate of the likelihood p(y_1:T | phi) in place of the exact one. The estimate is
unbiased, so the chain's stationary distribution is the exact posterior p(phi | y_1:T), whatever
the number of particles (fewer particles only make the chain stickier). Paper 004 (Berntorp &
Di Cairano) judges its online estimates against such an offline reference (its sec. 5, ref. [28]).

What is calibrated (``priors``, a dict name -> prior), in :mod:`vehjax.tune`'s bracket grammar
(one index: a standard deviation or a bias; tune's two-index covariance entries are not sampled):

* a model parameter by its name (``"cf"``), in the parameter's units;
* ``"R[<output>]"``: the measurement-noise std of that output [output units];
* ``"Q[<state>]"``: the process-noise std of that state [state units per step];
* ``"bias[<output>]"``: a constant sensor bias, y = h(x, u) + bias + noise [output units];
* ``"input[<input>]"``: the std of noise entering through that input [input units], for builders
  that take ``input_noise`` (every vehjax filter).

The earlier ``"R:ay"`` keys are refused with a ValueError giving the new spelling. A sampler's
settings are records (:mod:`~vehjax.calibrate.options`): ``chains=Chains(n, samples, warmup,
init)``, ``proposal=RandomWalk(std or cov, adaptation=Adaptation(windows, acceptance))``,
particle Gibbs's ``sweep=Sweep(n_particles, moves)``; a builder's options by
``functools.partial(builder, ...)``; the correlated estimate ``Correlated(builder,
correlation)`` in place of a builder.

The package, one concern a module:

* :mod:`~vehjax.calibrate.priors` (:mod:`vehjax.lib.priors`, shared with
  :func:`vehjax.tune.fit`'s ``priors=``: the same dict works in both): :class:`Normal`,
  :class:`LogNormal`, :class:`Uniform`, each
  with its bijection to the real line (the shared parameter transforms,
  :mod:`vehjax.lib.transforms`); the chain moves in that unconstrained space, and the target
  there is the posterior times the Jacobian of the map back: log p(y | x(z)) + log p(x(z)) +
  log |dx/dz|.
* :mod:`~vehjax.calibrate.likelihood`: any vehjax filter builder's likelihood as a function of
  the calibrated values (:func:`log_likelihood_fn`; for PMMH the bootstrap PF or
  :func:`fixed_noise_mpf`), the correlated estimate (:func:`cpm_log_likelihood_fn`) and their
  noise (:func:`log_likelihood_spread`, which should be about 1-1.5 at the posterior, Doucet et
  al. 2015; :func:`log_likelihood_difference_spread`).
* :mod:`~vehjax.calibrate.correlated`: the bootstrap PF as a function of its random numbers
  for the correlated pseudo-marginal method (Deligiannidis, Doucet & Pitt 2018).
* :mod:`~vehjax.calibrate.fixed_noise`: :func:`fixed_noise_mpf`, paper 004's marginalized PF
  with its noise statistics held at the chain's values, whose estimate varies far less where the
  model is affine in the states.
* :mod:`~vehjax.calibrate.adaptation`: the random walk's adaptation over the warm-up (windows
  of doubling length, Roberts & Rosenthal 2001's scaling, a scale tuned toward
  :func:`target_acceptance`).
* :mod:`~vehjax.calibrate.marginal`: :func:`pmmh`; :mod:`~vehjax.calibrate.gibbs`:
  :func:`particle_gibbs` with its conditional PF (:func:`conditional_pf_as`) and
  :func:`log_joint`.
* :mod:`~vehjax.calibrate.diagnostics`: :class:`PMMHResult`, split R-hat (:func:`split_rhat`,
  Gelman et al., BDA3 sec. 11.4) and the effective sample size (:func:`effective_sample_size`,
  BDA3 sec. 11.5 with Geyer's initial positive sequence) of every quantity.
"""

from .adaptation import (adaptation_windows, adapted_covariance, proposal_factor, scale_update,
                         target_acceptance)
from .diagnostics import PMMHResult, effective_sample_size, split_rhat
from .fixed_noise import fixed_noise_mpf
from .gibbs import conditional_pf_as, log_joint, particle_gibbs
from .likelihood import (cpm_log_likelihood_fn, log_likelihood_difference_spread,
                         log_likelihood_fn, log_likelihood_spread)
from .marginal import pmmh
from .options import Adaptation, Chains, Correlated, RandomWalk, Sweep
from .priors import PRIORS, LogNormal, Normal, Uniform, log_prior_unconstrained, to_physical

__all__ = ["Normal", "LogNormal", "Uniform", "PMMHResult", "pmmh", "Chains", "RandomWalk",
           "Adaptation", "Sweep", "Correlated", "log_likelihood_fn",
           "log_likelihood_spread", "cpm_log_likelihood_fn", "log_likelihood_difference_spread",
           "fixed_noise_mpf", "target_acceptance", "adaptation_windows",
           "adapted_covariance", "scale_update", "proposal_factor",
           "particle_gibbs", "conditional_pf_as", "log_joint", "split_rhat",
           "effective_sample_size"]
