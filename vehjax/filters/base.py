"""The Estimator contract shared by every filter and by :func:`vehjax.run`.

An estimator is a pair of pure functions, like optax's ``GradientTransformation``::

    init(x0, P0, theta0, P_theta0, key) -> state      # x0 (nx,), P0 (nx, nx); theta0 (p,) or None
    step(state, y, u) -> (state, StepOutput)          # y (ny,) with NaN for missing, u (nu,)

``state`` is any pytree of arrays (filters that draw random numbers carry their key in it).
Everything that configures a filter (model, Q, R, tuning) is closed over, so ``run`` treats
every filter alike and ``jax.vmap``/``jax.lax.scan`` see only arrays.

A ``step`` may carry an attribute
``runs_last(per_run_inputs: bool, dtype, default_theta: bool) -> Batch(prepare, step)``: the
same step for a whole batch of runs at once, with the runs axis last in every leaf of the
state, of y and of the StepOutput. ``prepare`` maps the whole input sequence, (T, nu) shared or
(T, nu, R) when ``per_run_inputs``, to what the batch ``step`` takes in place of u at each time;
``dtype`` is the filter's float dtype and ``default_theta`` says that every run was started
with ``theta0=None``. ``vehjax.run`` then uses it instead of ``vmap``-ing ``step`` (see
:mod:`vehjax.filters.runs_last`). It belongs to that function: an estimator whose ``step`` is
replaced (``est._replace(step=...)``) is run with ``vmap`` again.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax.numpy as jnp


class StepOutput(NamedTuple):
    """What one filter step reports for the current time.

    Attributes:
        mean: filtered state estimate, (nx,).
        cov: its covariance, (nx, nx).
        loglik: log p(y_t | y_{1:t-1}) of the observed components, scalar.
        nis: normalised innovation squared of the observed components, scalar.
        n_obs: how many measurement components were observed (not NaN), scalar int.
        params: parameter estimate, (p,); shape (0,) for state-only filters.
        params_cov: its covariance, (p, p); shape (0, 0) for state-only filters.
    """

    mean: jnp.ndarray
    cov: jnp.ndarray
    loglik: jnp.ndarray
    nis: jnp.ndarray
    n_obs: jnp.ndarray
    params: jnp.ndarray
    params_cov: jnp.ndarray


class Estimator(NamedTuple):
    """``Estimator(init, step)``: see the module docstring for the signatures.

    Attributes:
        init: builds the filter state from the prior.
        step: predicts with ``u`` then updates with ``y``; returns the new state and a StepOutput.
        nx: state dimension the filter estimates.
        param_names: names of the parameters it estimates (empty for state-only filters).
        name: short label used in tables and plots.
        needs_key: whether ``init`` needs a PRNG key (particle filters).
    """

    init: Callable[..., Any]
    step: Callable[..., tuple[Any, StepOutput]]
    nx: int
    param_names: tuple[str, ...] = ()
    name: str = "estimator"
    needs_key: bool = False


def check_estimate(model, estimate) -> tuple[tuple[str, ...], tuple[int, ...]]:
    """Names of the parameters to estimate and their indices in ``model.param_names``.

    ``estimate`` is one name or a sequence of unique names of the model's parameters. Raises
    ValueError naming ``estimate`` when it is missing, empty, not strings, repeated or unknown.
    """
    known = tuple(model.param_names)
    if estimate is None:
        raise ValueError(f"estimate: required, the names of the parameters to estimate from {known}")
    if isinstance(estimate, str):
        estimate = (estimate,)
    try:
        names = tuple(estimate)
    except TypeError:
        raise ValueError(f"estimate: expected a sequence of parameter names, got {estimate!r}") from None
    if not names:
        raise ValueError(f"estimate: expected at least one parameter name from {known}, got none")
    if not all(isinstance(n, str) for n in names):
        raise ValueError(f"estimate: expected parameter names (strings), got {names!r}")
    if len(set(names)) != len(names):
        raise ValueError(f"estimate: names must be unique, got {names!r}")
    unknown = [n for n in names if n not in known]
    if unknown:
        raise ValueError(f"estimate: unknown parameter name(s) {unknown}; this model has {known}")
    return names, tuple(known.index(n) for n in names)
