"""The likelihoods particle MCMC calibrates with, as functions of the calibrated values.

What is calibrated (``names``; :func:`targets` reads them), in :mod:`vehjax.tune`'s bracket
grammar (one index: a standard deviation; ``vehjax.tune``'s two-index covariance entries
``"R[a,b]"`` are not sampled here):

* a model parameter by its name (``"cf"``), in the parameter's units;
* ``"R[<output>]"``: the measurement-noise std of that output [output units];
* ``"Q[<state>]"``: the process-noise std of that state [state units per step];
* ``"bias[<output>]"``: a constant sensor bias, y = h(x, u) + bias + noise [output units];
* ``"input[<input>]"``: the std of noise entering through that input [input units], for builders
  that take ``input_noise`` (every vehjax filter).

The earlier spelling ``"R:ay"`` is refused with a ValueError that gives the new one.

:func:`log_likelihood_fn`: any vehjax filter builder's log-likelihood (estimate), a fresh key
per evaluation; :func:`cpm_log_likelihood_fn`: the bootstrap PF's estimate as a function of its
random numbers (:mod:`vehjax.calibrate.correlated`), for the correlated pseudo-marginal chain.
:func:`log_likelihood_spread` and :func:`log_likelihood_difference_spread` measure how noisy
either is.
"""

from __future__ import annotations

import re
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import validation
from ..filtering import filter as run_filter
from ..filters import input_noise as inoise
from ..lib import square_root
from . import correlated
from .options import Correlated

__all__ = ["Targets", "QUANTITY_KINDS", "parse_quantity", "targets", "with_values",
           "log_likelihood_fn", "log_likelihood_spread", "cpm_log_likelihood_fn",
           "log_likelihood_difference_spread"]


class Targets(NamedTuple):
    params: tuple      # (index in priors, index in theta)
    r_std: tuple       # (index in priors, output index)
    q_std: tuple       # (index in priors, state index)
    bias: tuple        # (index in priors, output index)
    inputs: tuple      # (index in priors, input name)


#: the quantities named by a bracket key ``"<kind>[<name>]"``: the model's names they index
QUANTITY_KINDS = {"R": "output_names", "Q": "state_names", "bias": "output_names",
                  "input": "input_names"}
_KEY = re.compile(r"^(\w+)\[([^\[\]]*)\]$")
#: the most evaluations a spread takes (they run side by side, one filter each)
MAX_EVALS = 100_000
_OLD_KEY = re.compile(r"^(R|Q|bias|input):(.*)$")


def parse_quantity(name: str):
    """``(kind, indices)`` of a bracket key ``"R[ay]"`` (kind "R", indices ("ay",)) whose kind
    is one of :data:`QUANTITY_KINDS`, None for any other name (a model parameter's). The old
    spelling ``"R:ay"`` raises ValueError naming ``priors`` and the new spelling."""
    old = _OLD_KEY.match(name)
    if old:
        raise ValueError(f"priors: {name!r}: quantities are spelled {old[1]}[{old[2]}] (the "
                         f"bracket grammar of vehjax.tune; one index: a standard deviation), "
                         f"not {name!r}")
    m = _KEY.match(name)
    if m is None or m[1] not in QUANTITY_KINDS:
        return None
    return m[1], tuple(part.strip() for part in m[2].split(","))


def targets(model, names) -> Targets:
    """Where each name's value goes (:data:`QUANTITY_KINDS`, model parameters); ValueError
    naming ``priors`` for an unknown name, an old ``"R:ay"`` key or a covariance entry."""
    params, r_std, q_std, bias, inputs = [], [], [], [], []
    dests = {"R": r_std, "Q": q_std, "bias": bias, "input": inputs}
    for i, name in enumerate(names):
        q = parse_quantity(name)
        if q is not None:
            kind, idx = q
            known = tuple(getattr(model, QUANTITY_KINDS[kind]))
            if len(idx) != 1:
                raise ValueError(f"priors: {name!r}: calibrate samples standard deviations, "
                                 f"one index ({kind}[<name>]), not covariance entries")
            if idx[0] not in known:
                raise ValueError(f"priors: {name!r}: no {idx[0]!r} among {known}")
            dests[kind].append((i, idx[0] if kind == "input" else known.index(idx[0])))
        elif name in model.param_names:
            params.append((i, model.param_names.index(name)))
        else:
            raise ValueError(
                f"priors: unknown name {name!r}; expected a model parameter {model.param_names} "
                f"or 'R[<output>]', 'Q[<state>]', 'bias[<output>]', 'input[<input>]'")
    return Targets(tuple(params), tuple(r_std), tuple(q_std), tuple(bias), tuple(inputs))


def with_values(tg: Targets, theta, Q, R, ys, values):
    """The named quantities set to ``values`` (d,) physical: (theta (np,), Q (nx, nx) with the
    ``Q[...]`` variances, R (ny, ny) with the ``R[...]`` variances, ys (T, ny) minus the
    ``bias[...]`` values, the ``input[...]`` stds as a dict input name -> std, None without)."""
    for i, j in tg.params:
        theta = theta.at[j].set(values[i])
    for i, j in tg.q_std:
        Q = Q.at[j, j].set(values[i] ** 2)
    for i, j in tg.r_std:
        R = R.at[j, j].set(values[i] ** 2)
    for i, j in tg.bias:
        ys = ys.at[:, j].add(-values[i])
    noise = {name: values[i] for i, name in tg.inputs} if tg.inputs else None
    return theta, Q, R, ys, noise


def _no_fixed_input_noise(tg: Targets, kwargs):
    if tg.inputs and "input_noise" in kwargs:
        raise ValueError("builder: input_noise is calibrated ('input[...]' priors); drop it "
                         "from the builder's options")


def log_likelihood_fn(builder, model, measurements, inputs, *, x0, P0, Q, R, names):
    """``loglik(values (d,), key) -> ()``: the filter's log-likelihood estimate of the data with
    the quantities ``names`` (see the module docstring) set to ``values`` (physical units).

    ``builder(model, Q, R)`` builds the filter (``vehjax.filters.bootstrap_pf`` for PMMH, its
    options by ``functools.partial(bootstrap_pf, n_particles=N)``; a Kalman filter's exact
    likelihood gives plain Metropolis-Hastings). Q, R: (n,) variances or (n, n) covariances;
    named stds replace their diagonal entries. A run that diverges (or re-initialises its
    particles) has likelihood zero (-inf).
    """
    func, kwargs = validation.builder_options(builder)
    tg = targets(model, names)
    ys, us = validation.data(measurements, inputs, model.ny, model.nu, "one")
    validation.prior(model.nx, x0, P0)  # checked here, before a trace; the filter takes them
    Q = validation.cov("Q", Q, model.nx, allow_psd=True)
    R = validation.cov("R", R, model.ny)
    ys, us = jnp.asarray(ys, float), jnp.asarray(us, float)
    Q, R = jnp.asarray(Q), jnp.asarray(R)
    _no_fixed_input_noise(tg, kwargs)
    theta_base = jnp.asarray(model.theta, float)

    def loglik(values, key):
        theta, Qv, Rv, y, noise = with_values(tg, theta_base, Q, R, ys, values)
        kw = dict(kwargs)
        if tg.inputs:
            kw["input_noise"] = noise
        est = func(model, Qv, Rv, **kw)
        res = run_filter(est, y, us, x0=x0, P0=P0, theta0=theta, key=key,
                         return_covariances=False)
        ll = jnp.sum(res.loglik)
        return jnp.where(res.diverged | ~jnp.isfinite(ll), -jnp.inf, ll)

    return loglik


# -- the correlated pseudo-marginal likelihood ----------------------------------------------
def cpm_log_likelihood_fn(correlated_estimate, model, measurements, inputs, *, x0, P0, Q, R,
                          names):
    """The bootstrap PF's log-likelihood estimate as a function of its random numbers, for the
    correlated pseudo-marginal method: ``(loglik(values (d,), aux) -> (), draw(key) -> aux)``,
    aux a :class:`vehjax.calibrate.correlated.Aux` of standard normals
    (:func:`vehjax.calibrate.correlated.log_likelihood`: particles sorted along a Hilbert curve
    (the default ``sort``) and resampled systematically at every step). The same model and
    likelihood as :func:`log_likelihood_fn` with ``vehjax.filters.bootstrap_pf``; ``values`` as
    there. ``correlated_estimate``: a :class:`Correlated` (its builder's options; its
    correlation is the chain's, unused here).

    Raises:
        ValueError: ``correlated_estimate`` not a :class:`Correlated` (which checks that its
            builder is the bootstrap PF with only the options it reproduces).
    """
    if not isinstance(correlated_estimate, Correlated):
        raise ValueError(f"builder: expected vehjax.calibrate.Correlated(builder, correlation) "
                         f"(the correlated estimate, of vehjax.filters.bootstrap_pf only), got "
                         f"{correlated_estimate!r}")
    kwargs = correlated_estimate.options
    n = validation.integer("n_particles", kwargs.get("n_particles", 1000), 2)
    tg = targets(model, names)
    _no_fixed_input_noise(tg, kwargs)
    ys, us = validation.data(measurements, inputs, model.ny, model.nu, "one")
    x0a, P0a = validation.prior(model.nx, x0, P0)
    Qn = np.asarray(validation.cov("Q", Q, model.nx, allow_psd=True), float)
    Rn = validation.cov("R", R, model.ny)
    ys, us = jnp.asarray(ys, float), jnp.asarray(us, float)
    x0a, L0 = jnp.asarray(x0a, float), jnp.asarray(np.linalg.cholesky(np.asarray(P0a, float)))
    Rj = jnp.asarray(Rn, float)
    LQ_fixed = jnp.asarray(square_root.chol_const(Qn))
    Lu_fixed = inoise.input_factor(kwargs.get("input_noise"), model.input_names)
    if tg.inputs:
        k = len(tg.inputs)
    else:
        k = 0 if Lu_fixed is None else int(np.shape(Lu_fixed)[1])
    theta_base = jnp.asarray(model.theta, float)
    T = ys.shape[0]

    def loglik(values, aux):
        theta, Qv, Rv, y, noise = with_values(tg, theta_base, jnp.asarray(Qn), Rj, ys, values)
        LQ = jnp.linalg.cholesky(Qv) if tg.q_std else LQ_fixed
        Lu = inoise.input_factor(noise, model.input_names) if tg.inputs else Lu_fixed
        Lu = None if Lu is None else jnp.asarray(Lu, float)
        return correlated.log_likelihood(model.transition, model.observe, y, us, theta, x0a, L0,
                                         LQ, Rv, jnp.zeros(model.ny), aux, Lu)

    def draw(key):
        return correlated.draw_aux(key, T, n, model.nx, k)

    return loglik, draw


def log_likelihood_difference_spread(correlated_estimate, model, measurements, inputs=None, *,
                                     x0, P0, Q, R, values, key, n_evals: int = 32):
    """How correlated the correlated estimates are, at fixed ``values`` (dict name -> physical
    value): over ``n_evals`` draws of aux, the std [nats] of log p_hat(y | values, aux') - log
    p_hat(y | values, aux) with aux' aux's Crank-Nicolson move (``correlated_estimate``: a
    :class:`Correlated`, its correlation rho), which is the noise the correlated chain's
    acceptance ratio sees, and the std of log p_hat(y | values, aux) itself (independent
    estimates, the plain PMMH chain's). Returns (std of the difference, std of the estimate)
    (:func:`cpm_log_likelihood_fn`)."""
    n_evals = validation.integer("n_evals", n_evals, 2, MAX_EVALS)
    names = tuple(values)
    loglik, draw = cpm_log_likelihood_fn(correlated_estimate, model, measurements, inputs, x0=x0,
                                         P0=P0, Q=Q, R=R, names=names)
    rho = correlated_estimate.correlation
    v = jnp.asarray([float(values[n]) for n in names])

    def pair(k):
        ka, ke = jax.random.split(k)
        aux = draw(ka)
        return loglik(v, aux), loglik(v, correlated.crank_nicolson(aux, draw(ke), rho))

    a, b = (np.asarray(t) for t in jax.jit(jax.vmap(pair))(jax.random.split(key, n_evals)))
    return float(np.std(b - a, ddof=1)), float(np.std(a, ddof=1))


def log_likelihood_spread(builder, model, measurements, inputs=None, *, x0, P0, Q, R, values,
                          key, n_evals: int = 32):
    """The std [nats] of a particle filter's log-likelihood estimate at fixed ``values`` (dict
    name -> physical value, as the priors of :func:`pmmh`), over ``n_evals`` keys (vmapped),
    and its mean: (std, mean). ``builder`` as :func:`log_likelihood_fn`'s. Doucet, Pitt,
    Deligiannidis & Kohn (2015, Biometrika 102(2)): PMMH is most efficient for its cost with
    this std about 1.0-1.5 at the posterior mean; a larger one makes the chain stick."""
    n_evals = validation.integer("n_evals", n_evals, 2, MAX_EVALS)
    names = tuple(values)
    loglik = log_likelihood_fn(builder, model, measurements, inputs, x0=x0, P0=P0, Q=Q, R=R,
                               names=names)
    v = jnp.asarray([float(values[n]) for n in names])
    lls = np.asarray(jax.jit(jax.vmap(lambda k: loglik(v, k)))(jax.random.split(key, n_evals)))
    return float(np.std(lls, ddof=1)), float(np.mean(lls))
