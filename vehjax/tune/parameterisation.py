"""Unconstrained coordinates of the fitted quantities: the maps from the optimiser's vector to
the physical values (:mod:`vehjax.tune`; docs/tune.md in full).

* a covariance by its log-diagonal (``A = diag(exp(2 d))``) or its log-Cholesky factor
  (``A = L L^T``, ``L`` lower triangular with diagonal ``exp(d)``): :class:`Cov`;
* the input noise, stds by input name (log stds) or a covariance like Q: :class:`InputNoise`;
* model parameters by the parameter-domain transforms the filters use (a box, a half line,
  or free; unit scale): :func:`param_transform`.

Both covariance maps keep the covariance positive definite for every coordinate vector.
"""

from __future__ import annotations

from typing import Mapping

import jax.numpy as jnp
import numpy as np

from .. import validation
from ..filters import bounds as bounds_maps  # the one import of the parameter-domain maps
from ..filters import input_noise as _inoise

__all__ = ["Cov", "InputNoise", "is_diag", "param_transform"]


def is_diag(A: np.ndarray) -> bool:
    """Whether A has no non-zero entry off its diagonal."""
    return not np.any(A - np.diag(np.diagonal(A)))


class Cov:
    """Log-diagonal or log-Cholesky parameterisation of an (n, n) covariance: ``z0`` the
    coordinates of ``A``, ``cov(z)`` the covariance at ``z``."""

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


class InputNoise:
    """Parameterisation of the input noise (its starting value the builder's ``input_noise``
    option, ``functools.partial(builder, input_noise=...)``): a dict ``{input name: std}`` is
    fitted by the log standard deviations of the named inputs (the builder gets
    ``{name: exp(z)}``), an (nu, nu) covariance like Q0 (log-diagonal or log-Cholesky, positive
    definite)."""

    def __init__(self, spec, model):
        names = tuple(model.input_names)
        _inoise.input_factor(spec, names)  # the filters' own checks, ValueError naming it
        if isinstance(spec, Mapping):
            self.names = tuple(n for n in names if n in spec)
            self.z0 = np.log(np.array([float(spec[n]) for n in self.names]))
            self.cov = None
        else:
            S = validation.cov("input_noise", np.asarray(spec, dtype=float), len(names),
                              allow_diag=False)
            self.names, self.diag = names, is_diag(S)
            self.cov = Cov(S, self.diag)
            self.z0 = self.cov.z0

    def __call__(self, z):
        if self.cov is None:
            return {n: jnp.exp(z[i]) for i, n in enumerate(self.names)}
        return self.cov(z)


def param_transform(params, bounds, theta0: np.ndarray, names: tuple, domains=None):
    """(indices (q,) in ``names``, the parameter-domain ``Transform``) of the fitted parameters;
    ValueError naming ``bounds``. ``domains``: the model's declared physical domains
    (``model.param_domains()``) or None. A fitted parameter's box is its domain, narrowed by
    ``bounds`` where given; a parameter with neither is kept positive when its starting value
    is positive, else left free (docs/tune.md, Parameterisations)."""
    bounds = validation.keyed("bounds", bounds, params, "the fitted params")
    idx = np.array([names.index(p) for p in params], dtype=int)
    low, high = np.empty(len(params)), np.empty(len(params))
    dom_lo, dom_hi = ((np.full(len(names), -np.inf), np.full(len(names), np.inf))
                      if domains is None else domains.bounds())
    for j, p in enumerate(params):
        v = float(theta0[idx[j]])
        declared = np.isfinite(dom_lo[idx[j]]) or np.isfinite(dom_hi[idx[j]])
        if p in bounds or declared:
            low[j], high[j] = _box(p, bounds.get(p), dom_lo[idx[j]], dom_hi[idx[j]])
            if not low[j] < v < high[j]:
                show = lambda b: None if np.isinf(b) else float(b)  # noqa: E731
                raise ValueError(
                    f"bounds: the starting value {p} = {v} (model.theta) must lie strictly "
                    f"inside ({show(low[j])}, {show(high[j])}); set it with "
                    f"model.with_theta({p}=...)"
                )
        else:
            low[j], high[j] = (0.0 if v > 0 else -np.inf), np.inf
    return idx, bounds_maps.Transform(low, high)


def _box(name: str, given, dom_lo: float, dom_hi: float) -> tuple[float, float]:
    """(low, high): the parameter's domain narrowed by its ``bounds`` entry ``given`` (or None);
    ValueError naming ``bounds`` and the parameter where the two do not overlap."""
    low, high = (-np.inf, np.inf) if given is None else bounds_maps.check_pair("bounds", name,
                                                                                given)
    low, high = max(low, dom_lo), min(high, dom_hi)
    if not low < high:
        raise ValueError(f"bounds: {name}'s bounds {given} lie outside its physical domain "
                         f"({dom_lo:g}, {dom_hi:g})")
    return low, high


def check_bounds(params, bounds, model) -> None:
    """``bounds`` of the fitted ``params`` checked against ``model``'s declared domains before
    anything is fitted (a staged fit's first stage is another model's): ValueError naming
    ``bounds`` and the parameter for an unknown name, a bad pair, or bounds wholly outside the
    parameter's domain. Whether the start lies inside is checked where the start is known."""
    bounds = validation.keyed("bounds", bounds, params, "the fitted params")
    names, domains = tuple(model.param_names), model.param_domains()
    dom_lo, dom_hi = ((np.full(len(names), -np.inf), np.full(len(names), np.inf))
                      if domains is None else domains.bounds())
    for p, given in bounds.items():
        _box(p, given, dom_lo[names.index(p)], dom_hi[names.index(p)])
