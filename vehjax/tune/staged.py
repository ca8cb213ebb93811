"""Where a fit starts and what it is measured against: :func:`fit`, the public entry point of
:mod:`vehjax.tune`.

Why. A saturating tyre model (``SingleTrack(tyres="brush" | "pacejka")``) fitted from its
nominal values on a drive near the limit falls into a trap: with a friction coefficient near 1
the model cannot produce the 1.2-1.5 g the car reached, the filter explains the difference by
input and sensor noise, and the optimiser stops there, at a likelihood below that of the
simpler linear model and sometimes with mu "not determined". The likelihood has a better
optimum, which a start above the trap reaches.

What :func:`fit` does, by default (``start="data"``, ``compare=True``), for a model that
declares a nested model (:meth:`vehjax.models.BaseModel.nested_model`; the saturating tyres
nest the linear ones):

1. fit the nested model first: its parameters among ``params``, the same noise, filter and
   options, no standard errors;
2. start the model from the nested fit's values (its parameters, Q, R, the input noise, x0)
   and each fitted parameter that has a floor the data imply
   (:meth:`~vehjax.models.BaseModel.data_floors`; mu >= the drive's peak |ay| / g) at
   :data:`FLOOR_MARGIN` times its floor; the other parameters at ``model.theta``;
3. if that fit's log-likelihood is below the nested model's by more than
   :data:`BELOW_NESTED`, a second start: the floored parameters at the geometric middle of the
   first start and their domain's upper end (twice the first start where it has none); the
   better of the two is the result (``TuneResult.starts`` lists both);
4. report (``TuneResult.nested``, ``below_nested``, ``below_floor`` and a warning) a result
   whose log-likelihood stays below the nested model's, or whose parameter ends far below its
   floor.

A model without a nested model is fitted from the data's floors alone (step 2 without the
nested values). ``start="theta"`` fits from ``model.theta`` and the given noise as they are,
still compared with the nested model's fit when ``compare=True``; ``start="theta",
compare=False`` fits no nested model at all. With ``start="data"`` the nested model is always
fitted (it gives the start); ``compare=False`` then only leaves ``TuneResult.nested`` empty and
reports nothing against it. A floor's parameter is reported whichever start was taken.

Cost: the nested fit (cheaper per evaluation: for the single-track model a linear tyre curve,
about half the time of the saturating fit on the same drive) plus the model's own fit, which
from a start near the optimum takes fewer iterations; a second start only where the first
stayed below the nested model, on the same compiled program. Where the host has a core to
spare (``side_by_side`` of :mod:`vehjax.execution`) the model's program is compiled in a second
thread while the nested model is fitted. Measured on the benchmark drives:
``benchmarks/bench_fit_limit.py``.

The nested model is not exactly nested for the single-track model: its linear tyres use small
slip angles and cos(delta) = 1, which the saturating ones do not, so on a drive that stays
far from the limit the two likelihoods differ by a little either way; :data:`BELOW_NESTED`
keeps that from being reported.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
import warnings

import numpy as np

from .. import execution, validation
from .diagnostics import Checks
from .driver import check_optimizer, compile_objective, fit_start
from . import priors as tune_priors
from .likelihood import check_data, draws_random_numbers, objective
from .options import STARTS, Fitted, Options, fitted, start_record
from .parameterisation import check_bounds
from .release import release_priors, start_value, to_release
from .result import Comparison, TuneResult

__all__ = ["fit", "STARTS", "BELOW_NESTED", "FLOOR_MARGIN", "start_values"]

#: a fit whose log-likelihood is below the nested model's by more than this (natural log
#: units, summed over the runs) is below it
BELOW_NESTED = 1.0
#: a parameter with a data floor starts this factor above it
FLOOR_MARGIN = 1.05


def _label(model) -> str:
    """``"SingleTrack (m, iz, lf, lr, cf, cr)"``: the model's class and parameter names."""
    return f"{type(model).__name__} ({', '.join(model.param_names)})"


def _inside(value: float, lo: float, hi: float) -> float:
    """``value`` moved at least 5 % of a finite domain's width inside it."""
    if math.isfinite(lo) and math.isfinite(hi):
        pad = 0.05 * (hi - lo)
        return min(max(value, lo + pad), hi - pad)
    return value


def start_values(model, floors: dict, params, bounds=None, second: bool = False) -> dict:
    """The starting values of the fitted parameters among ``floors`` ({name: floor}):
    ``FLOOR_MARGIN * floor`` (the first start), or the geometric middle of that and the upper
    end of the parameter's domain (narrowed by ``bounds``), twice it where there is none
    (``second=True``); moved inside the domain. ``{name: value}``."""
    domains = model.param_domains()
    n = len(model.param_names)
    lo, hi = domains.bounds() if domains is not None else (np.full(n, -np.inf), np.full(n, np.inf))
    out = {}
    for k, floor in floors.items():
        if k not in params:
            continue
        j = model.param_names.index(k)
        a, b = (bounds or {}).get(k, (None, None))
        low = float(lo[j]) if a is None else max(float(lo[j]), float(a))
        high = float(hi[j]) if b is None else min(float(hi[j]), float(b))
        v = FLOOR_MARGIN * floor
        if second:
            v = math.sqrt(v * high) if math.isfinite(high) and v > 0 else 2.0 * v
        out[k] = _inside(v, low, high)
    return out


def _nested_likelihood(builder, nested, Q0, R0, ys, us, x0, P0, key):
    """The nested model's log-likelihood at its given values, when nothing of it is fitted."""
    obj = objective(builder, nested, Q0, R0, ys, us, x0=x0, P0=P0,
                    params=Fitted(noise=("R",)), key=key)
    return -float(obj.loss(obj.z0, obj.data)[0]) * obj.n_steps


def _nested_args(nested, args: dict):
    """The nested fit's arguments: its parameters among ``params`` and their bounds, the rest
    as given; None when nothing of it is fitted."""
    params = tuple(p for p in args["params"] if p in nested.param_names)
    if not (params or args["noise"] or args["fit_x0"]):
        return None
    bounds = {k: v for k, v in (args["bounds"] or {}).items() if k in params}
    priors = {k: v for k, v in args["priors"].items() if k in params}
    return dict(args, params=params, bounds=bounds or None, priors=priors)


def _call(args: dict) -> dict:
    """The keywords of :func:`~vehjax.tune.driver.fit_start`'s ``args`` and
    :func:`~vehjax.tune.driver.compile_objective` from a stage's ``args`` (x0, P0, params,
    bounds, noise, fit_x0, priors): what is fitted as a :class:`~vehjax.tune.Fitted`."""
    return dict(x0=args["x0"], P0=args["P0"],
                params=Fitted(args["params"], args["noise"], args["fit_x0"], args["bounds"],
                              args["priors"]))


def _fit_nested(builder, nested, Q0, R0, ys, us, args: dict, nargs, options: Options,
                compiled=None, diagnose: bool = False):
    """(the nested model's :class:`~vehjax.tune.TuneResult` or None, its
    :class:`~vehjax.tune.result.Comparison`, its warnings held back); ``nargs`` from
    :func:`_nested_args`, ``compiled`` its program or None; ``diagnose``: with standard errors
    and the score tests (:mod:`vehjax.tune.release`), else without."""
    t0 = time.perf_counter()
    if nargs is None:
        ll = _nested_likelihood(builder, nested, Q0, R0, ys, us, args["x0"], args["P0"],
                                options.key)
        return None, Comparison(_label(nested), ll, {}, time.perf_counter() - t0), []
    checks = _nested_checks(nested, nargs, options, diagnose)
    se = options.standard_errors if checks is not None else False
    res, caught = _quietly(fit_start, builder, nested, Q0, R0, ys, us, _call(nargs),
                           dataclasses.replace(options, standard_errors=se),
                           compiled=compiled, checks=checks or Checks((), innovations=False))
    return res, Comparison(_label(nested), res.loglik, dict(res.values),
                           res.seconds + (0.0 if compiled is None else
                                          compiled.stats["compile_seconds"])), caught


def _nested_checks(nested, nargs: dict, options: Options, diagnose: bool):
    """The nested fit's diagnostics (:class:`~vehjax.tune.diagnostics.Checks`): the score tests
    of its held data-sheet values (those it may release), no innovation checks; None where it
    has no standard errors (not ``diagnose``, nothing such held, or none asked for)."""
    held = tuple(k for k in nested.spec_priors() if k not in nargs["params"])
    if not (diagnose and held and options.standard_errors is not None):
        return None
    return Checks(held, innovations=False)


def _model_checks(options: Options):
    """The model's own fit's diagnostics: every held parameter's score test and the innovation
    checks where it has standard errors, else None."""
    return None if options.standard_errors is None else Checks()


def _nested_stage(builder, nested, model, Q0, R0, ys, us, args: dict, options: Options,
                  diagnose: bool):
    """The nested model's fit (:func:`_fit_nested`; ``model``'s program, at its start,
    compiled beside its compile and its fit: :func:`_compile_ahead`), and made again where the data
    reject a held value that ``model`` may release (``diagnose``; :mod:`vehjax.tune.release`).
    Returns (the nested fit or None, its Comparison, the model's program's future or None,
    the model's fit's arguments, the released ``{name: ScoreTest}``); its warnings raised,
    naming it."""
    nargs = _nested_args(nested, args)
    ahead = _compile_ahead(builder, model, Q0, R0, ys, us, args, options)
    nprog = None if nargs is None else compile_objective(
        builder, nested, Q0, R0, ys, us, key=options.key, **_call(nargs),
        checks=_nested_checks(nested, nargs, options, diagnose), beside=ahead is not None)
    lin, cmp, held = _fit_nested(builder, nested, Q0, R0, ys, us, args, nargs, options, nprog,
                                 diagnose=diagnose)
    released = to_release(lin, model, args["params"]) if diagnose and lin else {}
    if released:  # the nested model again with them; the model's program compiled anew,
        # beside that fit
        nargs = _widened(nargs, model, released)
        bn, m, Qn, Rn, nargs = _released_start(builder, nested, Q0, R0, nargs, lin, released)
        args = _widened(args, model, released)
        ahead = _compile_ahead(builder, model, Q0, R0, ys, us, args, options)
        nprog = compile_objective(bn, m, Qn, Rn, ys, us, key=options.key, **_call(nargs),
                                  beside=ahead is not None)
        lin, cmp, held = _fit_nested(bn, m, Qn, Rn, ys, us, args, nargs, options, nprog)
    _reissue(held, cmp.model)
    return lin, cmp, ahead, args, released


def _check_ahead(builder, model, Q0, R0, args: dict, options: Options) -> None:
    """What the model's own fit would refuse, checked before the nested model's fit: bounds
    outside a parameter's domain; Q0, R0, the noise, the builder and its keywords (the filter
    built once at the start, nothing traced); scoring with a particle filter."""
    params = validation.names("params", args["params"], model.param_names, allow_empty=True)
    check_bounds(params, args["bounds"], model)
    stochastic = draws_random_numbers(builder, model, Q0, R0,
                                      Fitted(params, args["noise"], args["fit_x0"]))
    check_optimizer(options.optimizer, stochastic)


def _quietly(fn, *args, **kwargs):
    """(``fn(*args, **kwargs)``, the warnings it raised), the warnings held back: a fit that a
    later stage supersedes does not speak for the result."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = fn(*args, **kwargs)
    return res, list(caught)


def _reissue(caught, label: str | None = None) -> None:
    """Raise the warnings held back (:func:`_quietly`) for the caller of :func:`fit`; those of
    the nested model's fit say so (``label``: its description)."""
    for w in caught:
        text = str(w.message)
        if label is not None:
            nested = f"vehjax.tune (the nested {label}'s fit):"
            text = (text.replace("vehjax.tune:", nested, 1) if "vehjax.tune:" in text
                    else f"{nested} {text}")
        warnings.warn(text, w.category, stacklevel=3)


def _widened(args: dict, model, names) -> dict:
    """``args`` with the released ``names`` fitted, under ``model``'s data-sheet priors."""
    return dict(args, params=tuple(args["params"]) + tuple(names),
                priors={**args["priors"], **release_priors(model, names)})


def _released_start(builder, model, Q0, R0, args: dict, res, released: dict) -> tuple:
    """(builder, model, Q0, R0, args) of a fit made again from ``res``'s values, each
    released parameter at its :func:`~vehjax.tune.release.start_value`."""
    builder, model, Q0, R0, args = _from_nested(builder, model, Q0, R0, args, res)
    return builder, model.with_theta(**{k: start_value(t, args["priors"][k])
                               for k, t in released.items()}), Q0, R0, args


def _compile_ahead(builder, model, Q0, R0, ys, us, args: dict, options: Options):
    """The model's program (:func:`~vehjax.tune.driver.compile_objective`) compiled in a second
    host thread while this one fits the nested model: a future, or None where the platform
    does one thing at a time (``side_by_side`` of :mod:`vehjax.execution`). ``model`` is at a
    start that differs from the fit's only in fitted values (steps 2-3 move nothing else), so
    the program serves every start. The thread runs in a copy of this one's context (the
    execution strategy in force)."""
    if execution.current().side_by_side < 2:
        return None
    return execution.in_thread(compile_objective, builder, model, Q0, R0, ys, us,
                               key=options.key, **_call(args), checks=_model_checks(options))


def _compiled(future):
    """The program compiled ahead, or None: not compiled ahead, or its compile failed (the fit
    then compiles its own, and raises what is wrong)."""
    if future is None:
        return None
    try:
        return future.result()
    except Exception:  # noqa: BLE001 - the fit's own compile reports it
        return None


def _from_nested(builder, model, Q0, R0, args: dict, lin) -> tuple:
    """(builder, model, Q0, R0, args) with the nested fit's values as the start (the fitted
    input noise the builder's ``input_noise``)."""
    if lin is None:
        return builder, model, Q0, R0, args
    args = dict(args)
    given = {k: float(model.theta[model.param_names.index(k)]) for k in lin.params}
    model = model.with_theta(**{k: given[k] if k in lin.on_bound else v
                                for k, v in lin.params.items()})
    noise = args["noise"]
    Q0 = _off_bounds(lin.Q, Q0, "Q", model.state_names, lin.on_bound) if "Q" in noise else Q0
    R0 = _off_bounds(lin.R, R0, "R", model.output_names, lin.on_bound) if "R" in noise else R0
    if "input" in noise:
        inoise = lin.input_noise
        func, options = validation.builder_options(builder)
        if isinstance(inoise, dict):  # stds by name: those on their bound start as given
            start = options.get("input_noise") or {}
            inoise = {k: start.get(k, v) if f"input[{k}]" in lin.on_bound else v
                      for k, v in inoise.items()}
        builder = functools.partial(func, **{**options, "input_noise": inoise})
    if args["fit_x0"]:
        args["x0"] = lin.x0
    return builder, model, Q0, R0, args


def _off_bounds(fitted, given, name: str, components, on_bound: dict) -> np.ndarray:
    """The nested fit's covariance ``fitted`` as the model's start, its variances that ended on
    their bound (zero) back at the ``given`` start: a quantity reaches its bound only at an
    infinite coordinate (:mod:`vehjax.tune.boundaries`), so a start there could neither move
    nor be told on its bound; from the given start the model's fit finds the bound again and
    reports it (``on_bound``) as a fit from ``start="theta"`` does."""
    out = np.array(fitted, dtype=float)
    g = np.asarray(given, dtype=float)
    for i, c in enumerate(components):
        if f"{name}[{c},{c}]" in on_bound:
            v = g[i] if g.ndim == 1 else g[i, i]
            if out.ndim == 1:
                out[i] = v
            else:
                out[i, i] = v
    return out


def fit(builder, model, Q0, R0, measurements, inputs=None, *, x0, P0, params=(),
        options: Options | None = None, start="data") -> TuneResult:
    """Fit Q, R, the input noise, named model parameters and optionally x0 by maximum
    likelihood, with standard errors, from a start the data give (module docstring).

    Args:
        builder, model, Q0, R0, measurements, inputs, x0, P0, params, options:
            as :func:`vehjax.tune.driver.fit_from_theta` (``builder``'s own options given with
            it, ``functools.partial(builder, **options)``; ``params`` names or
            :class:`vehjax.tune.Fitted`; ``options`` :class:`vehjax.tune.Options`, the
            optimiser, the standard errors, the progress bar, a particle filter's key;
            ``model.theta`` the starting parameter values where the start is "theta"; a
            parameter with a prior is fitted, by penalised likelihood:
            :mod:`vehjax.tune.priors`; the nested model's fit takes the priors of its
            parameters, and of two starts the higher penalised likelihood is kept).
        start: ``"data"`` (default): the nested model's fit and the data's floors give the
            start (module docstring, steps 1-3); ``"theta"``: ``model.theta``, Q0, R0 and the
            given input noise as they are; or :class:`vehjax.tune.Start` (that and whether to
            compare with the nested model and to release held parameters the data reject:
            :mod:`vehjax.tune.release`, ``TuneResult.released``).

    Returns:
        :class:`~vehjax.tune.TuneResult`, the best start's, with ``nested``, ``below_nested``,
        ``below_floor``, ``starts`` and ``released``; ``seconds`` counts every stage. The
        warnings of a stage that a later one supersedes (a fit made again with released
        parameters) are not raised; those of the nested model's fit name it.

    Raises:
        ValueError: naming the argument (``start`` and those of
            :func:`~vehjax.tune.driver.fit_from_theta`), before anything is traced.
    """
    t0 = time.perf_counter()
    stages, what = start_record(start), fitted(params)
    start, compare = stages.values, stages.compare
    options = validation.record("options", options, Options)
    validation.model(model)
    ys, us, _, _ = check_data(model, measurements, inputs, x0, P0)
    all_floors = model.data_floors(ys, us)
    priors, bounds = tune_priors.check(what.priors, model, what.bounds)
    params = what.names
    if priors:  # the prior'd parameters fitted; the names checked here, before the nested fit
        params = tune_priors.fitted_params(
            validation.names("params", params, model.param_names, allow_empty=True), priors)
    args = dict(x0=x0, P0=P0, params=params, bounds=bounds, noise=what.noise, fit_x0=what.x0,
                priors=priors)
    _check_ahead(builder, model, Q0, R0, args, options)
    diagnose = stages.release and options.standard_errors is not None
    given = model  # the user's model: its held values and their data-sheet priors
    nested = model.nested_model() if compare or start == "data" else None
    lin = cmp = ahead = None
    released = {}
    if nested is not None:
        ahead_model = model.with_theta(**start_values(model, all_floors, params, bounds)) \
            if start == "data" else model
        lin, cmp, ahead, args, released = _nested_stage(
            builder, nested, ahead_model, Q0, R0, ys, us, args, options,
            diagnose and start == "data")
    if start == "data":
        builder, model, Q0, R0, args = _from_nested(builder, model, Q0, R0, args, lin)
        model = model.with_theta(**start_values(model, all_floors, params, bounds))
    compiled = _compiled(ahead)
    if compiled is None and cmp is not None:  # one compile for a second start too
        compiled = compile_objective(builder, model, Q0, R0, ys, us, key=options.key,
                                     **_call(args), checks=_model_checks(options))

    def one(m):
        res, caught = _quietly(fit_start, builder, m, Q0, R0, ys, us, _call(args), options,
                               floors=all_floors, compiled=compiled)
        starts.append(({k: float(m.theta[m.param_names.index(k)]) for k in args["params"]},
                       res.loglik))
        return res, caught

    starts = []
    best, held = one(model)
    if start == "data" and cmp is not None and best.loglik < cmp.loglik - BELOW_NESTED:
        second = start_values(model, all_floors, params, bounds, second=True)
        if second:
            res, caught = one(model.with_theta(**second))
            if res.loglik + res.log_prior > best.loglik + best.log_prior:
                best, held = res, caught
    more = to_release(best, given, args["params"]) if diagnose else {}
    if more:  # released by the model's own fit: made again from its values
        args = _widened(args, given, more)
        b, m, Q0, R0, args = _released_start(builder, model, Q0, R0, args, best, more)
        best, held = _quietly(fit_start, b, m, Q0, R0, ys, us, _call(args), options,
                              floors=all_floors)
        released = {**released, **more}
    _reissue(held)
    below = compare and cmp is not None and best.loglik < cmp.loglik - BELOW_NESTED
    if below:
        warnings.warn(
            f"vehjax.tune: the fitted model's log-likelihood {best.loglik:.6g} is below the "
            f"nested {cmp.model}'s {cmp.loglik:.6g} on the same data: the fit stopped at a "
            f"worse optimum than the simpler model reaches; use the nested model, or start "
            f"from the data (start='data')", stacklevel=2)
    if released:
        warnings.warn("vehjax.tune: " + "; ".join(best.release_lines(released)),
                      stacklevel=2)
    return best._replace(nested=cmp if compare else None, below_nested=below,
                         starts=tuple(starts), seconds=time.perf_counter() - t0,
                         released=released)
