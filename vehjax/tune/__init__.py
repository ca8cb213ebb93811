"""Tuning: fit noise covariances, model parameters and x0 by maximising the filter's likelihood.

::

    res = vehjax.tune.fit_noise(vehjax.filters.ukf, model, Q0, R0, sim.measurements, sim.inputs,
                                x0=x0, P0=P0)
    res.Q, res.R                 # fitted covariances (full matrices)
    res.history                  # loss per iteration
    out = vehjax.run(res.estimator, ys, us, x0=x0, P0=P0)   # the tuned filter, ready to run
    print(res.summary())         # fitted values with names and units

    res = vehjax.tune.fit(vehjax.filters.ekf, model, Q0, R0, ys, us, x0=x0, P0=P0,
                          params=("m", "iz"))                 # model parameters too

What is fitted: ``params``, names or :class:`Fitted` (names, noise, x0, bounds, priors); how:
``options``, :class:`Options` (the optimiser, a record each: :class:`Adam`, :class:`LBFGS`,
:class:`Scoring`, :class:`FirstOrder`; :class:`StandardErrors`; progress; a particle filter's
key); where from: ``start``, "data", "theta" or :class:`Start` (:mod:`vehjax.tune.options`).
The builder's own options go with it, as :mod:`vehjax.calibrate` takes them:
``fit(functools.partial(vehjax.filters.ekf, sqrt=True, input_noise={"delta": 0.002}), ...)``.

The objective is the summed log-likelihood ``sum_r vehjax.filter(est, y_r, u_r, ...).loglik.sum()``
over a batch of runs (one run ``(T, ny)`` or a batch ``(R, T, ny)``), ``jax.grad`` of it through
``vehjax.filter`` vmapped over the runs, with the estimator rebuilt by ``builder(model, Q, R)``
inside the differentiated function. The optimiser minimises the loss
``-sum loglik / (R T)``, the negative mean log-likelihood per step, which is what
``history`` records.

Priors (:mod:`vehjax.tune.priors`): ``Fitted(priors={"iz": LogNormal(2763.0, 0.3), "m":
Normal(1500.0, 75.0)})`` (the objects of :mod:`vehjax.lib.priors`, the same dict
:func:`vehjax.calibrate.pmmh` takes) fits each named parameter by penalised likelihood, the loss
``-(sum loglik + sum_j log p_j(theta_j)) / (R T)`` (the MAP estimate in physical coordinates);
``TuneResult.loglik`` stays the plain log-likelihood, ``pulls`` and ``log_prior`` report the rest.

Where a fit starts (:mod:`vehjax.tune.staged`): by default (``start="data"``) a model that nests a
simpler one (``model.nested_model()``) is fitted after it, a parameter with a floor the data imply
(``model.data_floors``) starts just above it, and the result says where the fit stays below the
nested model (``TuneResult.nested``, ``below_nested``, ``below_floor``); ``start="theta"`` fits
from ``model.theta`` and the given noise (:func:`fit_from_theta`).

Parameterisations: a diagonal ``Q0``/``R0`` is fitted as log standard deviations, a full one by
its log-Cholesky factor (both keep Q positive definite); a model parameter in ``params`` stays in
its declared domain (``model.param_domains()``), narrowed by ``Fitted.bounds``; ``x0``
(``Fitted(x0=True)``) and the input noise (``Fitted(noise=(..., "input"))``) can be fitted too.

Optimisers (:mod:`vehjax.tune.optimisers`): ``"scoring"`` (BHHH on forward-mode scores, then
Newton steps; the default for deterministic filters with at most 12 fitted coordinates),
``"lbfgs"`` (``optax.lbfgs``, the default with more), ``"adam"`` (the default for particle
filters) or any ``optax.GradientTransformation``; every part of a fit evaluates one compiled
program, the loss and its gradient (:mod:`vehjax.tune.program`).

How sure: the standard errors and correlations of every fitted quantity in its units, from the
observed information by the delta method (:mod:`vehjax.tune.information`), undetermined
directions named (``TuneResult.undetermined``); a quantity the likelihood pushes beyond a bound is
reported on it (``TuneResult.on_bound``, :mod:`vehjax.tune.boundaries`). Where the model and the
data disagree: score tests of each parameter held fixed (``TuneResult.score_tests``) and the
innovations' whiteness per output (``TuneResult.innovations``, :func:`check_innovations`).

A particle filter (``builder=vehjax.filters.bootstrap_pf``, :mod:`vehjax.tune.particle`) is
differentiated with stop-gradient resampling (Scibior & Wood 2021; its forward pass is the
bootstrap PF's, value for value): the score estimate is consistent (bias O(1/N)) with a
Monte-Carlo error; prefer adam (the resampling makes the objective unsuitable for a line search).

See docs/tune.md for each part in full: the priors' every use, the start and the nested
comparison, each parameterisation's map, each optimiser's steps, stopping rules and Hessian, the
standard errors, bounds, score tests, and the particle filter's gradient.

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
               optimisers, options, priors, program, quantities, staged)
from .driver import fit_from_theta, fit_noise
from .staged import fit
from .compare import StructureComparison, compare
from .diagnostics import ScoreTest
from .innovations import InnovationCheck, check_innovations
from .information import Uncertainty, hessian_from_gradients, uncertainty
from .likelihood import Objective, objective, prepare
from .optimisers import scoring_direction
from .options import (LBFGS, Adam, FirstOrder, Fitted, Options, Scoring, StandardErrors,
                      Start)
from .particle import stop_gradient, stop_gradient_pf
from .program import forward_scores, score_outer_product
from .quantities import fitted_quantities
from .result import Comparison, TuneResult

__all__ = ["fit", "fit_from_theta", "fit_noise", "objective", "Objective", "TuneResult", "stop_gradient_pf",
           "forward_scores", "score_outer_product", "scoring_direction",
           "uncertainty", "Uncertainty", "fitted_quantities", "hessian_from_gradients",
           "stop_gradient", "prepare", "Comparison", "compare", "StructureComparison",
           "check_innovations", "InnovationCheck", "ScoreTest", "Fitted", "Options", "Start",
           "Adam", "LBFGS", "Scoring", "FirstOrder", "StandardErrors"]
