"""Offline calibration by particle MCMC: particle marginal Metropolis-Hastings (:func:`pmmh`) and
particle Gibbs with ancestor sampling (:func:`particle_gibbs`).

Andrieu, Doucet & Holenstein (2010), "Particle Markov chain Monte Carlo methods", JRSS B 72(3):
a Metropolis-Hastings chain over the unknown quantities phi whose acceptance ratio uses a particle
filter's estimate of the likelihood p(y_1:T | phi) in place of the exact one. The estimate is
unbiased, so the chain's stationary distribution is the exact posterior p(phi | y_1:T), whatever
the number of particles (fewer particles only make the chain stickier). Paper 004 (Berntorp &
Di Cairano) judges its online estimates against such an offline reference (its sec. 5, ref. [28]).

What is calibrated (``priors``, a dict name -> prior):

* a model parameter by its name (``"cf"``), in the parameter's units;
* ``"R:<output>"``: the measurement-noise std of that output [output units];
* ``"Q:<state>"``: the process-noise std of that state [state units per step];
* ``"bias:<output>"``: a constant sensor bias, y = h(x, u) + bias + noise [output units];
* ``"input:<input>"``: the std of noise entering through that input [input units], for builders
  that take ``input_noise`` (every vehjax filter).

Likelihoods: any vehjax filter builder (:func:`log_likelihood_fn`); for PMMH the bootstrap PF
or :func:`fixed_noise_mpf`, paper 004's marginalized PF with its noise statistics held at the
chain's values (each particle a sequence of input-noise draws with a Kalman filter over every
state given them), whose estimate varies far less where the model is affine in the states.

Each prior (:class:`Normal`, :class:`LogNormal`, :class:`Uniform`) carries its bijection to the
real line (identity, log, logit). The chain moves in that unconstrained space with a Gaussian
random walk, and the target there is the posterior times the Jacobian of the map back:
log p(y | x(z)) + log p(x(z)) + log |dx/dz|.

Proposal: the random-walk covariance starts as ``(0.1 * prior scale)^2`` per coordinate
(unconstrained units) unless ``proposal_std`` is given. With ``adapt`` the warm-up is cut into
windows of doubling length (:func:`adaptation_windows`; the first 80 % of it); after each the
proposal becomes s^2 (2.38^2 / d) C (Roberts & Rosenthal 2001's scaling) with C the covariance of
that window's draws pooled over chains, shrunk toward the previous estimate
(:func:`adapted_covariance`), and s a scale tuned toward a target acceptance rate
(:func:`scale_update`; :func:`target_acceptance`: 0.44 for d = 1 to 0.234 for an exact
likelihood, lower for a noisy estimate). Later windows are longer, so the estimate settles as the chains
reach the posterior; strongly correlated quantities get a proposal along their correlation. The
proposal is fixed after the last window, so the draws kept after warm-up come from a plain
Metropolis-Hastings chain. :func:`log_likelihood_spread` measures the particle filter's
log-likelihood noise, which should be about 1-1.5 at the posterior (Doucet et al. 2015).

Correlated pseudo-marginal (``pmmh(..., correlation=rho)``, Deligiannidis, Doucet & Pitt 2018):
the chain carries the bootstrap PF's random numbers and moves them by a Crank-Nicolson step with
each proposal (:func:`cpm_log_likelihood_fn`, :mod:`vehjax._cpm`), so that the acceptance ratio
compares two strongly correlated estimates; :func:`log_likelihood_difference_spread` measures
how correlated they are.

Random streams: one ``key`` is split into one key per chain; iteration i of chain c draws its
proposal, its accept uniform and its particle filter's key from ``fold_in(key_c, i + 1)``
(the starting values' likelihood from ``fold_in(key_c, 0)``), so a run
is reproducible and a chain's draws do not depend on the number of chains.

Particle Gibbs with ancestor sampling (Lindsten, Jordan & Schon 2014, JMLR 15; paper 004's
[29]) alternates a conditional particle filter with ancestor sampling, which draws a state
trajectory given the current values and the previous trajectory, with Metropolis-Hastings moves of
the values given the trajectory on the exact joint density p(x_0:T, y | values). It needs the
transition density, so the process noise must be additive Gaussian with Q positive definite;
it mixes with a few tens of particles where PMMH needs the likelihood estimate's variance near 1.

Chains are vmapped (one particle filter per chain per iteration, all in one ``lax.scan``).
Diagnostics: split R-hat (:func:`split_rhat`, Gelman et al., BDA3 sec. 11.4) and the
effective sample size (:func:`effective_sample_size`, BDA3 sec. 11.5 with Geyer's initial
positive sequence) of every quantity.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from . import _validate

__all__ = ["Normal", "LogNormal", "Uniform", "PMMHResult", "pmmh", "log_likelihood_fn",
           "log_likelihood_spread", "cpm_log_likelihood_fn", "log_likelihood_difference_spread",
           "fixed_noise_mpf", "target_acceptance", "adaptation_windows",
           "adapted_covariance", "scale_update", "proposal_factor",
           "particle_gibbs", "conditional_pf_as", "log_joint", "split_rhat",
           "effective_sample_size"]

_LOG_2PI = math.log(2.0 * math.pi)


# -- priors ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class Normal:
    """Normal prior N(mean, std^2) on the real line; unconstrained coordinate z = x."""

    mean: float
    std: float

    def __post_init__(self):
        _validate.number("Normal.mean", self.mean)
        _validate.number("Normal.std", self.std, 0.0)

    def to_unconstrained(self, x):
        return jnp.asarray(x, float)

    def from_unconstrained(self, z):
        return z

    def log_density(self, x):
        return -0.5 * ((x - self.mean) / self.std) ** 2 - math.log(self.std) - 0.5 * _LOG_2PI

    def log_jacobian(self, z):
        """log |dx/dz| at z."""
        return 0.0 * z

    center = property(lambda self: self.mean)
    scale = property(lambda self: self.std)  # in unconstrained units


@dataclass(frozen=True)
class LogNormal:
    """Positive quantity with log x ~ N(log median, sigma^2); z = log x."""

    median: float
    sigma: float

    def __post_init__(self):
        _validate.number("LogNormal.median", self.median, 0.0)
        _validate.number("LogNormal.sigma", self.sigma, 0.0)

    def to_unconstrained(self, x):
        return jnp.log(jnp.asarray(x, float))

    def from_unconstrained(self, z):
        return jnp.exp(z)

    def log_density(self, x):
        lx = jnp.log(x)
        return (-0.5 * ((lx - math.log(self.median)) / self.sigma) ** 2 - math.log(self.sigma)
                - 0.5 * _LOG_2PI - lx)

    def log_jacobian(self, z):
        return z

    center = property(lambda self: self.median)
    scale = property(lambda self: self.sigma)


@dataclass(frozen=True)
class Uniform:
    """Uniform prior on (low, high); z = logit((x - low) / (high - low))."""

    low: float
    high: float

    def __post_init__(self):
        lo = _validate.number("Uniform.low", self.low)
        _validate.number("Uniform.high", self.high, lo)

    def to_unconstrained(self, x):
        p = (jnp.asarray(x, float) - self.low) / (self.high - self.low)
        return jnp.log(p) - jnp.log1p(-p)

    def from_unconstrained(self, z):
        return self.low + (self.high - self.low) * jax.nn.sigmoid(z)

    def log_density(self, x):
        inside = (x > self.low) & (x < self.high)
        return jnp.where(inside, -math.log(self.high - self.low), -jnp.inf)

    def log_jacobian(self, z):
        return math.log(self.high - self.low) + jax.nn.log_sigmoid(z) + jax.nn.log_sigmoid(-z)

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


# -- the likelihood -------------------------------------------------------------------------
class _Targets(NamedTuple):
    params: tuple      # (index in priors, index in theta)
    r_std: tuple       # (index in priors, output index)
    q_std: tuple       # (index in priors, state index)
    bias: tuple        # (index in priors, output index)
    inputs: tuple      # (index in priors, input name)


def _targets(model, names) -> _Targets:
    params, r_std, q_std, bias, inputs = [], [], [], [], []
    for i, name in enumerate(names):
        kind, _, what = name.partition(":")
        table = {"R": (model.output_names, r_std), "Q": (model.state_names, q_std),
                 "bias": (model.output_names, bias), "input": (model.input_names, inputs)}
        if what and kind in table:
            known, dest = table[kind]
            if what not in known:
                raise ValueError(f"priors: {name!r}: no {what!r} among {tuple(known)}")
            dest.append((i, what if kind == "input" else known.index(what)))
        elif name in model.param_names:
            params.append((i, model.param_names.index(name)))
        else:
            raise ValueError(
                f"priors: unknown name {name!r}; expected a model parameter {model.param_names} "
                f"or 'R:<output>', 'Q:<state>', 'bias:<output>', 'input:<input>'")
    return _Targets(tuple(params), tuple(r_std), tuple(q_std), tuple(bias), tuple(inputs))


def _with_values(tg: _Targets, theta, Q, R, ys, values):
    """The named quantities set to ``values`` (d,) physical: (theta (np,), Q (nx, nx) with the
    ``Q:`` variances, R (ny, ny) with the ``R:`` variances, ys (T, ny) minus the ``bias:``
    values, the ``input:`` stds as a dict input name -> std, None without)."""
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


def log_likelihood_fn(builder, model, measurements, inputs, *, x0, P0, Q, R, names,
                      builder_kwargs=None):
    """``loglik(values (d,), key) -> ()``: the filter's log-likelihood estimate of the data with
    the quantities ``names`` (see the module docstring) set to ``values`` (physical units).

    ``builder(model, Q, R, **builder_kwargs)`` builds the filter (``vehjax.filters.bootstrap_pf``
    for PMMH; a Kalman filter's exact likelihood gives plain Metropolis-Hastings). Q, R: (n,)
    variances or (n, n) covariances; named stds replace their diagonal entries. A run that
    diverges (or re-initialises its particles) has likelihood zero (-inf).
    """
    from .filtering import filter as run_filter

    tg = _targets(model, names)
    ys, us = _validate.data(measurements, inputs, model.ny, model.nu, "one")
    ys, us = jnp.asarray(ys, float), jnp.asarray(us, float)
    Q = jnp.asarray(_validate.cov("Q", Q, model.nx, allow_psd=True))
    R = jnp.asarray(_validate.cov("R", R, model.ny))
    kwargs = dict(builder_kwargs or {})
    if tg.inputs and "input_noise" in kwargs:
        raise ValueError("builder_kwargs: input_noise is calibrated ('input:' priors); drop it")
    theta_base = jnp.asarray(model.theta, float)

    def loglik(values, key):
        theta, Qv, Rv, y, noise = _with_values(tg, theta_base, Q, R, ys, values)
        kw = dict(kwargs)
        if tg.inputs:
            kw["input_noise"] = noise
        est = builder(model, Qv, Rv, **kw)
        res = run_filter(est, y, us, x0=x0, P0=P0, theta0=theta, key=key,
                         return_covariances=False)
        ll = jnp.sum(res.loglik)
        return jnp.where(res.diverged | ~jnp.isfinite(ll), -jnp.inf, ll)

    return loglik


# -- the correlated pseudo-marginal likelihood ----------------------------------------------
#: ``builder_kwargs`` of the bootstrap PF that the correlated estimate (:mod:`vehjax._cpm`)
#: reproduces; it resamples systematically at every step
_CPM_KWARGS = ("n_particles", "resampling", "input_noise")


def _check_correlation(correlation):
    """``correlation`` (rho of the Crank-Nicolson move) as a float in (0, 1); ValueError."""
    import numbers

    ok = isinstance(correlation, numbers.Real) and not isinstance(correlation, (bool, np.bool_))
    rho = float(correlation) if ok else float("nan")
    if not 0.0 < rho < 1.0:
        raise ValueError(f"correlation: expected a number in (0, 1) (the Crank-Nicolson move's "
                         f"rho), got {correlation!r}")
    return rho


def cpm_log_likelihood_fn(builder, model, measurements, inputs, *, x0, P0, Q, R, names,
                          builder_kwargs=None):
    """The bootstrap PF's log-likelihood estimate as a function of its random numbers, for the
    correlated pseudo-marginal method: ``(loglik(values (d,), aux) -> (), draw(key) -> aux)``,
    aux a :class:`vehjax._cpm.Aux` of standard normals (:func:`vehjax._cpm.log_likelihood`:
    particles sorted along a Hilbert curve (the default ``sort``) and resampled systematically at
    every step). The same model and likelihood as :func:`log_likelihood_fn` with
    ``vehjax.filters.bootstrap_pf``; ``values`` as there.

    Raises:
        ValueError: ``builder`` not ``vehjax.filters.bootstrap_pf`` (the only filter whose
            random numbers this reproduces), or ``builder_kwargs`` other than ``n_particles``,
            ``resampling="systematic"`` and ``input_noise``.
    """
    from . import _cpm
    from .filters import bootstrap_pf
    from .filters import input_noise as _inoise
    from .filters._model import chol_const

    if builder is not bootstrap_pf:
        raise ValueError(f"correlation: the correlated estimate is written for "
                         f"vehjax.filters.bootstrap_pf only, got builder {builder!r}; use "
                         f"correlation=None")
    kwargs = dict(builder_kwargs or {})
    extra = sorted(set(kwargs) - set(_CPM_KWARGS))
    if extra or kwargs.get("resampling", "systematic") != "systematic":
        raise ValueError(f"builder_kwargs: with correlation the bootstrap PF resamples "
                         f"systematically at every step and takes only {_CPM_KWARGS} "
                         f"(resampling='systematic'), got {kwargs!r}")
    n = _validate.integer("n_particles", kwargs.get("n_particles", 1000), 2)
    tg = _targets(model, names)
    if tg.inputs and "input_noise" in kwargs:
        raise ValueError("builder_kwargs: input_noise is calibrated ('input:' priors); drop it")
    ys, us = _validate.data(measurements, inputs, model.ny, model.nu, "one")
    ys, us = jnp.asarray(ys, float), jnp.asarray(us, float)
    x0a, P0a = _validate.prior(model.nx, x0, P0)
    x0a, L0 = jnp.asarray(x0a, float), jnp.asarray(np.linalg.cholesky(np.asarray(P0a, float)))
    Qn = np.asarray(_validate.cov("Q", Q, model.nx, allow_psd=True), float)
    Rj = jnp.asarray(_validate.cov("R", R, model.ny), float)
    LQ_fixed = jnp.asarray(chol_const(Qn))
    Lu_fixed = _inoise.input_factor(kwargs.get("input_noise"), model.input_names)
    if tg.inputs:
        k = len(tg.inputs)
    else:
        k = 0 if Lu_fixed is None else int(np.shape(Lu_fixed)[1])
    theta_base = jnp.asarray(model.theta, float)
    T = ys.shape[0]

    def loglik(values, aux):
        theta, Qv, Rv, y, noise = _with_values(tg, theta_base, jnp.asarray(Qn), Rj, ys, values)
        LQ = jnp.linalg.cholesky(Qv) if tg.q_std else LQ_fixed
        Lu = _inoise.input_factor(noise, model.input_names) if tg.inputs else Lu_fixed
        Lu = None if Lu is None else jnp.asarray(Lu, float)
        return _cpm.log_likelihood(model.transition, model.observe, y, us, theta, x0a, L0, LQ,
                                   Rv, jnp.zeros(model.ny), aux, Lu)

    def draw(key):
        return _cpm.draw_aux(key, T, n, model.nx, k)

    return loglik, draw


def log_likelihood_difference_spread(builder, model, measurements, inputs=None, *, x0, P0, Q,
                                     R, values, key, correlation, n_evals: int = 32,
                                     builder_kwargs=None):
    """How correlated the correlated estimates are, at fixed ``values`` (dict name -> physical
    value): over ``n_evals`` draws of aux, the std [nats] of log p_hat(y | values, aux') - log
    p_hat(y | values, aux) with aux' aux's Crank-Nicolson move (``correlation`` rho), which is
    the noise the correlated chain's acceptance ratio sees, and the std of log p_hat(y | values,
    aux) itself (independent estimates, the plain PMMH chain's). Returns (std of the
    difference, std of the estimate) (:func:`cpm_log_likelihood_fn`)."""
    from . import _cpm

    rho = _check_correlation(correlation)
    names = tuple(values)
    loglik, draw = cpm_log_likelihood_fn(builder, model, measurements, inputs, x0=x0, P0=P0,
                                         Q=Q, R=R, names=names, builder_kwargs=builder_kwargs)
    v = jnp.asarray([float(values[n]) for n in names])
    n_evals = _validate.integer("n_evals", n_evals, 2)

    def pair(k):
        ka, ke = jax.random.split(k)
        aux = draw(ka)
        return loglik(v, aux), loglik(v, _cpm.crank_nicolson(aux, draw(ke), rho))

    a, b = (np.asarray(t) for t in jax.jit(jax.vmap(pair))(jax.random.split(key, n_evals)))
    return float(np.std(b - a, ddof=1)), float(np.std(a, ddof=1))


# -- the marginalized PF's likelihood with fixed noise statistics -----------------------------
#: :func:`fixed_noise_mpf`'s NiW prior: gamma0 (the offset's and biases' prior variance over the
#: noise variance) and nu0 (degrees of freedom), so small and so large that the statistics stay
#: at the given values over a drive (forgetting 1: a datum moves gamma by a relative 1e-12 and a
#: covariance by about 1 / nu0 of itself); the Student-t predictive is then Gaussian to ~1 / nu0.
FIXED_GAMMA0, FIXED_NU0 = 1e-12, 1e8


def _fixed_noise_model(model, noisy_input: str):
    """The model :func:`fixed_noise_mpf` runs the marginalized PF on: states ``("_const",) +
    model.state_names`` (a constant, unobserved first state: the filter needs a particle
    state; every model state is a Kalman state), inputs ``model.input_names + ("_<input>_h",)
    + model.param_names``: the noisy input enters the transition, its noise-free copy the
    observation (so the input noise is process noise only, as the Gaussian filters'
    ``input_noise``), and the model's parameters arrive as inputs (they may be traced values
    of a PMMH chain). No parameters of its own."""
    from .models import Model

    nu = len(model.input_names)
    i = model.input_names.index(noisy_input)

    def f(X, U, th):
        del th
        return jnp.concatenate([X[:1], model.transition(X[1:], U[:nu], U[nu + 1:])])

    def h(X, U, th):
        del th
        return model.observe(X[1:], U[:nu].at[i].set(U[nu]), U[nu + 1:])

    return Model(f, h, model.dt, ("_const",) + tuple(model.state_names),
                 input_names=tuple(model.input_names) + (f"_{noisy_input}_h",)
                 + tuple(f"_theta_{n}" for n in model.param_names),
                 output_names=tuple(model.output_names), fast_math=False)


def _fixed_noise_filter(aug, n_particles, name, q_std, resampling, ess_threshold):
    """:func:`vehjax.filters.marginalized_pf` on :func:`_fixed_noise_model`'s ``aug`` with
    the statistics held (placeholder stds 1: :func:`fixed_noise_mpf`'s ``init`` sets them)."""
    from .filters import NiW, marginalized_pf

    states = aug.state_names[1:]
    return marginalized_pf(
        aug, n_particles, noisy_input=name, sensors=tuple(aug.output_names),
        linear_states=states, linear_noise_std=q_std,
        niw=NiW(std0={k: 1.0 for k in (name,) + tuple(aug.output_names)}, forgetting=1.0,
                gamma0=FIXED_GAMMA0, nu0=FIXED_NU0), kalman_states="all", resampling=resampling,
        ess_threshold=ess_threshold)


def fixed_noise_mpf(model, Q, R, *, input_noise, n_particles: int = 100,
                    resampling: str = "systematic", ess_threshold: float = 0.5):
    """A builder for :func:`pmmh` / :func:`log_likelihood_fn`: the marginalized PF of paper 004
    (:func:`vehjax.filters.marginalized_pf`, ``kalman_states="all"``) with its noise statistics
    fixed at the given values, as a state-only estimator of ``model``'s states.

    Model: x_t = f(x_{t-1}, u_t + w_t, theta) + v_t, y_t = h(x_t, u_t, theta) + e_t, with
    w_t ~ N(0, s^2) on the one input named in ``input_noise`` (s its std, input units),
    v_t ~ N(0, diag Q), e_t ~ N(0, diag R): the model of a Gaussian filter given the same Q, R
    and ``input_noise`` (exact for it where f and h are affine in x and u). Every model state is
    in each particle's Kalman filter; a particle is a sequence of input-noise draws w_1:t, each
    drawn from its conditional given y_t, weighted by the predictive of y_t given the
    particle's past (a fully adapted, Rao-Blackwellised PF): its likelihood estimate is
    unbiased, with far less variance than the bootstrap PF's. The NiW statistics start at
    offset 0, biases 0, the stds s and sqrt(diag R), with gamma0, nu0 =
    :data:`FIXED_GAMMA0`, :data:`FIXED_NU0` and forgetting 1, so they stay there.

    Args:
        model: a vehjax model affine in its states and in the noisy input (the filter checks).
        Q: (nx,) variances or (nx, nx) (its diagonal is used) per step, concrete (not
            calibrated: ``Q:`` priors are refused).
        R: (ny,) variances or (ny, ny) (its diagonal is used: the outputs' noises independent).
        input_noise: dict with one entry, input name -> std [input units] (may be traced).
        n_particles, resampling, ess_threshold: as :func:`vehjax.filters.marginalized_pf`.

    Returns:
        ``Estimator``: state-only (``theta0`` replaces the model's parameters), ``needs_key``.
    """
    from .filters.base import Estimator, StepOutput

    if not isinstance(input_noise, Mapping) or len(input_noise) != 1:
        raise ValueError(f"input_noise: expected one input name -> std, got {input_noise!r}")
    (name, s_u), = input_noise.items()
    if name not in model.input_names:
        raise ValueError(f"input_noise: {name!r} not among the inputs {model.input_names}")
    try:
        Qd = np.asarray(Q, float)
    except jax.errors.TracerArrayConversionError:
        raise ValueError("Q: fixed_noise_mpf takes a fixed Q (its values set the Kalman "
                         "filters' noise when built); drop the 'Q:' priors") from None
    q_std = np.sqrt(np.diag(Qd) if Qd.ndim == 2 else Qd)
    R = jnp.asarray(R, float)
    r_std = jnp.sqrt(jnp.diag(R) if R.ndim == 2 else R)
    aug = _fixed_noise_model(model, name)
    ny, nx = len(model.output_names), len(model.state_names)
    # built from concrete values only (its model checks run numerically), also when the
    # builder is called under a PMMH chain's trace
    with jax.ensure_compile_time_eval():
        mpf = _fixed_noise_filter(aug, n_particles, name, q_std, resampling, ess_threshold)
    i_u = model.input_names.index(name)
    theta_model = jnp.asarray(model.theta, float)

    def init(x0, P0, theta0=None, P_theta0=None, key=None):
        del P_theta0
        x0 = jnp.asarray(x0, float)
        P0 = jnp.asarray(P0, float)
        P0 = jnp.diag(P0) if P0.ndim == 1 else P0
        Pa = jnp.zeros((nx + 1, nx + 1)).at[0, 0].set(1.0).at[1:, 1:].set(P0)
        stats = jnp.concatenate([jnp.stack([0.0, jnp.asarray(s_u, float)]), jnp.zeros(ny),
                                 r_std])
        th = theta_model if theta0 is None else jnp.asarray(theta0, float)
        return mpf.init(jnp.concatenate([jnp.zeros(1), x0]), Pa, stats, None, key), th

    def step(state, y, u):
        st, th = state
        st, out = mpf.step(st, y, jnp.concatenate([u, u[i_u:i_u + 1], th]))
        return (st, th), StepOutput(
            mean=out.mean[1:], cov=out.cov[1:, 1:], loglik=out.loglik, nis=out.nis,
            n_obs=out.n_obs, params=jnp.zeros((0,), out.mean.dtype),
            params_cov=jnp.zeros((0, 0), out.mean.dtype), reinit=out.reinit)

    return Estimator(init=init, step=step, nx=nx, name="fixed_noise_mpf", needs_key=True,
                     ny=ny, nu=len(model.input_names), workload="small_dense",
                     n_theta=len(model.param_names))


# -- the chain ------------------------------------------------------------------------------
class _Chain(NamedTuple):
    z: jnp.ndarray          # (d,) unconstrained
    log_target: jnp.ndarray  # () log-lik estimate + log prior of z
    loglik: jnp.ndarray      # () the estimate held with z
    aux: object = None       # correlated estimates: the random numbers of that estimate


def _mh_iteration(loglik, priors, L_prop, key_chain, move=None):
    """One PMMH step of one chain: ``(chain, i) -> (chain, (z, loglik, accepted))``. Without
    ``move`` the estimate is drawn afresh from the iteration's key (``loglik(values, key)``);
    with it (correlated pseudo-marginal) the chain carries the estimate's random numbers and
    proposes ``move(aux, key)`` with z, accepted or rejected together (``loglik(values, aux)``)."""

    def step(chain: _Chain, i):
        k = jax.random.fold_in(key_chain, i + 1)
        k_prop, k_acc, k_pf = jax.random.split(k, 3)
        z_new = chain.z + L_prop @ jax.random.normal(k_prop, chain.z.shape, chain.z.dtype)
        if move is None:
            aux_new = None
            ll_new = loglik(to_physical(priors, z_new), k_pf)
        else:
            aux_new = move(chain.aux, k_pf)
            ll_new = loglik(to_physical(priors, z_new), aux_new)
        lt_new = ll_new + log_prior_unconstrained(priors, z_new)
        lt_new = jnp.where(jnp.isfinite(lt_new), lt_new, -jnp.inf)
        accept = jnp.log(jax.random.uniform(k_acc, (), chain.z.dtype)) < lt_new - chain.log_target
        aux = None if move is None else jax.tree_util.tree_map(
            lambda a, b: jnp.where(accept, a, b), aux_new, chain.aux)
        new = _Chain(jnp.where(accept, z_new, chain.z), jnp.where(accept, lt_new, chain.log_target),
                     jnp.where(accept, ll_new, chain.loglik), aux)
        return new, (new.z, new.loglik, accept)

    return step


#: Roberts, Gelman & Gilks (1997): the random walk's optimal scale on a d-dimensional Gaussian
#: target is 2.38 / sqrt(d) times the target's covariance, where the acceptance is 0.234
RW_SCALE, RW_ACCEPTANCE = 2.38, 0.234


#: the optimal random walk's acceptance rate on a d-dimensional Gaussian target, d = 1..10
#: (Gelman, Roberts & Gilks 1996, Bayesian Statistics 5, table 1); 0.234 beyond
_RW_ACCEPTANCE_D = (0.441, 0.352, 0.316, 0.279, 0.275, 0.266, 0.261, 0.255, 0.25, 0.247)


def target_acceptance(d: int, loglik_std=0.0):
    """The acceptance rate to tune a random walk toward in d dimensions when the log-likelihood
    is estimated with Gaussian noise of std ``loglik_std`` [nats]: the exact-likelihood optimum
    a_d (Gelman, Roberts & Gilks 1996: 0.44 for d = 1 down to 0.234 for large d) times the
    factor the noise takes off it at the large-d optimal scale l = 2.38 (Sherlock, Thiery,
    Roberts & Rosenthal 2015, Ann. Statist. 43(1): acceptance 2 Phi(-sqrt(l^2 + 2 sigma^2) / 2),
    0.234 at sigma = 0, 0.144 at 1.2, 0.11 at 1.5). Dimensionless, in (0, 1)."""
    d = _validate.integer("d", d, 1)
    s = float(loglik_std)
    a_d = _RW_ACCEPTANCE_D[d - 1] if d <= len(_RW_ACCEPTANCE_D) else RW_ACCEPTANCE
    noisy = math.erfc(0.5 * math.sqrt(RW_SCALE**2 + 2.0 * s * s) / math.sqrt(2.0))
    return a_d * noisy / math.erfc(0.5 * RW_SCALE / math.sqrt(2.0))


def adaptation_windows(warmup: int, windows: int) -> np.ndarray:
    """The iterations (1-based counts) after which the warm-up re-estimates the proposal:
    ``windows`` windows whose lengths double (1, 2, 4, ...) and fill the first 80 % of the
    warm-up; the last 20 % runs with the final proposal. (k,) ints, strictly increasing, k <=
    windows (windows shorter than 4 iterations merged into the next); empty for 0 windows."""
    if windows <= 0 or warmup < 2:
        return np.zeros(0, int)
    span = max(1, int(0.8 * warmup))
    w = 2.0 ** np.arange(windows)
    ends = np.unique(np.round(span * np.cumsum(w) / w.sum()).astype(int))
    keep = np.diff(np.concatenate([[0], ends])) >= 4
    keep[-1] = True
    ends = ends[keep]
    return ends[ends >= 1]


def adapted_covariance(s1, s2, count, cov_prev, prior_count):
    """The target's covariance estimated from one window's draws pooled over chains, shrunk
    toward the previous estimate: (count C + prior_count cov_prev) / (count + prior_count), C the
    draws' covariance (ddof 1) from their sums s1 = sum z (d,), s2 = sum z z^T (d, d) over
    ``count`` draws (unconstrained units). The shrinkage keeps a short window whose chains
    barely moved from collapsing the proposal. (d, d), symmetric."""
    mean = s1 / count
    cov = (s2 - count * jnp.outer(mean, mean)) / (count - 1)
    cov = (count * cov + prior_count * cov_prev) / (count + prior_count)
    return 0.5 * (cov + cov.T)


def scale_update(log_scale, acceptance, target):
    """The random walk's log scale after a window with acceptance rate ``acceptance``, toward
    ``target``: for a random walk of scale l (in units of the target's std) on a Gaussian target
    the acceptance is 2 Phi(-l / 2) (Roberts, Gelman & Gilks 1997), so the scale that gives
    ``target`` is the current one times Phi^-1(target / 2) / Phi^-1(acceptance / 2). The
    acceptance is clipped to [0.005, 0.95] and the factor to [1/4, 4] (one window's estimate).
    Scalars in, scalar out (log of a dimensionless factor)."""
    a = jnp.clip(acceptance, 0.005, 0.95)
    ratio = jax.scipy.stats.norm.ppf(0.5 * target) / jax.scipy.stats.norm.ppf(0.5 * a)
    return log_scale + jnp.log(jnp.clip(ratio, 0.25, 4.0))


def proposal_factor(cov, log_scale, L_prev):
    """The random walk's Cholesky factor exp(log_scale) chol((2.38^2 / d) cov) (plus a 1e-10
    relative jitter), or ``L_prev`` when that is not positive definite. (d, d) lower."""
    d = cov.shape[0]
    cov = cov + 1e-10 * jnp.maximum(1.0, jnp.max(jnp.diag(cov))) * jnp.eye(d)
    L = jnp.exp(log_scale) * jnp.linalg.cholesky((RW_SCALE**2 / d) * cov)
    return jnp.where(jnp.all(jnp.isfinite(L)), L, L_prev)


class _Adapt(NamedTuple):
    """The warm-up's adaptation state: the target's covariance estimate and the proposal's log
    scale, the proposal factor they give, and the current window's sums."""
    cov: jnp.ndarray        # (d, d) unconstrained
    log_scale: jnp.ndarray  # ()
    L: jnp.ndarray          # (d, d) proposal factor in use
    s1: jnp.ndarray         # (d,) window sums
    s2: jnp.ndarray         # (d, d)
    n: jnp.ndarray          # () draws in the window (over chains)
    acc: jnp.ndarray        # () accepted moves in the window


def _adapt_init(L0):
    """Adaptation state whose proposal is L0: cov = L0 L0^T d / 2.38^2, scale 1."""
    d = L0.shape[0]
    z = jnp.zeros((), L0.dtype)
    return _Adapt(L0 @ L0.T * d / RW_SCALE**2, z, L0, jnp.zeros(d, L0.dtype),
                  jnp.zeros((d, d), L0.dtype), z, z)


def _adapt_step(ad: _Adapt, i, z, accepted, ends, target, prior_count):
    """After iteration i (0-based) with draws z (C, d) and acceptances (C,) (or rates): add
    them to the window; at a window's end (i + 1 in ``ends``) re-estimate the covariance
    (:func:`adapted_covariance`) and the scale (:func:`scale_update`), set the proposal
    (:func:`proposal_factor`) and start a new window."""
    s1, s2 = ad.s1 + z.sum(axis=0), ad.s2 + z.T @ z
    n, acc = ad.n + z.shape[0], ad.acc + jnp.sum(accepted)
    ad = ad._replace(s1=s1, s2=s2, n=n, acc=acc)
    if len(ends) == 0:
        return ad

    def update(ad):
        cov = adapted_covariance(ad.s1, ad.s2, ad.n, ad.cov, prior_count)
        cov = jnp.where(jnp.all(jnp.isfinite(cov)), cov, ad.cov)
        ls = scale_update(ad.log_scale, ad.acc / ad.n, target)
        zero = jnp.zeros_like(ad.n)
        return _Adapt(cov, ls, proposal_factor(cov, ls, ad.L), 0.0 * ad.s1, 0.0 * ad.s2, zero,
                      zero)

    # only at a window's end (a branch, not a select: the rest of the time costs nothing)
    return jax.lax.cond(jnp.any(i + 1 == jnp.asarray(ends)), update, lambda ad: ad, ad)


def _sampler(loglik, priors, n_iter: int, ends, target: float, prior_count: float,
             draw=None, move=None):
    """``(keys (C,), z0 (C, d), L0 (d, d)) -> (draws (C, n, d), logliks (C, n), accepted (C, n),
    L, starting log targets (C,))``: the starting values' likelihoods, then ``n_iter``
    iterations of every chain (one ``lax.scan`` over iterations, the chains vmapped inside it),
    the proposal re-estimated from the pooled draws after each iteration count in ``ends``
    (:func:`_adapt_step`; empty: never). Correlated estimates: ``draw(key) -> aux`` the
    starting random numbers (from ``fold_in(key_c, 0)``), ``move(aux, key) -> aux`` their
    proposal (:func:`_mh_iteration`)."""

    def first(key, z):
        if draw is None:
            ll = loglik(to_physical(priors, z), jax.random.fold_in(key, 0))
            return _Chain(z, ll + log_prior_unconstrained(priors, z), ll)
        aux = draw(jax.random.fold_in(key, 0))
        ll = loglik(to_physical(priors, z), aux)
        return _Chain(z, ll + log_prior_unconstrained(priors, z), ll, aux)

    def run(keys, z0, L0):
        chains = jax.vmap(first)(keys, z0)

        def body(carry, i):
            chains, ad = carry
            chains, out = jax.vmap(
                lambda k, c: _mh_iteration(loglik, priors, ad.L, k, move)(c, i))(keys, chains)
            ad = _adapt_step(ad, i, out[0], out[2], ends, target, prior_count)
            return (chains, ad), out

        (_, ad), (zs, lls, acc) = jax.lax.scan(body, (chains, _adapt_init(L0)),
                                               jnp.arange(n_iter))
        return (jnp.swapaxes(zs, 0, 1), jnp.swapaxes(lls, 0, 1), jnp.swapaxes(acc, 0, 1), ad.L,
                chains.log_target)

    return jax.jit(run)


def log_likelihood_spread(builder, model, measurements, inputs=None, *, x0, P0, Q, R, values,
                          key, n_evals: int = 32, builder_kwargs=None):
    """The std [nats] of a particle filter's log-likelihood estimate at fixed ``values`` (dict
    name -> physical value, as the priors of :func:`pmmh`), over ``n_evals`` keys (vmapped),
    and its mean: (std, mean). Doucet, Pitt, Deligiannidis & Kohn (2015, Biometrika 102(2)):
    PMMH is most efficient for its cost with this std about 1.0-1.5 at the posterior mean; a
    larger one makes the chain stick."""
    names = tuple(values)
    loglik = log_likelihood_fn(builder, model, measurements, inputs, x0=x0, P0=P0, Q=Q, R=R,
                               names=names, builder_kwargs=builder_kwargs)
    v = jnp.asarray([float(values[n]) for n in names])
    n_evals = _validate.integer("n_evals", n_evals, 2)
    lls = np.asarray(jax.jit(jax.vmap(lambda k: loglik(v, k)))(jax.random.split(key, n_evals)))
    return float(np.std(lls, ddof=1)), float(np.mean(lls))


class PMMHResult(NamedTuple):
    """The draws of :func:`pmmh` after warm-up and their diagnostics.

    Attributes:
        names: the calibrated quantities, d names.
        samples: (chains, samples, d) draws in physical units.
        loglik: (chains, samples) the likelihood estimate held with each draw.
        acceptance: (chains,) acceptance rate after warm-up.
        mean, std: (d,) posterior mean and std over all chains' draws.
        rhat: (d,) split R-hat (< 1.01 to 1.05 for well-mixed chains).
        ess: (d,) effective sample size over all chains.
        proposal_cov: (d, d) the random walk's covariance after warm-up (unconstrained units).
    """

    names: tuple
    samples: np.ndarray
    loglik: np.ndarray
    acceptance: np.ndarray
    mean: np.ndarray
    std: np.ndarray
    rhat: np.ndarray
    ess: np.ndarray
    proposal_cov: np.ndarray

    def summary(self) -> str:
        """A table: name, mean, std, 2.5 / 97.5 % quantiles, R-hat, ESS."""
        flat = self.samples.reshape(-1, len(self.names))
        lines = [f"{'quantity':>14} {'mean':>12} {'std':>11} {'2.5%':>12} {'97.5%':>12} "
                 f"{'R-hat':>6} {'ESS':>7}"]
        for k, name in enumerate(self.names):
            lo, hi = np.percentile(flat[:, k], [2.5, 97.5])
            lines.append(f"{name:>14} {self.mean[k]:12.5g} {self.std[k]:11.4g} {lo:12.5g} "
                         f"{hi:12.5g} {self.rhat[k]:6.3f} {self.ess[k]:7.0f}")
        lines.append(f"acceptance {np.mean(self.acceptance):.2f} ({self.samples.shape[0]} chains "
                     f"x {self.samples.shape[1]} draws)")
        return "\n".join(lines)


def _check_priors(priors) -> tuple:
    if not isinstance(priors, Mapping) or not priors:
        raise ValueError("priors: expected a non-empty dict name -> Normal/LogNormal/Uniform")
    for name, p in priors.items():
        if not isinstance(p, PRIORS):
            raise ValueError(f"priors: {name!r}: expected Normal, LogNormal or Uniform, got {p!r}")
    return tuple(priors), tuple(priors.values())


def _proposal_factor(priors, proposal_std, proposal_cov=None):
    d = len(priors)
    if proposal_cov is not None:
        if proposal_std is not None:
            raise ValueError("proposal_cov: give proposal_std or proposal_cov, not both")
        C = np.asarray(proposal_cov, float)
        L = np.linalg.cholesky(C) if C.shape == (d, d) and np.all(np.isfinite(C)) \
            and np.allclose(C, C.T) and np.all(np.linalg.eigvalsh(C) > 0) else None
        if L is None:
            raise ValueError(f"proposal_cov: expected a symmetric positive definite ({d}, {d}) "
                             f"matrix (unconstrained units), got {proposal_cov!r}")
        return L
    if proposal_std is None:
        return np.diag([0.1 * p.scale for p in priors])
    s = np.broadcast_to(np.asarray(proposal_std, float), (d,)) if np.ndim(proposal_std) <= 1 \
        else None
    if s is None or not np.all(np.isfinite(s)) or np.any(s <= 0):
        raise ValueError(f"proposal_std: expected a positive number or {d} positive numbers "
                         f"(unconstrained units), got {proposal_std!r}")
    return np.diag(s)


def _starting_values(priors, init, names) -> np.ndarray:
    """(d,) unconstrained starting values: ``init`` where given, else the priors' centres."""
    init = _validate.keyed("init", init, names)
    z0 = np.array([float(p.to_unconstrained(init.get(n, p.center))) for n, p in zip(names, priors)])
    if not np.all(np.isfinite(z0)):
        raise ValueError(f"init: a starting value lies outside its prior's support: {init!r}")
    return z0


def pmmh(builder, model, measurements, inputs=None, *, x0, P0, Q, R, priors, key,
         chains: int = 4, samples: int = 1000, warmup: int = 500, proposal_std=None,
         adapt: bool = True, adapt_windows: int = 5, acceptance_target=None,
         init=None, builder_kwargs=None, proposal_cov=None, correlation=None) -> PMMHResult:
    """Particle marginal Metropolis-Hastings over named quantities of a model and its noise.

    Args:
        builder: filter builder ``builder(model, Q, R, **builder_kwargs)``: for PMMH
            ``vehjax.filters.bootstrap_pf`` (``builder_kwargs={"n_particles": N}``), whose
            likelihood estimate is unbiased, or :func:`fixed_noise_mpf` (the marginalized PF
            with fixed noise statistics: unbiased, far less noisy for models affine in the
            states); a Kalman filter gives exact Metropolis-Hastings.
        model: a vehjax model; its ``theta`` holds the parameters that are not calibrated.
        measurements: (T, ny) one drive, NaN components missing; inputs (T, nu) or None.
        x0, P0: the prior of the state before the first step.
        Q, R: process / measurement noise, (n,) variances or (n, n); named stds replace their
            diagonal entries.
        priors: dict name -> :class:`Normal` / :class:`LogNormal` / :class:`Uniform` (module
            docstring for the names).
        key: PRNG key; every random number of the run comes from it.
        chains: number of chains C >= 2 (vmapped); samples: draws kept per chain; warmup:
            iterations discarded per chain (>= 2 when ``adapt``).
        proposal_std: random-walk std per quantity in unconstrained units (scalar or (d,));
            default 0.1 x the prior's scale.
        proposal_cov: instead of ``proposal_std``, the random walk's starting covariance
            (d, d) in unconstrained units, e.g. a pilot chain's ``PMMHResult.proposal_cov``.
        adapt: re-estimate the proposal during the warm-up (module docstring).
        adapt_windows: how many times (windows of doubling length over the first 80 % of the
            warm-up, :func:`adaptation_windows`).
        acceptance_target: the acceptance rate the scale is tuned toward; default
            ``target_acceptance(d)`` (exact likelihood; 0.44 for d = 1 to 0.234); for a
            particle filter's estimate ``target_acceptance(d, std)`` with the estimate's std
            (:func:`log_likelihood_spread`).
        init: dict name -> starting value (physical); default the prior's centre (median).
        correlation: None (default): every iteration's estimate has its own random numbers
            (the plain pseudo-marginal chain). rho in (0, 1): correlated pseudo-marginal
            (Deligiannidis, Doucet & Pitt 2018): the chain carries the bootstrap PF's random
            numbers aux (:func:`cpm_log_likelihood_fn`, :mod:`vehjax._cpm`), each proposal
            moves them to rho aux + sqrt(1 - rho^2) eps with the random walk's step and both
            are accepted or rejected together; the acceptance ratio then sees the noise of a
            difference of two strongly correlated estimates
            (:func:`log_likelihood_difference_spread`) instead of two independent ones.
            Only for ``builder=vehjax.filters.bootstrap_pf``. rho near 1 (e.g. 0.99 to 0.9999,
            1 - rho about N / T by Deligiannidis et al.'s scaling) keeps that noise small for
            a one-dimensional state; with several states the sorted resampling keeps less of
            the correlation, the less the longer the record (:mod:`vehjax._cpm`): measure it
            with :func:`log_likelihood_difference_spread` before relying on it.

    Returns:
        :class:`PMMHResult`.

    Raises:
        ValueError: naming the argument, for unknown names, bad priors or sizes, or a zero
            likelihood at the starting values; ``correlation`` outside (0, 1) or with a
            builder other than the bootstrap PF.
    """
    names, prs = _check_priors(priors)
    rho = None if correlation is None else _check_correlation(correlation)
    chains = _validate.integer("chains", chains, 2)
    samples = _validate.integer("samples", samples, 4)
    warmup = _validate.integer("warmup", warmup, 2 if adapt else 0)
    adapt_windows = _validate.integer("adapt_windows", adapt_windows, 1)
    if acceptance_target is None:
        acceptance_target = target_acceptance(len(prs))
    acceptance_target = _validate.number("acceptance_target", acceptance_target, 0.0)
    if not acceptance_target < 1.0:
        raise ValueError(f"acceptance_target: expected a number in (0, 1), got "
                         f"{acceptance_target!r}")
    draw = move = None
    if rho is None:
        loglik = log_likelihood_fn(builder, model, measurements, inputs, x0=x0, P0=P0, Q=Q,
                                   R=R, names=names, builder_kwargs=builder_kwargs)
    else:
        from ._cpm import crank_nicolson

        loglik, draw = cpm_log_likelihood_fn(builder, model, measurements, inputs, x0=x0,
                                             P0=P0, Q=Q, R=R, names=names,
                                             builder_kwargs=builder_kwargs)

        def move(aux, k):
            return crank_nicolson(aux, draw(k), rho)
    L0 = _proposal_factor(prs, proposal_std, proposal_cov)
    z0 = np.tile(_starting_values(prs, init, names), (chains, 1))
    keys = _validate.key(key, chains)
    ends = adaptation_windows(warmup, adapt_windows) if adapt else np.zeros(0, int)
    run = _sampler(loglik, prs, warmup + samples, ends, acceptance_target, 5.0 * len(prs),
                   draw, move)
    zs, lls, acc, L, lt0 = run(keys, jnp.asarray(z0), jnp.asarray(L0))
    if not np.all(np.isfinite(np.asarray(lt0))):
        raise ValueError("init: the likelihood estimate at the starting values is zero (the "
                         "filter diverged or the prior excludes them); give other init values "
                         "or more particles")
    return _result(names, prs, zs, lls, acc, L, warmup)


# -- particle Gibbs with ancestor sampling ---------------------------------------------------
def _gauss_logpdf(e, L):
    """log N(e; 0, L L^T) for e (..., n) and a lower Cholesky factor L (n, n): (...)."""
    z = jax.scipy.linalg.solve_triangular(L, jnp.moveaxis(e, -1, 0), lower=True)
    n = L.shape[0]
    return (-0.5 * jnp.sum(z**2, axis=0) - jnp.sum(jnp.log(jnp.diag(L)))
            - 0.5 * n * _LOG_2PI)


def _obs_logpdf(y, yhat, r_var):
    """Sum over the observed (finite) components of log N(y_j; yhat_j, r_var_j): (...,)."""
    obs = jnp.isfinite(y)
    e = jnp.where(obs, y - yhat, 0.0)
    terms = -0.5 * (e**2 / r_var + jnp.log(r_var) + _LOG_2PI)
    return jnp.sum(jnp.where(obs, terms, 0.0), axis=-1)


def _pg_parts(model, tg, theta_base, Q, R, values):
    """(theta, chol(Q), R's diagonal, bias (ny,)) with the named quantities set to ``values``."""
    theta = theta_base
    for i, j in tg.params:
        theta = theta.at[j].set(values[i])
    for i, j in tg.q_std:
        Q = Q.at[j, j].set(values[i] ** 2)
    r_var = jnp.diag(R)
    for i, j in tg.r_std:
        r_var = r_var.at[j].set(values[i] ** 2)
    bias = jnp.zeros(model.ny)
    for i, j in tg.bias:
        bias = bias.at[j].set(values[i])
    return theta, jnp.linalg.cholesky(Q), r_var, bias


def conditional_pf_as(model, key, ref, theta, LQ, r_var, bias, ys, us, x0, LP0, n: int):
    """One sweep of the conditional particle filter with ancestor sampling (Lindsten, Jordan &
    Schon 2014, Algorithm 2): a new state trajectory (T + 1, nx) given the reference ``ref``.

    Model: x_0 ~ N(x0, LP0 LP0^T), x_t = f(x_{t-1}, u_t) + N(0, LQ LQ^T),
    y_t = h(x_t, u_t) + bias + N(0, diag(r_var)) (NaN components of y_t missing). Particle n - 1
    is the reference; its ancestor at each step is drawn with weights w_{t-1}^j
    p(ref_t | x_{t-1}^j); the others resample multinomially and propagate; one trajectory is
    drawn by its final weight and traced back through the ancestors.
    """
    f = jax.vmap(model.transition, in_axes=(0, None, None))
    h = jax.vmap(model.observe, in_axes=(0, None, None))
    nx = LQ.shape[0]
    k0, key = jax.random.split(key)
    X0 = (x0 + jax.random.normal(k0, (n, nx)) @ LP0.T).at[n - 1].set(ref[0])

    def step(carry, inp):
        X, logw, key = carry
        y, u, xref = inp
        key, ka, kn, kr = jax.random.split(key, 4)
        FX = f(X, u, theta)
        anc = jax.random.categorical(ka, logw, shape=(n,))
        anc = anc.at[n - 1].set(jax.random.categorical(kr, logw + _gauss_logpdf(xref - FX, LQ)))
        Xn = (FX[anc] + jax.random.normal(kn, (n, nx)) @ LQ.T).at[n - 1].set(xref)
        logw = _obs_logpdf(y, h(Xn, u, theta) + bias, r_var)
        logw = jnp.where(jnp.isfinite(logw), logw, -jnp.inf)
        return (Xn, logw, key), (Xn, anc)

    (_, logw, key), (Xs, ancs) = jax.lax.scan(step, (X0, jnp.zeros(n), key), (ys, us, ref[1:]))
    k = jax.random.categorical(key, logw)

    def back(k, inp):
        X, anc = inp
        return anc[k], X[k]

    k0, traj = jax.lax.scan(back, k, (Xs, ancs), reverse=True)
    return jnp.concatenate([X0[k0][None], traj])


def log_joint(model, traj, theta, LQ, r_var, bias, ys, us, x0, LP0):
    """log p(x_0:T, y_1:T | theta) of a trajectory (T + 1, nx) under the model of
    :func:`conditional_pf_as`: ()."""
    fx = jax.vmap(model.transition, in_axes=(0, 0, None))(traj[:-1], us, theta)
    yhat = jax.vmap(model.observe, in_axes=(0, 0, None))(traj[1:], us, theta) + bias
    return (_gauss_logpdf(traj[0] - x0, LP0) + jnp.sum(_gauss_logpdf(traj[1:] - fx, LQ))
            + jnp.sum(_obs_logpdf(ys, yhat, r_var)))


def particle_gibbs(model, measurements, inputs=None, *, x0, P0, Q, R, priors, key,
                   n_particles: int = 20, chains: int = 4, samples: int = 1000,
                   warmup: int = 200, mh_steps: int = 3, proposal_std=None,
                   adapt: bool = True, adapt_windows: int = 5, acceptance_target=None,
                   init=None) -> PMMHResult:
    """Particle Gibbs with ancestor sampling (Lindsten, Jordan & Schon 2014) over named
    quantities (model parameters, ``"R:<output>"``, ``"Q:<state>"``, ``"bias:<output>"`` as in
    :func:`pmmh`; no input noise).

    Each sweep draws a state trajectory from :func:`conditional_pf_as` given the current
    values, then makes ``mh_steps`` random-walk Metropolis-Hastings moves of the values (in the
    priors' unconstrained coordinates) on log p(x_0:T, y | values) + log prior
    (:func:`log_joint`). Few particles suffice (ancestor sampling keeps the trajectory mixing).
    The model's process noise must be additive and Q positive definite; R is diagonal
    ((ny,) variances or a diagonal matrix).

    Args:
        model, measurements (T, ny), inputs (T, nu) or None, x0, P0, Q, R, priors, key,
            chains, samples, warmup, proposal_std, adapt, adapt_windows, acceptance_target,
            init: as in :func:`pmmh`; the adaptation tunes the moves of the values given the
            trajectory (pooled over chains, the acceptance averaged over the sweep's moves).
        n_particles: particles of the conditional PF, >= 2.
        mh_steps: Metropolis-Hastings moves of the values per sweep, >= 1.

    Returns:
        :class:`PMMHResult` (``loglik``: log p(x_0:T, y | values) of each draw with its
        trajectory).
    """
    names, prs = _check_priors(priors)
    tg = _targets(model, names)
    if tg.inputs:
        raise ValueError("priors: particle_gibbs does not calibrate input noise ('input:')")
    chains = _validate.integer("chains", chains, 2)
    samples = _validate.integer("samples", samples, 4)
    warmup = _validate.integer("warmup", warmup, 2 if adapt else 0)
    adapt_windows = _validate.integer("adapt_windows", adapt_windows, 1)
    if acceptance_target is None:
        acceptance_target = target_acceptance(len(prs))
    acceptance_target = _validate.number("acceptance_target", acceptance_target, 0.0)
    n = _validate.integer("n_particles", n_particles, 2)
    mh_steps = _validate.integer("mh_steps", mh_steps, 1)
    ys, us = _validate.data(measurements, inputs, model.ny, model.nu, "one")
    ys, us = jnp.asarray(ys, float), jnp.asarray(us, float)
    x0a, P0a = _validate.prior(model.nx, x0, P0)
    x0a, LP0 = jnp.asarray(x0a, float), jnp.asarray(np.linalg.cholesky(np.asarray(P0a, float)))
    Qm = jnp.asarray(_validate.cov("Q", Q, model.nx))
    Rm = np.asarray(_validate.cov("R", R, model.ny))
    if not np.allclose(Rm, np.diag(np.diag(Rm))):
        raise ValueError("R: particle_gibbs needs a diagonal measurement covariance")
    Rm = jnp.asarray(Rm)
    L = jnp.asarray(_proposal_factor(prs, proposal_std))
    z0 = jnp.tile(_starting_values(prs, init, names), (chains, 1))
    keys = _validate.key(key, chains)
    theta_base = jnp.asarray(model.theta, float)
    T = ys.shape[0]

    def parts(z):
        return _pg_parts(model, tg, theta_base, Qm, Rm, to_physical(prs, z))

    def target(z, traj):
        return log_joint(model, traj, *parts(z), ys, us, x0a, LP0) + log_prior_unconstrained(prs, z)

    ends = adaptation_windows(warmup, adapt_windows) if adapt else np.zeros(0, int)

    def sweep(key_c, z, traj, i, L):
        """One sweep of one chain: (z, traj) -> (z, traj, log joint, acceptance rate)."""
        k_pf, k_mh = jax.random.split(jax.random.fold_in(key_c, i))
        traj = conditional_pf_as(model, k_pf, traj, *parts(z), ys, us, x0a, LP0, n)

        def mh(zc, k):
            kp, ku = jax.random.split(k)
            zn = zc + L @ jax.random.normal(kp, zc.shape)
            d = target(zn, traj) - target(zc, traj)
            ok = jnp.log(jax.random.uniform(ku)) < jnp.where(jnp.isfinite(d), d, -jnp.inf)
            return jnp.where(ok, zn, zc), ok

        z, acc = jax.lax.scan(mh, z, jax.random.split(k_mh, mh_steps))
        return z, traj, log_joint(model, traj, *parts(z), ys, us, x0a, LP0), jnp.mean(acc)

    def run(keys, z0, L0):
        def body(carry, i):
            z, traj, ad = carry
            z, traj, lj, acc = jax.vmap(lambda k, zc, tc: sweep(k, zc, tc, i, ad.L))(
                keys, z, traj)
            ad = _adapt_step(ad, i, z, acc, ends, acceptance_target, 5.0 * len(prs))
            return (z, traj, ad), (z, lj, acc)

        traj0 = jnp.tile(x0a, (z0.shape[0], T + 1, 1))
        (_, _, ad), (zs, ljs, acc) = jax.lax.scan(body, (z0, traj0, _adapt_init(L0)),
                                                  jnp.arange(warmup + samples))
        return (jnp.swapaxes(zs, 0, 1), jnp.swapaxes(ljs, 0, 1), jnp.swapaxes(acc, 0, 1), ad.L)

    zs, ljs, acc, L = jax.jit(run)(keys, z0, L)
    return _result(names, prs, zs, ljs, acc, L, warmup)


def _result(names, prs, zs, lls, acc, L, warmup) -> PMMHResult:
    """The chains' draws after ``warmup`` in physical units, with their summaries: zs (chains,
    draws, d) unconstrained, lls the log-likelihood (or joint) per draw, acc the acceptances,
    L the proposal's Cholesky factor."""
    zs = np.asarray(zs)[:, warmup:]
    x = np.asarray(jax.vmap(jax.vmap(lambda z: to_physical(prs, z)))(jnp.asarray(zs)))
    flat = x.reshape(-1, len(names))
    L = np.asarray(L)
    return PMMHResult(
        names=names, samples=x, loglik=np.asarray(lls)[:, warmup:],
        acceptance=np.asarray(acc)[:, warmup:].mean(axis=1),
        mean=flat.mean(axis=0), std=flat.std(axis=0, ddof=1),
        rhat=split_rhat(x), ess=effective_sample_size(x), proposal_cov=L @ L.T)


# -- diagnostics ----------------------------------------------------------------------------
def _as_chains(draws) -> np.ndarray:
    x = np.asarray(draws, float)
    if x.ndim == 2:
        x = x[..., None]
    if x.ndim != 3 or x.shape[0] < 1 or x.shape[1] < 4:
        raise ValueError(f"draws: expected (chains, draws) or (chains, draws, d) with at least 4 "
                         f"draws, got shape {np.shape(draws)}")
    return x


def _split(x: np.ndarray) -> np.ndarray:
    """(M, N, d) -> (2M, N // 2, d): each chain's first and second half (a middle draw of an odd
    N dropped)."""
    n = x.shape[1] // 2
    return np.concatenate([x[:, :n], x[:, x.shape[1] - n:]], axis=0)


def split_rhat(draws) -> np.ndarray:
    """Split R-hat (Gelman et al., BDA3 eq. 11.4) of every quantity: (d,) or () for 2-D input.

    The chains (M, N[, d]) are cut in halves, giving m = 2M chains of n draws; with B the
    between-chain variance n / (m - 1) sum_j (mean_j - mean)^2 and W the mean within-chain
    variance (ddof 1), var+ = (n - 1) / n W + B / n and R-hat = sqrt(var+ / W).
    """
    x0 = np.asarray(draws)
    x = _split(_as_chains(draws))
    n = x.shape[1]
    means = x.mean(axis=1)
    B = n * means.var(axis=0, ddof=1)
    W = x.var(axis=1, ddof=1).mean(axis=0)
    var_plus = (n - 1) / n * W + B / n
    r = np.sqrt(var_plus / W)
    return r[0] if x0.ndim == 2 else r


def _autocov(x: np.ndarray) -> np.ndarray:
    """Biased autocovariance (divisor n) along axis 1 by FFT: (m, n, d) -> (m, n, d)."""
    n = x.shape[1]
    xc = x - x.mean(axis=1, keepdims=True)
    size = 1 << (2 * n - 1).bit_length()
    f = np.fft.rfft(xc, size, axis=1)
    return np.fft.irfft(f * np.conj(f), size, axis=1)[:, :n] / n


def effective_sample_size(draws) -> np.ndarray:
    """Effective sample size over all chains (BDA3 sec. 11.5, on split chains): (d,) or ().

    rho_t = 1 - (W - mean_j acov_j(t)) / var+, summed as tau = -1 + 2 sum_k (rho_2k + rho_2k+1)
    over Geyer's initial positive sequence (pairs while positive, made non-increasing);
    ESS = m n / tau.
    """
    x0 = np.asarray(draws)
    x = _split(_as_chains(draws))
    m, n, d = x.shape
    acov = _autocov(x)
    W = (acov[:, 0] * n / (n - 1)).mean(axis=0)
    B_over_n = x.mean(axis=1).var(axis=0, ddof=1)
    var_plus = (n - 1) / n * W + B_over_n
    rho = 1.0 - (W[None] - acov.mean(axis=0)) / var_plus[None]          # (n, d)
    ess = np.empty(d)
    for k in range(d):
        pairs = rho[: 2 * (n // 2), k].reshape(-1, 2).sum(axis=1)
        stop = np.flatnonzero(pairs <= 0.0)
        pairs = pairs[: stop[0] if stop.size else len(pairs)]
        pairs = np.minimum.accumulate(pairs) if pairs.size else pairs
        tau = max(-1.0 + 2.0 * pairs.sum(), 1.0 / np.log10(max(m * n, 10)))
        ess[k] = m * n / tau
    return ess[0] if x0.ndim == 2 else ess
