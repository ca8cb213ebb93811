"""What every filter built on a vehjax model needs: the prior, the model's parameters and
dimensions, the model's functions in the filter's dtype. Validation itself is
:mod:`vehjax.validation`."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from .. import validation
from ..lib.square_root import chol_const  # noqa: F401 (the filters' import of it)
from ..models.base import Model

def validate_prior(est, x0, P0) -> None:
    """Check a prior before tracing; ``est`` is an Estimator or the state dimension nx.

    ``x0`` is (nx,) or batched (R, nx); ``P0`` is (nx, nx) or (nx,) variances, or batched
    (R, nx, nx). Raises ValueError naming ``x0`` or ``P0`` (:func:`vehjax.validation.prior`,
    the one check of a prior).
    """
    nx = est if isinstance(est, (int, np.integer)) else est.nx
    validation.prior(nx, x0, P0, runs=validation.ANY_RUNS)


def prior(nx: int, x0, P0):
    """x0, P0 as arrays of one float dtype, checked (:func:`vehjax.validation.prior`: shapes
    always, values when concrete); P0 given as (nx,) variances becomes diagonal."""
    x0, P0 = validation.prior(nx, x0, P0)
    x0, P0 = jnp.asarray(x0), jnp.asarray(P0)
    dtype = jnp.result_type(x0.dtype, P0.dtype)
    if not jnp.issubdtype(dtype, jnp.floating):
        dtype = jnp.asarray(0.0).dtype  # the default float (float64 under vehjax)
    return x0.astype(dtype), P0.astype(dtype)


def model_theta(model, theta0, dtype):
    """theta0 (np,) (``model.theta`` when None) in ``dtype``."""
    if theta0 is None:
        theta0 = model.theta
    if np.shape(theta0) != (model.n_params,):
        raise ValueError(
            f"theta0: expected shape ({model.n_params},) for parameters {model.param_names}, "
            f"got shape {np.shape(theta0)}"
        )
    return jnp.asarray(theta0).astype(dtype)


def check_model(model):
    """(nx, ny) of a model satisfying :class:`vehjax.models.base.ModelProtocol`."""
    validation.model(model)
    return len(model.state_names), len(model.output_names)


def model_dims(model) -> dict:
    """The ``ny``/``nu``/``n_theta``/``theta_domains`` fields of an Estimator built on
    ``model`` (no domains for a model class of the user's own without ``param_domains``)."""
    domains = getattr(model, "param_domains", None)
    return dict(ny=len(model.output_names), nu=len(model.input_names),
                n_theta=len(model.param_names),
                theta_domains=domains() if callable(domains) else None)


def in_dtype(fn):
    """``fn(x, u, theta)`` with its output cast to the dtype of ``x`` (a model with float64
    constants must not silently turn a float32 filter into a float64 one)."""
    return lambda x, u, theta: jnp.asarray(fn(x, u, theta)).astype(x.dtype)


def per_point(model):
    """(transition, observe) of ``model`` for evaluation one point at a time (a filter step
    vmapped over runs): a user's :class:`~vehjax.models.Model` as written, without the
    vectorisable substitutes of ``fast_math``, which pay off only on long batches of points
    (runs-last steps, particles); built-in models as they are."""
    if isinstance(model, Model):
        f, h = model.written_fns
        return ((lambda x, u, th: jnp.asarray(f(x, u, th))),
                (lambda x, u, th: jnp.atleast_1d(jnp.asarray(h(x, u, th)))))
    return model.transition, model.observe


def point_fns(model, u, theta):
    """The model's transition and observation as functions of one state point, at (u, theta)
    (:func:`per_point`)."""
    f, h = (in_dtype(g) for g in per_point(model))
    return (lambda x: f(x, u, theta)), (lambda x: h(x, u, theta))


def cast_yu(y, u, dtype):
    return jnp.asarray(y).astype(dtype), jnp.asarray(u).astype(dtype)


