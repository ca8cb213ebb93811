"""Particle filters in a fit: stop-gradient resampling (Scibior & Wood 2021, "Differentiable
particle filtering without modifying the forward pass").

The particle filters resample through the function they are built with (the ``resample`` of
their ``resampling=Resampling(...)``).
:func:`vehjax.filters.smc.resample` gives every resampled particle the constant log weight
``-log N``; :func:`vehjax.filters.smc.resample_stop_gradient` gives it ``-log N + log W_a -
stop_gradient(log W_a)``: the same value, but its gradient carries the ancestor's log weight.
A fit builds a particle filter with the latter (:func:`resample_keyword`): the forward pass is
the filter's own, value for value.
"""

from __future__ import annotations

import dataclasses
import inspect

from .. import validation
from ..filters import smc
from ..filters.base import Estimator
from ..filters.particle import bootstrap_pf
from ..filters.smc import Resampling

__all__ = ["stop_gradient", "stop_gradient_pf", "resample_keyword"]


def stop_gradient(estimator: Estimator) -> Estimator:
    """Refused: stop-gradient resampling is chosen when a particle filter is built.

    Build the filter with ``resampling=Resampling(resample=smc.resample_stop_gradient)``
    (``bootstrap_pf``, ``liu_west_ukf``, ``marginalized_pf``) or use :func:`stop_gradient_pf`;
    :func:`vehjax.tune.fit` and :func:`vehjax.tune.objective` do so for a particle filter's
    builder themselves.

    Raises:
        ValueError: naming ``estimator``, always (a built filter's resampling cannot be
            changed).
    """
    name = getattr(estimator, "name", type(estimator).__name__)
    raise ValueError(
        f"estimator: stop_gradient cannot change the resampling of a built filter ({name!r}); "
        f"build it with resampling=vehjax.filters.Resampling("
        f"resample=vehjax.filters.smc.resample_stop_gradient), e.g. "
        f"vehjax.filters.bootstrap_pf(model, Q, R, resampling=...), or use "
        f"vehjax.tune.stop_gradient_pf(model, Q, R, ...)")


def resample_keyword(builder, name: str, options: dict) -> dict:
    """The keyword that makes ``builder`` (a particle filter's, called ``name``) resample with
    stop-gradient weights: ``{"resampling": Resampling(..., resample=smc.resample_stop_gradient)}``
    (the scheme and threshold of its ``options``' own ``resampling``, else the defaults), or
    {} when that record already names a ``resample`` (the caller's own choice) or is not a
    :class:`~vehjax.filters.Resampling` (the builder names it). It replaces the caller's.

    Whether ``builder`` takes the keyword is read from its signature
    (``inspect.signature``: a parameter ``resampling`` or ``**kwargs``); a builder without a
    readable signature is called with it and says itself when it does not take it.

    Raises:
        ValueError: naming ``builder``, when its signature shows no ``resampling`` keyword.
    """
    given = options.get("resampling")
    if given is not None and (not isinstance(given, Resampling) or given.resample is not None):
        return {}
    try:
        params = inspect.signature(builder).parameters.values()
    except (TypeError, ValueError):  # no signature to read: let the call say
        params = ()
    if params and not any(q.name == "resampling" or q.kind is q.VAR_KEYWORD for q in params):
        raise ValueError(
            f"builder: {name} draws random numbers (a particle filter) but takes no "
            f"resampling= keyword; tune differentiates a particle filter with stop-gradient "
            f"resampling, passed as resampling=vehjax.filters.Resampling("
            f"resample=vehjax.filters.smc.resample_stop_gradient)")
    base = Resampling() if given is None else given
    return {"resampling": dataclasses.replace(base, resample=smc.resample_stop_gradient)}


def stop_gradient_pf(model, Q, R, n_particles: int = 1000, *,
                     resampling: Resampling = Resampling()) -> Estimator:
    """``vehjax.filters.bootstrap_pf(model, Q, R, ..., resampling=Resampling(...,
    resample=smc.resample_stop_gradient))``: the bootstrap PF with stop-gradient resampling
    (Scibior & Wood 2021), a builder with bootstrap_pf's arguments (``resampling``'s scheme and
    threshold kept, its function replaced).

    The result has the bootstrap PF's ``init`` and forward pass, value for value (random
    numbers, particles, resampling decisions and indices, outputs); only gradients differ:
    after a resampling, particle i's normalised log weight is ``-log N + log W_a -
    stop_gradient(log W_a)`` (value ``-log N``) for its ancestor a
    (:func:`vehjax.filters.smc.stop_gradient_weights`). The gradient of ``sum_t loglik_t`` is
    then the Fisher-identity estimate of the score, ``sum_i W_T^i grad log p(x^i_0:T, y_1:T)``
    along the particles' ancestral paths (the particles reparameterised, ``f(x) + chol(Q) z``),
    a consistent estimate of ``grad log p(y_1:T)`` (bias O(1/N))."""
    rs = validation.record("resampling", resampling, Resampling)
    return bootstrap_pf(model, Q, R, n_particles=n_particles,
                        resampling=dataclasses.replace(rs, resample=smc.resample_stop_gradient))
