"""The model type every vehjax filter works on.

A model is an equinox Module holding the sampling period ``dt``, the integrator, the names of its
states, inputs, parameters and outputs, and the nominal parameter vector ``theta``. Its two methods
are pure functions on 1-D arrays::

    transition(x, u, theta) -> x_next     # (nx,), (nu,), (np,) -> (nx,)
    observe(x, u, theta)    -> y          # (nx,), (nu,), (np,) -> (ny,)

Built-in vehicle models subclass :class:`VehicleModel` and write the continuous-time
``derivative(x, u, theta)``; ``transition`` integrates it over ``dt`` with explicit Euler or RK4.
A user's own discrete-time model is wrapped by :class:`Model`.

Models hold ``theta`` as an array, so ``jax.jit(model.transition)`` on the bound method fails
(JAX would hash the model); jit a lambda, ``jax.jit(lambda x, u, th: model.transition(x, u, th))``,
or use ``equinox.filter_jit``.

Physical domains: every built-in model declares the interval each parameter must lie in
(``PARAM_DOMAINS``, :mod:`vehjax.models.domains`) and the largest plausible magnitude of its
states (``STATE_ENVELOPE``); ``model.param_domains()`` and ``model.state_envelope()`` read them
(:class:`BaseModel`). A user's :class:`Model` has none unless given ``domains=``.
"""

from __future__ import annotations

import abc

from typing import Callable, ClassVar, Protocol, runtime_checkable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import execution, validation
from ..runtime.substitute import fast_elementary
from .domains import Interval, ParamDomains, envelope, gather, interval

INTEGRATORS = ("euler", "rk4")


def integrate(derivative: Callable, x, u, theta, dt: float, integrator: str, substeps: int = 1):
    """``substeps`` steps of ``xdot = derivative(x, u, theta)`` over ``dt / substeps`` seconds
    each (explicit Euler or classical RK4), input held constant.

    Traced (inside ``jit``, ``vmap``, a filter's scan), ``derivative`` is one ``jax.jit`` call
    traced once: the stages of every sub-step share its trace and JAX's transformations of it
    (a fit's forward-mode tangents through the EKF's Jacobians), about half the trace of a fit's
    program for the single-track model with two RK4 sub-steps; XLA inlines the call, the
    arithmetic is the same. Several sub-steps are a loop (``lax.fori_loop``) where the
    platform's strategy says so (``rolled_substeps`` of :mod:`vehjax.execution`: on the CPU),
    else written out. Called with concrete arrays, ``derivative`` runs as it is, written out."""
    h = dt / substeps
    traced = any(validation.is_tracer(v) for v in (x, u, theta))
    d = jax.jit(lambda a, b, c: derivative(a, b, c)) if traced else derivative
    if traced and substeps > 1 and execution.current().rolled_substeps:
        return jax.lax.fori_loop(0, substeps, lambda _, xk: _integrator_step(
            d, xk, u, theta, h, integrator), x)
    for _ in range(substeps):
        x = _integrator_step(d, x, u, theta, h, integrator)
    return x


def _integrator_step(derivative: Callable, x, u, theta, h: float, integrator: str):
    """One Euler or RK4 step of ``h`` seconds."""
    if integrator == "euler":
        return x + h * derivative(x, u, theta)
    k1 = derivative(x, u, theta)
    k2 = derivative(x + 0.5 * h * k1, u, theta)
    k3 = derivative(x + 0.5 * h * k2, u, theta)
    k4 = derivative(x + h * k3, u, theta)
    return x + h / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def _check_dt(dt) -> float:
    return validation.number("dt", dt, 0.0)


def _check_integrator(integrator) -> str:
    if integrator not in INTEGRATORS:
        raise ValueError(f"integrator: expected one of {INTEGRATORS}, got {integrator!r}")
    return integrator


def _check_names(arg: str, names) -> tuple[str, ...]:
    if isinstance(names, str):
        raise ValueError(f"{arg}: expected a sequence of names, got the single string {names!r}")
    names = tuple(names)
    if not all(isinstance(n, str) and n for n in names):
        raise ValueError(f"{arg}: expected non-empty strings, got {names!r}")
    if len(set(names)) != len(names):
        raise ValueError(f"{arg}: names must be unique, got {names!r}")
    return names


def _check_theta(theta, param_names: tuple[str, ...]):
    theta = validation.array("theta", theta)  # real and finite, or ValueError naming theta
    theta = theta.astype(np.float64).reshape(-1) if theta.ndim <= 1 else theta
    if theta.ndim != 1 or theta.shape[0] != len(param_names):
        raise ValueError(
            f"theta: expected shape ({len(param_names)},) for parameters {param_names}, "
            f"got shape {np.shape(theta)}"
        )
    return jnp.asarray(theta)


def _user_domains(domains, names: tuple[str, ...]) -> ParamDomains | None:
    """:class:`Model`'s ``domains=`` as ParamDomains over ``names``; ValueError naming
    ``domains`` for an unknown name or an entry that is no interval."""
    if domains is None:
        return None
    if isinstance(domains, ParamDomains):  # a wrapped model's, kept as they are
        if domains.names != names:
            raise ValueError(f"domains: expected the domains of parameters {names}, got those "
                             f"of {domains.names}")
        return domains
    if not isinstance(domains, dict):
        raise ValueError(f"domains: expected a dict parameter name -> interval such as "
                         f"'(0, inf)', got {domains!r}")
    given = validation.keyed("domains", domains, names, "the model's parameters")
    out = []
    for n in names:
        d = given.get(n, Interval(-np.inf, np.inf))
        if isinstance(d, str):
            try:
                d = interval(d)
            except ValueError as e:
                raise ValueError(f"domains[{n!r}]: {e}") from None
        if not isinstance(d, Interval):
            raise ValueError(f"domains[{n!r}]: expected an interval such as '(0, inf)' or "
                             f"vehjax.models.domains.Interval, got {d!r}")
        out.append(d)
    return ParamDomains(names, tuple(out), "Model")


@runtime_checkable
class ModelProtocol(Protocol):
    """What every filter, ``simulate`` and ``run`` need of a model: the interface a user's own
    model class must offer (:class:`Model` and the built-in models do).

    ``transition(x, u, theta) -> x_next`` and ``observe(x, u, theta) -> y`` are pure functions
    on 1-D arrays; ``theta`` the nominal parameter vector (np,); ``dt`` the sampling period, s.
    """

    dt: float
    theta: jnp.ndarray
    state_names: tuple[str, ...]
    input_names: tuple[str, ...]
    param_names: tuple[str, ...]
    output_names: tuple[str, ...]

    def transition(self, x, u, theta): ...

    def observe(self, x, u, theta): ...


@runtime_checkable
class DrivableModel(ModelProtocol, Protocol):
    """A model the closed-loop driver of :mod:`vehjax.scenarios` can steer along a course (every
    built-in vehicle model): the methods it calls, in the model's own units."""

    def drive_input(self, x, delta, accel, speed, theta):
        """Input vector (nu,) for road-wheel angle ``delta`` [rad], longitudinal acceleration
        ``accel`` [m/s^2] and target ``speed`` [m/s]."""

    def body_velocity(self, x, u, theta):
        """(vx, vy, r): body-frame velocity [m/s] and yaw rate [rad/s]."""

    def pose(self, x):
        """(X, Y, psi) when the state carries the pose, else None."""

    def speed(self, x):
        """Longitudinal speed [m/s]."""

    def initial_state(self, speed):
        """State (nx,) driving straight at ``speed`` [m/s]."""


class BaseModel(eqx.Module):
    """What filters, ``simulate`` and ``run`` rely on. Not instantiated directly.

    Attributes:
        dt: sampling period, s.
        theta: nominal ("true") parameter vector, shape (np,).
        state_names, input_names, param_names, output_names: tuples of names.
        state_units, input_units, param_units, output_units: tuples of unit strings, same lengths.

    Physical domains (:mod:`vehjax.models.domains`):

    * ``param_domains()``: the :class:`~vehjax.models.domains.ParamDomains` of the model's
      parameters, in ``param_names`` order (``.bounds()`` gives the (low, high) arrays, -inf /
      +inf for open ends; ``.intervals[j]`` says whether each end is closed and why the domain
      is what it is; ``.describe()`` lists them), or None when the model declares none (a
      :class:`Model` built without ``domains=``: nothing is checked). A built-in model declares
      them in its class-level ``PARAM_DOMAINS`` (name -> Interval), and its docstring states the
      sign convention they follow. They are checked (:func:`vehjax.validation.in_domain`,
      ValueError naming the argument, the parameter, its value and its domain) where the model
      is built (``theta=``), by :meth:`with_theta`, by :func:`vehjax.simulate` (``theta=``) and
      by :func:`vehjax.filter` / :func:`vehjax.run` (``theta0`` of a state-only filter).
    * ``state_envelope()``: (nx,) largest plausible magnitude per state (+inf where none), or
      None (finiteness only); a built-in model declares it in ``STATE_ENVELOPE``.
      :func:`vehjax.simulate` flags a run whose states leave it (``Simulation.diverged``).
    """

    dt: float = eqx.field(static=True)
    theta: jnp.ndarray
    #: its functions' shapes and dtypes were checked (:func:`vehjax.validation.model_shapes`):
    #: at construction for :class:`Model`, by the tests for the built-in models
    shapes_checked: ClassVar[bool] = True
    #: parameter name -> :class:`~vehjax.models.domains.Interval` (empty: no domains declared)
    PARAM_DOMAINS: ClassVar[dict] = {}
    #: state name -> largest plausible magnitude in the state's unit (empty: finiteness only)
    STATE_ENVELOPE: ClassVar[dict] = {}

    def param_domains(self) -> ParamDomains | None:
        """The domains of ``param_names`` (class docstring), or None when none are declared."""
        return gather(self.PARAM_DOMAINS, self.param_names, type(self).__name__)

    def nested_model(self) -> "BaseModel | None":
        """A simpler model nested in this one, or None (the default: none declared).

        Nested: the same states, inputs and outputs; its parameters a subset of this model's
        with the same names and meanings; this model approaches it in a limit of the others
        (the saturating tyres of :class:`~vehjax.models.SingleTrack` at a large friction
        coefficient give its linear tyres). :func:`vehjax.tune.fit` fits it first: its fitted
        values start this model's fit, and its likelihood is the least this model's fit should
        reach."""
        return None

    def spec_priors(self) -> dict:
        """``{parameter name: prior}``: how well a data sheet gives each parameter, centred at
        this model's ``theta`` (default: none declared).

        A built-in model declares them for the values a user takes from a data sheet rather
        than from the drive (a car's mass, yaw inertia, centre of gravity): where the data
        reject such a value held fixed (its score test, :mod:`vehjax.tune.diagnostics`),
        :func:`vehjax.tune.fit` fits it under this prior (:mod:`vehjax.tune.release`). The
        priors are :mod:`vehjax.lib.priors` objects."""
        return {}

    def data_floors(self, measurements, inputs) -> dict:
        """``{parameter name: the least value the measured data allow}`` (default: none).

        A built-in model declares a floor where its physics bounds what it can produce: e.g. a
        saturating tyre model cannot produce a lateral acceleration above mu g, so mu is at
        least the drive's peak |ay| / g. :func:`vehjax.tune.fit` starts such a parameter at
        its floor and reports a fit that ends far below it.

        Args:
            measurements: (T, ny) or (R, T, ny) in ``output_names`` order, NaN missing.
            inputs: (T, nu) or (R, T, nu), or None.
        """
        return {}

    def state_envelope(self) -> np.ndarray | None:
        """(nx,) largest plausible |state| (+inf where none), or None (finiteness only)."""
        return envelope(self.STATE_ENVELOPE, self.state_names)

    @property
    def nx(self) -> int:
        return len(self.state_names)

    @property
    def nu(self) -> int:
        return len(self.input_names)

    @property
    def ny(self) -> int:
        return len(self.output_names)

    @property
    def n_params(self) -> int:
        return len(self.param_names)

    def param_index(self, names) -> tuple[int, ...]:
        """Indices of ``names`` in ``param_names``; ValueError naming any unknown one."""
        if isinstance(names, str):
            names = (names,)
        unknown = [n for n in names if n not in self.param_names]
        if unknown:
            raise ValueError(
                f"estimate: unknown parameter name(s) {unknown}; this model has {self.param_names}"
            )
        return tuple(self.param_names.index(n) for n in names)

    def with_theta(self, **values) -> "BaseModel":
        """A copy with some nominal parameters replaced, by name: ``model.with_theta(m=1800.0)``."""
        idx = self.param_index(tuple(values))
        theta = np.array(self.theta, dtype=float)
        theta[list(idx)] = [float(v) for v in values.values()]
        validation.in_domain("with_theta", theta, self.param_domains())
        return eqx.tree_at(lambda m: m.theta, self, jnp.asarray(theta))

    def describe(self) -> str:
        """A human-readable listing of states, inputs, parameters (nominal, unit) and outputs."""

        def fmt(names, units):
            return ", ".join(f"{n} [{u}]" for n, u in zip(names, units))

        params = ", ".join(
            f"{n} = {float(v):.6g} [{u}]"
            for n, v, u in zip(self.param_names, np.asarray(self.theta), self.param_units)
        )
        return "\n".join(
            [
                f"{type(self).__name__} (dt = {self.dt} s, integrator = {getattr(self, 'integrator', '-')})",
                f"  states:     {fmt(self.state_names, self.state_units)}",
                f"  inputs:     {fmt(self.input_names, self.input_units)}",
                f"  parameters: {params}",
                f"  outputs:    {fmt(self.output_names, self.output_units)}",
            ]
        )


class VehicleModel(BaseModel):
    """A continuous-time model integrated over ``dt``; subclasses define ``derivative`` and
    ``observe`` and class-level names, units and nominal parameters.

    Subclasses set the ClassVars below and may override ``output_names``/``output_units`` as
    properties when they offer several output sets.
    """

    integrator: str = eqx.field(static=True)

    STATE_NAMES: ClassVar[tuple[str, ...]] = ()
    STATE_UNITS: ClassVar[tuple[str, ...]] = ()
    INPUT_NAMES: ClassVar[tuple[str, ...]] = ()
    INPUT_UNITS: ClassVar[tuple[str, ...]] = ()
    PARAM_NAMES: ClassVar[tuple[str, ...]] = ()
    PARAM_UNITS: ClassVar[tuple[str, ...]] = ()
    PARAM_NOMINAL: ClassVar[tuple[float, ...]] = ()

    def __init__(self, dt: float = 0.01, integrator: str = "rk4", theta=None):
        self.dt = _check_dt(dt)
        self.integrator = _check_integrator(integrator)
        self.theta = _check_theta(self.PARAM_NOMINAL if theta is None else theta, self.PARAM_NAMES)
        validation.in_domain("theta", self.theta, self.param_domains())

    state_names = property(lambda self: self.STATE_NAMES)
    state_units = property(lambda self: self.STATE_UNITS)
    input_names = property(lambda self: self.INPUT_NAMES)
    input_units = property(lambda self: self.INPUT_UNITS)
    param_names = property(lambda self: self.PARAM_NAMES)
    param_units = property(lambda self: self.PARAM_UNITS)

    @abc.abstractmethod
    def derivative(self, x, u, theta):
        """Continuous-time state derivative, (nx,) -> (nx,) in state units per second."""

    @abc.abstractmethod
    def observe(self, x, u, theta):
        """Measurement for state ``x`` under input ``u``, shape (ny,)."""

    def transition(self, x, u, theta):
        """State after ``dt`` seconds with input ``u`` held constant, shape (nx,)."""
        return integrate(self.derivative, x, u, theta, self.dt, self.integrator)


class Model(BaseModel):
    """A user's own discrete-time model from two pure functions.

    Args:
        transition: ``f(x, u, theta) -> x_next`` on 1-D arrays, pure and jit-able.
        observe: ``h(x, u, theta) -> y`` on 1-D arrays.
        dt: sampling period, s (> 0).
        state_names, param_names, input_names, output_names: names of the vector components.
        theta: nominal parameters, shape (len(param_names),); zeros when omitted.
        units: optional dict name -> unit string for any of the names.
        fast_math: evaluate the functions with ``jnp.sin``, ``cos``, ``tan``, ``arctan`` and
            ``arctan2`` replaced by :mod:`vehjax.lib.elementary`'s vectorisable versions (same results
            to a few ulps, gradients intact; see :func:`vehjax.runtime.substitute.fast_elementary`),
            which XLA on CPU fuses into vector loops: about twice as fast a filter on a model
            written with trigonometry. False keeps the functions exactly as given. Filters
            that evaluate the model one point at a time (EKF; every Gaussian filter's per-run
            step, vmapped over runs) call the functions as written (``written_fns``): on short
            vectors the substitutes cost more than they save (``vehjax bench all`` measures
            both forms).
        domains: optional dict parameter name -> domain, each an
            :class:`~vehjax.models.domains.Interval` or its text (``"(0, inf)"``, ``"[0, 3]"``);
            parameters it does not name are unbounded. Or a model's ``param_domains()`` (a
            wrapper of a built-in model keeps its domains). Checked like a built-in model's
            (:class:`BaseModel`); None (default): no domains, nothing checked.

    Example::

        model = Model(transition=lambda x, u, th: th[0] * x + u, observe=lambda x, u, th: x,
                      dt=0.1, state_names=("x",), param_names=("a",), input_names=("u",),
                      output_names=("y",), theta=[0.9])
    """

    transition_fn: Callable = eqx.field(static=True)
    observe_fn: Callable = eqx.field(static=True)
    written_fns: tuple = eqx.field(static=True)  # (transition, observe) as given (no fast_math)
    state_names: tuple[str, ...] = eqx.field(static=True)
    input_names: tuple[str, ...] = eqx.field(static=True)
    param_names: tuple[str, ...] = eqx.field(static=True)
    output_names: tuple[str, ...] = eqx.field(static=True)
    units: tuple[tuple[str, str], ...] = eqx.field(static=True)
    domains: ParamDomains | None = eqx.field(static=True)

    def __init__(
        self,
        transition: Callable,
        observe: Callable,
        dt: float,
        state_names,
        param_names=(),
        input_names=(),
        output_names=None,
        theta=None,
        units: dict | None = None,
        fast_math: bool = True,
        domains: dict | None = None,
    ):
        if not callable(transition):
            raise ValueError(f"transition: expected a function f(x, u, theta), got {transition!r}")
        if not callable(observe):
            raise ValueError(f"observe: expected a function h(x, u, theta), got {observe!r}")
        self.written_fns = (transition, observe)
        if validation.flag("fast_math", fast_math):
            transition, observe = fast_elementary(transition), fast_elementary(observe)
        self.transition_fn = transition
        self.observe_fn = observe
        self.dt = _check_dt(dt)
        self.state_names = _check_names("state_names", state_names)
        if not self.state_names:
            raise ValueError("state_names: expected at least one state")
        self.param_names = _check_names("param_names", param_names)
        self.input_names = _check_names("input_names", input_names)
        if output_names is None:
            output_names = tuple(f"y{i}" for i in range(len(self._probe_output())))
        self.output_names = _check_names("output_names", output_names)
        theta = np.zeros(len(self.param_names)) if theta is None else theta
        self.theta = _check_theta(theta, self.param_names)
        self.units = tuple(sorted((units or {}).items()))
        self.domains = _user_domains(domains, self.param_names)
        validation.in_domain("theta", self.theta, self.domains)
        validation.model_shapes(self)  # transition -> (nx,), observe -> (ny,), or ValueError

    def param_domains(self) -> ParamDomains | None:
        """The ``domains=`` given, for every parameter (unnamed ones unbounded), or None."""
        return self.domains

    def _probe_output(self):
        x = jnp.zeros(len(self.state_names))
        u = jnp.zeros(len(self.input_names))
        th = jnp.zeros(len(self.param_names))
        return np.atleast_1d(np.asarray(self.observe_fn(x, u, th)))

    def _units_for(self, names):
        d = dict(self.units)
        return tuple(d.get(n, "-") for n in names)

    state_units = property(lambda self: self._units_for(self.state_names))
    input_units = property(lambda self: self._units_for(self.input_names))
    param_units = property(lambda self: self._units_for(self.param_names))
    output_units = property(lambda self: self._units_for(self.output_names))

    def transition(self, x, u, theta):
        return jnp.asarray(self.transition_fn(x, u, theta))

    def observe(self, x, u, theta):
        return jnp.atleast_1d(jnp.asarray(self.observe_fn(x, u, theta)))
