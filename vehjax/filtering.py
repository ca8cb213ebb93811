"""``vehjax.filter``: one run of an estimator, pure and traceable (``jax.jit``, ``jax.vmap``,
``jax.grad``), on the one-run engine (:mod:`vehjax.engine`, whose docstring gives the time
convention, what a diverged run holds and when a run is ``at_bound``).

::

    res = vehjax.filter(est, ys, us, x0=x0, P0=P0)      # ys (T, ny), us (T, nu)
    res.states          # (T, nx)
    res.loglik.sum()    # log p(y_1:T), differentiable w.r.t. Q, R, model parameters, x0
"""

from __future__ import annotations

import jax.numpy as jnp

from . import validation
from .runtime import eager
from .engine import AT_BOUND_FRACTION, AT_BOUND_RTOL, FilterResult, check_arguments, one_run
from .filters.base import Estimator

__all__ = ["FilterResult", "filter", "AT_BOUND_RTOL", "AT_BOUND_FRACTION"]


def filter(estimator: Estimator, measurements, inputs, *, x0, P0, theta0=None, P_theta0=None,
           key=None, return_covariances: bool = True) -> FilterResult:
    """Run ``estimator`` over one run of T steps: ``init``, then ``lax.scan`` of ``step``.

    Pure and traceable: call it under ``jax.jit``, ``jax.vmap`` (over runs) or ``jax.grad``
    (e.g. of ``filter(...).loglik.sum()`` with respect to Q, R, model parameters or x0, with the
    estimator built inside the differentiated function). NaN measurement components are missing
    and give no NaN gradients.

    Args:
        estimator: a :class:`vehjax.filters.Estimator`.
        measurements: (T, ny); NaN components are missing; +-inf is refused (under a trace,
            where values are unknown, any non-finite component is treated as missing).
        inputs: (T, nu); None when the model has no inputs.
        x0: state before the first step, (nx,).
        P0: its covariance, (nx, nx) or (nx,) variances.
        theta0, P_theta0: initial parameter estimate (p,) and covariance (p, p) or (p,)
            variances for filters that estimate parameters, both or neither
            (``estimator.param_prior`` when None, if the filter has one); for state-only
            filters ``theta0`` (np,) replaces the model's parameters and P_theta0 is None.
        key: PRNG key, required when ``estimator.needs_key``.
        return_covariances: also return ``covariances`` and ``params_cov``.

    Returns:
        :class:`FilterResult` of arrays (:mod:`vehjax.engine` for divergence and ``at_bound``).

    Raises:
        ValueError: naming the argument (and the first bad index), by the rules every entry
            point shares (:mod:`vehjax.validation`): shapes that do not fit and complex or
            non-numeric arrays (also under ``jit``); for concrete values also +-inf
            measurements, non-finite inputs, x0, P0, theta0, P_theta0, covariances that are
            not symmetric positive definite, a theta0 outside ``estimator.bounds`` (a state-only
            filter's outside the model's domains, ``estimator.theta_domains``); a missing
            key.
    """
    ys, us, x0, P0, th0, Pth0, _ = check_arguments(estimator, measurements, inputs, x0, P0,
                                                    theta0, P_theta0, key)
    return_covariances = validation.flag("return_covariances", return_covariances)
    # called eagerly: compiled as one program (vehjax.runtime.eager); under a trace: inline
    return eager.call(one_run, (estimator, return_covariances), {}, jnp.asarray(ys),
                       jnp.asarray(us), jnp.asarray(x0), jnp.asarray(P0), th0, Pth0, key)
