"""The objective of a fit: the negative mean log-likelihood per step of a batch of runs, as a
function of the unconstrained coordinates (:mod:`vehjax.tune`; docs/tune.md in full).

Everything is checked before tracing (:func:`prepare`, ValueError naming the argument); the
loss rebuilds the estimator with ``builder(model, Q, R, **options)`` (the builder's own
options given with it, ``functools.partial(builder, **options)``) inside the differentiated
function and runs :func:`vehjax.filter` vmapped over the runs.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import validation
from ..filtering import filter as _filter
from ..filters.base import Estimator
from ..filters.particle import bootstrap_pf
from .parameterisation import Cov, InputNoise, is_diag, param_transform
from .particle import resample_keyword, stop_gradient_pf
from . import priors as tune_priors
from .options import NOISE, NOISE_KINDS, Fitted, fitted

__all__ = ["Objective", "FitSetup", "objective", "prepare", "prepare_fit", "check_data", "NOISE",
           "NOISE_KINDS"]


class Objective(NamedTuple):
    """The objective :func:`vehjax.tune.fit` minimises, for use with an optimiser of one's own.

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


class FitSetup(NamedTuple):
    """A fit's set-up, checked before tracing (:func:`prepare`): what is fitted, from where, and
    the functions the optimisers, the standard errors and the report evaluate.

    Attributes:
        builder: the filter builder (``builder(model, Q, R, **builder_options)``), its
            options split off (:func:`vehjax.validation.builder_options`).
        builder_options: its options (a dict, as given with it by ``functools.partial``).
        params: names of the fitted model parameters (those with priors included).
        noise: which noise is fitted, a subset of ("Q", "R", "input").
        Qa, Ra: the starting (or held) Q (nx, nx) and R (ny, ny), numpy.
        diagQ, diagR: whether Q and R are fitted as diagonal.
        theta0: the model's starting parameter vector (np,).
        idx: the fitted parameters' indices in ``theta0``.
        theta_map: their bounded <-> unconstrained map (:mod:`vehjax.lib.transforms`).
        fit_x0: whether x0 is fitted.
        input: the fitted input noise's parameterisation (:class:`InputNoise`) or None.
        priors: ``{name: prior}`` as given; prior_fn: their log density of theta, or None.
        x0, P0: the runs' prior (x0 (nx,) or (R, nx), P0 (nx, nx) or (R, nx, nx)).
        z0: the starting coordinates (dict of unconstrained arrays).
        name: the filter's name; stochastic: whether it draws random numbers (a particle
            filter); workload: its kind of work (:attr:`Estimator.workload`).
        per_step: ``per_step(z, data) -> (log-likelihood per run and step, diverged)``.
        at: ``at(z, data) -> (estimator, model, Q, R, input noise, x0)`` at coordinates z.
        log_prior: ``log_prior(z)`` or None; log_prior0: its value at z0 (0.0 without).
        bounds: the fitted quantities' bounds (:func:`vehjax.tune.boundaries.quantity_bounds`),
            set by the driver; None before.
        anchored: positions in ``z["theta"]`` of the parameters that coordinates ``z`` with
            an ``"anchor"`` entry read relative to it (:func:`anchored_physical`); () none.
    """

    builder_options: dict
    params: tuple
    noise: tuple
    Qa: np.ndarray
    Ra: np.ndarray
    diagQ: bool
    diagR: bool
    theta0: np.ndarray
    idx: object
    fit_x0: bool
    input: object
    theta_map: object
    priors: dict
    prior_fn: Callable | None
    builder: Callable | None = None
    x0: np.ndarray | None = None
    P0: np.ndarray | None = None
    z0: dict | None = None
    name: str | None = None
    stochastic: bool = False
    per_step: Callable | None = None
    at: Callable | None = None
    workload: str | None = None
    log_prior: Callable | None = None
    log_prior0: float = 0.0
    bounds: dict | None = None
    anchored: tuple = ()


def float_array(name: str, value, allow_nan: bool = False) -> np.ndarray:
    """``value`` as a concrete float array by the rules every entry point shares (real; NaN
    missing in measurements, else finite); ValueError naming ``name``."""
    if validation.is_tracer(value):
        raise ValueError(f"{name}: expected a concrete array; call vehjax.tune outside jit/grad")
    return np.array(validation.array(name, value, missing=allow_nan), dtype=float)


def _check_builder(builder) -> tuple:
    """(the builder, its options): ``functools.partial(builder, **options)`` split
    (:func:`vehjax.validation.builder_options`, ValueError naming ``builder``)."""
    builder, options = validation.builder_options(builder)
    if builder is stop_gradient_pf:  # the same filter forward; its gradients are applied anyway
        return bootstrap_pf, options
    return builder, options


def _check_what(model, Q0, R0, what: Fitted, options: dict) -> FitSetup:
    """The fitted quantities (:class:`vehjax.tune.Fitted`) and their starting values checked
    (``options`` the builder's, :func:`_check_builder`):
    the set-up so far (the prior'd parameters added to the names, a Uniform prior's box to the
    bounds: :mod:`vehjax.tune.priors`)."""
    nx, ny = len(model.state_names), len(model.output_names)
    noise, params, bounds, fit_x0 = what.noise, what.names, what.bounds, what.x0
    # a Q0 that is not fitted may be singular (zero with the noise through the inputs)
    Qa = validation.cov("Q0", float_array("Q0", Q0), nx, allow_psd="Q" not in noise)
    Ra = validation.cov("R0", float_array("R0", R0), ny)
    names = tuple(model.param_names)
    params = validation.names("params", params, names, allow_empty=True)
    priors, bounds = tune_priors.check(what.priors, model, bounds)
    params = tune_priors.fitted_params(params, priors)
    theta0 = np.asarray(model.theta, dtype=float)
    idx, theta_map = param_transform(params, bounds, theta0, names, model.param_domains())
    if not noise and not params and not fit_x0:
        raise ValueError("params.noise: nothing to fit: noise=(), no parameter names and "
                         "x0=False")
    inp = None
    if "input" in noise:
        if options.get("input_noise") is None:
            raise ValueError("params.noise: 'input' fits the input noise, whose starting value "
                             "goes with the builder, functools.partial(builder, "
                             "input_noise={input name: std, ...})")
        inp = InputNoise(options["input_noise"], model)
    return FitSetup(builder_options=dict(options), params=params, noise=noise, Qa=Qa, Ra=Ra,
                diagQ=np.ndim(Q0) == 1 or is_diag(Qa), diagR=np.ndim(R0) == 1 or is_diag(Ra),
                theta0=theta0, idx=idx, fit_x0=fit_x0, input=inp, theta_map=theta_map,
                priors=priors, prior_fn=tune_priors.log_prior_fn(priors, names))


def check_data(model, measurements, inputs, x0, P0):
    """(ys (R, T, ny), us or None, x0, P0) by the checks every entry point shares
    (:mod:`vehjax.validation`): shapes, values, the prior."""
    ny, nu = len(model.output_names), len(model.input_names)
    ys, us = validation.data(float_array("measurements", measurements, allow_nan=True),
                            None if inputs is None else float_array("inputs", inputs), ny, nu,
                            "either")
    ys = ys[None] if ys.ndim == 2 else ys
    us = None if inputs is None else us
    x0a, P0a = validation.prior(len(model.state_names), float_array("x0", x0),
                               float_array("P0", P0), runs=ys.shape[0])
    return ys, us, np.asarray(x0a, dtype=float), np.asarray(P0a, dtype=float)


def _start_estimator(builder, model, setup: FitSetup, key, n_runs: int):
    """(the estimator at the starting values, the stop-gradient keyword, per-run keys or None):
    the builder checks its own arguments and says whether it needs a key."""
    est0 = _built(builder, model, setup)
    keys, sg = None, {}
    if est0.needs_key:  # a particle filter: differentiated with stop-gradient resampling
        sg = resample_keyword(builder, est0.name, setup.builder_options)
        if key is None:
            raise ValueError(f"key: {est0.name} draws random numbers; pass key=jax.random.key(...)")
        try:
            keys = jax.random.split(key, n_runs)
        except Exception:
            raise ValueError(f"key: expected a jax.random.key, got {key!r}") from None
    return est0, sg, keys


def _built(builder, model, setup: FitSetup) -> Estimator:
    """The state-only estimator ``builder`` makes at the starting values (ValueError naming
    ``builder`` where it is not one)."""
    try:
        est0 = builder(model, setup.Qa, setup.Ra, **setup.builder_options)
    except TypeError as err:  # not a state-only builder(model, Q, R, **kw), or bad keywords
        raise ValueError(
            f"builder: calling it as builder(model, Q, R, **options) failed ({err}); tune "
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
    return est0


def draws_random_numbers(builder, model, Q0, R0, what: Fitted) -> bool:
    """Whether the fit's filter is a particle filter (its optimiser by default adam, not a line
    search), found by building it at the starting values, before anything is traced;
    ValueError naming a bad argument as :func:`prepare` does (``what`` without its bounds and
    priors)."""
    what = Fitted(what.names, what.noise, what.x0)
    builder, options = _check_builder(builder)
    setup = _check_what(model, Q0, R0, what, options)
    return bool(_built(builder, model, setup).needs_key)


def anchored_physical(theta_map, zt, anchor, pos, held):
    """The physical parameters at the unconstrained ``zt`` (p,), the entries at ``pos`` (k,)
    read relative to their ``anchor`` coordinates (k,): ``held + g(zt) - g(anchor)`` there,
    g = ``theta_map.to_physical``. At ``zt[pos] == anchor`` those entries are ``held``
    (k,) exactly, where ``g(anchor)`` would round ``held`` through g and its inverse; their
    derivatives are g's. What lets a fit with parameters held run on the program of its
    score tests (:mod:`vehjax.tune.diagnostics`), which has their coordinates too, with the
    arithmetic of the fit's own program."""
    phys = theta_map.to_physical(zt)
    at_anchor = theta_map.to_physical(zt.at[pos].set(anchor))
    return phys.at[pos].set(held + (phys[pos] - at_anchor[pos]))


def _coordinates(setup: FitSetup):
    """(z0, unpack): the starting coordinates (a dict) and the map to the physical values; z
    with an ``"anchor"`` entry reads ``setup.anchored`` relative to it
    (:func:`anchored_physical`)."""
    noise, inp, idx, theta_map = setup.noise, setup.input, setup.idx, setup.theta_map
    Qa, Ra, theta0, x0a = setup.Qa, setup.Ra, setup.theta0, setup.x0
    covQ = Cov(Qa, setup.diagQ) if "Q" in noise else None
    covR = Cov(Ra, setup.diagR)
    z0 = {}
    if "Q" in noise:
        z0["Q"] = jnp.asarray(covQ.z0)
    if "R" in noise:
        z0["R"] = jnp.asarray(covR.z0)
    if inp is not None:
        z0["input"] = jnp.asarray(inp.z0)
    if setup.params:
        z0["theta"] = theta_map.to_unconstrained(jnp.asarray(theta0[idx]))
    if setup.fit_x0:
        z0["x0"] = jnp.asarray(x0a)

    def unpack(z):
        Q = covQ(z["Q"]) if "Q" in z else jnp.asarray(Qa)
        R = covR(z["R"]) if "R" in z else jnp.asarray(Ra)
        theta = jnp.asarray(theta0)
        if "theta" in z and "anchor" in z:
            pos = np.asarray(setup.anchored, dtype=int)
            theta = theta.at[idx].set(anchored_physical(
                theta_map, z["theta"], z["anchor"], pos, jnp.asarray(theta0[idx][pos])))
        elif "theta" in z:
            theta = theta.at[idx].set(theta_map.to_physical(z["theta"]))
        return {"Q": Q, "R": R, "theta": theta, "x0": z["x0"] if "x0" in z else jnp.asarray(x0a),
                "input": inp(z["input"]) if "input" in z else None}

    return z0, unpack


def _estimator_at(builder, model, setup: FitSetup, unpack, sg: dict):
    """``at(z, data) -> (estimator, model, Q, R, input noise or None, x0)``: the fit's filter
    built at the coordinates z (traceable), the values not fitted as given."""
    Qa, Ra, options = setup.Qa, setup.Ra, setup.builder_options

    def at(z, data):
        v = unpack(z)
        Q = v["Q"] if "Q" in z else Qa  # constants stay numpy: the builder may specialise
        R = v["R"] if "R" in z else Ra
        mdl = eqx.tree_at(lambda m: m.theta, model, v["theta"]) if "theta" in z else model
        kw = options if "input" not in z else {**options, "input_noise": v["input"]}
        est = builder(mdl, Q, R, **{**kw, **sg})  # sg replaces the caller's resampling
        return est, mdl, Q, R, kw.get("input_noise"), v["x0"] if "x0" in z else data[2]

    return at


def _per_step(at):
    """``per_step(z, data) -> (log p(y_t | y_1:t-1) per run and step (R, T), diverged (R,))``
    of the filter ``at`` builds (:func:`_estimator_at`)."""

    def per_step(z, data):
        ys_, us_, _, P0_, keys_ = data
        est, _, _, _, _, x0v = at(z, data)

        def one(y, u, xi, Pi, k):
            res = _filter(est, y, u, x0=xi, P0=Pi, key=k, return_covariances=False)
            return res.loglik, res.diverged

        # the prior given per run: the filter's carried state is batched over the runs from
        # its first step, so JAX traces the scan's body once for the runs (a shared prior
        # would make it iterate to a fixed point); the values are the same
        runs = ys_.shape[0]
        x0r = jnp.broadcast_to(x0v, (runs,) + x0v.shape[-1:])
        P0r = jnp.broadcast_to(P0_, (runs,) + P0_.shape[-2:])
        axes = (0, None if us_ is None or us_.ndim == 2 else 0, 0, 0,
                None if keys_ is None else 0)
        return jax.vmap(one, in_axes=axes)(ys_, us_, x0r, P0r, keys_)

    return per_step


def _log_prior(setup: FitSetup, unpack):
    """``log_prior(z) -> ()``: the priors' log density at the physical parameters of z
    (:func:`vehjax.tune.priors.log_prior_fn`), or None without a penalising prior."""
    fn = setup.prior_fn
    if fn is None or "theta" not in setup.z0:
        return None
    return lambda z: fn(unpack(z)["theta"])


def prepare_fit(builder, model, Q0, R0, measurements, inputs, x0, P0, what: Fitted, key,
                anchored: tuple = ()):
    """Everything checked before tracing (ValueError naming the argument): the
    :class:`Objective` and the fit's :class:`FitSetup` (the builder, the starting values, the
    parameterisations, ``per_step``, ``at``, ``log_prior``, ...) for the optimisers and the
    report; ``what`` a :class:`vehjax.tune.Fitted`; ``anchored``: names among its parameters
    that coordinates with an ``"anchor"`` entry read relative to it
    (:attr:`FitSetup.anchored`). With priors (:mod:`vehjax.tune.priors`) the
    loss is the penalised one, ``-(sum loglik + log prior) / (R T)``; its aux stays the plain
    log-likelihood per run."""
    builder, options = _check_builder(builder)
    validation.model(model)
    setup = _check_what(model, Q0, R0, fitted(what), options)
    ys, us, x0a, P0a = check_data(model, measurements, inputs, x0, P0)
    n_runs, T, _ = ys.shape
    est0, sg, keys = _start_estimator(builder, model, setup, key, n_runs)
    setup = setup._replace(builder=builder, x0=x0a, P0=P0a,
                           anchored=tuple(setup.params.index(p) for p in anchored))
    z0, unpack = _coordinates(setup)
    at = _estimator_at(builder, model, setup, unpack, sg)
    per_step = _per_step(at)
    setup = setup._replace(z0=z0)
    log_prior = _log_prior(setup, unpack)

    def loss(z, data):
        lls, div = per_step(z, data)
        ll = jnp.sum(lls, axis=-1)
        total = jnp.sum(ll) if log_prior is None else jnp.sum(ll) + log_prior(z)
        return -total / (n_runs * T), (ll, div)

    data = (jnp.asarray(ys), None if us is None else jnp.asarray(us), jnp.asarray(x0a),
            jnp.asarray(P0a), keys)
    setup = setup._replace(name=est0.name, stochastic=bool(est0.needs_key),
                 per_step=per_step, at=at, workload=est0.workload, log_prior=log_prior,
                 log_prior0=0.0 if log_prior is None else float(jax.jit(log_prior)(z0)))
    return Objective(loss, z0, data, unpack, n_runs * T), setup


def prepare(builder, model, Q0, R0, measurements, inputs=None, *, x0, P0, params=(),
            key=None):
    """(:class:`Objective`, :class:`FitSetup`) of :func:`objective` (same arguments): the
    objective and the fit's set-up, everything checked before tracing
    (:func:`prepare_fit`)."""
    return prepare_fit(builder, model, Q0, R0, measurements, inputs, x0, P0, fitted(params),
                       key)


def objective(builder, model, Q0, R0, measurements, inputs=None, *, x0, P0, params=(),
              key=None) -> Objective:
    """The objective of :func:`vehjax.tune.fit` (the same arguments: ``params`` names or
    :class:`vehjax.tune.Fitted`; ``key`` a particle filter's), to evaluate, differentiate or
    optimise with tools of one's own: ``obj.loss(obj.z0, obj.data)``,
    ``obj.unpack(z)["Q"]``. The builder's own options go with it,
    ``functools.partial(builder, **options)``."""
    return prepare(builder, model, Q0, R0, measurements, inputs, x0=x0, P0=P0, params=params,
                   key=key)[0]
