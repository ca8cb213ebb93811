"""The one-run engine that :func:`vehjax.filter`, :func:`vehjax.run`, :func:`vehjax.smooth` and
the smoothers share: a run's start, scan body and finish, traced, without validation.

The contract. An :class:`~vehjax.filters.Estimator` is ``init(x0, P0, theta0, P_theta0, key)``
and ``step(state, y, u) -> (state, StepOutput)``. One run is::

    state0, held0 = start(est, ys, us, x0, P0, th0, Pth0, key)   # checks the output's shapes
    body = scan_body(est.step, partial(output_ok, p=p), return_cov)
    state, per_step = jax.lax.scan(body, state0, (ys, us))
    result = finish(per_step, held0, est.bounds)                   # FilterResult

(:func:`one_run`). :func:`start` gives ``theta0`` its meaning once: for a filter that estimates
parameters, the caller's, else the estimator's ``param_prior``, else NaN until the first step's
estimate; for a state-only filter none (its ``theta0`` is the model's parameters, passed to
``init``). :func:`check_arguments` is the one check of a run's or a study's arguments (shapes,
values) before anything is traced, by the rules of :mod:`vehjax.validation`;
:func:`initial_parameters` is the one check of ``theta0`` and ``P_theta0`` (``theta0`` inside ``Estimator.bounds``, a
state-only filter's inside the model's domains ``Estimator.theta_domains``), for a run and for
a study (:func:`vehjax.run`). A runs-last batch (:mod:`vehjax.filters.runs_last`) uses the same
pieces with ``output_ok``'s ``pd``/``all_finite`` for that layout.

Time convention (the papers' order): ``x0``/``P0`` describe the state before the first step;
step ``t`` predicts with ``inputs[t]``, then updates with ``measurements[t]``.

Divergence: a step whose mean is not finite, whose covariance is not finite and positive
definite (also the parameter estimate and its covariance), or whose log-likelihood or NIS is not
finite is bad, and so is every later step of that run: their outputs hold the last good estimate
(the prior before the first step), their ``nis`` is NaN, ``n_obs`` 0 and ``loglik`` 0, and the
run is ``diverged``. A step with ``StepOutput.reinit`` (a particle filter that re-initialised
after its weights underflowed) flags the run ``diverged`` too but changes none of its outputs.
Holding the outputs after the first bad step gives exactly what freezing the filter state there
would give, since a frozen state is never used again.

Estimates on a bound: for a filter that declares parameter domains (``Estimator.bounds``), a run
is ``at_bound`` when, for some estimated parameter, the reported estimate (as held above) lies
within ``AT_BOUND_RTOL`` times the bound's scale of a finite bound on more than
``AT_BOUND_FRACTION`` of the run's T steps. The scale of a two-sided domain is its width
high - low; of a one-sided one, max(|bound|, |theta0|) with theta0 the run's initial estimate
(the first step's estimate when the filter's own default was used). Such a run is not frozen or
flagged ``diverged``: its estimate is simply pressed against the edge of its domain, which
usually means the domain or the model is wrong for the data.
"""

from __future__ import annotations

from functools import partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from . import validation
from .filters.bounds import check_inside
from .lib.linalg import is_pd
from .filters.base import Estimator, StepOutput

__all__ = [
    "FilterResult", "AT_BOUND_RTOL", "AT_BOUND_FRACTION", "check_step_output", "start",
    "all_finite", "output_ok", "scan_body", "on_bound", "initial_parameters", "finish",
    "one_run",
    "check_arguments",
]

#: Distance to a finite bound, relative to the bound's scale, within which an estimate is on it.
AT_BOUND_RTOL = 1e-2
#: A run is ``at_bound`` when a parameter is on a bound on more than this fraction of its steps.
AT_BOUND_FRACTION = 0.2


class FilterResult(NamedTuple):
    """Per-step outputs of one run of T steps (a leading runs axis under ``vmap``).

    Attributes:
        states: filtered state estimates, (T, nx).
        covariances: their covariances, (T, nx, nx); None when not asked for.
        params: parameter estimates, (T, p); p = 0 for state-only filters.
        params_cov: their covariances, (T, p, p); None when not asked for.
        loglik: log p(y_t | y_1:t-1) of the observed components per step, (T,); 0 from the
            step the run diverged. ``loglik.sum()`` is the log-likelihood of the run.
        nis: normalised innovation squared of the observed components, (T,); NaN from the step
            the run diverged.
        n_obs: number of observed measurement components per step, (T,) int32 (the degrees of
            freedom of ``nis``); 0 from the step the run diverged.
        diverged: bool scalar, the run diverged or re-initialised.
        diverged_at: int32 scalar, the first step it did, or -1.
        at_bound: bool scalar, a parameter estimate sat on a bound of its domain for more than
            ``AT_BOUND_FRACTION`` of the steps (module docstring); False without domains.
        state: the filter's state after the last step (its ``init``/``step`` pytree), to go on
            filtering from; not held on divergence. None from :func:`finish` alone.
    """

    states: jnp.ndarray
    covariances: jnp.ndarray | None
    params: jnp.ndarray
    params_cov: jnp.ndarray | None
    loglik: jnp.ndarray
    nis: jnp.ndarray
    n_obs: jnp.ndarray
    diverged: jnp.ndarray
    diverged_at: jnp.ndarray
    at_bound: jnp.ndarray
    state: Any = None


def check_step_output(out, nx: int, p: int):
    """ValueError unless a StepOutput (or its shape) has the shapes of the contract."""
    expected = {"mean": (nx,), "cov": (nx, nx), "loglik": (), "nis": (), "n_obs": (),
                "params": (p,), "params_cov": (p, p), "reinit": ()}
    for field, shape in expected.items():
        got = getattr(out, field).shape
        if got != shape:
            raise ValueError(
                f"estimator: step returned StepOutput.{field} of shape {got}, expected {shape} "
                f"(nx = {nx}, {p} estimated parameters)"
            )


def start(estimator: Estimator, y, u, x0, P0, th0, Pth0, key):
    """(filter state, outputs held before the first step) of one run; checks the shapes of the
    step's output. y (T, ny), u (T, nu) are only read for shapes."""
    nx, p = estimator.nx, len(estimator.param_names)
    state0 = estimator.init(x0, P0, th0, Pth0, key)
    _, out_shape = jax.eval_shape(estimator.step, state0, y[0], u[0])
    check_step_output(out_shape, nx, p)

    def cast(a, like):
        return jnp.asarray(a).astype(like.dtype)

    if p and th0 is None and estimator.param_prior is not None:
        th0, Pth0 = estimator.param_prior
    if not p:  # a state-only filter's theta0 is the model's parameters, not an estimate
        th0 = Pth0 = None
    # no prior given (a filter that starts from the model's nominal values): NaN until the
    # first step's estimate, which is what the held value is for
    held0 = (
        cast(x0, out_shape.mean),
        cast(P0, out_shape.cov),
        cast(jnp.full((p,), jnp.nan) if th0 is None else th0, out_shape.params),
        cast(jnp.full((p, p), jnp.nan) if Pth0 is None else Pth0, out_shape.params_cov),
    )
    return state0, held0


def all_finite(a):
    return jnp.all(jnp.isfinite(a))


def output_ok(out: StepOutput, p: int, pd=is_pd, all_finite=all_finite):
    """Whether a step's output is good (module docstring): a scalar for one run, or (C,) for a
    runs-last batch (``pd`` and ``all_finite`` of :mod:`vehjax.filters.runs_last`, on arrays
    with the runs axis last)."""
    good = all_finite(out.mean) & pd(out.cov)
    good = good & jnp.isfinite(out.loglik) & jnp.isfinite(out.nis)
    if p:
        good = good & all_finite(out.params) & pd(out.params_cov)
    return good


def scan_body(step, ok, return_cov: bool):
    """Scan body: one filter step, returning the per-step outputs and whether they are good.
    ``ok(out)`` is :func:`output_ok` for the layout at hand."""

    def body(state, yu):
        state, out = step(state, *yu)
        per_step = (
            out.mean,
            out.cov if return_cov else None,
            out.params,
            out.params_cov if return_cov else None,
            out.loglik,
            out.nis,
            out.n_obs.astype(jnp.int32),
            ok(out),
            jnp.asarray(out.reinit, bool),
        )
        return state, per_step

    return body


def on_bound(params, theta0, bounds):
    """Whether a run's parameter estimates sat on a bound (module docstring): bool scalar.

    Args:
        params: the run's estimates per step, (T, p), physical units.
        theta0: its initial estimate, (p,); where NaN (no initial estimate known) the first
            step's estimate stands in.
        bounds: ``Estimator.bounds``, (low, high) p floats each with +-inf open ends, or None.
    """
    if bounds is None or params.shape[-1] == 0:
        return jnp.zeros((), bool)
    low, high = (np.asarray(b, dtype=float) for b in bounds)
    has_lo, has_hi = np.isfinite(low), np.isfinite(high)
    if not (has_lo.any() or has_hi.any()):
        return jnp.zeros((), bool)
    dt = params.dtype
    theta0 = theta0.astype(dt)
    ref = jnp.abs(jnp.where(jnp.isfinite(theta0), theta0, params[0]))
    width = jnp.asarray(np.where(has_lo & has_hi, high - low, 0.0), dt)
    two = has_lo & has_hi
    lo = jnp.asarray(np.where(has_lo, low, 0.0), dt)
    hi = jnp.asarray(np.where(has_hi, high, 0.0), dt)
    tol_lo = AT_BOUND_RTOL * jnp.where(two, width, jnp.maximum(jnp.abs(lo), ref))
    tol_hi = AT_BOUND_RTOL * jnp.where(two, width, jnp.maximum(jnp.abs(hi), ref))
    near = (has_lo & (params - lo <= tol_lo)) | (has_hi & (hi - params <= tol_hi))
    return jnp.any(jnp.mean(near, axis=0) > AT_BOUND_FRACTION)


def initial_parameters(estimator: Estimator, theta0, P_theta0, runs=None):
    """``theta0`` and ``P_theta0`` of one run (``runs`` None: :func:`vehjax.filter`,
    :func:`vehjax.smooth`) or of a study of ``runs`` runs (:func:`vehjax.run`), checked once
    for every entry point before anything is traced. Returns (th0, Pth0) as arrays or None.

    Their meaning. For a filter that estimates parameters (``Estimator.param_names``): the
    initial estimate (p,) and its covariance (p, p) or (p,) variances (or one per run), theta0
    strictly inside ``Estimator.bounds``; absent, the filter starts from its own prior
    (``Estimator.param_prior``, which :func:`start` then reports) or from the model's nominal
    values. For a state-only filter: theta0 replaces the model's parameters, inside the model's
    domains (``Estimator.theta_domains``), and P_theta0 is None. A study's state-only filter
    takes theta0 only where the estimator says its model's parameter count (``n_theta``), whose
    length is checked here, as tracing the runs would find it too late; one run's is checked by
    the filter's ``init``. The rules and messages are :mod:`vehjax.validation`'s."""
    names = tuple(estimator.param_names)
    th0, Pth0 = validation.initial_params(
        names, theta0, P_theta0, runs=runs, has_prior=estimator.param_prior is not None,
        label=f"estimator {estimator.name!r}",
        model_theta=runs is None or estimator.n_theta is not None)
    if names:
        # a concrete theta0 of the right shape strictly inside the domains (a wrong shape is
        # validation's error; traced values are not checked)
        if th0 is not None and estimator.bounds is not None and np.shape(th0)[-1:] == (
                len(names),):
            check_inside("theta0", th0, *estimator.bounds, names)
        return th0, Pth0
    if runs is not None and th0 is not None and th0.shape[-1] != estimator.n_theta:
        raise ValueError(f"theta0: expected the model's {estimator.n_theta} parameters, shape "
                         f"({estimator.n_theta},) or ({runs}, {estimator.n_theta}), got "
                         f"{th0.shape}")
    # a state-only filter's theta0 is the model's parameters: inside the model's domains
    validation.in_domain("theta0", th0, estimator.theta_domains)
    return th0, Pth0


def finish(per_step, held0, bounds=None) -> FilterResult:
    """Outputs of one run from the stacked per-step outputs of :func:`scan_body` (leading axis
    T): everything from the first bad step on is held (module docstring); ``bounds``
    (``Estimator.bounds``) for ``at_bound``."""
    mean, cov, params, pcov, loglik, nis, n_obs, ok, reinit = per_step
    T = mean.shape[0]
    bad = jnp.cumsum(~ok) > 0
    first_bad = jnp.where(jnp.any(bad), jnp.argmax(bad), T)
    last_good = jnp.maximum(first_bad - 1, 0)

    def hold(seq, before):
        if seq is None:
            return None
        value = jnp.where(first_bad > 0, seq[last_good], before.astype(seq.dtype))
        mask = bad.reshape((T,) + (1,) * (seq.ndim - 1))
        return jnp.where(mask, value[None], seq)

    x0, P0, th0, Pth0 = held0
    flag = bad | reinit
    params = hold(params, th0)
    return FilterResult(
        states=hold(mean, x0),
        covariances=hold(cov, P0),
        params=params,
        params_cov=hold(pcov, Pth0),
        loglik=jnp.where(bad, 0.0, loglik).astype(loglik.dtype),
        nis=jnp.where(bad, jnp.nan, nis),
        n_obs=jnp.where(bad, 0, n_obs).astype(jnp.int32),
        diverged=jnp.any(flag),
        diverged_at=jnp.where(jnp.any(flag), jnp.argmax(flag), -1).astype(jnp.int32),
        at_bound=on_bound(params, th0, bounds),
    )


def one_run(estimator: Estimator, return_cov: bool, y, u, x0, P0, th0, Pth0, key):
    """One run, traced, without validation: y (T, ny), u (T, nu); x0 (nx,), P0 (nx, nx)."""
    p = len(estimator.param_names)
    state0, held0 = start(estimator, y, u, x0, P0, th0, Pth0, key)
    body = scan_body(estimator.step, partial(output_ok, p=p), return_cov)
    state, per_step = jax.lax.scan(body, state0, (y, u))
    return finish(per_step, held0, estimator.bounds)._replace(state=state)


def check_arguments(estimator, ys, us, x0, P0, theta0, P_theta0, key, study: bool = False):
    """The one check of a run's arguments before anything is traced, by the rules of
    :mod:`vehjax.validation` that every entry point shares: concrete values in full, traced ones
    by dtype and shape.

    One run (:func:`vehjax.filter`, :func:`vehjax.smooth`, :class:`vehjax.Online`): ys (T, ny),
    us (T, nu), the prior and the initial parameters of that run. A study (``study`` True,
    :func:`vehjax.run`): ys (R, T, ny), us (T, nu) shared or (R, T, nu), the prior and the initial
    parameters shared or one per run, the key split per run.

    Returns:
        (ys, us, x0, P0, th0, Pth0, keys) as arrays; ``keys`` is ``jax.random.split(key, R)``
        of a study, None for one run (whose ``key`` goes to ``init`` as given) or without key.
    """
    if not isinstance(estimator, Estimator):
        raise ValueError(
            f"estimator: expected a vehjax.filters.Estimator, got {type(estimator).__name__}"
        )
    nx = estimator.nx
    if study:
        nx = int(nx)
        if nx < 1:
            raise ValueError(f"estimator: nx must be >= 1, got {estimator.nx}")
    ys, us = validation.data(ys, us, estimator.ny, estimator.nu, "many" if study else "one")
    runs = ys.shape[0] if study else None
    x0, P0 = validation.prior(nx, x0, P0, runs=runs)
    th0, Pth0 = initial_parameters(estimator, theta0, P_theta0, runs=runs)
    if estimator.needs_key and key is None:
        raise ValueError(
            f"key: estimator {estimator.name!r} draws random numbers; pass key=jax.random.key(...)"
        )
    keys = None
    if key is not None:
        keys = validation.key(key, runs if study else 1)  # a PRNG key (an int such as 0 is not)
    return ys, us, x0, P0, th0, Pth0, (keys if study else None)
