"""Priors of parameters and their maps to the real line, shared by particle MCMC
(:mod:`vehjax.calibrate`) and penalised maximum likelihood (:mod:`vehjax.tune`, ``priors=``).

Each prior (:class:`Normal`, :class:`LogNormal`, :class:`Uniform`) carries its bijection to the
real line, the parameter transforms of :mod:`vehjax.lib.transforms` (the ones the filters' and
tune's ``bounds=`` use): Normal the map "none" (z = x), LogNormal "lower" with low 0
(x = exp(z)), Uniform "box" (x = low + (high - low) sigmoid(z), evaluated from the nearer end).
The chain moves in that unconstrained space, and the target there is the posterior times the
Jacobian of the map back: log p(y | x(z)) + log p(x(z)) + log |dx/dz|
(:func:`log_prior_unconstrained` is the last two).

The maps take any value to a finite z, also one on or beyond the support's end (the transforms
clip the distance to a bound); :func:`starting_values` checks that starting values lie inside
the support before they are mapped.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping

import jax.numpy as jnp
import numpy as np

from .. import validation
from . import transforms
from .gaussian import log_density

__all__ = ["Normal", "LogNormal", "Uniform", "PRIORS", "log_prior_unconstrained",
           "to_physical", "check_priors", "starting_values", "pull", "support", "describe"]

_INF = float("inf")


class _Mapped:
    """The unconstrained coordinate of a prior: :mod:`vehjax.lib.transforms`' map ``_map()``
    -> (kind, low, high, scale)."""

    def to_unconstrained(self, x):
        """z of a physical value x (finite also on or beyond the support's ends)."""
        return transforms.inverse(*self._map(), jnp.asarray(x, float))

    def from_unconstrained(self, z):
        """The physical value x(z), inside the support."""
        return transforms.forward(*self._map(), jnp.asarray(z))

    def log_jacobian(self, z):
        """log |dx/dz| at z."""
        return transforms.log_derivative(*self._map(), jnp.asarray(z))


@dataclass(frozen=True)
class Normal(_Mapped):
    """Normal prior N(mean, std^2) on the real line; unconstrained coordinate z = x."""

    mean: float
    std: float

    def __post_init__(self):
        validation.number("Normal.mean", self.mean)
        validation.number("Normal.std", self.std, 0.0)

    def _map(self):
        return "none", -_INF, _INF, 1.0

    def log_density(self, x):
        return log_density(((x - self.mean) / self.std) ** 2, 2.0 * math.log(self.std), 1)

    center = property(lambda self: self.mean)
    scale = property(lambda self: self.std)  # in unconstrained units


@dataclass(frozen=True)
class LogNormal(_Mapped):
    """Positive quantity with log x ~ N(log median, sigma^2); z = log x."""

    median: float
    sigma: float

    def __post_init__(self):
        validation.number("LogNormal.median", self.median, 0.0)
        validation.number("LogNormal.sigma", self.sigma, 0.0)

    def _map(self):
        return "lower", 0.0, _INF, 1.0

    def log_density(self, x):
        lx = jnp.log(x)
        return log_density(((lx - math.log(self.median)) / self.sigma) ** 2,
                           2.0 * math.log(self.sigma), 1) - lx

    center = property(lambda self: self.median)
    scale = property(lambda self: self.sigma)

    @classmethod
    def within(cls, value: float, fraction: float) -> "LogNormal":
        """A positive value known to within ``fraction`` (0.3: "to 30 %") at one standard
        deviation: ``LogNormal(value, fraction)``, log x ~ N(log value, fraction^2), i.e. x
        within a factor exp(+-fraction) of ``value`` with 68 % probability (about +-fraction
        for fractions up to 0.3: exp(0.3) = 1.35, exp(-0.3) = 0.74). ValueError naming
        ``LogNormal.median`` / ``LogNormal.sigma`` for a value or fraction <= 0."""
        return cls(value, fraction)


@dataclass(frozen=True)
class Uniform(_Mapped):
    """Uniform prior on (low, high); z = logit((x - low) / (high - low))."""

    low: float
    high: float

    def __post_init__(self):
        lo = validation.number("Uniform.low", self.low)
        validation.number("Uniform.high", self.high, lo)

    def _map(self):
        return "box", float(self.low), float(self.high), 1.0

    def log_density(self, x):
        inside = (x > self.low) & (x < self.high)
        return jnp.where(inside, -math.log(self.high - self.low), -jnp.inf)

    center = property(lambda self: 0.5 * (self.low + self.high))
    scale = property(lambda self: 1.8)  # logistic std of a uniform on (0, 1)


PRIORS = (Normal, LogNormal, Uniform)


def log_prior_unconstrained(priors, z):
    """log p(x(z)) + log |dx/dz| summed over the coordinates: the prior density of z, (d,) -> ()."""
    total = 0.0
    for i, p in enumerate(priors):
        x = p.from_unconstrained(z[i])
        total = total + p.log_density(x) + p.log_jacobian(z[i])
    return total


def to_physical(priors, z):
    """(d,) unconstrained -> (d,) physical values."""
    return jnp.stack([p.from_unconstrained(z[i]) for i, p in enumerate(priors)])


def check_priors(priors) -> tuple:
    """(names, priors) of a ``priors`` dict name -> prior; ValueError naming ``priors``."""
    if not isinstance(priors, Mapping) or not priors:
        raise ValueError("priors: expected a non-empty dict name -> Normal/LogNormal/Uniform")
    for name, p in priors.items():
        if not isinstance(p, PRIORS):
            raise ValueError(f"priors: {name!r}: expected Normal, LogNormal or Uniform, got {p!r}")
    return tuple(priors), tuple(priors.values())


def starting_values(priors, init, names, name: str = "init") -> np.ndarray:
    """(d,) unconstrained starting values: ``init`` where given, else the priors' centres.
    ValueError naming ``init`` (``name``, e.g. a record's field) for an unknown name or a value
    outside its prior's support (zero prior density)."""
    init = validation.keyed(name, init, names)
    x0 = [init.get(n, p.center) for n, p in zip(names, priors)]
    inside = [bool(np.isfinite(float(p.log_density(jnp.asarray(x, float)))))
              for x, p in zip(x0, priors)]
    z0 = np.array([float(p.to_unconstrained(x)) for x, p in zip(x0, priors)])
    if not (all(inside) and np.all(np.isfinite(z0))):
        raise ValueError(f"{name}: a starting value lies outside its prior's support: {init!r}")
    return z0


def support(prior) -> tuple[float, float]:
    """(low, high) of the prior's support: (-inf, inf) Normal, (0, inf) LogNormal, (low, high)
    Uniform."""
    if isinstance(prior, Uniform):
        return float(prior.low), float(prior.high)
    if isinstance(prior, LogNormal):
        return 0.0, _INF
    return -_INF, _INF


def pull(prior, x) -> float:
    """How far a value x lies from the prior's centre, in the prior's standard deviations in
    its own coordinate: ``(x - mean) / std`` (Normal), ``(log x - log median) / sigma``
    (LogNormal); NaN for a Uniform (no centre it pulls toward). Dimensionless; the sign says
    the side (positive: above the centre)."""
    if isinstance(prior, Normal):
        return (float(x) - prior.mean) / prior.std
    if isinstance(prior, LogNormal):
        return (math.log(float(x)) - math.log(prior.median)) / prior.sigma
    return float("nan")


def describe(prior) -> str:
    """The prior in a few words: "2763 to 30 %" (LogNormal), "1500 +- 75" (Normal),
    "uniform on (0.1, 2)"."""
    if isinstance(prior, Normal):
        return f"{prior.mean:.6g} +- {prior.std:.3g}"
    if isinstance(prior, LogNormal):
        return f"{prior.median:.6g} to {100.0 * prior.sigma:.3g} %"
    return f"uniform on ({prior.low:.6g}, {prior.high:.6g})"
