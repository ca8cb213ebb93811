"""The option records of a fit (:func:`vehjax.tune.fit`, :func:`vehjax.tune.fit_from_theta`):

* what is fitted, the argument ``params``: parameter names, or :class:`Fitted` (the names, the
  noise, x0, the parameters' bounds and priors);
* how, the argument ``options``: :class:`Options` (the optimiser, the standard errors, the
  progress bar, the particle filter's key); the optimiser one record per optimiser
  (:class:`Adam`, :class:`LBFGS`, :class:`Scoring`, :class:`FirstOrder` for an optax
  transformation of one's own), the standard errors :class:`StandardErrors`;
* where from, the argument ``start`` of :func:`vehjax.tune.fit`: :class:`Start`.

Each record checks its fields when made (ValueError naming ``record.field``), before anything
is traced; the defaults are the fit's defaults. The shorthands (a tuple of names for
``params``, "adam" / "lbfgs" / "scoring" or an ``optax.GradientTransformation`` for
``optimizer``, True / False for ``standard_errors``, "data" / "theta" for ``start``) are mapped
to the records here, in one place (:func:`fitted`, :func:`optimizer_record`,
:func:`standard_errors_record`, :func:`start_record`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import optax

from .. import validation
from .optimisers import ADAM_LR, ADAM_STEPS, GTOL, LBFGS_STEPS

__all__ = ["Fitted", "Adam", "LBFGS", "Scoring", "FirstOrder", "StandardErrors", "Options",
           "Start", "fitted", "optimizer_record", "standard_errors_record", "start_record",
           "NOISE", "NOISE_KINDS", "OPTIMIZERS", "HESSIANS", "STARTS"]

NOISE = ("Q", "R")
NOISE_KINDS = ("Q", "R", "input")
HESSIANS = ("differences", "jax")
STARTS = ("data", "theta")
TOL = 1e-7
PATIENCE = 50


@dataclasses.dataclass(frozen=True)
class Fitted:
    """What a fit fits, the argument ``params`` in full (a tuple of names is
    ``Fitted(names)``).

    Attributes:
        names: model parameters to fit (default none); a parameter in ``priors`` is fitted too.
        noise: which noise to fit, a subset of ("Q", "R", "input") (default ("Q", "R")).
            "input" fits the input noise whose starting value is the builder's option
            ``input_noise`` (``functools.partial(builder, input_noise=...)``): stds by input
            name (log stds fitted, reported as ``"input[name]"`` stds in the input's unit) or
            an (nu, nu) covariance (fitted like Q0, reported in units squared).
        x0: also fit x0 (the shape it was given in), default False.
        bounds: ``{name: (lo, hi)}`` for fitted parameters, in their units, either end None
            (:mod:`vehjax.tune`).
        priors: ``{parameter name: prior}`` of :mod:`vehjax.lib.priors` (``Normal``,
            ``LogNormal``, ``LogNormal.within(value, 0.3)``, ``Uniform``; the dict
            :func:`vehjax.calibrate.pmmh` takes): each named parameter is fitted by penalised
            likelihood (MAP in physical coordinates; :mod:`vehjax.tune.priors`).

    The names, bounds and priors are checked against the model by the fit.
    """

    names: Any = ()
    noise: Any = NOISE
    x0: bool = False
    bounds: Any = None
    priors: Any = None

    def __post_init__(self):
        if isinstance(self.names, Mapping):
            raise ValueError("params: expected a sequence of parameter names; give their bounds "
                             "in vehjax.tune.Fitted(bounds={name: (lo, hi)})")
        if isinstance(self.names, str):
            object.__setattr__(self, "names", (self.names,))
        object.__setattr__(self, "noise", validation.names("params.noise", self.noise,
                                                           NOISE_KINDS, allow_empty=True))
        object.__setattr__(self, "x0", validation.flag("params.x0", self.x0))


def fitted(params) -> Fitted:
    """The argument ``params``, names or :class:`Fitted`, as a :class:`Fitted`."""
    return params if isinstance(params, Fitted) else Fitted(params)


def _steps(record: str, steps):
    return validation.integer(f"{record}.steps", steps, 1)


def _gtol(record: str, gtol):
    return validation.number(f"{record}.gtol", gtol, 0.0)


def _first_order_fields(self, record: str) -> None:
    object.__setattr__(self, "steps", _steps(record, self.steps))
    object.__setattr__(self, "tol", validation.number(f"{record}.tol", self.tol, 0.0,
                                                      low_open=False))
    object.__setattr__(self, "patience", validation.integer(f"{record}.patience",
                                                            self.patience, 1))
    object.__setattr__(self, "gtol", _gtol(record, self.gtol))


@dataclasses.dataclass(frozen=True)
class Adam:
    """Adam with a cosine-decayed rate, keeping the best point (:func:`vehjax.tune.optimisers.
    first_order`); the default for particle filters.

    Attributes:
        learning_rate: peak rate > 0 (default 0.05), cosine decay to 5 % over ``steps``.
        steps: maximum number of iterations, >= 1 (default 300).
        tol: relative improvement >= 0 of the best loss that resets ``patience``.
        patience: iterations >= 1 without that improvement before stopping (default 50).
        gtol: > 0, the gradient (mean negative log-likelihood per step, unconstrained
            coordinates) the Newton polish of a deterministic filter's standard errors aims at
            (docs/tune.md, "The options of a fit in full").
    """

    learning_rate: float = ADAM_LR
    steps: int = ADAM_STEPS
    tol: float = TOL
    patience: int = PATIENCE
    gtol: float = GTOL

    def __post_init__(self):
        object.__setattr__(self, "learning_rate", validation.number(
            "optimizer.learning_rate", self.learning_rate, 0.0))
        _first_order_fields(self, "optimizer")


@dataclasses.dataclass(frozen=True)
class FirstOrder:
    """An optax transformation of one's own, run as :class:`Adam` is (the best point kept,
    non-finite updates skipped); its rate is set inside it.

    Attributes:
        transformation: an ``optax.GradientTransformation``.
        steps, tol, patience, gtol: as :class:`Adam`'s (default 300, 1e-7, 50, 1e-6).
    """

    transformation: Any
    steps: int = ADAM_STEPS
    tol: float = TOL
    patience: int = PATIENCE
    gtol: float = GTOL

    def __post_init__(self):
        if not isinstance(self.transformation, optax.GradientTransformation):
            raise ValueError(f"optimizer.transformation: expected an "
                             f"optax.GradientTransformation, got {self.transformation!r}")
        _first_order_fields(self, "optimizer")


@dataclasses.dataclass(frozen=True)
class LBFGS:
    """``optax.lbfgs`` with its zoom line search (:func:`vehjax.tune.optimisers.lbfgs`); the
    default of deterministic filters with more than 12 fitted coordinates.

    Attributes:
        steps: maximum number of iterations, >= 1 (default 100).
        gtol: > 0, the projected gradient of the loss (mean negative log-likelihood per step,
            unconstrained coordinates) at which it stops; the Newton polish follows, and
            ``converged`` tests gtol there over the quantities not on a bound.
    """

    steps: int = LBFGS_STEPS
    gtol: float = GTOL

    def __post_init__(self):
        object.__setattr__(self, "steps", _steps("optimizer", self.steps))
        object.__setattr__(self, "gtol", _gtol("optimizer", self.gtol))


@dataclasses.dataclass(frozen=True)
class Scoring:
    """BHHH on forward-mode scores, then Newton steps (:func:`vehjax.tune.optimisers.scoring`);
    the default of deterministic filters with at most 12 fitted coordinates (L-BFGS, with the
    same fields, beyond). Deterministic filters only.

    Attributes:
        steps, gtol: as :class:`LBFGS`'s (default 100, 1e-6).
    """

    steps: int = LBFGS_STEPS
    gtol: float = GTOL

    def __post_init__(self):
        object.__setattr__(self, "steps", _steps("optimizer", self.steps))
        object.__setattr__(self, "gtol", _gtol("optimizer", self.gtol))


#: the optimisers by name, the one list of them (``vehjax.commands.config`` writes the names
#: out, importing no JAX; tests/test_cli_drive.py checks that they agree)
OPTIMIZERS = {"adam": Adam, "lbfgs": LBFGS, "scoring": Scoring}
_RECORDS = (Adam, LBFGS, Scoring, FirstOrder)


def optimizer_record(value):
    """The argument ``optimizer``: None (the default, chosen by the fit), a record, a name of
    :data:`OPTIMIZERS` (its record's defaults) or an ``optax.GradientTransformation``
    (:class:`FirstOrder` with its defaults); ValueError naming ``optimizer`` otherwise."""
    if value is None or isinstance(value, _RECORDS):
        return value
    if isinstance(value, optax.GradientTransformation):
        return FirstOrder(value)
    if not isinstance(value, str):
        raise ValueError(f"optimizer: expected None, {', '.join(map(repr, OPTIMIZERS))}, "
                         f"vehjax.tune.Adam/LBFGS/Scoring/FirstOrder(...) or an "
                         f"optax.GradientTransformation, got {value!r}")
    return OPTIMIZERS[validation.choice("optimizer", value, tuple(OPTIMIZERS))]()


def optimizer_name(record) -> str:
    """"adam", "lbfgs", "scoring" or "optax" (:attr:`vehjax.tune.TuneResult.optimizer`)."""
    if isinstance(record, FirstOrder):
        return "optax"
    return {Adam: "adam", LBFGS: "lbfgs", Scoring: "scoring"}[type(record)]


@dataclasses.dataclass(frozen=True)
class StandardErrors:
    """The standard errors of a fit (the observed information, the Hessian of the
    log-likelihood): standard errors, correlations, undetermined directions, and for
    deterministic filters the score tests of held parameters and the innovation checks
    (:mod:`vehjax.tune.diagnostics`), at the cost of one more compile (the filter with
    covariances; in forward mode the fit runs on the score tests' program,
    :func:`vehjax.tune.diagnostics.compile_shared`, else that is a second).

    Attributes:
        hessian: "differences" (default for deterministic filters: forward differences of
            JAX's exact gradient, relative error ~1e-6) or "jax" (``jax.hessian``, exact, one
            more compile; default for particle filters); None: the default.
    """

    hessian: str | None = None

    def __post_init__(self):
        if self.hessian is not None:
            validation.choice("options.standard_errors.hessian", self.hessian, HESSIANS)


def standard_errors_record(value):
    """The argument ``standard_errors``: True (:class:`StandardErrors` by default), False (none,
    returned as None) or a record; ValueError naming it otherwise (``"no"`` is refused, not
    read as True)."""
    if isinstance(value, StandardErrors):
        return value
    return StandardErrors() if validation.flag("options.standard_errors", value) else None


@dataclasses.dataclass(frozen=True)
class Options:
    """How a fit runs, the argument ``options``.

    Attributes:
        optimizer: None (default): :class:`Scoring` for deterministic filters (L-BFGS beyond 12
            fitted coordinates), :class:`Adam` for particle filters; or a record
            (:class:`Adam`, :class:`LBFGS`, :class:`Scoring`, :class:`FirstOrder`), a name
            ("adam", "lbfgs", "scoring": that record's defaults) or an
            ``optax.GradientTransformation`` (docs/tune.md, "Optimisers"). Held as the record.
        standard_errors: True (default), False, or :class:`StandardErrors`; held as the record
            or None.
        progress: show a progress bar (tqdm.auto when installed, else a line on stderr).
        key: PRNG key, required for particle filters; run r uses
            ``jax.random.split(key, R)[r]`` at every iteration.
    """

    optimizer: Any = None
    standard_errors: Any = True
    progress: bool = True
    key: Any = None

    def __post_init__(self):
        object.__setattr__(self, "optimizer", optimizer_record(self.optimizer))
        object.__setattr__(self, "standard_errors",
                           standard_errors_record(self.standard_errors))
        object.__setattr__(self, "progress", validation.flag("options.progress", self.progress))


@dataclasses.dataclass(frozen=True)
class Start:
    """Where :func:`vehjax.tune.fit` starts and what it compares with (:mod:`vehjax.tune.staged`),
    the argument ``start`` in full ("data" or "theta" is ``Start(values)``).

    Attributes:
        values: "data" (default): the nested model's fit and the data's floors give the start;
            "theta": ``model.theta``, Q0, R0 and the given input noise as they are.
        compare: fit the nested model (``model.nested_model()``) and report a result below its
            likelihood (default True; a model without one has nothing to compare).
        release: fit a held parameter the data reject under the model's data-sheet prior
            (``model.spec_priors()``; :mod:`vehjax.tune.release`) and say so
            (``TuneResult.released``), default True; False holds every given value as given.
            Needs the standard errors.
    """

    values: str = "data"
    compare: bool = True
    release: bool = True

    def __post_init__(self):
        validation.choice("start.values", self.values, STARTS)
        object.__setattr__(self, "compare", validation.flag("start.compare", self.compare))
        object.__setattr__(self, "release", validation.flag("start.release", self.release))


def start_record(value) -> Start:
    """The argument ``start``: "data", "theta" or :class:`Start`."""
    return value if isinstance(value, Start) else Start(value)
