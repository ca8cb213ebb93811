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
from .likelihood import NOISE, prepare_fit
from .options import LBFGS, Adam, Fitted, Options, Scoring, fitted, optimizer_name
from .quantities import coordinates, fitted_quantities
from .result import TuneResult, make_result

__all__ = ["fit_from_theta", "fit_noise", "fit_start", "compile_objective", "check_optimizer",
           "choose_optimizer"]


def check_optimizer(optimizer, stochastic: bool) -> None:
    """The optimiser record refused where the filter cannot take it, before anything is
    compiled: scoring needs a deterministic filter."""
    if stochastic and isinstance(optimizer, Scoring):
        raise ValueError("optimizer: 'scoring' needs a deterministic filter (EKF, UKF, CKF); "
                         "use vehjax.tune.Adam() for a particle filter")


def choose_optimizer(optimizer, stochastic: bool, forward: bool):
    """The optimiser record that runs: ``optimizer`` (:class:`vehjax.tune.Options`), or by
    default Adam for a particle filter, scoring for a deterministic one, L-BFGS (scoring's
    steps and gtol) where there are too many coordinates for forward mode (``forward``
    False)."""
    if optimizer is None:
        optimizer = Adam() if stochastic else Scoring() if forward else LBFGS()
    if isinstance(optimizer, Scoring) and not forward:
        optimizer = LBFGS(optimizer.steps, optimizer.gtol)
    return optimizer


def _progress(steps: int, enabled, name: str):
    """``(report(i, loss, best), bar)``: the fit's progress bar (:mod:`vehjax.runtime.progress`),
    labelled ``vehjax.tune (name)``, its text line rewritten at most 5 times a second."""
    label = f"vehjax.tune ({name})"
    bar = Progress(steps, label, bool(enabled), interval=0.2)

    def report(i: int, loss: float, best: float):
        bar.update(i, f"loss={loss:.6g}, best={best:.6g}",
                   f"{label}: iteration {i}/{steps}, loss {loss:.6g}, best {best:.6g}")

    return report, bar


def _optimise(loss, optimizer, n_steps: int, report, scales):
    """The chosen optimiser (a record of :mod:`vehjax.tune.options`) on the compiled loss:
    (x, aux, history, iterations, converged, skipped)."""
    steps, gtol = optimizer.steps, optimizer.gtol
    if isinstance(optimizer, Scoring):
        return (*opt.scoring(loss, steps, gtol, report, scales, n_steps), 0)
    if isinstance(optimizer, LBFGS):
        return (*opt.lbfgs(loss, steps, gtol, report), 0)
    first = (opt.first_order_optimizer("adam", optimizer.learning_rate, steps)
             if isinstance(optimizer, Adam) else
             opt.first_order_optimizer(optimizer.transformation, None, steps))
    return opt.first_order(loss, first, steps, optimizer.tol, optimizer.patience, report)


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


def _standard_errors(obj, setup, quantities, loss, x, scoring, hessian, gtol, scales, names):
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
        for _ in range(3 if scoring else 1):
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


def _diagnostics_ahead(setup, data, start, bounds, standard_errors, checks, augmented):
    """The diagnostics' programs (:func:`vehjax.tune.diagnostics.compile_ahead`; the score
    tests' only where ``augmented``) compiled from the start in a second host thread while
    the fit runs: a future, or None (no standard errors, a particle filter, nothing to
    compile, or a platform that does one thing at a time)."""
    if not standard_errors or setup.stochastic or execution.current().side_by_side < 2 or (
            not augmented and not checks.innovations):
        return None
    return execution.in_thread(diagnostics.compile_ahead, start, setup, data, bounds, checks,
                               augmented)


def _compiled_ahead(future, shared) -> diagnostics.Ahead:
    """The programs a future compiled, or none (no future, or a compile failed: the
    diagnostics then compile their own and raise what is wrong); ``shared`` the fit's own
    program where it serves the score tests (:func:`vehjax.tune.diagnostics.compile_shared`),
    else None."""
    ahead = diagnostics.Ahead()
    if future is not None:
        try:
            ahead = future.result()
        except Exception:  # noqa: BLE001 - the diagnostics' own compile reports it
            pass
    return ahead if shared is None else ahead._replace(augmented=shared)


def _start(model, Q0, R0, setup, x0) -> diagnostics.Start:
    """The fit's start as the diagnostics read it (:class:`vehjax.tune.diagnostics.Start`):
    the model, Q0, R0, the builder's input noise and x0 as given."""
    return diagnostics.Start(model, Q0, R0, setup.builder_options.get("input_noise"), x0)


def _program_plan(compiled, setup, names, start, checks, tests: bool):
    """(``compiled`` where given and it serves this fit, else None; whether the fit's program
    serves its score tests too): a given program with a layout serves the fit when
    :func:`vehjax.tune.program.serves` says so (one without is taken as given), and the tests
    when its held parameters are theirs; without a program, a fit with score tests in forward
    mode runs on theirs (:func:`vehjax.tune.diagnostics.compile_shared`); ``names`` the fit's
    coordinates' (:func:`vehjax.tune.quantities.coordinates`)."""
    if compiled is not None and compiled.layout is not None and not program.serves(
            compiled.layout, names, start.model):
        compiled = None
    extra = diagnostics.shared_extra(start.model, setup, checks.held) if tests else ()
    if not extra:
        return compiled, False
    if compiled is None:
        return None, True
    return compiled, compiled.layout is not None and compiled.layout.extra == extra


def fit_from_theta(builder, model, Q0, R0, measurements, inputs=None, *, x0, P0, params=(),
                   options: Options | None = None, floors=None) -> TuneResult:
    """Fit Q, R, the input noise, named model parameters and optionally x0 by maximum likelihood,
    with standard errors, from one start: ``model.theta``, Q0, R0 and the given input noise as
    they are (:func:`vehjax.tune.fit` chooses the start from the data first).

    Args:
        builder: a filter builder ``builder(model, Q, R) -> Estimator``, its own options
            (``sqrt``, ``alpha``, ``n_particles``, ``input_noise``, ...) given with it by
            ``functools.partial(builder, **options)``: ``vehjax.filters.ekf``, ``ukf``, ``ckf``
            (``functools.partial(vehjax.filters.ekf, sqrt=True)`` for the square-root forms),
            ``bootstrap_pf`` (differentiated with stop-gradient resampling,
            :func:`vehjax.tune.stop_gradient_pf`), or one's own state-only builder.
        model: a vehjax model; ``model.theta`` holds the starting parameter values.
        Q0, R0: starting covariances, (n, n) or (n,) variances; diagonal ones are fitted as
            diagonal, full ones as full (:mod:`vehjax.tune`). Positive definite when fitted; a Q0
            that is not fitted may be positive semi-definite (zero, with input noise).
        measurements: (T, ny) one run or (R, T, ny) runs; NaN components are missing.
        inputs: (T, nu) shared or (R, T, nu) per run; None for a model without inputs.
        x0, P0: prior of every run: x0 (nx,) or (R, nx), P0 (nx, nx), (nx,) or (R, nx, nx).
        params: names of model parameters to fit (default none), or
            :class:`vehjax.tune.Fitted`: the names, which noise (default ("Q", "R"); "input"
            fits the input noise whose starting value is the builder's ``input_noise``),
            x0, the parameters' bounds and priors (penalised likelihood, MAP in physical
            coordinates; ``loglik`` stays the plain log-likelihood, :mod:`vehjax.tune.priors`).
        options: :class:`vehjax.tune.Options`: the optimiser (None, default: "scoring", BHHH
            then Newton steps, for deterministic filters with at most 12 fitted coordinates,
            "lbfgs" for those with more, "adam" for particle filters; or a record
            :class:`vehjax.tune.Adam`, ``LBFGS``, ``Scoring``, ``FirstOrder``, docs/tune.md,
            "Optimisers"), the standard errors (True, False or
            :class:`vehjax.tune.StandardErrors`: the observed information, and for
            deterministic filters the score tests of held parameters and the innovation checks,
            :mod:`vehjax.tune.diagnostics`, at the cost of one more compile, the filter with
            covariances; the fit itself runs on the score tests' program), the progress bar
            and a particle filter's PRNG key (required for particle filters; run r uses
            ``jax.random.split(key, R)[r]`` at every iteration). None: ``Options()``.
        floors: ``{parameter name: least value the data allow}`` (``model.data_floors``), or
            None: a parameter that ends far below its floor is reported
            (``TuneResult.below_floor``), not called undetermined.

    Returns:
        :class:`TuneResult`. A warning names the quantities the data do not determine
        (:func:`vehjax.tune.uncertainty`), also in ``TuneResult.undetermined``, and those on a
        bound of their domain with the likelihood increasing beyond it
        (:mod:`vehjax.tune.boundaries`), also in ``TuneResult.on_bound``, and the model
        parameters held fixed whose values the data contradict (``TuneResult.score_tests``,
        :mod:`vehjax.tune.diagnostics`).

    Raises:
        ValueError: naming the argument, before anything is traced: an unknown parameter name,
            wrong shapes, a Q0/R0/P0 that is not positive definite, a missing key, nothing to
            fit, scoring with a particle filter (the records check their own fields); ``priors``
            naming the parameter: an unknown name, no prior object, a prior outside the
            parameter's domain (:func:`vehjax.tune.priors.check`).
    """
    return fit_start(builder, model, Q0, R0, measurements, inputs,
                     dict(x0=x0, P0=P0, params=params),
                     validation.record("options", options, Options), floors=floors)


def _finish(obj, setup, loss, x, optimizer, std_errors, gtol, scales, names, quantities):
    """After the optimiser: the standard errors' Newton polish and information
    (:func:`_standard_errors`), or scoring's Newton polish alone; (x, aux or None, max
    |gradient|, the polish converged, uncertainty or None, on bound, Hessian or None)."""
    scoring = isinstance(optimizer, Scoring)
    if std_errors is not None:
        return _standard_errors(obj, setup, quantities, loss, x, scoring, std_errors.hessian,
                                gtol, scales, names)
    aux, grad_max, polished = None, float("nan"), False
    if scoring:  # the Newton polish finishes scoring
        free = _bounds_at(obj, setup, quantities, x, loss.vg(x)[2], names)[3]
        x, aux, g, _ = opt.newton(loss, x, scales, gtol,
                                  lambda f: difference_hessian(loss, f, scales), free,
                                  curvature_after=False)
    else:
        g = loss.vg(x)[2]
    on, _, _, free = _bounds_at(obj, setup, quantities, x, g, names)
    if scoring:
        grad_max = float(np.max(np.abs(g)))
        polished = _free_gradient(g, free) <= gtol
    return x, aux, grad_max, polished, None, on, None


def fit_start(builder, model, Q0, R0, measurements, inputs, args: dict, options: Options, *,
              floors=None, compiled: program.Program | None = None,
              checks: diagnostics.Checks = diagnostics.Checks()) -> TuneResult:
    """:func:`fit_from_theta` with ``args`` its keywords (x0, P0, params) and
    two more for :func:`vehjax.tune.fit`'s stages: ``compiled``, the program of this fit's
    objective compiled for another start, differing only in the fitted values
    (:func:`compile_objective`; None: compiled here), and ``checks``, which diagnostics the
    standard errors come with (:class:`vehjax.tune.diagnostics.Checks`; by default the score
    tests of every held parameter and the innovation checks)."""
    t_start = time.perf_counter()
    what, key = fitted(args["params"]), options.key
    x0 = args["x0"]
    std_errors, user_opt = options.standard_errors, options.optimizer
    obj, setup = prepare_fit(builder, model, Q0, R0, measurements, inputs, x0, args["P0"], what,
                             key)
    check_optimizer(user_opt, setup.stochastic)  # before compiling
    hessian = None if std_errors is None else std_errors.hessian
    differences = not setup.stochastic and hessian in (None, "differences")
    start = _start(model, Q0, R0, setup, x0)
    tests = std_errors is not None and not setup.stochastic
    names, scales = coordinates(setup, model, obj.z0)
    compiled, sharing = _program_plan(compiled, setup, names, start, checks, tests)
    ahead = _diagnostics_ahead(setup, obj.data, start, what.bounds, std_errors is not None,
                               checks, augmented=not sharing)
    if sharing and compiled is None:
        compiled = diagnostics.compile_shared(start, setup, obj.data, what.bounds, checks.held)
    shared = compiled if sharing else None
    flat0, unravel0 = jax.flatten_util.ravel_pytree(obj.z0)
    if setup.log_prior is not None:  # a narrow prior: the coordinate's size is its width
        # one program: evaluated op by op, the prior's value, gradient and Hessian compile
        # about a hundred small XLA programs (1.2 s on the 2-core CPU)
        curvature = jax.jit(lambda f: program.prior_terms(setup.log_prior, unravel0, f, 1)[2])
        scales = tune_priors.prior_scales(scales, np.diagonal(np.asarray(curvature(flat0))))
    setup = setup._replace(bounds=boundaries.quantity_bounds(setup, model))
    box = boundaries.coordinate_box(names, flat0, setup.bounds)
    loss = program.compiled_loss(obj, setup, batch_hessian=differences and
                                 program.batched_hessian(obj.n_steps) and (
                                     std_errors is not None or user_opt is None
                                     or isinstance(user_opt, Scoring)), box=box,
                                 compiled=compiled)
    optimizer = choose_optimizer(user_opt, setup.stochastic, loss.vgo is not None)
    report, bar = _progress(optimizer.steps, options.progress, setup.name)
    x, aux, history, iters, converged, skipped = _optimise(loss, optimizer, obj.n_steps, report,
                                                           scales)
    bar.close()
    quantities = _quantity_map(obj, setup, model, loss.unravel)
    x, aux_polish, grad_max, polished, unc, on, Hm = _finish(
        obj, setup, loss, x, optimizer, std_errors, optimizer.gtol, scales, names, quantities)
    aux = aux if aux_polish is None else aux_polish
    converged = converged or polished
    z = loss.unravel(jnp.asarray(x))
    res = make_result(obj, setup, model, z, aux, (history, iters, converged, skipped), unc,
                      grad_max, t_start, on, floors)
    if std_errors is not None and not setup.stochastic:  # the nested fit of fit() pays nothing
        res = res._replace(**diagnostics.fit_diagnostics(
            res, setup, obj.data, z, what.bounds, tuple(on), _compiled_ahead(ahead, shared), checks,
            (tuple(names), np.asarray(Hm, dtype=float))))
    st = loss.stats
    return res._replace(seconds=time.perf_counter() - t_start, evaluations=st["evaluations"],
                        optimizer=optimizer_name(optimizer), derivatives=st["mode"],
                        compile_seconds=st["compile_seconds"], hessian_batches=st["batch_evaluations"],
                        hessian_compile_seconds=st["batch_compile_seconds"],
                        compile_cpu_seconds=st["compile_cpu_seconds"])


def compile_objective(builder, model, Q0, R0, measurements, inputs=None, *, x0, P0, params=(),
                      key=None, checks: diagnostics.Checks | None = None,
                      beside: bool = False) -> program.Program:
    """The program :func:`fit_from_theta` compiles for these arguments (those of
    :func:`vehjax.tune.objective`), to hand to fits of the same objective from other starts
    (:func:`fit_start`'s ``compiled``): the fitted values are the program's argument,
    everything else (the data, the model's other parameters, the noise not fitted) its
    constants. ``checks``: the fit has standard errors with these diagnostics, so its program
    is its score tests' where it can be (:func:`vehjax.tune.diagnostics.compile_shared`);
    None: without. ``beside``: the fit runs while another program compiles
    (:func:`vehjax.execution.direction_block`)."""
    what = fitted(params)
    obj, setup = prepare_fit(builder, model, Q0, R0, measurements, inputs, x0, P0, what, key)
    if checks is not None:
        shared = diagnostics.compile_shared(_start(model, Q0, R0, setup, x0), setup, obj.data,
                                            what.bounds, checks.held, beside)
        if shared is not None:
            return shared
    return program.compile_program(obj, setup, beside)


def fit_noise(builder, model, Q0, R0, measurements, inputs=None, *, x0, P0, noise=NOISE,
              options: Options | None = None) -> TuneResult:
    """Fit the noise covariances Q and R (``noise``: both by default, a subset of ("Q", "R",
    "input")) by maximum likelihood: :func:`fit_from_theta` with no model parameters
    (``params=vehjax.tune.Fitted(noise=noise)``). Same result."""
    return fit_from_theta(builder, model, Q0, R0, measurements, inputs, x0=x0, P0=P0,
                          params=Fitted(noise=noise), options=options)
