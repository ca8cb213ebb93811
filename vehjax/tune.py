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

Parameterisations (unconstrained vector -> physical value), chosen from the starting values:

* a diagonal ``Q0``/``R0`` ((n,) variances, or a matrix with zero off-diagonal entries) is fitted
  as diagonal: ``Q = diag(exp(2 d))`` (log standard deviations);
* a full one as full, by its log-Cholesky factor: ``Q = L L^T``, ``L`` lower triangular with
  diagonal ``exp(d)`` and free entries below it. Both keep Q positive definite.
* model parameters named in ``params``: ``bounds={name: (lo, hi)}`` gives a box
  (``lo + (hi - lo) sigmoid(s)``), ``(lo, None)`` a lower bound (``lo + exp(s)``), ``(None, hi)`` an
  upper bound, ``(None, None)`` none; a parameter not in ``bounds`` is kept positive
  (``exp(s)``) when its starting value is positive, else left free. The starting values are
  ``model.theta`` (set them with ``model.with_theta(...)``). The maps are the parameter-domain
  transforms the filters use, :mod:`vehjax.filters._bounds` (unit scale).
* ``x0`` (``fit_x0=True``): free, shared (nx,) or one per run (R, nx) as given.

* the input noise (``noise=(..., "input")``, starting value ``builder_kwargs["input_noise"]``):
  stds by input name as log standard deviations, a covariance like Q.

Optimisers. ``"scoring"``, the default for deterministic filters (EKF, UKF, CKF and their
square-root forms) with at most 12 fitted coordinates: the derivatives by forward mode
(:func:`forward_scores`: each step's score with n tangents carried through the filter, several
times cheaper than reverse mode through a long scan), BHHH steps on the outer product of the
per-step scores (:func:`score_outer_product`, :func:`scoring_direction`; a Gauss-Newton-type
curvature from the same evaluation) with a backtracking line search, then Newton steps on the
Hessian by differences of the gradient, which the standard errors need anyway.
``"lbfgs"``, the default with more coordinates: L-BFGS (:func:`lbfgs_direction`) with a weak-Wolfe line search
(:func:`wolfe_search`), stopping when every component of the gradient of the loss with respect
to the unconstrained coordinates is at most ``gtol`` (the projected gradient: the coordinates are
unconstrained), then one Newton step on the Hessian. ``"adam"``, the default for particle
filters (learning rate 0.05 with a cosine decay to 5 % of it over ``steps``, on the unconstrained
scale, i.e. about 5 % relative change of a standard deviation per step at first), or any
``optax.GradientTransformation``: updates whose gradient is not finite are skipped, and the fit
ends when the best loss has not improved by more than ``tol * max(1, |best|)`` for ``patience``
iterations; the values at the best loss are returned. Every part of a fit (iterations, line
search, curvature) evaluates one compiled program, the loss and its gradient; a long fit
(``_BATCH_HESSIAN_STEPS`` run-steps or more, forward mode) also compiles the gradient at the
Hessian's 2 n central-difference points side by side, which costs about 2 evaluations; a
shorter one forms the Hessian by forward differences, n evaluations (:func:`_difference_hessian`).

How sure. Every fit reports the standard error of each fitted quantity in its units and their
correlations (``TuneResult.std_errors``, ``correlations``), from the observed information: the
Hessian of minus the log-likelihood in the unconstrained coordinates (differences of JAX's
exact gradient, or ``hessian="jax"``), inverted over the directions the data determine and
carried to the physical quantities by the delta method (:func:`uncertainty`). Directions with no
or too little curvature are named (``TuneResult.undetermined`` and a warning): a parameter or
noise entry the data cannot determine does not come back silently at its start value.

Particle filter. A particle filter (``builder=vehjax.filters.bootstrap_pf``) is differentiated
with stop-gradient resampling, built with ``resample=vehjax.filters.smc.resample_stop_gradient``
(:func:`stop_gradient_pf`; Scibior & Wood 2021, "Differentiable
particle filtering without modifying the forward pass"): its forward pass is the bootstrap PF's,
value for value (same keys, same particles, same log-likelihood), and after a resampling each
particle's log weight is ``-log N + log W_a - stop_gradient(log W_a)`` for its ancestor a, so
the gradient of the log-likelihood estimate also carries the score of the resampling.
Particles are moved by the reparameterised ``f(x) + chol(Q) z``, so gradients with respect to
Q, R, model parameters and x0 all flow. The estimate of the score is consistent
(bias O(1/N)), with a Monte-Carlo error; each run uses the key ``jax.random.split(key, R)[r]``
for every iteration (common random numbers), as :func:`vehjax.run` does. Prefer adam: the
piecewise-constant resampling makes the PF's objective unsuitable for a line search.
"""

from __future__ import annotations

import inspect
import sys
import time
import warnings
from typing import Any, Callable, Mapping, NamedTuple

import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import optax

from . import validation
from .filtering import filter as _filter
from .filters import bounds as _bounds
from .filters import input_noise as _inoise
from .filters import smc
from .filters.base import Estimator
from .filters.particle import bootstrap_pf
from .models.base import BaseModel

__all__ = ["fit", "fit_noise", "objective", "Objective", "TuneResult", "stop_gradient_pf",
           "forward_scores", "score_outer_product", "scoring_direction",
           "uncertainty", "Uncertainty", "fitted_quantities"]

_NOISE = ("Q", "R")
_NOISE_KINDS = ("Q", "R", "input")
_OPTIMIZERS = ("adam", "lbfgs", "scoring")
_ADAM_LR = 0.05
_ADAM_STEPS = 300
_LBFGS_STEPS = 100
_GTOL = 1e-6  # L-BFGS: max |d loss / dz| at convergence (loss per step, z unconstrained)
_RCOND = 1e-8  # undetermined: eigenvalue of the scaled information below this x the largest
_MAX_SCALED_STD = 1.0  # ... or a standard error above the quantity's own size (scaled units)


# ----------------------------------------------------------------------------------------------
# results


class TuneResult(NamedTuple):
    """What :func:`fit` and :func:`fit_noise` return.

    Attributes:
        Q: fitted process-noise covariance, (nx, nx) (``Q0`` when Q was not fitted).
        R: fitted measurement-noise covariance, (ny, ny) (``R0`` when not fitted).
        theta: the fitted model's whole parameter vector, (np,).
        params: fitted model parameters by name (empty when none were fitted).
        x0: the fitted initial state ((nx,) or (R, nx)), or the given one.
        model: the model with the fitted parameters (``model.with_theta``).
        estimator: ``builder(model, Q, R, **builder_kwargs)`` at the fitted values, ready for
            :func:`vehjax.run`.
        loglik: total log-likelihood of the runs at the fitted values (sum over runs).
        loglik0: the same at the starting values.
        history: loss per iteration, (iterations,): ``-sum loglik / (R T)`` at the values that
            iteration started from.
        iterations: how many optimiser iterations ran.
        converged: L-BFGS (and deterministic filters after the Newton polish): the gradient
            reached ``gtol``; adam and custom optimisers: the loss stopped improving
            (``patience``).
        diverged: how many runs diverged (``vehjax.filter``'s flag) at the fitted values.
        skipped: iterations whose gradient was not finite.
        values: every fitted quantity by name: ``"Q[x,x]"``, ``"R[y,y]"``, a parameter name,
            ``"x0[v]"`` (``"x0[r,v]"`` per run); covariances as variances/covariances.
        units: the unit of each entry of ``values`` (``"m^2"``, ``"kg"``, ...; ``"-"`` unknown).
        seconds: wall-clock time of the fit, including compilation.
        std_errors: standard error of each entry of ``values`` in its units (same keys), from
            the observed information (the Hessian of the log-likelihood by JAX in the
            unconstrained coordinates, carried to the physical quantities by the delta method);
            inf for a quantity the data do not determine; empty with
            ``standard_errors=False``. For a particle filter a Monte-Carlo estimate.
        correlations: (m, m) correlations of the entries of ``values`` (in their order); NaN
            rows and columns for undetermined quantities.
        undetermined: names of the fitted quantities (coordinates) along directions of no or
            too little curvature (:func:`uncertainty`); a warning names them too.
        gradient: max |d loss / dz| at the result (the loss per step, z unconstrained).
        input_noise: the fitted input noise as the builder takes it (stds by name or a
            covariance), or the given one, or None.
        evaluations: evaluations of the compiled loss-and-gradient program (optimiser, line
            search, Hessian by differences, Newton polish).
        optimizer: the optimiser that ran ("scoring", "lbfgs", "adam" or "optax").
        derivatives: "forward" (:func:`forward_scores`) or "reverse" (``jax.value_and_grad``).
        compile_seconds: wall-clock seconds of compiling that program (part of ``seconds``).
        hessian_batches: calls of the program that evaluates the gradient at the Hessian's 2 n
            difference points at once (long forward-mode fits, :data:`_BATCH_HESSIAN_STEPS`;
            0 when the points went through the one program, one by one).
        hessian_compile_seconds: wall-clock seconds of compiling that second program (part of
            ``seconds``; 0.0 when there was none).
        compile_cpu_seconds: CPU seconds (``time.process_time``, every thread of the process)
            of compiling the loss-and-gradient program: on a machine shared with other work
            the compile's wall-clock time says more about the load than about the compile.
    """

    Q: np.ndarray
    R: np.ndarray
    theta: np.ndarray
    params: dict
    x0: np.ndarray
    model: Any
    estimator: Estimator
    loglik: float
    loglik0: float
    history: np.ndarray
    iterations: int
    converged: bool
    diverged: int
    skipped: int
    values: dict
    units: dict
    seconds: float
    std_errors: dict = {}
    correlations: np.ndarray | None = None
    undetermined: tuple = ()
    gradient: float = float("nan")
    input_noise: Any = None
    evaluations: int = 0
    optimizer: str = ""
    derivatives: str = ""
    compile_seconds: float = float("nan")
    hessian_batches: int = 0
    hessian_compile_seconds: float = 0.0
    compile_cpu_seconds: float = float("nan")

    def summary(self) -> str:
        """A text table of the fitted values with their units and the log-likelihood."""
        lines = [
            f"{self.estimator.name} tuned in {self.iterations} iterations ({self.seconds:.1f} s)"
            f"{', converged' if self.converged else ''}: log-likelihood {self.loglik0:.6g} -> "
            f"{self.loglik:.6g}" + (f", {self.diverged} runs diverged" if self.diverged else "")
        ]
        width = max((len(k) for k in self.values), default=0)
        for k, v in self.values.items():
            se = self.std_errors.get(k)
            pm = "" if se is None else f" +- {se:.3g}"
            lines.append(f"  {k:<{width}} = {v:.6g}{pm} [{self.units[k]}]")
        if self.undetermined:
            lines.append(f"  not determined by the data: {', '.join(self.undetermined)}")
        return "\n".join(lines)


class Objective(NamedTuple):
    """The objective :func:`fit` minimises, for use with an optimiser of one's own.

    Attributes:
        loss: ``loss(z, data) -> (value, (loglik (R,), diverged (R,)))``, value the negative
            mean log-likelihood per step; pure and differentiable in ``z``.
        z0: starting point, a dict of unconstrained arrays (keys among "Q", "R", "theta", "x0").
        data: the batch of runs the loss reads (pass it as the second argument).
        unpack: ``unpack(z) -> dict`` of physical values: "Q" (nx, nx), "R" (ny, ny), "theta"
            (np,) the model's whole parameter vector, "x0".
        n_steps: R T, the number of run-steps the loss is averaged over.
    """

    loss: Callable
    z0: dict
    data: tuple
    unpack: Callable
    n_steps: int


# ----------------------------------------------------------------------------------------------
# parameterisations


def _is_diag(A: np.ndarray) -> bool:
    return not np.any(A - np.diag(np.diagonal(A)))


class _Cov:
    """Log-diagonal or log-Cholesky parameterisation of an (n, n) covariance."""

    def __init__(self, A: np.ndarray, diag: bool):
        self.n, self.diag = A.shape[0], diag
        self.rows, self.cols = np.tril_indices(self.n, -1)
        L = np.linalg.cholesky(A)
        d = np.log(np.diagonal(L))
        self.z0 = d if diag else np.concatenate([d, L[self.rows, self.cols]])

    def __call__(self, z):
        n = self.n
        if self.diag:
            return jnp.diag(jnp.exp(2.0 * z))
        L = jnp.diag(jnp.exp(z[:n])).at[self.rows, self.cols].set(z[n:])
        return L @ L.T


class _InputNoise:
    """Parameterisation of the input noise (``builder_kwargs["input_noise"]``, its starting
    value): a dict ``{input name: std}`` is fitted by the log standard deviations of the named
    inputs (the builder gets ``{name: exp(z)}``), an (nu, nu) covariance like Q0 (log-diagonal
    or log-Cholesky, positive definite)."""

    def __init__(self, spec, model):
        names = tuple(model.input_names)
        _inoise.input_factor(spec, names)  # the filters' own checks, ValueError naming it
        if isinstance(spec, Mapping):
            self.names = tuple(n for n in names if n in spec)
            self.z0 = np.log(np.array([float(spec[n]) for n in self.names]))
            self.cov = None
        else:
            S = validation.cov("input_noise", np.asarray(spec, dtype=float), len(names),
                              allow_diag=False)
            self.names, self.diag = names, _is_diag(S)
            self.cov = _Cov(S, self.diag)
            self.z0 = self.cov.z0

    def __call__(self, z):
        if self.cov is None:
            return {n: jnp.exp(z[i]) for i, n in enumerate(self.names)}
        return self.cov(z)


def _param_transform(params, bounds, theta0: np.ndarray, names: tuple):
    """(indices (q,) in ``names``, :class:`vehjax.filters._bounds.Transform`) of the fitted
    parameters; ValueError naming ``bounds``. A parameter not in ``bounds`` is kept positive when
    its starting value is positive, else left free (module docstring)."""
    bounds = validation.keyed("bounds", bounds, params, "the fitted params")
    idx = np.array([names.index(p) for p in params], dtype=int)
    low, high = np.empty(len(params)), np.empty(len(params))
    for j, p in enumerate(params):
        v = float(theta0[idx[j]])
        if p in bounds:
            low[j], high[j] = _bounds.check_pair("bounds", p, bounds[p])
            if not low[j] < v < high[j]:
                show = lambda b: None if np.isinf(b) else float(b)  # noqa: E731
                raise ValueError(
                    f"bounds: the starting value {p} = {v} (model.theta) must lie strictly "
                    f"inside ({show(low[j])}, {show(high[j])}); set it with "
                    f"model.with_theta({p}=...)"
                )
        else:
            low[j], high[j] = (0.0 if v > 0 else -np.inf), np.inf
    return idx, _bounds.Transform(low, high)


def _units(model, attr: str, n: int) -> tuple:
    if isinstance(model, BaseModel):
        return tuple(getattr(model, attr))
    return ("-",) * n


def _sq(u: str) -> str:
    if u == "-":
        return "-"
    return f"{u}^2" if u.isalnum() else f"({u})^2"


def _prod(a: str, b: str) -> str:
    if "-" in (a, b):
        return "-"
    if a == b:
        return _sq(a)
    wrap = (lambda u: u if u.isalnum() else f"({u})")
    return f"{wrap(a)}*{wrap(b)}"


# ----------------------------------------------------------------------------------------------
# the stop-gradient particle filter
#
# The particle filters resample through the function they are built with (``resample=``).
# vehjax.filters.smc.resample gives every resampled particle the constant log weight -log N;
# vehjax.filters.smc.resample_stop_gradient gives it -log N + log W_a - stop_gradient(log W_a):
# the same value, but its gradient carries the ancestor's log weight. tune builds a particle
# filter with the latter: the forward pass is the filter's own, value for value.


def stop_gradient(estimator: Estimator) -> Estimator:
    """Refused: stop-gradient resampling is chosen when a particle filter is built.

    Build the filter with ``resample=vehjax.filters.smc.resample_stop_gradient``
    (``bootstrap_pf``, ``liu_west_ukf``, ``marginalized_pf``) or use :func:`stop_gradient_pf`;
    :func:`fit` and :func:`objective` do so for a particle filter's builder themselves.

    Raises:
        ValueError: naming ``estimator``, always (a built filter's resampling cannot be
            changed).
    """
    name = getattr(estimator, "name", type(estimator).__name__)
    raise ValueError(
        f"estimator: stop_gradient cannot change the resampling of a built filter ({name!r}); "
        f"build it with resample=vehjax.filters.smc.resample_stop_gradient, e.g. "
        f"vehjax.filters.bootstrap_pf(model, Q, R, resample=...), or use "
        f"vehjax.tune.stop_gradient_pf(model, Q, R, ...)")


def _stop_gradient_kwargs(builder, name: str, builder_kwargs) -> dict:
    """The keyword that makes ``builder`` (a particle filter's, called ``name``) resample with
    stop-gradient weights: ``{"resample": smc.resample_stop_gradient}``, or {} when
    ``builder_kwargs`` already names a ``resample``. ValueError naming ``builder`` when it takes
    no ``resample`` keyword."""
    if "resample" in builder_kwargs:  # the caller's own choice
        return {}
    try:
        params = inspect.signature(builder).parameters.values()
    except (TypeError, ValueError):  # no signature to read: let the call say
        params = ()
    if params and not any(q.name == "resample" or q.kind is q.VAR_KEYWORD for q in params):
        raise ValueError(
            f"builder: {name} draws random numbers (a particle filter) but takes no resample= "
            f"keyword; tune differentiates a particle filter with stop-gradient resampling, "
            f"passed as resample=vehjax.filters.smc.resample_stop_gradient")
    return {"resample": smc.resample_stop_gradient}


def stop_gradient_pf(model, Q, R, n_particles: int = 1000, resampling: str = "systematic",
                     ess_threshold: float = 0.5) -> Estimator:
    """``vehjax.filters.bootstrap_pf(model, Q, R, ..., resample=smc.resample_stop_gradient)``:
    the bootstrap PF with stop-gradient resampling (Scibior & Wood 2021), a builder with
    bootstrap_pf's arguments.

    The result has the bootstrap PF's ``init`` and forward pass, value for value (random
    numbers, particles, resampling decisions and indices, outputs); only gradients differ:
    after a resampling, particle i's normalised log weight is ``-log N + log W_a -
    stop_gradient(log W_a)`` (value ``-log N``) for its ancestor a
    (:func:`vehjax.filters.smc.stop_gradient_weights`). The gradient of ``sum_t loglik_t`` is
    then the Fisher-identity estimate of the score, ``sum_i W_T^i grad log p(x^i_0:T, y_1:T)``
    along the particles' ancestral paths (the particles reparameterised, ``f(x) + chol(Q) z``),
    a consistent estimate of ``grad log p(y_1:T)`` (bias O(1/N))."""
    return bootstrap_pf(model, Q, R, n_particles, resampling, ess_threshold,
                        resample=smc.resample_stop_gradient)


# ----------------------------------------------------------------------------------------------
# validation and the objective


def _float_array(name: str, value, allow_nan: bool = False) -> np.ndarray:
    if validation.is_tracer(value):
        raise ValueError(f"{name}: expected a concrete array; call vehjax.tune outside jit/grad")
    # the rules every entry point shares (real; NaN missing in measurements, else finite)
    return np.array(validation.array(name, value, missing=allow_nan), dtype=float)


def _check_builder(builder):
    if not callable(builder):
        raise ValueError(
            f"builder: expected a filter builder such as vehjax.filters.ukf, got {builder!r}"
        )
    if builder is stop_gradient_pf:  # the same filter forward; its gradients are applied anyway
        return bootstrap_pf
    return builder


def _prepare(builder, model, Q0, R0, measurements, inputs, x0, P0, params, bounds, noise,
             fit_x0, key, builder_kwargs):
    """Everything checked before tracing; returns the pieces of the objective."""
    builder = _check_builder(builder)
    validation.model(model)
    nx, ny, nu = len(model.state_names), len(model.output_names), len(model.input_names)
    noise = validation.names("noise", noise, _NOISE_KINDS, allow_empty=True)
    # a Q0 that is not fitted may be singular (zero with the noise through the inputs)
    Qa = validation.cov("Q0", _float_array("Q0", Q0), nx, allow_psd="Q" not in noise)
    Ra = validation.cov("R0", _float_array("R0", R0), ny)
    diagQ = np.ndim(Q0) == 1 or _is_diag(Qa)
    diagR = np.ndim(R0) == 1 or _is_diag(Ra)
    names = tuple(model.param_names)
    if isinstance(params, Mapping):
        raise ValueError("params: expected a sequence of parameter names; give their bounds in "
                         "bounds={name: (lo, hi)}")
    params = validation.names("params", params, names, allow_empty=True)
    theta0 = np.asarray(model.theta, dtype=float)
    idx, theta_map = _param_transform(params, bounds, theta0, names)
    if not isinstance(fit_x0, (bool, np.bool_)):
        raise ValueError(f"fit_x0: expected True or False, got {fit_x0!r}")
    if not noise and not params and not fit_x0:
        raise ValueError("noise: nothing to fit: noise=(), params=() and fit_x0=False")
    if builder_kwargs is None:
        builder_kwargs = {}
    if not isinstance(builder_kwargs, Mapping):
        raise ValueError(f"builder_kwargs: expected a dict of keyword arguments, got "
                         f"{builder_kwargs!r}")
    builder_kwargs = dict(builder_kwargs)
    inp = None
    if "input" in noise:
        if builder_kwargs.get("input_noise") is None:
            raise ValueError("noise: 'input' fits the input noise, whose starting value goes in "
                             "builder_kwargs={'input_noise': {input name: std, ...}}")
        inp = _InputNoise(builder_kwargs["input_noise"], model)

    # the checks every entry point shares (vehjax.validation): shapes, values, the prior
    ys, us = validation.data(_float_array("measurements", measurements, allow_nan=True),
                            None if inputs is None else _float_array("inputs", inputs), ny, nu,
                            "either")
    ys = ys[None] if ys.ndim == 2 else ys
    us = None if inputs is None else us
    n_runs, T, _ = ys.shape
    x0a, P0a = validation.prior(nx, _float_array("x0", x0), _float_array("P0", P0), runs=n_runs)
    x0a, P0a = np.asarray(x0a, dtype=float), np.asarray(P0a, dtype=float)

    # the builder with the starting values: checks its own arguments, says whether it needs a key
    try:
        est0 = builder(model, Qa, Ra, **builder_kwargs)
    except TypeError as err:  # not a state-only builder(model, Q, R, **kw), or bad keywords
        raise ValueError(
            f"builder: calling it as builder(model, Q, R, **builder_kwargs) failed ({err}); tune "
            f"takes a state-only filter builder (ekf, ukf, ckf, ackf, bootstrap_pf) and fits "
            f"model parameters with params="
        ) from None
    if not isinstance(est0, Estimator):
        raise ValueError(f"builder: expected a function returning a vehjax.filters.Estimator, "
                         f"got {type(est0).__name__}")
    if est0.param_names:
        raise ValueError(f"builder: {est0.name} estimates parameters {est0.param_names}; tune "
                         f"a state-only filter (ekf, ukf, ckf, bootstrap_pf) and fit model "
                         f"parameters with params=")
    keys, sg = None, {}
    if est0.needs_key:  # a particle filter: differentiated with stop-gradient resampling
        sg = _stop_gradient_kwargs(builder, est0.name, builder_kwargs)
        if key is None:
            raise ValueError(f"key: {est0.name} draws random numbers; pass key=jax.random.key(...)")
        try:
            keys = jax.random.split(key, n_runs)
        except Exception:
            raise ValueError(f"key: expected a jax.random.key, got {key!r}") from None

    covQ = _Cov(Qa, diagQ) if "Q" in noise else None
    covR = _Cov(Ra, diagR)
    z0 = {}
    if "Q" in noise:
        z0["Q"] = jnp.asarray(covQ.z0)
    if "R" in noise:
        z0["R"] = jnp.asarray(covR.z0)
    if inp is not None:
        z0["input"] = jnp.asarray(inp.z0)
    if params:
        z0["theta"] = theta_map.to_unconstrained(jnp.asarray(theta0[idx]))
    if fit_x0:
        z0["x0"] = jnp.asarray(x0a)

    def unpack(z):
        Q = covQ(z["Q"]) if "Q" in z else jnp.asarray(Qa)
        R = covR(z["R"]) if "R" in z else jnp.asarray(Ra)
        theta = jnp.asarray(theta0)
        if "theta" in z:
            theta = theta.at[idx].set(theta_map.to_physical(z["theta"]))
        return {"Q": Q, "R": R, "theta": theta, "x0": z["x0"] if "x0" in z else jnp.asarray(x0a),
                "input": inp(z["input"]) if "input" in z else None}

    def per_step(z, data):
        """(log p(y_t | y_1:t-1) per run and step (R, T), diverged (R,)) at coordinates z."""
        ys_, us_, x0_, P0_, keys_ = data
        v = unpack(z)
        Q = v["Q"] if "Q" in z else Qa  # constants stay numpy: the builder may specialise
        R = v["R"] if "R" in z else Ra
        mdl = eqx.tree_at(lambda m: m.theta, model, v["theta"]) if "theta" in z else model
        kw = builder_kwargs if "input" not in z else {**builder_kwargs, "input_noise": v["input"]}
        est = builder(mdl, Q, R, **kw, **sg)
        x0v = v["x0"] if "x0" in z else x0_

        def one(y, u, xi, Pi, k):
            res = _filter(est, y, u, xi, Pi, key=k, return_covariances=False)
            return res.loglik, res.diverged

        axes = (0, None if us_ is None or us_.ndim == 2 else 0, 0 if x0v.ndim == 2 else None,
                0 if P0_.ndim == 3 else None, None if keys_ is None else 0)
        return jax.vmap(one, in_axes=axes)(ys_, us_, x0v, P0_, keys_)

    def loss(z, data):
        lls, div = per_step(z, data)
        ll = jnp.sum(lls, axis=-1)
        return -jnp.sum(ll) / (n_runs * T), (ll, div)

    data = (jnp.asarray(ys), None if us is None else jnp.asarray(us), jnp.asarray(x0a),
            jnp.asarray(P0a), keys)
    info = dict(name=est0.name, builder=builder, builder_kwargs=builder_kwargs, params=params,
                noise=noise, x0=x0a, Qa=Qa, Ra=Ra, diagQ=diagQ, diagR=diagR, theta0=theta0,
                fit_x0=fit_x0, input=inp, theta_map=theta_map, P0=P0a,
                stochastic=bool(est0.needs_key), per_step=per_step, workload=est0.workload)
    return Objective(loss, z0, data, unpack, n_runs * T), info


def objective(builder, model, Q0, R0, measurements, inputs=None, *, x0, P0, params=(),
              bounds=None, noise=_NOISE, fit_x0: bool = False, key=None,
              builder_kwargs=None) -> Objective:
    """The objective of :func:`fit` (same arguments), to evaluate, differentiate or optimise
    with tools of one's own: ``obj.loss(obj.z0, obj.data)``, ``obj.unpack(z)["Q"]``."""
    obj, _ = _prepare(builder, model, Q0, R0, measurements, inputs, x0, P0, params, bounds,
                      noise, fit_x0, key, builder_kwargs)
    return obj


# ----------------------------------------------------------------------------------------------
# progress


class _Progress:
    """tqdm.auto when installed, else one line on stderr rewritten at most 5 times a second."""

    def __init__(self, total: int, enabled: bool, label: str):
        self.enabled, self.total, self.label = enabled, total, label
        self.bar = None
        self.t0 = self.last = time.perf_counter()
        if not enabled:
            return
        try:
            from tqdm.auto import tqdm
        except ImportError:
            tqdm = None
        if tqdm is not None:
            self.bar = tqdm(total=total, desc=label, leave=True)

    def update(self, i: int, loss: float, best: float):
        if not self.enabled:
            return
        if self.bar is not None:
            self.bar.update(1)
            self.bar.set_postfix(loss=f"{loss:.6g}", best=f"{best:.6g}", refresh=False)
            return
        now = time.perf_counter()
        if now - self.last < 0.2 and i < self.total:
            return
        self.last = now
        sys.stderr.write(f"\r{self.label}: iteration {i}/{self.total}, loss {loss:.6g}, "
                         f"best {best:.6g}, {now - self.t0:.1f} s")
        sys.stderr.flush()

    def close(self, i: int, loss: float, best: float):
        if not self.enabled:
            return
        if self.bar is not None:
            self.bar.close()
            return
        self.last = -1.0
        self.update(i, loss, best)
        sys.stderr.write("\n")
        sys.stderr.flush()


def _optimizer(optimizer, learning_rate, steps):
    """(optax transformation, is_lbfgs)."""
    if isinstance(optimizer, str):
        validation.choice("optimizer", optimizer, _OPTIMIZERS)
        if optimizer == "adam":
            lr = _ADAM_LR if learning_rate is None else learning_rate
            sched = optax.cosine_decay_schedule(lr, max(steps, 1), alpha=0.05)
            return optax.apply_if_finite(optax.adam(sched), max_consecutive_errors=10), False
        return None, True  # vehjax's own L-BFGS / scoring on the compiled loss
    if isinstance(optimizer, optax.GradientTransformation):
        if learning_rate is not None:
            raise ValueError("learning_rate: set it inside your own optax optimizer, not here")
        return optax.apply_if_finite(optimizer, max_consecutive_errors=10), False
    raise ValueError(f"optimizer: expected 'adam', 'lbfgs' or an optax.GradientTransformation, "
                     f"got {optimizer!r}")


# ----------------------------------------------------------------------------------------------
# the fitted quantities, their coordinates, and how well the data determine them


def _cov_names(prefix: str, names: tuple, n: int, diag: bool):
    """Names of the (a <= b) entries of a fitted covariance, in the order :func:`fit` reports
    them, and of its coordinates (log-diagonal, then the Cholesky entries below it)."""
    entries = [(a, b) for a in range(n) for b in range(a, n if not diag else a + 1)]
    values = [f"{prefix}[{names[a]},{names[b]}]" for a, b in entries]
    rows, cols = np.tril_indices(n, -1)
    coords = [f"{prefix}[{names[i]},{names[i]}]" for i in range(n)]
    if not diag:
        coords += [f"{prefix}[{names[c]},{names[r]}]" for r, c in zip(rows, cols)]
    return entries, values, coords


def fitted_quantities(info, model, v):
    """The fitted quantities as ``[(name, unit, value)]`` from the physical values ``v``
    (:attr:`Objective.unpack`'s dict; jax or numpy): covariance entries ``"Q[a,b]"``,
    ``"R[a,b]"`` (variances / covariances, units squared), input-noise stds ``"input[u]"``
    (the input's unit) or covariance entries ``"input[u,w]"``, parameters by name, ``"x0[v]"``
    / ``"x0[r,v]"``. Traceable: the Jacobian of the values by JAX gives the delta method."""
    out = []
    su = _units(model, "state_units", len(model.state_names))
    ou = _units(model, "output_units", len(model.output_names))
    iu = _units(model, "input_units", len(model.input_names))
    for name, diag, cnames, cu in (("Q", info["diagQ"], model.state_names, su),
                                   ("R", info["diagR"], model.output_names, ou)):
        if name not in info["noise"]:
            continue
        entries, names, _ = _cov_names(name, cnames, len(cnames), diag)
        for (a, b), k in zip(entries, names):
            out.append((k, _sq(cu[a]) if a == b else _prod(cu[a], cu[b]), v[name][a, b]))
    inp = info["input"]
    if inp is not None:
        names = tuple(model.input_names)
        if inp.cov is None:
            for n in inp.names:
                out.append((f"input[{n}]", iu[names.index(n)], v["input"][n]))
        else:
            entries, keys, _ = _cov_names("input", names, len(names), inp.diag)
            for (a, b), k in zip(entries, keys):
                out.append((k, _sq(iu[a]) if a == b else _prod(iu[a], iu[b]), v["input"][a, b]))
    pu = _units(model, "param_units", len(model.param_names))
    for p in info["params"]:
        j = model.param_names.index(p)
        out.append((p, pu[j], v["theta"][j]))
    if info["fit_x0"]:
        x0 = v["x0"]
        for idx in np.ndindex(np.shape(x0)):
            comp = model.state_names[idx[-1]]
            k = f"x0[{comp}]" if np.ndim(x0) == 1 else f"x0[{idx[0]},{comp}]"
            out.append((k, su[idx[-1]], x0[idx]))
    return out


def _coordinates(info, model, z0):
    """(names (n,), scales (n,)) of the unconstrained coordinates, flattened in
    ``jax.flatten_util.ravel_pytree`` order (dict keys sorted). A scale is the size of a change
    of that coordinate that would be as large as the quantity itself: 1 for log standard
    deviations and log/logit parameter maps, |theta0| for a free parameter, sqrt(A0_rr) for a
    Cholesky entry below the diagonal, the prior standard deviation sqrt(P0_ii) for x0."""
    per = {}
    for name, diag, cnames, A0 in (("Q", info["diagQ"], model.state_names, info["Qa"]),
                                   ("R", info["diagR"], model.output_names, info["Ra"])):
        if name in z0:
            n = len(cnames)
            _, _, coords = _cov_names(name, cnames, n, diag)
            rows, _ = np.tril_indices(n, -1)
            sc = np.ones(n) if diag else np.concatenate([np.ones(n), np.sqrt(np.diag(A0))[rows]])
            per[name] = (coords, sc)
    inp = info["input"]
    if inp is not None:
        if inp.cov is None:
            per["input"] = ([f"input[{n}]" for n in inp.names], np.ones(len(inp.names)))
        else:
            n = len(inp.names)
            _, _, coords = _cov_names("input", inp.names, n, inp.diag)
            L0 = np.exp(inp.z0[:n])  # the starting standard deviations
            rows, _ = np.tril_indices(n, -1)
            per["input"] = (coords, np.ones(n) if inp.diag else np.concatenate(
                [np.ones(n), L0[rows]]))
    if "theta" in z0:
        th = info["theta0"][[model.param_names.index(p) for p in info["params"]]]
        free = np.array([k == "none" for k in info["theta_map"].kinds])
        per["theta"] = (list(info["params"]),
                        np.where(free, np.where(th != 0, np.abs(th), 1.0), 1.0))
    if "x0" in z0:
        P0 = info["P0"]
        sd = np.sqrt(np.diagonal(P0, axis1=-2, axis2=-1))
        x0 = info["x0"]
        names, sc = [], []
        for idx in np.ndindex(x0.shape):
            comp = model.state_names[idx[-1]]
            names.append(f"x0[{comp}]" if x0.ndim == 1 else f"x0[{idx[0]},{comp}]")
            sc.append(sd[idx[-1]] if sd.ndim == 1 else sd[idx[0], idx[-1]])
        per["x0"] = (names, np.asarray(sc))
    names, scales = [], []
    for key in sorted(z0):
        names += list(per[key][0])
        scales.append(per[key][1])
    return tuple(names), np.concatenate(scales)


class Uncertainty(NamedTuple):
    """What :func:`uncertainty` returns.

    Attributes:
        cov: (m, m) covariance of the fitted quantities in their units (delta method), with
            inf on the diagonal of a quantity an undetermined direction moves.
        std_errors: (m,) standard errors, sqrt of its diagonal (inf: undetermined).
        correlations: (m, m), NaN in the rows and columns of undetermined quantities.
        undetermined: names of the coordinates in the undetermined directions.
        eigenvalues: (n,) eigenvalues of the scaled observed information, ascending.
        determined: (n,) bool, which eigen-directions the data determine.
    """

    cov: np.ndarray
    std_errors: np.ndarray
    correlations: np.ndarray
    undetermined: tuple
    eigenvalues: np.ndarray
    determined: np.ndarray


def uncertainty(info_matrix, jac, scales, coord_names, rcond: float = _RCOND,
                max_std: float = _MAX_SCALED_STD) -> Uncertainty:
    """Standard errors and correlations of fitted quantities from the observed information.

    With ``I`` (n, n) the observed information of the unconstrained coordinates z (the Hessian
    of minus the log-likelihood), ``S = diag(scales)`` and ``I_s = S I S = V diag(lam) V^T``,
    an eigen-direction is undetermined when ``lam <= rcond * max(lam)`` (no curvature: the data
    do not move the likelihood along it) or ``lam < 1 / max_std^2`` (its standard error exceeds
    ``max_std`` of the scale, the quantity's own size: not determined to within a factor of
    about e for a log coordinate). The covariance of z over the determined directions is
    ``S V_d diag(1/lam_d) V_d^T S``, that of the quantities ``J cov_z J^T`` (delta method,
    ``jac`` = J = d quantities / dz, (m, n)). A coordinate is named undetermined when its
    component in an undetermined direction is at least 0.3 (the largest always).
    """
    Iz = np.asarray(info_matrix, dtype=float)
    J = np.asarray(jac, dtype=float)
    scales = np.asarray(scales, dtype=float)
    Is = 0.5 * (Iz + Iz.T) * np.outer(scales, scales)
    if not np.all(np.isfinite(Is)):
        n = len(scales)
        return Uncertainty(np.full((J.shape[0],) * 2, np.nan), np.full(J.shape[0], np.nan),
                           np.full((J.shape[0],) * 2, np.nan), tuple(coord_names),
                           np.full(n, np.nan), np.zeros(n, bool))
    lam, V = np.linalg.eigh(Is)
    top = max(float(lam.max()), np.finfo(float).tiny)
    det = (lam > rcond * top) & (lam >= 1.0 / max_std**2)
    Vd = V[:, det]
    cov_z = (scales[:, None] * Vd / lam[det]) @ (Vd.T * scales[None, :])
    cov = J @ cov_z @ J.T
    bad_coords = np.zeros(len(scales), bool)
    for k in np.flatnonzero(~det):
        v = np.abs(V[:, k])
        bad_coords |= (v >= 0.3) | (v == v.max())
    moved = np.any((J != 0) & bad_coords[None, :], axis=1)
    se = np.sqrt(np.maximum(np.diag(cov), 0.0))
    se[moved] = np.inf
    cov[np.ix_(moved, moved)] = np.nan
    cov[moved, moved] = np.inf
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(se, se)
    corr[moved, :] = np.nan
    corr[:, moved] = np.nan
    names = tuple(n for n, b in zip(coord_names, bad_coords) if b)
    return Uncertainty(cov, se, corr, names, lam, det)


# ----------------------------------------------------------------------------------------------
# fitting


def _finite(*arrays) -> bool:
    return all(bool(np.all(np.isfinite(np.asarray(a)))) for a in arrays)


def _check_start(f, *derivatives):
    """FloatingPointError unless the loss ``f`` and its ``derivatives`` at the starting values
    are finite."""
    if not (np.isfinite(f) and _finite(*derivatives)):
        raise FloatingPointError(
            "vehjax.tune: the log-likelihood or its gradient is not finite at the starting "
            "values; check Q0, R0, x0, P0 and the measurements")


class _Loss(NamedTuple):
    """The loss on a flat vector of coordinates (``ravel_pytree`` of z): ``vg(f) -> (loss,
    aux, grad)`` compiled once per fit and used by every part of it (the optimiser, its line
    search, the curvature, the Newton polish), so that a fit compiles one program.
    ``vgo(f) -> (loss, aux, grad, opg)`` (forward mode only, else None) also gives the outer
    product of the per-step scores (:func:`score_outer_product`) from the same evaluation.
    ``grads(F) -> (k, n)``: the gradients at the k = 2 n points F (k, n) of the Hessian's
    central differences (:func:`hessian_from_gradients`) in one vmapped forward-mode program,
    or None (:data:`_BATCH_HESSIAN_STEPS`). ``stats``: ``mode`` ("forward" or "reverse"),
    ``compile_seconds``, ``evaluations`` (of vg/vgo; a repeated point is not evaluated again),
    ``batch_compile_seconds`` and ``batch_evaluations`` (of grads)."""

    vg: Callable
    unravel: Callable
    x0: np.ndarray
    vgo: Callable | None = None
    stats: dict | None = None
    grads: Callable | None = None


def forward_scores(per_step, f, data):
    """Per-step log-likelihoods and their derivatives by forward mode.

    ``n`` Jacobian-vector products of ``per_step`` along the coordinate axes, vmapped: one
    pass through the filter carrying n tangents beside the state, nothing stored for a
    backward pass. For a few coordinates and long runs this is several times cheaper than
    reverse mode through the scan (SingleTrack EKF, 5 coordinates, 2,000 steps, 2-core CPU:
    85-113 against 359-452 CPU-us per step, compile 10-21 against 21-54 CPU-s), and it gives
    every step's score, not only their sum.

    Args:
        per_step: ``per_step(f, data) -> (loglik (R, T), aux)``, f (n,) flat coordinates.
        f: (n,) point; data: the objective's data.

    Returns:
        (loglik (R, T), d loglik / df (n, R, T), aux).
    """
    basis = jnp.eye(f.shape[0], dtype=f.dtype)

    def jvp(v):
        return jax.jvp(lambda g: per_step(g, data), (f,), (v,), has_aux=True)

    return jax.vmap(jvp, out_axes=(None, 0, None))(basis)


def score_outer_product(scores, n_steps: int):
    """The BHHH matrix (Berndt, Hall, Hall & Hausman 1974): ``sum_t s_t s_t^T / n_steps`` of
    the per-step scores ``s_t = d log p(y_t | y_1:t-1) / dz`` (``scores`` (n, ...) with the
    steps in the trailing axes), (n, n). At the true parameters it has the expectation of the
    Hessian of the mean negative log-likelihood per step (the information identity), so it
    is a positive semi-definite Gauss-Newton-type curvature from first derivatives only."""
    s = scores.reshape(scores.shape[0], -1)
    return (s @ s.T) / n_steps


#: forward-mode derivatives (:func:`forward_scores`) for at most this many coordinates; reverse
#: mode beyond (its cost does not grow with the number of coordinates)
_FORWARD_MAX = 12

#: fits of at least this many run-steps (R T) with forward-mode derivatives and a Hessian by
#: differences compute the Hessian's 2 n gradients in one program vmapped over the 2 n points
#: (a second compile, once per fit): the filter's scan on XLA:CPU is bound by the cost of
#: launching many tiny operations per step, so 2 n points side by side cost about 1.8
#: evaluations of one point rather than 2 n (SingleTrack EKF with input noise, 5 coordinates,
#: 2-core CPU: 175 against 95 CPU-us per step). That program's compile (10-16 s wall on the
#: shared 2-core machine) is what the ~8 evaluations saved cost at about 20,000 steps (the
#: 20,000-step fit of benchmarks/bench_fit.py measured 63 s with it against 57 s without,
#: back to back), so it pays from a few times that length. That was against the 2 n central
#: differences one by one; against the n forward differences now taken without it
#: (:func:`_difference_hessian`) it saves about n - 2 evaluations, so the length where it pays
#: is longer (not re-measured).
_BATCH_HESSIAN_STEPS = 50000

#: forward differences of the gradient for the Hessian (:func:`_difference_hessian`): steps of
#: this fraction of each coordinate's scale. Truncation error ~ rel, rounding of the gradient
#: ~ 1e-14 / rel (relative): on the 20,000-step single-track fit of benchmarks/bench_fit.py
#: the Hessian is within 7e-7 (standard errors 8e-7) of central differences at 1e-4
_FORWARD_REL = 1e-6


def _flat_loss(obj, info=None, batch_hessian: bool = False) -> _Loss:
    """The compiled loss of a fit (:class:`_Loss`): forward mode for deterministic filters with
    at most ``_FORWARD_MAX`` coordinates, else ``jax.value_and_grad``; compiled ahead of time
    once, with the XLA options :mod:`vehjax.execution` gives the estimator's workload.
    ``batch_hessian`` (forward mode only): also give ``_Loss.grads`` (its program compiled at
    its first call)."""
    from . import execution

    flat, unravel = jax.flatten_util.ravel_pytree(obj.z0)
    n = flat.shape[0]
    forward = (info is not None and not info["stochastic"] and n <= _FORWARD_MAX)
    if forward:
        per_step = info["per_step"]

        def program(f, data):
            ll, dll, (lls_div) = forward_scores(lambda g, d: per_step(unravel(g), d), f, data)
            loss = -jnp.sum(ll) / obj.n_steps
            grad = -jnp.sum(dll.reshape(n, -1), axis=1) / obj.n_steps
            return loss, (jnp.sum(ll, axis=-1), lls_div), grad, score_outer_product(dll,
                                                                                     obj.n_steps)
    else:
        vgf = jax.value_and_grad(lambda f, data: obj.loss(unravel(f), data), has_aux=True)

        def program(f, data):
            (v, aux), g = vgf(f, data)
            return v, aux, g, None

    options = None
    if info is not None:
        options = execution.compiler_options(execution.current(), info["workload"])
    t0, c0 = time.perf_counter(), time.process_time()
    compiled = jax.jit(program).lower(jnp.asarray(flat), obj.data).compile(
        compiler_options=options)
    stats = {"mode": "forward" if forward else "reverse",
             "compile_seconds": time.perf_counter() - t0,
             "compile_cpu_seconds": time.process_time() - c0, "evaluations": 0,
             "batch_compile_seconds": 0.0, "batch_evaluations": 0, "options": options}
    last = []  # (point, result) of the latest evaluation: the optimiser's last point is the
    # Newton polish's first

    def vgo(f):
        f = np.array(f, dtype=float)
        if last and np.array_equal(last[0], f):
            return last[1]
        stats["evaluations"] += 1
        v, aux, g, B = compiled(jnp.asarray(f, dtype=flat.dtype), obj.data)
        out = (float(v), aux, np.asarray(g, dtype=float),
               None if B is None else np.asarray(B, dtype=float))
        last[:] = [f, out]
        return out

    def vg(f):
        return vgo(f)[:3]

    grads = _batched_gradients(per_step, unravel, obj, flat, options, stats) \
        if forward and batch_hessian else None
    return _Loss(vg, unravel, np.asarray(flat, dtype=float), vgo if forward else None, stats,
                 grads)


def _batched_gradients(per_step, unravel, obj, flat, options, stats):
    """``_Loss.grads``: the gradient of the loss at 2 n points at once (forward mode, vmapped
    over the points), compiled at its first call (the first Hessian of the fit). Compiled in
    the caller's thread: XLA:CPU already runs an evaluation on both cores of the 2-core
    machine, and a compile in a background thread slowed the iterations as much as it hid."""
    n = flat.shape[0]

    def program(F, data):
        def one(f):
            _, dll, _ = forward_scores(lambda g, d: per_step(unravel(g), d), f, data)
            return -jnp.sum(dll.reshape(n, -1), axis=1) / obj.n_steps

        return jax.vmap(one)(F)

    box = {}

    def grads(F):
        if "compiled" not in box:
            t0 = time.perf_counter()
            box["compiled"] = jax.jit(program).lower(
                jnp.zeros((2 * n, n), flat.dtype), obj.data).compile(compiler_options=options)
            stats["batch_compile_seconds"] = time.perf_counter() - t0
        stats["batch_evaluations"] += 1
        return np.asarray(box["compiled"](jnp.asarray(F, dtype=flat.dtype), obj.data),
                          dtype=float)

    return grads


def wolfe_search(vg, x, f0: float, g0, d, t: float = 1.0, c1: float = 1e-4, c2: float = 0.9,
                 tries: int = 40):
    """A step t along the descent direction d (n,) from x satisfying the weak Wolfe conditions
    ``f(x + t d) <= f0 + c1 t g0.d`` and ``g(x + t d).d >= c2 g0.d``, by bracketing and
    bisection (Lewis & Overton 2013); a non-finite value counts as too long a step.
    Returns (t, (f, aux, g)) or None when no step decreases the loss (at the numerical
    optimum, or d is no descent direction)."""
    dg0 = float(g0 @ d)
    if not dg0 < 0:
        return None
    lo, hi, armijo = 0.0, np.inf, None
    for _ in range(tries):
        f, aux, g = vg(x + t * d)
        if not (np.isfinite(f) and _finite(g)) or f > f0 + c1 * t * dg0:
            hi = t
        else:
            armijo = (t, (f, aux, g))
            if float(g @ d) < c2 * dg0:
                lo = t
            else:
                return armijo
        t = 0.5 * (lo + hi) if np.isfinite(hi) else 2.0 * t
    return armijo


def lbfgs_direction(g, S: list, Y: list):
    """-H g by the L-BFGS two-loop recursion from the pairs s_k = x_{k+1} - x_k, y_k = g_{k+1}
    - g_k (oldest first), initial H = (s.y / y.y) I of the newest pair (Nocedal & Wright,
    Algorithm 7.4)."""
    q = np.array(g, dtype=float)
    alphas = []
    for s, y in zip(reversed(S), reversed(Y)):
        a = (s @ q) / (y @ s)
        alphas.append(a)
        q -= a * y
    if S:
        q *= (S[-1] @ Y[-1]) / (Y[-1] @ Y[-1])
    for (s, y), a in zip(zip(S, Y), reversed(alphas)):
        q += (a - (y @ q) / (y @ s)) * s
    return -q


def _lbfgs(loss: _Loss, steps: int, gtol: float, bar, memory: int = 10):
    """L-BFGS with a weak-Wolfe line search on the compiled loss. Stops, converged, when
    max |grad| <= gtol, or when no step decreases the loss. Returns (x, aux, history,
    iterations, converged)."""
    x = loss.x0
    f, aux, g = loss.vg(x)
    _check_start(f, g)
    S, Y, history, converged, i = [], [], [], False, 0
    for i in range(1, steps + 1):
        history.append(f)
        bar.update(i, f, f)
        if np.max(np.abs(g)) <= gtol:
            converged = True
            break
        d = lbfgs_direction(g, S, Y)
        if not g @ d < 0:  # lost positive curvature: restart from steepest descent
            S, Y, d = [], [], -g
        t0 = 1.0 if S else min(1.0, 1.0 / max(np.max(np.abs(g)), 1e-12))
        found = wolfe_search(loss.vg, x, f, g, d, t0)
        if found is None:
            break
        t, (f_new, aux, g_new) = found
        s, y = t * d, g_new - g
        if s @ y > 1e-12 * np.linalg.norm(s) * np.linalg.norm(y):
            S, Y = (S + [s])[-memory:], (Y + [y])[-memory:]
        x, f, g = x + s, f_new, g_new
    bar.close(i, f, f)
    return x, aux, history, i, converged


def scoring_direction(g, B, scales, damping: float = 0.0):
    """The BHHH / scoring step ``-(B + damping lam_max I)^-1 g`` in the scaled coordinates
    ``S z`` (S = diag(scales), the coordinates' natural sizes), over the directions where the
    scaled B has curvature above 1e-10 of its largest eigenvalue (a step of zero along the
    others): g (n,) gradient, B (n, n) positive semi-definite curvature. Returns (n,)."""
    Bs = B * np.outer(scales, scales)
    lam, V = np.linalg.eigh(0.5 * (Bs + Bs.T))
    top = max(float(lam.max()), np.finfo(float).tiny)
    keep = lam > 1e-10 * top
    gs = V[:, keep].T @ (scales * g)
    return -scales * (V[:, keep] @ (gs / (lam[keep] + damping * top)))


def _scoring(loss: _Loss, steps: int, gtol: float, bar, scales, c1: float = 1e-4):
    """BHHH (method of scoring with the outer product of the per-step scores,
    :func:`score_outer_product`) with Levenberg damping and a backtracking (Armijo) line search,
    every trial one evaluation of the forward-mode program (value, gradient and curvature
    together). Stops, converged, when max |grad| <= gtol; hands over (not converged) to the
    Newton polish when a step gains less than 1e-11 max(1, |loss|) or no step decreases the
    loss: BHHH converges linearly where the observed and the expected curvature differ, Newton
    quadratically from there. Returns (x, aux, history, iterations, converged)."""
    x = loss.x0
    f, aux, g, B = loss.vgo(x)
    _check_start(f, g, B)
    history, converged, i, damping = [], False, 0, 0.0
    for i in range(1, steps + 1):
        history.append(f)
        bar.update(i, f, f)
        if np.max(np.abs(g)) <= gtol:
            converged = True
            break
        d = scoring_direction(g, B, scales, damping)
        dg = float(g @ d)
        if not dg < 0:
            d, dg = -g * scales**2, -float(g @ (g * scales**2))
        t, new = 1.0, None
        for _ in range(30):
            cand = loss.vgo(x + t * d)
            if np.isfinite(cand[0]) and _finite(cand[2], cand[3]) and \
                    cand[0] <= f + c1 * t * dg:
                new = cand
                break
            t *= 0.25 if not np.isfinite(cand[0]) else 0.5
        if new is None:
            break
        damping = damping / 10.0 if t == 1.0 else max(10.0 * damping, 1e-3)
        gain = f - new[0]
        x, (f, aux, g, B) = x + t * d, new
        if gain < 1e-11 * max(1.0, abs(f)):
            break
    bar.close(i, f, f)
    return x, aux, history, i, converged


def _first_order(loss: _Loss, opt, steps: int, tol: float, patience: int, bar):
    """adam or a custom optax transformation on the compiled loss: steps with a non-finite
    gradient are skipped (``apply_if_finite``); stops, converged, when the best loss has not
    improved by ``tol * max(1, |best|)`` for ``patience`` iterations. Returns (best x, its aux,
    history, iterations, converged, skipped)."""
    update = jax.jit(opt.update)
    x = jnp.asarray(loss.x0)
    state = jax.tree.map(lambda a: jnp.array(a, dtype=jnp.asarray(a).dtype), opt.init(x))
    history, best, best_x, best_aux = [], np.inf, loss.x0, None
    since = skipped = i = 0
    converged, f = False, np.nan
    for i in range(1, steps + 1):
        f, aux, g = loss.vg(x)
        history.append(f)
        if not (np.isfinite(f) and _finite(g)):
            skipped += 1
        if np.isfinite(f) and (not np.isfinite(best) or f < best - tol * max(1.0, abs(best))):
            best, best_x, best_aux, since = f, np.asarray(x), aux, 0
        else:
            since += 1
        bar.update(i, f, best)
        updates, state = update(jnp.asarray(g), state, x)
        x = optax.apply_updates(x, updates)
        if since >= patience:
            converged = True
            break
    bar.close(i, f, best)
    if not np.isfinite(best):
        raise FloatingPointError(
            "vehjax.tune: the log-likelihood is not finite at the starting values; check Q0, R0, "
            "x0, P0 and the measurements")
    return best_x, best_aux, history, i, converged, skipped


def hessian_from_gradients(vg, x, scales, rel: float = 1e-4, grads=None, g0=None):
    """The Hessian (n, n) of the loss at x by differences of its exact (JAX) gradient, column i
    from steps of rel * scales[i] (the coordinate's natural size, see :func:`_coordinates`),
    symmetrised.

    Central differences (default): steps +-h, 2 n gradient evaluations of the compiled loss,
    no further compilation, truncation error O(rel^2) relative; or, with ``grads(F (2 n, n))
    -> (2 n, n)`` (``_Loss.grads``), the same 2 n points in one call. Forward differences when
    ``g0`` (n,), the gradient at x, is given: ``(g(x + h e_i) - g0) / h``, n evaluations,
    truncation error O(rel) relative, rounding O(1e-14 / rel) (:func:`fit` takes rel =
    :data:`_FORWARD_REL`)."""
    n = len(x)
    x = np.asarray(x, dtype=float)
    h = rel * np.asarray(scales, dtype=float)
    E = np.diag(h)
    if g0 is not None:
        g0 = np.asarray(g0, dtype=float)
        H = np.stack([(vg(x + E[i])[2] - g0) / h[i] for i in range(n)], axis=1)
    elif grads is not None:
        G = grads(np.concatenate([x + E, x - E]))
        H = ((G[:n] - G[n:]) / (2 * h)[:, None]).T
    else:
        H = np.zeros((n, n))
        for i in range(n):
            H[:, i] = (vg(x + E[i])[2] - vg(x - E[i])[2]) / (2 * h[i])
    return 0.5 * (H + H.T)


def _newton(loss: _Loss, x, scales, gtol: float, hessian):
    """The curvature at x and one Newton step on its determined directions, kept when the loss
    does not increase (the curvature is then recomputed where the step was large). Returns
    (x, aux, max |gradient|, Hessian of the mean loss)."""
    f, aux, g = loss.vg(x)
    Hm = hessian(x)
    if not (np.all(np.isfinite(Hm)) and _finite(g)):
        return x, aux, float(np.max(np.abs(g))), Hm
    lam, V = np.linalg.eigh(Hm * np.outer(scales, scales))
    keep = lam > _RCOND * max(float(lam.max()), np.finfo(float).tiny)
    if np.max(np.abs(g)) <= 1e-3 * gtol or not np.any(keep):
        return x, aux, float(np.max(np.abs(g))), Hm
    step = -scales * (V[:, keep] @ ((V[:, keep].T @ (scales * g)) / lam[keep]))
    f_new, aux_new, g_new = loss.vg(x + step)
    if np.isfinite(f_new) and _finite(g_new) and f_new <= f + 1e-14 * max(1.0, abs(f)):
        x, aux, g = x + step, aux_new, g_new
        if np.max(np.abs(step / scales)) > 1e-3:  # moved far: the curvature there
            Hm = hessian(x)
    return x, aux, float(np.max(np.abs(g))), Hm


def _difference_hessian(loss: _Loss, x, scales):
    """The Hessian of the mean loss at x for :func:`fit` (:func:`hessian_from_gradients`): the
    2 n central-difference points in one call of ``loss.grads`` where the fit has that batched
    program, else forward differences from the gradient at x (n evaluations of the compiled
    loss; the one at x is the latest evaluation, not repeated) with steps :data:`_FORWARD_REL`
    of each coordinate's scale."""
    if loss.grads is not None:
        return hessian_from_gradients(loss.vg, x, scales, grads=loss.grads)
    return hessian_from_gradients(loss.vg, x, scales, rel=_FORWARD_REL, g0=loss.vg(x)[2])


def _check_fit_options(learning_rate, tol, gtol, hessian, steps, patience, optimizer):
    """:func:`fit`'s optimiser options checked (ValueError naming the first bad one):
    (learning_rate, tol, gtol) as numbers."""
    if learning_rate is not None:
        learning_rate = validation.number("learning_rate", learning_rate, 0.0)
    tol = validation.number("tol", tol, 0.0, low_open=False)
    gtol = validation.number("gtol", gtol, 0.0)
    if hessian is not None:
        validation.choice("hessian", hessian, ("differences", "jax"))
    if steps is not None:
        validation.integer("steps", steps, 1)
    if patience is not None:
        validation.integer("patience", patience, 1)
    if optimizer is not None and not isinstance(optimizer, optax.GradientTransformation):
        if not isinstance(optimizer, str):
            raise ValueError(f"optimizer: expected 'adam', 'lbfgs' or an "
                             f"optax.GradientTransformation, got {optimizer!r}")
        validation.choice("optimizer", optimizer, _OPTIMIZERS)
    return learning_rate, tol, gtol


def fit(builder, model, Q0, R0, measurements, inputs=None, *, x0, P0, params=(), bounds=None,
        noise=_NOISE, fit_x0: bool = False, optimizer=None, learning_rate=None,
        steps: int | None = None, tol: float = 1e-7, patience: int | None = None,
        gtol: float = _GTOL, key=None, builder_kwargs=None, progress: bool = True,
        standard_errors: bool = True, hessian: str | None = None) -> TuneResult:
    """Fit Q, R, the input noise, named model parameters and optionally x0 by maximum likelihood,
    with standard errors.

    Args:
        builder: a filter builder ``builder(model, Q, R, **builder_kwargs) -> Estimator``:
            ``vehjax.filters.ekf``, ``ukf``, ``ckf`` (``builder_kwargs={"sqrt": True}`` for the
            square-root forms), ``bootstrap_pf`` (differentiated with stop-gradient
            resampling, :func:`stop_gradient_pf`), or one's own state-only builder.
        model: a vehjax model; ``model.theta`` holds the starting parameter values.
        Q0, R0: starting covariances, (n, n) or (n,) variances; diagonal ones are fitted as
            diagonal, full ones as full (module docstring). Positive definite when fitted; a Q0
            that is not fitted may be positive semi-definite (zero, with input noise).
        measurements: (T, ny) one run or (R, T, ny) runs; NaN components are missing.
        inputs: (T, nu) shared or (R, T, nu) per run; None for a model without inputs.
        x0, P0: prior of every run: x0 (nx,) or (R, nx), P0 (nx, nx), (nx,) or (R, nx, nx).
        params: names of model parameters to fit (default none).
        bounds: ``{name: (lo, hi)}`` for fitted parameters, either end None (module docstring).
        noise: which noise to fit, a subset of ("Q", "R", "input") (default ("Q", "R")).
            "input" fits the input noise whose starting value is
            ``builder_kwargs["input_noise"]``: stds by input name (log stds fitted, reported as
            ``"input[name]"`` stds in the input's unit) or an (nu, nu) covariance (fitted like
            Q0, reported in units squared).
        fit_x0: also fit x0 (the shape it was given in).
        optimizer: None (default): "scoring" for deterministic filters with at most 12
            fitted coordinates (forward-mode derivatives), "lbfgs" for those with more,
            "adam" for particle filters; "adam", "lbfgs", "scoring" or an
            ``optax.GradientTransformation``. "scoring": BHHH steps (the outer product of the
            per-step scores as curvature, :func:`score_outer_product`) with a line search,
            then Newton steps on the Hessian by differences (up to 3) until ``gtol``.
        learning_rate: > 0; adam's peak rate (default 0.05, cosine decay to 5 % over
            ``steps``); not for L-BFGS (line search).
        steps: maximum number of iterations, >= 1 (default 300 adam, 100 lbfgs/scoring).
        tol: >= 0 (adam, custom): the improvement of the best loss that resets ``patience``,
            relative to max(1, |best loss|).
        patience: >= 1 (adam, custom), iterations without improvement before stopping (default
            50: adam's momentum can overshoot for a few tens of iterations).
        gtol: > 0, L-BFGS stops, converged, when every component of the gradient of the loss
            (the mean negative log-likelihood per step) with respect to the unconstrained
            coordinates is at most gtol (the parameterisation is unconstrained: this is the
            projected gradient), or when its line search finds no lower loss. For every
            deterministic filter a Newton step on the Hessian then polishes the result, and
            ``converged`` says whether the gradient there is at most gtol.
        key: PRNG key, required for particle filters; run r uses ``jax.random.split(key, R)[r]``
            at every iteration.
        builder_kwargs: further keyword arguments of ``builder`` (``sqrt``, ``alpha``,
            ``n_particles``, ``input_noise``, ...).
        progress: show a progress bar (tqdm.auto when installed, else a line on stderr).
        standard_errors: compute the observed information (the Hessian of the log-likelihood),
            standard errors, correlations and the undetermined directions (default).
        hessian: how the Hessian is formed from JAX's exact gradient: "differences" (the
            default for deterministic filters) by forward differences of the gradient, steps
            1e-6 of each coordinate's natural size, with the one compiled gradient program
            (n evaluations beside the one at the point, relative error ~1e-6; central
            differences, 2 n points in one call, where a long fit compiles the batched
            program); "jax": ``jax.hessian`` (forward over
            reverse), exact, one more program to compile (on a vehicle model that compile can
            take longer than the fit); the default for particle filters, whose resampling
            makes differences unreliable.

    Returns:
        :class:`TuneResult`. A warning names the quantities the data do not determine
        (:func:`uncertainty`), also in ``TuneResult.undetermined``.

    Raises:
        ValueError: naming the argument, before anything is traced: an unknown parameter name,
            wrong shapes, a Q0/R0/P0 that is not positive definite, learning_rate <= 0,
            steps < 1, an unknown optimizer, a missing key, nothing to fit.
    """
    t_start = time.perf_counter()
    learning_rate, tol, gtol = _check_fit_options(learning_rate, tol, gtol, hessian, steps,
                                                  patience, optimizer)
    obj, info = _prepare(builder, model, Q0, R0, measurements, inputs, x0, P0, params, bounds,
                         noise, fit_x0, key, builder_kwargs)
    if optimizer == "scoring" and info["stochastic"]:
        raise ValueError("optimizer: 'scoring' needs a deterministic filter (EKF, UKF, CKF); "
                         "use 'adam' for a particle filter")
    differences = not info["stochastic"] and hessian in (None, "differences")
    loss = _flat_loss(obj, info, batch_hessian=differences and obj.n_steps >= _BATCH_HESSIAN_STEPS
                      and (standard_errors or optimizer in (None, "scoring")))
    if optimizer is None:
        optimizer = ("adam" if info["stochastic"] else
                     "scoring" if loss.vgo is not None else "lbfgs")
    if optimizer == "scoring" and loss.vgo is None:  # too many coordinates for forward mode
        optimizer = "lbfgs"
    lbfgs = isinstance(optimizer, str) and optimizer in ("lbfgs", "scoring")
    if lbfgs and learning_rate is not None:
        raise ValueError(f"learning_rate: {optimizer} takes its steps by a line search; leave "
                         f"it None")
    steps = _LBFGS_STEPS if steps is None and lbfgs else _ADAM_STEPS if steps is None else steps
    patience = 50 if patience is None else patience
    opt = None if lbfgs else _optimizer(optimizer, learning_rate, steps)[0]

    bar = _Progress(steps, bool(progress), f"vehjax.tune ({info['name']})")
    skipped = 0
    coord_names, scales = _coordinates(info, model, obj.z0)
    if optimizer == "scoring":
        x, aux, history, iters, converged = _scoring(loss, steps, gtol, bar, scales)
    elif lbfgs:
        x, aux, history, iters, converged = _lbfgs(loss, steps, gtol, bar)
    else:
        x, aux, history, iters, converged, skipped = _first_order(loss, opt, steps, tol,
                                                                  patience, bar)
    unc, grad_max = None, float("nan")
    if optimizer == "scoring" and not standard_errors:  # the Newton polish finishes scoring
        hess = lambda f: _difference_hessian(loss, f, scales)  # noqa: E731
        x, aux, grad_max, _ = _newton(loss, x, scales, gtol, hess)
        converged = converged or grad_max <= gtol
    if standard_errors:
        if hessian is None:
            hessian = "jax" if info["stochastic"] else "differences"
        if hessian == "jax":
            hfn = jax.jit(jax.hessian(lambda f, data: obj.loss(loss.unravel(f), data)[0])).lower(
                jnp.asarray(loss.x0), obj.data).compile(compiler_options=loss.stats["options"])
            hess = lambda f: np.asarray(hfn(jnp.asarray(f), obj.data))  # noqa: E731
        else:
            hess = lambda f: _difference_hessian(loss, f, scales)  # noqa: E731
        if info["stochastic"]:  # no Newton step on a Monte-Carlo objective
            _, aux, g = loss.vg(x)
            grad_max, Hm = float(np.max(np.abs(g))), hess(x)
        else:
            for _ in range(3 if optimizer == "scoring" else 1):
                x, aux, grad_max, Hm = _newton(loss, x, scales, gtol, hess)
                if grad_max <= gtol:
                    break
            converged = converged or grad_max <= gtol
        qfn = lambda f: jnp.stack([jnp.asarray(q[2]) for q in fitted_quantities(  # noqa: E731
            info, model, obj.unpack(loss.unravel(f)))])
        unc = uncertainty(obj.n_steps * Hm, np.asarray(jax.jacfwd(qfn)(jnp.asarray(x))), scales,
                          coord_names)
    res = _result(obj, info, model, loss.unravel(jnp.asarray(x)), aux, history, iters,
                  converged, skipped, unc, grad_max, t_start)
    return res._replace(evaluations=loss.stats["evaluations"], optimizer=str(optimizer)
                        if isinstance(optimizer, str) else "optax",
                        derivatives=loss.stats["mode"],
                        compile_seconds=loss.stats["compile_seconds"],
                        hessian_batches=loss.stats["batch_evaluations"],
                        hessian_compile_seconds=loss.stats["batch_compile_seconds"],
                        compile_cpu_seconds=loss.stats["compile_cpu_seconds"])


def _result(obj, info, model, best_z, best_aux, history, iters, converged, skipped, unc,
            grad_max, t_start) -> TuneResult:
    """The :class:`TuneResult` at ``best_z``, with warnings for diverged runs and undetermined
    quantities."""
    ll, div = jax.jit(obj.loss)(best_z, obj.data)[1] if best_aux is None else best_aux
    v = jax.tree.map(np.asarray, obj.unpack(best_z))
    Q, R, theta, x0_fit = v["Q"], v["R"], v["theta"], v["x0"]
    Q, R = 0.5 * (Q + Q.T), 0.5 * (R + R.T)
    fitted_model = model
    if info["params"]:
        fitted_model = model.with_theta(**{p: float(theta[model.param_names.index(p)])
                                           for p in info["params"]})
    kw = dict(info["builder_kwargs"])
    if v["input"] is not None:
        kw["input_noise"] = ({k: float(s) for k, s in v["input"].items()}
                             if isinstance(v["input"], dict) else np.asarray(v["input"]))
    estimator = info["builder"](fitted_model, Q, R, **kw)
    n_div = int(np.sum(np.asarray(div)))
    if n_div:
        warnings.warn(f"vehjax.tune: {n_div} of {len(div)} runs diverged at the fitted values; "
                      f"their log-likelihood counts only the steps before", stacklevel=3)
    qs = fitted_quantities(info, model, v)
    values = {k: float(x) for k, _, x in qs}
    units = {k: u for k, u, _ in qs}
    se, corr, undetermined = {}, np.full((len(qs),) * 2, np.nan), ()
    if unc is not None:
        se = {k: float(s) for (k, _, _), s in zip(qs, unc.std_errors)}
        corr, undetermined = unc.correlations, unc.undetermined
        if undetermined:
            warnings.warn(
                f"vehjax.tune: the data do not determine {', '.join(undetermined)} (no or too "
                f"little curvature of the log-likelihood; their standard errors are inf): "
                f"fix them, or give data that excite them", stacklevel=3)
    return TuneResult(
        Q=Q, R=R, theta=np.asarray(theta),
        params={p: float(theta[model.param_names.index(p)]) for p in info["params"]},
        x0=x0_fit, model=fitted_model, estimator=estimator,
        loglik=float(np.sum(np.asarray(ll))), loglik0=-history[0] * obj.n_steps,
        history=np.asarray(history), iterations=iters, converged=converged, diverged=n_div,
        skipped=skipped, values=values, units=units, seconds=time.perf_counter() - t_start,
        std_errors=se, correlations=corr, undetermined=undetermined, gradient=grad_max,
        input_noise=kw.get("input_noise"),
    )


def fit_noise(builder, model, Q0, R0, measurements, inputs=None, *, x0, P0, noise=_NOISE,
              **kwargs) -> TuneResult:
    """Fit the noise covariances Q and R (``noise``: both by default) by maximum likelihood:
    :func:`fit` with no model parameters. Same arguments and result."""
    if "params" in kwargs:
        raise ValueError("params: fit_noise fits Q and R only; use vehjax.tune.fit for model "
                         "parameters")
    return fit(builder, model, Q0, R0, measurements, inputs, x0=x0, P0=P0, noise=noise, **kwargs)
