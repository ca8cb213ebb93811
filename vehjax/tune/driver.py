"""The drivers of a fit from one start: :func:`fit_from_theta` (noise, model parameters, x0,
from the model's ``theta`` and the given noise as they are) and :func:`fit_noise` (the noise
only): the objective (:mod:`vehjax.tune.likelihood`) compiled once
(:mod:`vehjax.tune.program`), an optimiser (:mod:`vehjax.tune.optimisers`), the observed
information and standard errors (:mod:`vehjax.tune.information`), the result
(:mod:`vehjax.tune.result`). The method is described in :mod:`vehjax.tune`."""

from __future__ import annotations

import time

import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import optax

from .. import execution, validation
from ..runtime.progress import Progress
from . import optimisers as opt
from . import program
from . import boundaries, diagnostics
from . import priors as tune_priors
from .information import MAX_SCALED_STD, difference_hessian, uncertainty
from .likelihood import NOISE, prepare
from .optimisers import GTOL
from .quantities import coordinates, fitted_quantities
from .result import TuneResult, make_result

__all__ = ["fit_from_theta", "fit_noise", "compile_objective", "check_options", "OPTIONS"]


def _check_fit_options(learning_rate, tol, gtol, hessian, steps, patience, optimizer,
                       progress=True, standard_errors=True):
    """:func:`fit`'s optimiser and report options checked (ValueError naming the first bad
    one; the flags by :func:`vehjax.validation.flag`: ``progress="no"`` is refused, not read
    as True): (learning_rate, tol, gtol) as numbers."""
    validation.flag("progress", progress)
    validation.flag("standard_errors", standard_errors)
    if learning_rate is not None:
        learning_rate = validation.number("learning_rate", learning_rate, 0.0)
        if optimizer in ("lbfgs", "scoring"):
            raise ValueError(f"learning_rate: {optimizer} takes its steps by a line search; "
                             f"leave it None")
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
        validation.choice("optimizer", optimizer, opt.OPTIMIZERS)
    return learning_rate, tol, gtol


#: the optimiser's and the report's options of :func:`fit_from_theta`
OPTIONS = ("optimizer", "learning_rate", "steps", "tol", "patience", "gtol", "key",
           "progress", "standard_errors", "hessian")


def check_options(options: dict, stochastic: bool | None = None) -> None:
    """``**options`` of :func:`vehjax.tune.fit` checked before anything is traced: TypeError
    for a name :func:`fit_from_theta` does not take, ValueError naming a bad value. With
    ``stochastic`` False (the filter is deterministic) a ``learning_rate`` without an
    ``optimizer`` is refused: the default optimiser is then a line search; with True (a
    particle filter) the optimizer "scoring"."""
    for k in options:
        if k not in OPTIONS:
            raise TypeError(f"fit() got an unexpected keyword argument {k!r}")
    if stochastic and options.get("optimizer") == "scoring":
        raise ValueError("optimizer: 'scoring' needs a deterministic filter (EKF, UKF, CKF); "
                         "use 'adam' for a particle filter")
    if stochastic is False and options.get("optimizer") is None \
            and options.get("learning_rate") is not None:
        raise ValueError("learning_rate: the default optimizer of a deterministic filter "
                         "(scoring, or lbfgs beyond 12 fitted coordinates) takes its steps by a "
                         "line search; leave it None, or pass optimizer='adam'")
    _check_fit_options(options.get("learning_rate"), options.get("tol", 0.0),
                       options.get("gtol", GTOL), options.get("hessian"), options.get("steps"),
                       options.get("patience"), options.get("optimizer"),
                       options.get("progress", True), options.get("standard_errors", True))


def _progress(steps: int, enabled, name: str):
    """``(report(i, loss, best), bar)``: the fit's progress bar (:mod:`vehjax.runtime.progress`),
    labelled ``vehjax.tune (name)``, its text line rewritten at most 5 times a second."""
    label = f"vehjax.tune ({name})"
    bar = Progress(steps, label, bool(enabled), interval=0.2)

    def report(i: int, loss: float, best: float):
        bar.update(i, f"loss={loss:.6g}, best={best:.6g}",
                   f"{label}: iteration {i}/{steps}, loss {loss:.6g}, best {best:.6g}")

    return report, bar


def _optimise(loss, optimizer, opts: dict, report, scales):
    """The chosen optimiser on the compiled loss: (x, aux, history, iterations, converged,
    skipped)."""
    steps, gtol = opts["steps"], opts["gtol"]
    if optimizer == "scoring":
        return (*opt.scoring(loss, steps, gtol, report, scales, opts["n_steps"]), 0)
    if optimizer == "lbfgs":
        return (*opt.lbfgs(loss, steps, gtol, report), 0)
    return opt.first_order(loss, opts["first"], steps, opts["tol"], opts["patience"], report)


def _hessian_fn(obj, setup, loss, hessian, scales):
    """``hess(x) -> (n, n)``, the Hessian of the mean loss: ``jax.hessian`` compiled
    (``"jax"``, the default for particle filters) or differences of the compiled gradient."""
    if hessian is None:
        hessian = "jax" if setup.stochastic else "differences"
    if hessian == "jax":
        hfn = jax.jit(jax.hessian(lambda f, data: obj.loss(loss.unravel(f), data)[0])).lower(
            jnp.asarray(loss.x0), obj.data).compile(compiler_options=loss.stats["options"])
        return _AtLastPoint(lambda f: np.asarray(hfn(jnp.asarray(f), obj.data)))
    return _AtLastPoint(lambda f: difference_hessian(loss, f, scales))


class _AtLastPoint:
    """``hess`` remembering its last point: the Newton polish asks for the curvature where its
    previous step ended, which that step computed already, or kept from where it started when
    the step was short (:func:`vehjax.tune.optimisers.newton`: :meth:`remember`)."""

    def __init__(self, hess):
        self.hess, self.last = hess, None

    def __call__(self, f):
        f = np.array(f, dtype=float)
        if self.last is None or not np.array_equal(self.last[0], f):
            self.last = (f, self.hess(f))
        return self.last[1]

    def remember(self, f, H) -> None:
        """Take H as the curvature at f."""
        self.last = (np.array(f, dtype=float), H)


def _quantity_map(obj, setup, model, unravel):
    """``at(x) -> (names, values (m,), d values / d coordinates (m, n))`` of the fitted
    quantities (:func:`vehjax.tune.quantities.fitted_quantities`) at the coordinates x, compiled
    once per fit: evaluated eagerly, their Jacobian compiled each small operation on its own
    (seconds on a vehicle model's fit)."""
    names = []

    def values(f):
        qs = fitted_quantities(setup, model, obj.unpack(unravel(f)))
        names[:] = [k for k, _, _ in qs]
        return jnp.stack([jnp.asarray(q[2]) for q in qs])

    program_ = jax.jit(lambda f: (values(f), jax.jacfwd(values)(f)))

    def at(x):
        v, J = program_(jnp.asarray(x))
        return list(names), np.asarray(v, dtype=float), np.asarray(J, dtype=float)

    return at


def _bounds_at(obj, setup, quantities, x, g, names):
    """The quantities on a bound at x (:func:`vehjax.tune.boundaries.on_bounds`), the Jacobian
    (m, n) of the quantities with respect to the coordinates, and the free-coordinates mask;
    ``quantities`` from :func:`_quantity_map`."""
    qnames, vals, J = quantities(x)
    on = boundaries.on_bounds(setup.bounds, names, dict(zip(qnames, vals.tolist())), g, J,
                              qnames, obj.n_steps)
    return on, J, qnames, np.array([n not in on for n in names], dtype=bool)


def _free_gradient(g, free) -> float:
    """max |g| over the free coordinates (0 when every coordinate is on a bound)."""
    g = np.abs(np.asarray(g, dtype=float))[free]
    return float(np.max(g)) if g.size else 0.0


def _standard_errors(obj, setup, quantities, loss, x, optimizer, hessian, gtol, scales, names):
    """The Newton polish (deterministic filters) and the observed information at its end over
    the free coordinates, the quantities on a bound held there: (x, aux, max |gradient|,
    polished to gtol over the free coordinates, :class:`vehjax.tune.Uncertainty`, the
    quantities on a bound, the Hessian of the mean loss there (n, n))."""
    hess = _hessian_fn(obj, setup, loss, hessian, scales)
    if setup.stochastic:  # no Newton step on a Monte-Carlo objective
        _, aux, g = loss.vg(x)
        Hm = hess(x)
    else:  # polish the free coordinates, the quantities on a bound held there
        free = _bounds_at(obj, setup, quantities, x, loss.vg(x)[2], names)[3]
        for _ in range(3 if optimizer == "scoring" else 1):
            x, aux, g, Hm = opt.newton(loss, x, scales, gtol, hess, free)
            hess.remember(x, Hm)  # the curvature newton gives for where it ended
            if _free_gradient(g, free) <= gtol:
                break
    on, J, qnames, free = _bounds_at(obj, setup, quantities, x, g, names)
    polished = not setup.stochastic and _free_gradient(g, free) <= gtol
    max_std = np.where([n.startswith("x0[") for n in names], np.inf, MAX_SCALED_STD)
    unc = uncertainty(obj.n_steps * Hm, J, scales, names, max_std=max_std, fixed=~free,
                      pinned=np.array([q in on for q in qnames], dtype=bool))
    return x, aux, float(np.max(np.abs(g))), polished, unc, on, Hm


def _diagnostics_ahead(setup, data, model, Q0, R0, x0, builder_kwargs, bounds, standard_errors,
                       checks):
    """The diagnostics' programs (:func:`vehjax.tune.diagnostics.compile_ahead`) compiled from
    the start in a second host thread while the fit runs: a future, or None (no standard
    errors, a particle filter, or a platform that does one thing at a time)."""
    if not standard_errors or setup.stochastic or execution.current().side_by_side < 2:
        return None
    start = diagnostics.Start(model, Q0, R0, (builder_kwargs or {}).get("input_noise"), x0)
    return execution.in_thread(diagnostics.compile_ahead, start, setup, data, bounds, checks)


def _compiled_ahead(future) -> diagnostics.Ahead:
    """The programs a future compiled, or none (no future, or a compile failed: the
    diagnostics then compile their own and raise what is wrong)."""
    if future is None:
        return diagnostics.Ahead()
    try:
        return future.result()
    except Exception:  # noqa: BLE001 - the diagnostics' own compile reports it
        return diagnostics.Ahead()


def fit_from_theta(builder, model, Q0, R0, measurements, inputs=None, *, x0, P0, params=(),
                   bounds=None, noise=NOISE, fit_x0: bool = False, optimizer=None,
                   learning_rate=None, steps: int | None = None, tol: float = 1e-7,
                   patience: int | None = None, gtol: float = GTOL, key=None,
                   builder_kwargs=None, progress: bool = True, standard_errors: bool = True,
                   hessian: str | None = None, floors=None,
                   compiled: program.Program | None = None, priors=None,
                   checks: diagnostics.Checks = diagnostics.Checks()) -> TuneResult:
    """Fit Q, R, the input noise, named model parameters and optionally x0 by maximum likelihood,
    with standard errors, from one start: ``model.theta``, Q0, R0 and the given input noise as
    they are (:func:`vehjax.tune.fit` chooses the start from the data first).

    Args:
        builder: a filter builder ``builder(model, Q, R, **builder_kwargs) -> Estimator``:
            ``vehjax.filters.ekf``, ``ukf``, ``ckf`` (``builder_kwargs={"sqrt": True}`` for the
            square-root forms), ``bootstrap_pf`` (differentiated with stop-gradient
            resampling, :func:`vehjax.tune.stop_gradient_pf`), or one's own state-only builder.
        model: a vehjax model; ``model.theta`` holds the starting parameter values.
        Q0, R0: starting covariances, (n, n) or (n,) variances; diagonal ones are fitted as
            diagonal, full ones as full (:mod:`vehjax.tune`). Positive definite when fitted; a Q0
            that is not fitted may be positive semi-definite (zero, with input noise).
        measurements: (T, ny) one run or (R, T, ny) runs; NaN components are missing.
        inputs: (T, nu) shared or (R, T, nu) per run; None for a model without inputs.
        x0, P0: prior of every run: x0 (nx,) or (R, nx), P0 (nx, nx), (nx,) or (R, nx, nx).
        params: names of model parameters to fit (default none).
        bounds: ``{name: (lo, hi)}`` for fitted parameters, either end None (:mod:`vehjax.tune`).
        noise: which noise to fit, a subset of ("Q", "R", "input") (default ("Q", "R")).
            "input" fits the input noise whose starting value is
            ``builder_kwargs["input_noise"]``: stds by input name (log stds fitted, reported as
            ``"input[name]"`` stds in the input's unit) or an (nu, nu) covariance (fitted like
            Q0, reported in units squared).
        fit_x0: also fit x0 (the shape it was given in).
        optimizer: None (default): "scoring" (BHHH then Newton steps, forward-mode
            derivatives) for deterministic filters with at most 12 fitted coordinates,
            "lbfgs" for those with more, "adam" for particle filters; or one of those names,
            or an ``optax.GradientTransformation`` (docs/tune.md, "Optimisers").
        steps: maximum number of iterations, >= 1 (default 300 adam, 100 lbfgs/scoring).
        learning_rate, tol, patience: adam's (and a custom optimiser's) peak rate > 0 (default
            0.05, cosine decay to 5 % over ``steps``), the relative improvement >= 0 of the best
            loss that resets ``patience``, and iterations >= 1 without it before stopping (50).
        gtol: > 0, the projected gradient of the loss (mean negative log-likelihood per
            step, unconstrained coordinates) at which L-BFGS and scoring stop; deterministic
            fits then take a Newton polish, and ``converged`` tests gtol there over the
            quantities not on a bound (docs/tune.md, "The options of a fit in full").
        key: PRNG key, required for particle filters; run r uses ``jax.random.split(key, R)[r]``
            at every iteration.
        builder_kwargs: further keyword arguments of ``builder`` (``sqrt``, ``alpha``,
            ``n_particles``, ``input_noise``, ...).
        progress: show a progress bar (tqdm.auto when installed, else a line on stderr).
        standard_errors: compute the observed information (the Hessian of the
            log-likelihood): standard errors, correlations, undetermined directions, and for
            deterministic filters the score tests of held parameters and the innovation checks
            (:mod:`vehjax.tune.diagnostics`), at the cost of two more compiles (default True).
        hessian: "differences" (default for deterministic filters: forward differences of
            JAX's exact gradient, relative error ~1e-6) or "jax" (``jax.hessian``, exact, one
            more compile; default for particle filters).
        floors: ``{parameter name: least value the data allow}`` (``model.data_floors``), or
            None: a parameter that ends far below its floor is reported
            (``TuneResult.below_floor``), not called undetermined.
        priors: ``{parameter name: prior}`` of :mod:`vehjax.lib.priors` (``Normal``,
            ``LogNormal``, ``LogNormal.within(value, 0.3)``, ``Uniform``; the dict
            :func:`vehjax.calibrate.pmmh` takes): each named parameter is fitted by penalised
            likelihood (MAP in physical coordinates); ``loglik`` stays the plain log-likelihood
            (:mod:`vehjax.tune.priors`).
        compiled: the program of this fit's objective compiled for another start, differing
            only in the fitted values (:func:`compile_objective`; :func:`vehjax.tune.fit`
            compiles the next stage's while it fits the nested model); None (default):
            compiled here.
        checks: which diagnostics the standard errors come with
            (:class:`vehjax.tune.diagnostics.Checks`); by default the score tests of every
            held parameter and the innovation checks (:func:`vehjax.tune.fit`'s nested stage
            asks for the score tests of what it may release only).

    Returns:
        :class:`TuneResult`. A warning names the quantities the data do not determine
        (:func:`vehjax.tune.uncertainty`), also in ``TuneResult.undetermined``, and those on a
        bound of their domain with the likelihood increasing beyond it
        (:mod:`vehjax.tune.boundaries`), also in ``TuneResult.on_bound``, and the model
        parameters held fixed whose values the data contradict (``TuneResult.score_tests``,
        :mod:`vehjax.tune.diagnostics`).

    Raises:
        ValueError: naming the argument, before anything is traced: an unknown parameter name,
            wrong shapes, a Q0/R0/P0 that is not positive definite, learning_rate <= 0,
            steps < 1, an unknown optimizer, a missing key, nothing to fit; ``priors``
            naming the parameter: an unknown name, no prior object, a prior outside the
            parameter's domain (:func:`vehjax.tune.priors.check`).
    """
    t_start = time.perf_counter()
    learning_rate, tol, gtol = _check_fit_options(learning_rate, tol, gtol, hessian, steps,
                                                  patience, optimizer, progress,
                                                  standard_errors)
    obj, setup = prepare(builder, model, Q0, R0, measurements, inputs, x0, P0, params, bounds,
                         noise, fit_x0, key, builder_kwargs, priors)
    check_options(dict(optimizer=optimizer, learning_rate=learning_rate),  # before compiling
                  stochastic=setup.stochastic)
    differences = not setup.stochastic and hessian in (None, "differences")
    ahead = _diagnostics_ahead(setup, obj.data, model, Q0, R0, x0, builder_kwargs, bounds,
                               standard_errors, checks)
    names, scales = coordinates(setup, model, obj.z0)
    flat0, unravel0 = jax.flatten_util.ravel_pytree(obj.z0)
    if setup.log_prior is not None:  # a narrow prior: the coordinate's size is its width
        scales = tune_priors.prior_scales(scales, np.diagonal(np.asarray(program.prior_terms(
            setup.log_prior, unravel0, flat0, 1)[2])))
    setup = setup._replace(bounds=boundaries.quantity_bounds(setup, model))
    box = boundaries.coordinate_box(names, flat0, setup.bounds)
    loss = program.compiled_loss(obj, setup, batch_hessian=differences and obj.n_steps >=
                                 program.BATCH_HESSIAN_STEPS and (standard_errors or optimizer
                                                                  in (None, "scoring")), box=box,
                                 compiled=compiled)
    if optimizer is None:
        optimizer = ("adam" if setup.stochastic else
                     "scoring" if loss.vgo is not None else "lbfgs")
    if optimizer == "scoring" and loss.vgo is None:  # too many coordinates for forward mode
        optimizer = "lbfgs"
    line_search = isinstance(optimizer, str) and optimizer in ("lbfgs", "scoring")
    if line_search and learning_rate is not None:
        raise ValueError(f"learning_rate: {optimizer} takes its steps by a line search; leave "
                         f"it None")
    steps = (opt.LBFGS_STEPS if line_search else opt.ADAM_STEPS) if steps is None else steps
    patience = 50 if patience is None else patience
    first = None if line_search else opt.first_order_optimizer(optimizer, learning_rate, steps)
    report, bar = _progress(steps, progress, setup.name)
    x, aux, history, iters, converged, skipped = _optimise(
        loss, optimizer, dict(steps=steps, gtol=gtol, tol=tol, patience=patience, first=first,
                              n_steps=obj.n_steps),
        report, scales)
    bar.close()
    unc, grad_max = None, float("nan")
    quantities = _quantity_map(obj, setup, model, loss.unravel)
    if standard_errors:
        x, aux, grad_max, polished, unc, on, Hm = _standard_errors(
            obj, setup, quantities, loss, x, optimizer, hessian, gtol, scales, names)
        converged = converged or polished
    else:
        if optimizer == "scoring":  # the Newton polish finishes scoring
            free = _bounds_at(obj, setup, quantities, x, loss.vg(x)[2], names)[3]
            x, aux, g, _ = opt.newton(loss, x, scales, gtol,
                                      lambda f: difference_hessian(loss, f, scales), free,
                                      curvature_after=False)
        else:
            g = loss.vg(x)[2]
        on, _, _, free = _bounds_at(obj, setup, quantities, x, g, names)
        if optimizer == "scoring":
            grad_max = float(np.max(np.abs(g)))
            converged = converged or _free_gradient(g, free) <= gtol
    z = loss.unravel(jnp.asarray(x))
    res = make_result(obj, setup, model, z, aux, history, iters, converged, skipped, unc,
                      grad_max, t_start, on, floors)
    if standard_errors and not setup.stochastic:  # the nested fit of fit() pays nothing
        res = res._replace(**diagnostics.fit_diagnostics(
            res, setup, obj.data, z, bounds, tuple(on), _compiled_ahead(ahead), checks,
            (tuple(names), np.asarray(Hm, dtype=float))))
    st = loss.stats
    return res._replace(seconds=time.perf_counter() - t_start, evaluations=st["evaluations"], optimizer=str(optimizer)
                        if isinstance(optimizer, str) else "optax", derivatives=st["mode"],
                        compile_seconds=st["compile_seconds"], hessian_batches=st["batch_evaluations"],
                        hessian_compile_seconds=st["batch_compile_seconds"],
                        compile_cpu_seconds=st["compile_cpu_seconds"])


def compile_objective(builder, model, Q0, R0, measurements, inputs=None, *, x0, P0, params=(),
                      bounds=None, noise=NOISE, fit_x0: bool = False, key=None,
                      builder_kwargs=None, priors=None) -> program.Program:
    """The program :func:`fit_from_theta` compiles for these arguments, to hand to fits of the
    same objective from other starts (``compiled=``): the fitted values are the program's
    argument, everything else (the data, the model's other parameters, the noise not fitted)
    its constants."""
    obj, setup = prepare(builder, model, Q0, R0, measurements, inputs, x0, P0, params, bounds,
                         noise, fit_x0, key, builder_kwargs, priors)
    return program.compile_program(obj, setup)


def fit_noise(builder, model, Q0, R0, measurements, inputs=None, *, x0, P0, noise=NOISE,
              **kwargs) -> TuneResult:
    """Fit the noise covariances Q and R (``noise``: both by default) by maximum likelihood:
    :func:`fit_from_theta` with no model parameters. Same arguments and result."""
    if "params" in kwargs:
        raise ValueError("params: fit_noise fits Q and R only; use vehjax.tune.fit for model "
                         "parameters")
    return fit_from_theta(builder, model, Q0, R0, measurements, inputs, x0=x0, P0=P0, noise=noise,
                          **kwargs)
