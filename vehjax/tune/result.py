"""What a fit returns: :class:`TuneResult` (the fitted values by name with their units and
standard errors, the tuned estimator, the optimiser's record) and its text summary."""

from __future__ import annotations

import time
import warnings
from typing import Any, NamedTuple

import jax
import numpy as np

from ..filters.base import Estimator
from . import priors as tune_priors
from .diagnostics import diagnostics_text
from .release import release_text
from .quantities import fitted_quantities

__all__ = ["TuneResult", "Comparison", "make_result", "below_floors", "FLOOR_FRACTION"]

#: a parameter that ends below this fraction of its data floor (``model.data_floors``) is
#: reported as below it: a floor is estimated from noisy peaks, so a fit a few per cent below
#: it can be right, one 10 % below it cannot reproduce the data
FLOOR_FRACTION = 0.9


class Comparison(NamedTuple):
    """The nested model's fit a fit is compared with (:func:`vehjax.tune.fit`).

    Attributes:
        model: the nested model, described (``model.describe()``'s first line).
        loglik: its log-likelihood at its fitted values (the same data, noise and filter).
        values: its fitted quantities by name (as :attr:`TuneResult.values`).
        seconds: the wall-clock time of its fit.
    """

    model: str
    loglik: float
    values: dict
    seconds: float


class TuneResult(NamedTuple):
    """What :func:`vehjax.tune.fit` and :func:`vehjax.tune.fit_noise` return.

    Attributes:
        Q: fitted process-noise covariance, (nx, nx) (``Q0`` when Q was not fitted).
        R: fitted measurement-noise covariance, (ny, ny) (``R0`` when not fitted).
        theta: the fitted model's whole parameter vector, (np,).
        params: fitted model parameters by name (empty when none were fitted).
        x0: the fitted initial state ((nx,) or (R, nx)), or the given one.
        model: the model with the fitted parameters (``model.with_theta``).
        estimator: ``builder(model, Q, R, **options)`` (the builder's own options) at the
            fitted values, ready for :func:`vehjax.run`.
        loglik: total log-likelihood of the runs at the fitted values (sum over runs).
        loglik0: the same at the starting values.
        history: loss per iteration, (iterations,): ``-sum loglik / (R T)`` at the values that
            iteration started from.
        iterations: how many optimiser iterations ran.
        converged: deterministic filters: the projected gradient reached ``gtol`` and each
            quantity on a bound has the likelihood increasing beyond it (the bounded maximum's
            KKT conditions); adam and custom optimisers: the loss stopped improving.
        diverged: how many runs diverged (``vehjax.filter``'s flag) at the fitted values.
        skipped: iterations whose gradient was not finite.
        values: every fitted quantity by name: ``"Q[x,x]"``, ``"R[y,y]"``, a parameter name,
            ``"x0[v]"`` (``"x0[r,v]"`` per run); covariances as variances/covariances.
        units: the unit of each entry of ``values`` (``"m^2"``, ``"kg"``, ...; ``"-"`` unknown).
        seconds: wall-clock time of the fit, including compilation.
        std_errors: standard error of each entry of ``values`` in its units (same keys), from
            the observed information by the delta method; inf for an undetermined quantity, NaN
            for one on a bound; empty with ``standard_errors=False``.
        correlations: (m, m) correlations of the entries of ``values`` (in their order); NaN
            rows and columns for undetermined quantities.
        undetermined: names of the fitted quantities (coordinates) along directions of no or
            too little curvature (:func:`vehjax.tune.uncertainty`); a warning names them too.
            A quantity on a bound is not among them.
        on_bound: ``{name: (side, bound, dlogL)}`` for each fitted quantity that ended on a
            bound of its domain, with the log-likelihood's derivative pointing out of the box
            (:mod:`vehjax.tune.boundaries`); a warning names them too.
        gradient: max |d loss / dz| at the result (the loss per step, z unconstrained; every
            coordinate, those of quantities on a bound small as their map flattens there).
        input_noise: the fitted input noise as the builder takes it (stds by name or a
            covariance), or the given one, or None.
        evaluations, optimizer, derivatives, compile_seconds, hessian_batches,
            hessian_compile_seconds, compile_cpu_seconds: what the fit cost: evaluations of
            the compiled loss-and-gradient program, the optimiser that ran, "forward" or
            "reverse" derivatives, the compile's wall-clock seconds (part of ``seconds``),
            calls and compile seconds of the batched Hessian program, the compile's CPU seconds.
        below_floor: ``{name: (value, floor)}``: model parameters that ended below
            :data:`FLOOR_FRACTION` of the least value the data allow (``model.data_floors``).
        nested: the :class:`Comparison` with the nested model's fit (``model.nested_model()``),
            or None when none was made.
        below_nested: the log-likelihood is below the nested model's by more than
            :data:`vehjax.tune.staged.BELOW_NESTED`: a worse optimum than the simpler model
            reaches (a warning gives both values).
        starts: ``((start values by name, log-likelihood reached), ...)``, one per start
            :func:`vehjax.tune.fit` tried, in order; the result is the best of them.
        priors, pulls, log_prior: the priors as given (``priors=``), each Normal/LogNormal
            prior's pull (the estimate's signed distance from its centre in its standard
            deviations; beyond :data:`vehjax.tune.priors.PULL_WARN` a warning), and the sum of
            the log densities (``loglik + log_prior`` is what the fit maximised).
        score_tests, released: ``{name: ScoreTest}`` of each held model parameter (the score
            test of its value, :mod:`vehjax.tune.diagnostics`), and of each one
            :func:`vehjax.tune.fit` released under its data-sheet prior because the data
            rejected its given value (:mod:`vehjax.tune.release`).
        innovations: ``{output: InnovationCheck}``: each measured output's mean NIS, lag-1
            autocorrelation and Ljung-Box test of the fitted filter's innovations
            (:mod:`vehjax.tune.innovations`); the summary names the coloured ones. As
            ``score_tests``, else empty.
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
    on_bound: dict = {}
    below_floor: dict = {}
    nested: Comparison | None = None
    below_nested: bool = False
    starts: tuple = ()
    # priors
    priors: dict = {}
    pulls: dict = {}
    log_prior: float = 0.0
    # diagnostics (score tests, innovations)
    score_tests: dict = {}
    innovations: dict = {}
    # held values the data rejected, fitted under their data-sheet priors
    released: dict = {}

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
            pm = "" if se is None or k in self.on_bound else f" +- {se:.3g}"
            lines.append(f"  {k:<{width}} = {v:.6g}{pm} [{self.units[k]}]" + (
                f" {bound_text(k, *self.on_bound[k])}" if k in self.on_bound else "") + (
                f" {tune_priors.prior_text(self.priors[k], self.pulls.get(k))}" if k in self.priors
                else ""))
        if self.undetermined:
            lines.append(f"  not determined by the data: {', '.join(self.undetermined)}")
        for k, (v, floor) in self.below_floor.items():
            lines.append(f"  {floor_text(k, v, floor)}")
        if self.nested is not None:
            lines.append(f"  nested {self.nested.model}: log-likelihood {self.nested.loglik:.6g}"
                         f" ({'above' if self.nested.loglik > self.loglik else 'below'} this "
                         f"fit's by {abs(self.nested.loglik - self.loglik):.3g})")
        lines += [f"  {t}" for t in self.release_lines(self.released)]
        lines += [f"  {t}" for t in diagnostics_text(self.score_tests, self.innovations)]
        if len(self.starts) > 1:
            lines.append(f"  starts tried: {len(self.starts)}, log-likelihoods " + ", ".join(
                f"{ll:.6g}" for _, ll in self.starts))
        return "\n".join(lines)


    def release_lines(self, released: dict) -> list:
        """What the report says of each parameter in ``released`` ({name: ScoreTest}), at
        this result's values (:func:`vehjax.tune.release.release_text`)."""
        return [release_text(k, t, self.priors[k], self.params[k]) for k, t in released.items()]


def bound_text(name: str, side: str, bound: float, dlogl: float) -> str:
    """What the report says of a quantity on a bound: "on its upper bound 0.6 (the likelihood
    increases beyond it: d logL/d a = 12.3)"."""
    return (f"on its {side} bound {bound:.6g} (the likelihood increases beyond it: "
            f"d logL/d {name} = {dlogl:.3g})")


def floor_text(name: str, value: float, floor: float) -> str:
    """What the report says of a parameter below its data floor."""
    return (f"{name} = {value:.6g} is below {floor:.6g}, the least value the data allow: the "
            f"model cannot produce what was measured, and the fit explains it by noise")


def below_floors(model, theta, floors) -> dict:
    """``{name: (value, floor)}`` of the parameters of ``theta`` (np,) below
    :data:`FLOOR_FRACTION` of their ``floors`` ({name: floor})."""
    out = {}
    for k, floor in (floors or {}).items():
        value = float(theta[model.param_names.index(k)])
        if value < FLOOR_FRACTION * floor:
            out[k] = (value, float(floor))
    return out


def make_result(obj, info, model, best_z, best_aux, search: tuple, unc, grad_max, t_start,
                on_bound=None, floors=None) -> TuneResult:
    """The :class:`TuneResult` at ``best_z``, with warnings for diverged runs, quantities on a
    bound and undetermined quantities; ``search`` the optimiser's (history, iterations,
    converged, skipped)."""
    history, iters, converged, skipped = search
    ll, div = jax.jit(obj.loss)(best_z, obj.data)[1] if best_aux is None else best_aux
    v = jax.tree.map(np.asarray, jax.jit(obj.unpack)(best_z))  # one compile, not one an operation
    Q, R, theta, x0_fit = v["Q"], v["R"], v["theta"], v["x0"]
    Q, R = 0.5 * (Q + Q.T), 0.5 * (R + R.T)
    fitted_model = model
    if info.params:
        fitted_model = model.with_theta(**{p: float(theta[model.param_names.index(p)])
                                           for p in info.params})
    kw = dict(info.builder_options)
    if v["input"] is not None:
        kw["input_noise"] = ({k: float(s) for k, s in v["input"].items()}
                             if isinstance(v["input"], dict) else np.asarray(v["input"]))
    estimator = info.builder(fitted_model, Q, R, **kw)
    n_div = int(np.sum(np.asarray(div)))
    if n_div:
        warnings.warn(f"vehjax.tune: {n_div} of {len(div)} runs diverged at the fitted values; "
                      f"their log-likelihood counts only the steps before", stacklevel=3)
    qs = fitted_quantities(info, model, v)
    values = {k: float(x) for k, _, x in qs}
    units = {k: u for k, u, _ in qs}
    se, corr, undetermined = {}, np.full((len(qs),) * 2, np.nan), ()
    below = below_floors(model, theta, floors)
    if below:
        warnings.warn("vehjax.tune: " + "; ".join(floor_text(k, *b) for k, b in below.items()),
                      stacklevel=3)
    if unc is not None:
        se = {k: float(s) for (k, _, _), s in zip(qs, unc.std_errors)}
        corr = unc.correlations
        undetermined = tuple(k for k in unc.undetermined if k not in below)
        if undetermined:
            warnings.warn(
                f"vehjax.tune: the data do not determine {', '.join(undetermined)} (no or too "
                f"little curvature of the log-likelihood; their standard errors are inf): "
                f"fix them, or give data that excite them", stacklevel=3)
    priors = dict(info.priors or {})
    pulls, log_prior = tune_priors.report(priors, model, theta)
    message = tune_priors.pull_warning(priors, pulls, values)
    if message:
        warnings.warn(message, stacklevel=3)
    on_bound = dict(on_bound or {})
    if on_bound:
        warnings.warn("vehjax.tune: " + "; ".join(
            f"{k} is {bound_text(k, *b)}" for k, b in on_bound.items()) + ": the fit is the "
            "maximum within the bounds; widen them if the physics allows", stacklevel=3)
    return TuneResult(
        Q=Q, R=R, theta=np.asarray(theta),
        params={p: float(theta[model.param_names.index(p)]) for p in info.params},
        x0=x0_fit, model=fitted_model, estimator=estimator,
        loglik=float(np.sum(np.asarray(ll))),
        loglik0=-history[0] * obj.n_steps - info.log_prior0,
        history=np.asarray(history), iterations=iters, converged=converged, diverged=n_div,
        skipped=skipped, values=values, units=units, seconds=time.perf_counter() - t_start,
        std_errors=se, correlations=corr, undetermined=undetermined, gradient=grad_max,
        input_noise=kw.get("input_noise"), on_bound=on_bound, below_floor=below,
        priors=priors, pulls=pulls, log_prior=log_prior,
    )
