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

Optimisers: ``"adam"`` (default; learning rate 0.05 with a cosine decay to 5 % of it over
``steps``, on the unconstrained scale, i.e. about 5 % relative change of a standard deviation per
step at first), ``"lbfgs"`` (``optax.lbfgs`` with its zoom line search: few iterations, for
smooth objectives such as the Gaussian filters'), or any ``optax.GradientTransformation``.
Updates whose gradient is not finite (a run that diverged during a step) are skipped (adam,
custom) or stop the fit (lbfgs). Early stopping: the fit ends when the best loss has not
improved by more than ``tol * max(1, |best|)`` for ``patience`` iterations; the values at the best
loss are returned.

Particle filter. A particle filter (``builder=vehjax.filters.bootstrap_pf``) is differentiated
with stop-gradient resampling, :func:`stop_gradient` (Scibior & Wood 2021, "Differentiable
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

import math
import sys
import threading
import time
import warnings
from typing import Any, Callable, Mapping, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from . import _validate
from .filtering import filter as _filter
from .filters import _bounds
from .filters import resampling as _rs
from .filters import smc
from .filters.base import Estimator
from .filters.particle import bootstrap_pf
from .models.base import BaseModel

__all__ = ["fit", "fit_noise", "objective", "Objective", "TuneResult", "stop_gradient",
           "stop_gradient_pf"]

_NOISE = ("Q", "R")
_OPTIMIZERS = ("adam", "lbfgs")
_ADAM_LR = 0.05
_ADAM_STEPS = 300
_LBFGS_STEPS = 100


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
        converged: the fit stopped early (no improvement for ``patience`` iterations).
        diverged: how many runs diverged (``vehjax.filter``'s flag) at the fitted values.
        skipped: iterations whose gradient was not finite.
        values: every fitted quantity by name: ``"Q[x,x]"``, ``"R[y,y]"``, a parameter name,
            ``"x0[v]"`` (``"x0[r,v]"`` per run); covariances as variances/covariances.
        units: the unit of each entry of ``values`` (``"m^2"``, ``"kg"``, ...; ``"-"`` unknown).
        seconds: wall-clock time of the fit, including compilation.
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

    def summary(self) -> str:
        """A text table of the fitted values with their units and the log-likelihood."""
        lines = [
            f"{self.estimator.name} tuned in {self.iterations} iterations ({self.seconds:.1f} s)"
            f"{', converged' if self.converged else ''}: log-likelihood {self.loglik0:.6g} -> "
            f"{self.loglik:.6g}" + (f", {self.diverged} runs diverged" if self.diverged else "")
        ]
        width = max((len(k) for k in self.values), default=0)
        for k, v in self.values.items():
            lines.append(f"  {k:<{width}} = {v:.6g} [{self.units[k]}]")
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


def _param_transform(params, bounds, theta0: np.ndarray, names: tuple):
    """(indices (q,) in ``names``, :class:`vehjax.filters._bounds.Transform`) of the fitted
    parameters; ValueError naming ``bounds``. A parameter not in ``bounds`` is kept positive when
    its starting value is positive, else left free (module docstring)."""
    bounds = _validate.keyed("bounds", bounds, params, "the fitted params")
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
# The bootstrap PF resamples through vehjax.filters.smc.resample, which gives every resampled
# particle the constant log weight -log N. Stop-gradient resampling gives it
# -log N + log W_a - stop_gradient(log W_a) instead: the same value, but its gradient carries the
# ancestor's log weight. Until smc.resample does this itself (the change is the two lines marked
# in _sg_resample), stop_gradient() swaps it in while the filter's step is traced: the forward
# pass is the filter's own, by construction, and nothing of the filter is copied here.

_PATCH_LOCK = threading.RLock()
_SG_CALLS = [0]


def _sg_resample(particles, w, log_w, u, scheme: str, threshold: float):
    """``smc.resample`` with stop-gradient weights: same values, the ancestors' log weights in
    the gradient."""
    _SG_CALLS[0] += 1
    n = w.shape[-1]
    if threshold <= 0.0:
        return particles, log_w, w, jnp.zeros((), bool)
    idx = _rs.indices_from_uniforms(scheme, jax.lax.stop_gradient(w), u, n)
    do = smc.ess(w) < threshold * n
    particles = jax.tree.map(lambda a: jnp.where(do, jnp.take(a, idx, axis=-1), a), particles)
    lw_a = jnp.take(log_w, idx)
    # 0 in value (also for an ancestor whose log weight is not finite)
    corr = jnp.where(jnp.isfinite(lw_a), lw_a - jax.lax.stop_gradient(lw_a), 0.0)
    log_w = jnp.where(do, corr - math.log(n), log_w)  # was: -math.log(n)
    w = jnp.where(do, (1.0 / n) * jnp.exp(corr), w)  # was: 1.0 / n
    return particles, log_w, w, do


def stop_gradient(estimator: Estimator) -> Estimator:
    """A particle filter with stop-gradient resampling (Scibior & Wood 2021).

    ``estimator`` is a particle filter of :mod:`vehjax.filters` that resamples through
    :func:`vehjax.filters.smc.resample` (``bootstrap_pf``). The result has the same ``init``
    and the same forward pass, value for value (random numbers, particles, resampling
    decisions and indices, outputs); only gradients differ: after a resampling, particle i's
    normalised log weight is ``-log N + log W_a - stop_gradient(log W_a)`` (value ``-log N``) for
    its ancestor a, where the filter puts the constant ``-log N``. The gradient of
    ``sum_t loglik_t`` is then the Fisher-identity estimate of the score,
    ``sum_i W_T^i grad log p(x^i_0:T, y_1:T)`` along the particles' ancestral paths (the
    particles reparameterised, ``f(x) + chol(Q) z``), a consistent estimate of
    ``grad log p(y_1:T)`` (bias O(1/N)).

    Raises:
        ValueError: naming ``estimator`` when it is not a particle filter.
        RuntimeError: when the step, traced, did not resample through ``smc.resample``.
    """
    if not isinstance(estimator, Estimator) or not estimator.needs_key:
        raise ValueError(f"estimator: expected a particle filter (an Estimator with needs_key), "
                         f"got {getattr(estimator, 'name', type(estimator).__name__)!r}")
    base_step = estimator.step

    def step(state, y, u):
        with _PATCH_LOCK:
            original, calls = smc.resample, _SG_CALLS[0]
            smc.resample = _sg_resample
            try:
                out = base_step(state, y, u)
            finally:
                smc.resample = original
        if _SG_CALLS[0] == calls:
            raise RuntimeError(
                f"vehjax.tune.stop_gradient: {estimator.name}'s step did not call "
                f"vehjax.filters.smc.resample; stop-gradient resampling cannot be applied")
        return out

    return estimator._replace(step=step, name=f"{estimator.name} (stop-gradient)", batch=None)


def stop_gradient_pf(model, Q, R, n_particles: int = 1000, resampling: str = "systematic",
                     ess_threshold: float = 0.5) -> Estimator:
    """``stop_gradient(vehjax.filters.bootstrap_pf(model, Q, R, ...))``: the bootstrap PF with
    stop-gradient resampling, a builder with bootstrap_pf's arguments (see
    :func:`stop_gradient`)."""
    return stop_gradient(bootstrap_pf(model, Q, R, n_particles, resampling, ess_threshold))


# ----------------------------------------------------------------------------------------------
# validation and the objective


def _float_array(name: str, value, allow_nan: bool = False) -> np.ndarray:
    if _validate.is_tracer(value):
        raise ValueError(f"{name}: expected a concrete array; call vehjax.tune outside jit/grad")
    try:
        a = np.array(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected a numeric array, got {type(value).__name__}") from None
    bad = np.isinf(a) if allow_nan else ~np.isfinite(a)
    if np.any(bad):
        raise ValueError(f"{name}: expected finite values" + (" (NaN marks a missing component)"
                                                            if allow_nan else ""))
    return a


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
    _validate.model(model)
    nx, ny, nu = len(model.state_names), len(model.output_names), len(model.input_names)
    Qa = _validate.cov("Q0", _float_array("Q0", Q0), nx)
    Ra = _validate.cov("R0", _float_array("R0", R0), ny)
    diagQ = np.ndim(Q0) == 1 or _is_diag(Qa)
    diagR = np.ndim(R0) == 1 or _is_diag(Ra)

    noise = _validate.names("noise", noise, _NOISE, allow_empty=True)
    names = tuple(model.param_names)
    if isinstance(params, Mapping):
        raise ValueError("params: expected a sequence of parameter names; give their bounds in "
                         "bounds={name: (lo, hi)}")
    params = _validate.names("params", params, names, allow_empty=True)
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

    ys = _float_array("measurements", measurements, allow_nan=True)
    if ys.ndim == 2:
        ys = ys[None]
    if ys.ndim != 3 or ys.shape[1] == 0 or ys.shape[2] != ny:
        raise ValueError(f"measurements: expected shape (T, {ny}) for one run or (R, T, {ny}) "
                         f"for R runs, got {np.shape(measurements)}")
    n_runs, T, _ = ys.shape
    if inputs is None:
        if nu:
            raise ValueError(f"inputs: required, shape ({T}, {nu}) or ({n_runs}, {T}, {nu})")
        us = None
    else:
        us = _float_array("inputs", inputs)
        if us.shape not in ((T, nu), (n_runs, T, nu)):
            raise ValueError(f"inputs: expected shape ({T}, {nu}) shared by the runs or "
                             f"({n_runs}, {T}, {nu}), got {us.shape}")
    x0a = _float_array("x0", x0)
    if x0a.shape not in ((nx,), (n_runs, nx)):
        raise ValueError(f"x0: expected shape ({nx},) or ({n_runs}, {nx}), got {x0a.shape}")
    P0a = _float_array("P0", P0)
    if P0a.shape == (nx,):
        P0a = np.diag(P0a)
    if P0a.shape not in ((nx, nx), (n_runs, nx, nx)):
        raise ValueError(f"P0: expected shape ({nx}, {nx}), ({nx},) variances or "
                         f"({n_runs}, {nx}, {nx}), got {np.shape(P0)}")
    for i, Pi in enumerate(P0a.reshape(-1, nx, nx)):
        _validate.cov("P0" if P0a.ndim == 2 else f"P0[{i}]", Pi, nx)

    # the builder with the starting values: checks its own arguments, says whether it needs a key
    est0 = builder(model, Qa, Ra, **builder_kwargs)
    if not isinstance(est0, Estimator):
        raise ValueError(f"builder: expected a function returning a vehjax.filters.Estimator, "
                         f"got {type(est0).__name__}")
    if est0.param_names:
        raise ValueError(f"builder: {est0.name} estimates parameters {est0.param_names}; tune "
                         f"a state-only filter (ekf, ukf, ckf, bootstrap_pf) and fit model "
                         f"parameters with params=")
    keys = None
    if est0.needs_key:
        if key is None:
            raise ValueError(f"key: {est0.name} draws random numbers; pass key=jax.random.key(...)")
        try:
            keys = jax.random.split(key, n_runs)
        except Exception:
            raise ValueError(f"key: expected a jax.random.key, got {key!r}") from None

    covQ, covR = _Cov(Qa, diagQ), _Cov(Ra, diagR)
    z0 = {}
    if "Q" in noise:
        z0["Q"] = jnp.asarray(covQ.z0)
    if "R" in noise:
        z0["R"] = jnp.asarray(covR.z0)
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
        return {"Q": Q, "R": R, "theta": theta, "x0": z["x0"] if "x0" in z else jnp.asarray(x0a)}

    def loss(z, data):
        ys_, us_, x0_, P0_, keys_ = data
        v = unpack(z)
        Q = v["Q"] if "Q" in z else Qa  # constants stay numpy: the builder may specialise
        R = v["R"] if "R" in z else Ra
        mdl = eqx.tree_at(lambda m: m.theta, model, v["theta"]) if "theta" in z else model
        est = builder(mdl, Q, R, **builder_kwargs)
        if est.needs_key:  # a particle filter: differentiated with stop-gradient resampling
            est = stop_gradient(est)
        x0v = v["x0"] if "x0" in z else x0_

        def one(y, u, xi, Pi, k):
            res = _filter(est, y, u, xi, Pi, key=k, return_covariances=False)
            return res.loglik.sum(), res.diverged

        axes = (0, None if us_ is None or us_.ndim == 2 else 0, 0 if x0v.ndim == 2 else None,
                0 if P0_.ndim == 3 else None, None if keys_ is None else 0)
        ll, div = jax.vmap(one, in_axes=axes)(ys_, us_, x0v, P0_, keys_)
        return -jnp.sum(ll) / (n_runs * T), (ll, div)

    data = (jnp.asarray(ys), None if us is None else jnp.asarray(us), jnp.asarray(x0a),
            jnp.asarray(P0a), keys)
    info = dict(name=est0.name, builder=builder, builder_kwargs=builder_kwargs, params=params,
                noise=noise, x0=x0a, Qa=Qa, Ra=Ra, diagQ=diagQ, diagR=diagR, theta0=theta0,
                fit_x0=fit_x0)
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


# ----------------------------------------------------------------------------------------------
# fitting


def _optimizer(optimizer, learning_rate, steps):
    """(optax transformation, is_lbfgs)."""
    if isinstance(optimizer, str):
        _validate.choice("optimizer", optimizer, _OPTIMIZERS)
        if optimizer == "adam":
            lr = _ADAM_LR if learning_rate is None else learning_rate
            sched = optax.cosine_decay_schedule(lr, max(steps, 1), alpha=0.05)
            return optax.apply_if_finite(optax.adam(sched), max_consecutive_errors=10), False
        return optax.lbfgs(learning_rate=learning_rate), True
    if isinstance(optimizer, optax.GradientTransformation):
        if learning_rate is not None:
            raise ValueError("learning_rate: set it inside your own optax optimizer, not here")
        return optax.apply_if_finite(optimizer, max_consecutive_errors=10), False
    raise ValueError(f"optimizer: expected 'adam', 'lbfgs' or an optax.GradientTransformation, "
                     f"got {optimizer!r}")


def fit(builder, model, Q0, R0, measurements, inputs=None, *, x0, P0, params=(), bounds=None,
        noise=_NOISE, fit_x0: bool = False, optimizer="adam", learning_rate=None,
        steps: int | None = None, tol: float = 1e-7, patience: int | None = None, key=None,
        builder_kwargs=None, progress: bool = True) -> TuneResult:
    """Fit Q, R, named model parameters and optionally x0 by maximum likelihood.

    Args:
        builder: a filter builder ``builder(model, Q, R, **builder_kwargs) -> Estimator``:
            ``vehjax.filters.ekf``, ``ukf``, ``ckf`` (``builder_kwargs={"sqrt": True}`` for the
            square-root forms), ``bootstrap_pf`` (differentiated with stop-gradient
            resampling, :func:`stop_gradient`), or one's own state-only builder.
        model: a vehjax model; ``model.theta`` holds the starting parameter values.
        Q0, R0: starting covariances, (n, n) or (n,) variances, positive definite; diagonal
            ones are fitted as diagonal, full ones as full (module docstring).
        measurements: (T, ny) one run or (R, T, ny) runs; NaN components are missing.
        inputs: (T, nu) shared or (R, T, nu) per run; None for a model without inputs.
        x0, P0: prior of every run: x0 (nx,) or (R, nx), P0 (nx, nx), (nx,) or (R, nx, nx).
        params: names of model parameters to fit (default none).
        bounds: ``{name: (lo, hi)}`` for fitted parameters, either end None (module docstring).
        noise: which covariances to fit, a subset of ("Q", "R") (default both).
        fit_x0: also fit x0 (the shape it was given in).
        optimizer: "adam" (default), "lbfgs" or an ``optax.GradientTransformation``.
        learning_rate: > 0; adam's peak rate (default 0.05, cosine decay to 5 % over
            ``steps``), L-BFGS's fixed step instead of its line search (default: line search).
        steps: maximum number of iterations, >= 1 (default 300 adam, 100 lbfgs).
        tol: >= 0, the improvement of the best loss that resets ``patience``, relative to
            max(1, |best loss|).
        patience: >= 1, iterations without improvement before stopping (default 50 adam, whose
            momentum can overshoot for a few tens of iterations; 5 lbfgs).
        key: PRNG key, required for particle filters; run r uses ``jax.random.split(key, R)[r]``
            at every iteration.
        builder_kwargs: further keyword arguments of ``builder`` (``sqrt``, ``alpha``,
            ``n_particles``, ...).
        progress: show a progress bar (tqdm.auto when installed, else a line on stderr).

    Returns:
        :class:`TuneResult`.

    Raises:
        ValueError: naming the argument, before anything is traced: an unknown parameter name,
            wrong shapes, a Q0/R0/P0 that is not positive definite, learning_rate <= 0,
            steps < 1, an unknown optimizer, a missing key, nothing to fit.
    """
    t_start = time.perf_counter()
    if learning_rate is not None:
        learning_rate = _validate.number("learning_rate", learning_rate, 0.0)
    lbfgs = isinstance(optimizer, str) and optimizer == "lbfgs"
    steps = _validate.integer("steps", (_LBFGS_STEPS if lbfgs else _ADAM_STEPS)
                              if steps is None else steps, 1)
    patience = _validate.integer("patience", (5 if lbfgs else 50) if patience is None
                                 else patience, 1)
    tol = _validate.number("tol", tol, 0.0, low_open=False)
    opt, lbfgs = _optimizer(optimizer, learning_rate, steps)
    obj, info = _prepare(builder, model, Q0, R0, measurements, inputs, x0, P0, params, bounds,
                         noise, fit_x0, key, builder_kwargs)

    def finite(value, grad):
        return jnp.isfinite(value) & jax.tree.reduce(
            jnp.logical_and, jax.tree.map(lambda g: jnp.all(jnp.isfinite(g)), grad))

    if lbfgs:
        @jax.jit
        def step(z, state, data):
            fn = lambda zz: obj.loss(zz, data)[0]  # noqa: E731
            value, grad = optax.value_and_grad_from_state(fn)(z, state=state)
            updates, state = opt.update(grad, state, z, value=value, grad=grad, value_fn=fn)
            return optax.apply_updates(z, updates), state, value, finite(value, grad), None
    else:
        @jax.jit
        def step(z, state, data):
            (value, aux), grad = jax.value_and_grad(obj.loss, has_aux=True)(z, data)
            updates, state = opt.update(grad, state, z)
            return optax.apply_updates(z, updates), state, value, finite(value, grad), aux

    z = obj.z0
    # strongly typed state: a weak-typed leaf that becomes strong after one update would make
    # jit compile the step twice
    state = jax.tree.map(lambda a: jnp.array(a, dtype=jnp.asarray(a).dtype), opt.init(z))
    bar = _Progress(steps, bool(progress), f"vehjax.tune ({info['name']})")
    history, best, best_z, best_aux = [], np.inf, z, None
    since = skipped = i = 0
    converged = False
    value = np.nan
    for i in range(1, steps + 1):
        z_new, state, value, ok, aux = step(z, state, obj.data)
        value, ok = float(value), bool(ok)
        history.append(value)
        if not ok:
            skipped += 1
            if lbfgs:
                break
        if np.isfinite(value) and (not np.isfinite(best)
                                   or value < best - tol * max(1.0, abs(best))):
            best, best_z, best_aux, since = value, z, aux, 0
        else:
            since += 1
        bar.update(i, value, best)
        z = z_new
        if since >= patience:
            converged = True
            break
    bar.close(i, value, best)
    if not np.isfinite(best):
        raise FloatingPointError(
            "vehjax.tune: the log-likelihood is not finite at the starting values; check Q0, R0, "
            "x0, P0 and the measurements")
    if best_aux is None:  # L-BFGS: its step does not return the per-run outputs
        _, best_aux = jax.jit(obj.loss)(best_z, obj.data)
    ll, div = best_aux
    v = jax.tree.map(np.asarray, obj.unpack(best_z))
    Q, R, theta, x0_fit = v["Q"], v["R"], v["theta"], v["x0"]
    Q, R = 0.5 * (Q + Q.T), 0.5 * (R + R.T)
    fitted_model = model
    if info["params"]:
        fitted_model = model.with_theta(**{p: float(theta[model.param_names.index(p)])
                                           for p in info["params"]})
    estimator = info["builder"](fitted_model, Q, R, **info["builder_kwargs"])
    n_div = int(np.sum(np.asarray(div)))
    if n_div:
        warnings.warn(f"vehjax.tune: {n_div} of {len(div)} runs diverged at the fitted values; "
                      f"their log-likelihood counts only the steps before", stacklevel=2)

    values, units = {}, {}
    su = _units(model, "state_units", model.nx if isinstance(model, BaseModel) else Q.shape[0])
    ou = _units(model, "output_units", R.shape[0])
    for name, M, diag, cnames, cu in (("Q", Q, info["diagQ"], model.state_names, su),
                                      ("R", R, info["diagR"], model.output_names, ou)):
        if name not in info["noise"]:
            continue
        n = M.shape[0]
        for a in range(n):
            for b in range(a, n if not diag else a + 1):
                key_ = f"{name}[{cnames[a]},{cnames[b]}]"
                values[key_] = float(M[a, b])
                units[key_] = _sq(cu[a]) if a == b else _prod(cu[a], cu[b])
    pu = _units(model, "param_units", len(model.param_names))
    for p in info["params"]:
        j = model.param_names.index(p)
        values[p], units[p] = float(theta[j]), pu[j]
    if info["fit_x0"]:
        for idx in np.ndindex(x0_fit.shape):
            comp = model.state_names[idx[-1]]
            k = f"x0[{comp}]" if x0_fit.ndim == 1 else f"x0[{idx[0]},{comp}]"
            values[k], units[k] = float(x0_fit[idx]), su[idx[-1]]

    return TuneResult(
        Q=Q, R=R, theta=np.asarray(theta),
        params={p: float(theta[model.param_names.index(p)]) for p in info["params"]},
        x0=x0_fit, model=fitted_model, estimator=estimator,
        loglik=float(np.sum(np.asarray(ll))), loglik0=-history[0] * obj.n_steps,
        history=np.asarray(history), iterations=i, converged=converged, diverged=n_div,
        skipped=skipped, values=values, units=units, seconds=time.perf_counter() - t_start,
    )


def fit_noise(builder, model, Q0, R0, measurements, inputs=None, *, x0, P0, noise=_NOISE,
              **kwargs) -> TuneResult:
    """Fit the noise covariances Q and R (``noise``: both by default) by maximum likelihood:
    :func:`fit` with no model parameters. Same arguments and result."""
    if "params" in kwargs:
        raise ValueError("params: fit_noise fits Q and R only; use vehjax.tune.fit for model "
                         "parameters")
    return fit(builder, model, Q0, R0, measurements, inputs, x0=x0, P0=P0, noise=noise, **kwargs)
