"""Tuning: fit noise covariances, model parameters and x0 by maximising the filter's likelihood.

::

    res = vehjax.tune.fit_noise(vehjax.filters.ukf, model, Q0, R0, sim.measurements, sim.inputs,
                                x0=x0, P0=P0)
    res.Q, res.R                 # fitted covariances (full matrices)
    res.history                  # loss per iteration
    out = vehjax.run(res.estimator, ys, us, x0=x0, P0=P0)   # the tuned filter, ready to run
    print(res.summary())         # fitted values with names and units

    res = vehjax.tune.fit(vehjax.filters.ekf, model, Q0, R0, ys, us, x0=x0, P0=P0,
                          params=("m", "iz"), noise=("R",))   # model parameters too

The objective is the summed log-likelihood ``sum_r vehjax.filter(est, y_r, u_r, ...).loglik.sum()``
over a batch of runs (one run ``(T, ny)`` or a batch ``(R, T, ny)``), ``jax.grad`` of it through
``vehjax.filter`` vmapped over the runs, with the estimator rebuilt by ``builder(model, Q, R)``
inside the differentiated function. The optimiser minimises the loss
``-sum loglik / (R T)``, the negative mean log-likelihood per step, which is what
``history`` records.

Priors (:mod:`vehjax.tune.priors`). ``priors={"iz": LogNormal(2763.0, 0.3), "m":
Normal(1500.0, 75.0)}`` (the objects of :mod:`vehjax.lib.priors`, the same dict
:func:`vehjax.calibrate.pmmh` takes; ``LogNormal.within(2763.0, 0.3)`` for "known to 30 %")
fits each named parameter (added to ``params``) by penalised likelihood: the loss becomes
``-(sum loglik + sum_j log p_j(theta_j)) / (R T)`` in the physical parameters (the MAP estimate
in physical coordinates, no Jacobian term), in every part of the fit (loss, gradient, the
scoring curvature, the Newton polish, the standard errors: the posterior's curvature). A
Uniform prior is a box (``bounds``). Fixed (``model.theta``) and free (``params=``) are the
two ends of a prior, very narrow and very wide. ``TuneResult.loglik`` stays the plain
log-likelihood; ``priors``, ``pulls`` (the estimate's distance from the prior's centre in its
standard deviations; a warning beyond 3) and ``log_prior`` report the rest.

Where a fit starts (:mod:`vehjax.tune.staged`). By default (``start="data"``) a model that
nests a simpler one (``model.nested_model()``: the saturating tyres of
``SingleTrack(tyres="brush" | "pacejka")`` nest the linear ones) is fitted after it: the nested
model's fit gives the start, a parameter whose least value the data imply
(``model.data_floors``: mu >= the drive's peak |ay| / g) starts just above that floor, a second
start follows where the first stays below the nested model's likelihood, and the result says
so where it still does (``TuneResult.nested``, ``below_nested``, ``below_floor``).
``start="theta"`` fits from ``model.theta`` and the given noise as they are
(:func:`fit_from_theta`, still compared with the nested model unless ``compare=False``).

Parameterisations (unconstrained vector -> physical value), chosen from the starting values:

* a diagonal ``Q0``/``R0`` ((n,) variances, or a matrix with zero off-diagonal entries) is fitted
  as diagonal: ``Q = diag(exp(2 d))`` (log standard deviations);
* a full one as full, by its log-Cholesky factor: ``Q = L L^T``, ``L`` lower triangular with
  diagonal ``exp(d)`` and free entries below it. Both keep Q positive definite.
* model parameters named in ``params``: each stays in the physical domain its model declares
  (``model.param_domains()``, e.g. (0, 3) for a friction coefficient), narrowed by
  ``bounds={name: (lo, hi)}`` where given. A box (``lo + (hi - lo) sigmoid(s)``), a lower
  bound (``lo + exp(s)``), an upper bound or none; a parameter with neither a declared domain
  nor ``bounds`` is kept positive (``exp(s)``) when its starting value is positive, else left
  free. The starting values are
  ``model.theta`` (set them with ``model.with_theta(...)``). The maps are the parameter-domain
  transforms the filters use (unit scale; :mod:`vehjax.tune.parameterisation`).
* ``x0`` (``fit_x0=True``): free, shared (nx,) or one per run (R, nx) as given.

* the input noise (``noise=(..., "input")``, starting value ``builder_kwargs["input_noise"]``):
  stds by input name as log standard deviations, a covariance like Q.

Optimisers (:mod:`vehjax.tune.optimisers`). ``"scoring"``, the default for deterministic
filters (EKF, UKF, CKF and their square-root forms) with at most 12 fitted coordinates: the
derivatives by forward mode (:func:`forward_scores`: each step's score with n tangents carried
through the filter, several times cheaper than reverse mode through a long scan), BHHH steps
on the outer product of the per-step scores (:func:`score_outer_product`,
:func:`scoring_direction`; a Gauss-Newton-type curvature from the same evaluation) with a
backtracking line search (a full step that gains nearly its first-order prediction is
lengthened once: far from the optimum the outer product overestimates the curvature), handing
a slow tail (where the model does not fit the data exactly) or a step that gains less than
0.01 log-likelihood units to Newton steps on the Hessian by differences of the gradient,
which the standard errors need anyway. ``"lbfgs"``, the default with more coordinates:
``optax.lbfgs`` with its zoom line search (strong Wolfe conditions), stopping when every
component of the gradient of the loss with respect to the unconstrained coordinates is at most
``gtol`` (the projected gradient: the coordinates are unconstrained), then one Newton step on
the Hessian. ``"adam"``, the default for particle filters (learning rate 0.05 with a cosine
decay to 5 % of it over ``steps``, on the unconstrained scale, i.e. about 5 % relative change
of a standard deviation per step at first), or any ``optax.GradientTransformation``: updates
whose gradient is not finite are skipped, and the fit ends when the best loss has not improved
by more than ``tol * max(1, |best|)`` for ``patience`` iterations; the values at the best loss
are returned. Every part of a fit (iterations, line search, curvature) evaluates one compiled
program, the loss and its gradient (:mod:`vehjax.tune.program`); a long fit
(:data:`vehjax.tune.program.BATCH_HESSIAN_STEPS` run-steps or more, forward mode) also
compiles the gradient at the Hessian's 2 n central-difference points side by side, which costs
about 2 evaluations; a shorter one forms the Hessian by forward differences, n evaluations
evaluated at once on the host's cores (``side_by_side`` of :mod:`vehjax.execution`).

How sure (:mod:`vehjax.tune.information`). Every fit reports the standard error of each fitted
quantity in its units and their correlations (``TuneResult.std_errors``, ``correlations``),
from the observed information: the Hessian of minus the log-likelihood in the unconstrained
coordinates (differences of JAX's exact gradient, or ``hessian="jax"``), inverted over the
directions the data determine and carried to the physical quantities by the delta method
(:func:`uncertainty`). Directions with no or too little curvature are named
(``TuneResult.undetermined`` and a warning): a parameter or noise entry the data cannot
determine does not come back silently at its start value. The standard errors of a fitted
``x0`` come from the same curvature (its information from the first steps is always below the
prior's 1 / P0; that is no reason to call it undetermined).

On a bound (:mod:`vehjax.tune.boundaries`). Where the likelihood increases beyond a bound of a
quantity's domain (``bounds=`` of a parameter, 0 for a variance of a diagonal Q or R or an
input-noise std) the fit is the bound: the quantity is reported *on its bound*
(``TuneResult.on_bound``: the side, the bound and the derivative of the log-likelihood there,
pointing out of the box; the summary says "on its upper bound 0.6 (the likelihood increases
beyond it: d logL/d a = 125)" and a warning too), not "not determined", and the other
quantities' standard errors come from the curvature along the free directions, the bound ones
held. ``converged`` is the projected gradient's test: the gradient over the free coordinates
at most ``gtol``, the quantities on a bound with the likelihood increasing beyond them. The
optimiser keeps a bounded quantity's coordinate within
:data:`vehjax.tune.boundaries.LOG_RANGE` of its start and refuses points where more runs
diverge than at the start, so a fit ends where its estimator can be built (a one-step fit
too).

Where the model and the data disagree (:mod:`vehjax.tune.diagnostics`). A fit with standard
errors of a deterministic filter also tests each model parameter it held fixed: the score
(Lagrange-multiplier) test at the optimum, without a refit, says how much log-likelihood
freeing it would gain and where one Newton step would take it (``TuneResult.score_tests``);
and it checks each output's innovations for whiteness (``TuneResult.innovations``,
:func:`check_innovations` for a filter run of one's own). The summary and a warning name a
held value the data contradict, e.g. ``iz = 2700 [kg m^2] (held fixed): the data reject it:
freeing it would gain about 203 log-likelihood units (p < 1e-16; one step to 6900)``: fitted
values conditional on a wrong held one can be far off with small standard errors.

Particle filter (:mod:`vehjax.tune.particle`). A particle filter
(``builder=vehjax.filters.bootstrap_pf``) is differentiated with stop-gradient resampling, built
with ``resample=vehjax.filters.smc.resample_stop_gradient`` (:func:`stop_gradient_pf`; Scibior &
Wood 2021, "Differentiable particle filtering without modifying the forward pass"): its forward
pass is the bootstrap PF's, value for value (same keys, same particles, same log-likelihood),
and after a resampling each particle's log weight is ``-log N + log W_a - stop_gradient(log
W_a)`` for its ancestor a, so the gradient of the log-likelihood estimate also carries the score
of the resampling. Particles are moved by the reparameterised ``f(x) + chol(Q) z``, so
gradients with respect to Q, R, model parameters and x0 all flow. The estimate of the score is
consistent (bias O(1/N)), with a Monte-Carlo error; each run uses the key
``jax.random.split(key, R)[r]`` for every iteration (common random numbers), as
:func:`vehjax.run` does. Prefer adam: the piecewise-constant resampling makes the PF's
objective unsuitable for a line search.

Modules: :mod:`~vehjax.tune.likelihood` (the objective), :mod:`~vehjax.tune.parameterisation`
(the coordinates), :mod:`~vehjax.tune.priors` (penalised likelihood),
:mod:`~vehjax.tune.program` (the compiled loss and scores),
:mod:`~vehjax.tune.optimisers`, :mod:`~vehjax.tune.information` (observed information, standard
errors), :mod:`~vehjax.tune.boundaries` (quantities on a bound),
:mod:`~vehjax.tune.quantities` (names, units, scales), :mod:`~vehjax.tune.result`,
:mod:`~vehjax.tune.driver` (:func:`fit_from_theta`, :func:`fit_noise`),
:mod:`~vehjax.tune.staged` (:func:`fit`: the start and the comparison),
:mod:`~vehjax.tune.compare` (:func:`compare`: candidate structures side by side),
:mod:`~vehjax.tune.diagnostics` (score tests of the parameters held fixed) and
:mod:`~vehjax.tune.innovations` (:func:`check_innovations`: per-output whiteness). Measurements behind the
defaults:
``benchmarks/results/notes_tune.md``.
"""

from __future__ import annotations

from . import (boundaries, diagnostics, driver, information, innovations, likelihood,
               optimisers, priors, program, quantities, staged)
from .driver import fit_from_theta, fit_noise
from .staged import fit
from .compare import StructureComparison, compare
from .diagnostics import ScoreTest
from .innovations import InnovationCheck, check_innovations
from .information import Uncertainty, hessian_from_gradients, uncertainty
from .likelihood import Objective, objective, prepare
from .optimisers import scoring_direction
from .particle import stop_gradient, stop_gradient_pf
from .program import forward_scores, score_outer_product
from .quantities import fitted_quantities
from .result import Comparison, TuneResult

__all__ = ["fit", "fit_from_theta", "fit_noise", "objective", "Objective", "TuneResult", "stop_gradient_pf",
           "forward_scores", "score_outer_product", "scoring_direction",
           "uncertainty", "Uncertainty", "fitted_quantities", "hessian_from_gradients",
           "stop_gradient", "prepare", "Comparison", "compare", "StructureComparison",
           "check_innovations", "InnovationCheck", "ScoreTest"]
