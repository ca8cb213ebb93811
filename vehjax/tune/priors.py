"""Priors on model parameters in a fit: penalised likelihood (maximum a posteriori).

``priors={"iz": LogNormal(2763.0, 0.3), "m": Normal(1500.0, 75.0)}`` (the prior objects of
:mod:`vehjax.lib.priors`, the same ones and the same dict :func:`vehjax.calibrate.pmmh` takes)
says what the engineer knows of a parameter before the data: a yaw inertia from a spec sheet
to 30 %, a mass to 5 % (``LogNormal.within(1500.0, 0.05)``). Every parameter named there is
fitted (added to ``params`` when not among them), in the coordinate its domain gives it as for
``params`` (:func:`vehjax.tune.parameterisation.param_transform`; the prior's own map to the
real line is not used), and the fit maximises

    log L(theta) + sum_j log p_j(theta_j)

in the physical parameters theta: the maximum a posteriori (MAP) estimate in physical
coordinates (no Jacobian term of the map to the fit's coordinates, so the estimate does not
depend on them; for a LogNormal this is the mode of the posterior density in x, which with no
data is ``median exp(-sigma^2)``, not the median). The two ends: a prior much wider than the
likelihood's curvature is the plain fit (``params=``), a very narrow one holds the parameter at
its centre (fixed at ``model.theta``).

A :class:`~vehjax.lib.priors.Uniform` prior is a box: its (low, high) become the parameter's
``bounds`` (no penalty inside, its constant density counted in the reported log-prior); giving
both a Uniform prior and different ``bounds`` for one parameter is refused. A LogNormal prior on
a parameter whose domain reaches below 0 keeps it positive (its support; lower bound 0).

The penalty enters every part of the fit: the loss (:func:`vehjax.tune.likelihood.prepare`),
its gradient in the compiled program (forward and reverse mode,
:mod:`vehjax.tune.program`), the scoring optimiser's curvature (the BHHH matrix plus the
prior's negative Hessian, :func:`prior_curvature`), and through the gradient the Newton polish
and the observed information behind the standard errors (the Hessian of the penalised loss:
the posterior's curvature, the data's information plus the prior's).

Reference: e.g. Gelman et al., *Bayesian Data Analysis* (3rd ed.), sec. 4.1 (the normal
approximation at the posterior mode).
"""

from __future__ import annotations

import math
from typing import Mapping

import jax.numpy as jnp
import numpy as np

from ..filters import bounds as bounds_maps
from ..lib import priors as lp

__all__ = ["check", "fitted_params", "log_prior_fn", "prior_curvature", "prior_scales", "report",
           "prior_text", "pull_warning", "PULL_WARN"]

#: a parameter whose estimate lies more than this many prior standard deviations from its
#: prior's centre is reported: the data contradict the stated value
PULL_WARN = 3.0


def _domain(model, name: str) -> tuple[float, float]:
    """(low, high) of a parameter's declared physical domain, (-inf, inf) when none."""
    domains = model.param_domains()
    if domains is None:
        return -math.inf, math.inf
    lo, hi = domains.bounds()
    j = model.param_names.index(name)
    return float(lo[j]), float(hi[j])


def _check_one(name: str, prior, model, bounds: dict) -> None:
    """ValueError naming ``priors`` and ``name`` for a prior that cannot describe the
    parameter: its centre outside the domain, or a Uniform box outside it or beside other
    bounds; ``bounds`` (updated) gets the box a Uniform or LogNormal implies."""
    lo, hi = _domain(model, name)
    s_lo, s_hi = lp.support(prior)
    if isinstance(prior, lp.Uniform):
        if not (max(lo, s_lo) < min(hi, s_hi)):
            raise ValueError(f"priors: {name!r}: the prior's support ({s_lo:g}, {s_hi:g}) lies "
                             f"outside the parameter's domain ({lo:g}, {hi:g})")
        box = (s_lo, s_hi)
        given = bounds.get(name)
        if given is not None and bounds_maps.check_pair("bounds", name, given) != box:
            raise ValueError(f"priors: {name!r} has a Uniform prior and bounds={given}; give "
                             f"its box one way (the Uniform prior is a box)")
        bounds[name] = box
        return
    c = float(prior.center)
    if not lo < c < hi:
        raise ValueError(f"priors: {name!r}: the prior's centre {c:g} lies outside the "
                         f"parameter's domain ({lo:g}, {hi:g})")
    if s_lo > lo and name not in bounds:  # a LogNormal on a domain reaching below 0
        bounds[name] = (s_lo, None if math.isinf(hi) else hi)


def check(priors, model, bounds=None) -> tuple[dict, dict | None]:
    """(priors {name: prior}, bounds with the priors' boxes) of ``priors`` checked against the
    model before anything is traced: a dict parameter name -> Normal / LogNormal / Uniform
    (:mod:`vehjax.lib.priors`), or None / {} for none. ValueError naming ``priors`` and the
    parameter for an unknown name, a value that is no prior, a prior whose centre (Uniform: its
    box) lies outside the parameter's domain (``model.param_domains()``). Idempotent: the
    bounds it returns pass it again."""
    if priors is None or (isinstance(priors, Mapping) and not priors):
        return {}, bounds
    names, values = lp.check_priors(priors)  # the dict and its values, as calibrate checks them
    out = dict(bounds or {}) if bounds is None or isinstance(bounds, Mapping) else bounds
    for name, prior in zip(names, values):
        if name not in model.param_names:
            raise ValueError(f"priors: unknown parameter {name!r}; expected model parameters "
                             f"from {tuple(model.param_names)}")
        if isinstance(out, Mapping):
            _check_one(name, prior, model, out)
    return dict(zip(names, values)), out


def fitted_params(params, priors: dict) -> tuple:
    """``params`` with the prior'd parameters not among them appended (in ``priors``' order):
    a parameter with a prior is fitted."""
    params = tuple(params) if not isinstance(params, str) else (params,)
    return params + tuple(n for n in priors if n not in params)


def log_prior_fn(priors: dict, param_names):
    """``log_prior(theta (np,)) -> ()``, the sum of the Normal and LogNormal priors' log
    densities at the model's parameter vector (physical units, jax-traceable), or None when
    there is none (a Uniform is a box: no term)."""
    terms = [(list(param_names).index(n), p) for n, p in priors.items()
             if not isinstance(p, lp.Uniform)]
    if not terms:
        return None

    def log_prior(theta):
        return sum(p.log_density(theta[j]) for j, p in terms)

    return log_prior


def prior_curvature(hessian):
    """The prior's contribution to the scoring curvature: minus its Hessian (n, n) in the fit's
    coordinates, of which only the diagonal is nonzero (each prior reads one coordinate),
    floored at 0 so that the BHHH matrix it is added to stays positive semi-definite (a Normal
    prior read through a log coordinate is concave there only above half its mean)."""
    return jnp.diag(jnp.maximum(-jnp.diagonal(hessian), 0.0))


def prior_scales(scales, curvature):
    """The coordinates' natural sizes ``scales`` (n,) narrowed to twice the prior's standard
    deviation in the coordinate, ``2 / sqrt(c)`` with c (n,) the diagonal of the prior's
    curvature there (:func:`prior_curvature`, 0 where no prior reads the coordinate). A prior
    much narrower than the natural size would otherwise make the scaled information
    ill-conditioned (the other coordinates named undetermined beside it) and the Hessian's
    difference steps too long; twice its width keeps a parameter the prior alone determines
    above the size rule of :func:`vehjax.tune.uncertainty`."""
    scales = np.asarray(scales, dtype=float)
    c = np.asarray(curvature, dtype=float)
    with np.errstate(divide="ignore"):
        return np.where(c > 0, np.minimum(scales, 2.0 / np.sqrt(np.where(c > 0, c, 1.0))),
                        scales)


def report(priors: dict, model, theta) -> tuple[dict, float]:
    """(pulls {name: pull}, log-prior) at the parameter vector ``theta`` (np,): each prior's
    :func:`vehjax.lib.priors.pull` (Normal, LogNormal) and the sum of every prior's log density
    (a Uniform's constant included)."""
    pulls, total = {}, 0.0
    for n, p in priors.items():
        x = float(theta[model.param_names.index(n)])
        total += float(p.log_density(jnp.asarray(x)))
        if not isinstance(p, lp.Uniform):
            pulls[n] = lp.pull(p, x)
    return pulls, total


def prior_text(prior, pull) -> str:
    """What the summary says of a prior'd parameter: "(prior 2763 to 30 %: pulled 3.1 sigma
    from it)"; ``pull`` None for a Uniform."""
    if pull is None or not np.isfinite(pull):
        return f"(prior {lp.describe(prior)})"
    return f"(prior {lp.describe(prior)}: pulled {abs(pull):.2g} sigma from it)"


def pull_warning(priors: dict, pulls: dict, values: dict) -> str | None:
    """The warning for the parameters pulled more than :data:`PULL_WARN` standard deviations
    from their priors' centres, or None."""
    far = [n for n, z in pulls.items() if abs(z) > PULL_WARN]
    if not far:
        return None
    return "vehjax.tune: the data contradict the stated value of " + "; ".join(
        f"{n} (estimate {values[n]:.6g}, prior {lp.describe(priors[n])}: {abs(pulls[n]):.2g} "
        f"sigma from it)" for n in far) + ": check the prior, the model or the data"
