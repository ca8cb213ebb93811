"""The option records of the particle MCMC samplers, each checked when made (a ValueError
naming the argument and the field, before anything is traced).

* :class:`Chains`: how many chains, how long, from where (``chains=`` of :func:`pmmh` and
  :func:`particle_gibbs`).
* :class:`RandomWalk` with its :class:`Adaptation`: the Gaussian random walk in the priors'
  unconstrained coordinates and its tuning over the warm-up (``proposal=`` of both samplers).
* :class:`Sweep`: one sweep of particle Gibbs (its conditional PF's particles and the moves of
  the values given the trajectory; ``sweep=`` of :func:`particle_gibbs`).
* :class:`Correlated`: the correlated pseudo-marginal estimate (Deligiannidis, Doucet & Pitt
  2018), a variant of the likelihood: ``pmmh(Correlated(builder, correlation), ...)`` in place
  of a builder, and :func:`log_likelihood_difference_spread`'s estimate.

A builder's own options are given with it, ``functools.partial(vehjax.filters.bootstrap_pf,
n_particles=64)``; :func:`vehjax.validation.builder_options` reads them back.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping

import numpy as np

from .. import validation
from ..filters import Resampling, bootstrap_pf
from ..filters import smc

__all__ = ["Chains", "Adaptation", "RandomWalk", "Sweep", "Correlated", "CPM_KWARGS"]


@dataclasses.dataclass(frozen=True)
class Chains:
    """The chains of a particle MCMC run (``chains=`` of :func:`pmmh`, :func:`particle_gibbs`).

    Attributes:
        n: number of chains C >= 2 (vmapped; split R-hat compares them).
        samples: draws kept per chain, >= 4.
        warmup: iterations discarded per chain, >= 0 (>= 2 when the proposal adapts, checked by
            the sampler); None (default): the sampler's, 500 for :func:`pmmh`, 200 for
            :func:`particle_gibbs`.
        init: dict name -> starting value (physical units) or None: the prior's centre (median)
            of every quantity not named; the names are checked against the priors by the sampler.
    """

    n: int = 4
    samples: int = 1000
    warmup: int | None = None
    init: Mapping | None = None

    def __post_init__(self):
        object.__setattr__(self, "n", validation.integer("chains.n", self.n, 2))
        object.__setattr__(self, "samples", validation.integer("chains.samples", self.samples, 4))
        if self.warmup is not None:
            object.__setattr__(self, "warmup",
                               validation.integer("chains.warmup", self.warmup, 0))
        if self.init is not None and not isinstance(self.init, Mapping):
            raise ValueError(f"chains.init: expected a dict name -> value or None, got "
                             f"{self.init!r}")


@dataclasses.dataclass(frozen=True)
class Adaptation:
    """The random walk's adaptation over the warm-up (:mod:`vehjax.calibrate.adaptation`):
    ``windows`` re-estimates of the proposal, after windows of doubling length over the first
    80 % of the warm-up (:func:`adaptation_windows`), its scale tuned toward ``acceptance``.

    Attributes:
        windows: how many re-estimates, >= 1.
        acceptance: the acceptance rate the scale is tuned toward, in (0, 1); None (default):
            ``target_acceptance(d)`` of the d quantities (exact likelihood; 0.44 for d = 1 to
            0.234); for a particle filter's estimate ``target_acceptance(d, std)`` with the
            estimate's std (:func:`log_likelihood_spread`).
    """

    windows: int = 5
    acceptance: float | None = None

    def __post_init__(self):
        object.__setattr__(self, "windows",
                           validation.integer("proposal.adaptation.windows", self.windows, 1))
        if self.acceptance is not None:
            object.__setattr__(self, "acceptance", validation.number(
                "proposal.adaptation.acceptance", self.acceptance, 0.0, 1.0,
                what="a number in (0, 1)"))


@dataclasses.dataclass(frozen=True)
class RandomWalk:
    """The samplers' Gaussian random walk in the priors' unconstrained coordinates
    (``proposal=`` of :func:`pmmh` and :func:`particle_gibbs`; in particle Gibbs the moves of
    the values given the trajectory). Its start: ``std`` or ``cov`` (not both) or neither.

    Attributes:
        std: random-walk std per quantity, unconstrained units: a positive number or (d,)
            positive numbers; None: 0.1 x each prior's scale.
        cov: instead of ``std``, the starting covariance (d, d), unconstrained units,
            symmetric positive definite, e.g. a pilot chain's ``PMMHResult.proposal_cov``.
        adaptation: :class:`Adaptation` (default) re-estimates the proposal over the warm-up;
            None keeps the starting one throughout.
    """

    std: Any = None
    cov: Any = None
    adaptation: Adaptation | None = Adaptation()

    def __post_init__(self):
        if self.std is not None and self.cov is not None:
            raise ValueError("proposal.cov: give proposal.std or proposal.cov, not both")
        if self.std is not None:
            s = np.asarray(self.std, float) if np.ndim(self.std) <= 1 else None
            if s is None or s.size == 0 or not np.all(np.isfinite(s)) or np.any(s <= 0):
                raise ValueError(f"proposal.std: expected a positive number or positive "
                                 f"numbers (unconstrained units), got {self.std!r}")
        if self.adaptation is not None and not isinstance(self.adaptation, Adaptation):
            raise ValueError(f"proposal.adaptation: expected vehjax.calibrate.Adaptation(...) "
                             f"or None, got {self.adaptation!r}")


@dataclasses.dataclass(frozen=True)
class Sweep:
    """One sweep of :func:`particle_gibbs` (``sweep=``): a state trajectory from the conditional
    PF with ancestor sampling, then ``moves`` random-walk Metropolis-Hastings moves of the
    values given it.

    Attributes:
        n_particles: particles of the conditional PF, >= 2.
        moves: Metropolis-Hastings moves of the values per sweep, >= 1.
    """

    n_particles: int = 20
    moves: int = 3

    def __post_init__(self):
        object.__setattr__(self, "n_particles",
                           smc.check_n_particles(self.n_particles, "sweep.n_particles"))
        object.__setattr__(self, "moves", validation.integer("sweep.moves", self.moves, 1))


#: the bootstrap PF's options that the correlated estimate (:mod:`vehjax.calibrate.correlated`)
#: reproduces; it resamples systematically at every step
CPM_KWARGS = ("n_particles", "resampling", "input_noise")
_CPM_RESAMPLING = Resampling(scheme="systematic")


@dataclasses.dataclass(frozen=True)
class Correlated:
    """The correlated pseudo-marginal estimate (Deligiannidis, Doucet & Pitt 2018): the
    bootstrap PF's likelihood as a function of its random numbers aux, which the chain carries
    and moves to rho aux + sqrt(1 - rho^2) eps with each proposal
    (:func:`cpm_log_likelihood_fn`, :mod:`vehjax.calibrate.correlated`). Given to :func:`pmmh`
    in place of a builder, and to :func:`log_likelihood_difference_spread`.

    Attributes:
        builder: ``vehjax.filters.bootstrap_pf`` (the only filter whose random numbers this
            reproduces), its options by ``functools.partial``: only ``n_particles`` (default
            1000), ``resampling=Resampling(scheme="systematic")`` and ``input_noise``.
        correlation: rho of the Crank-Nicolson move, in (0, 1); near 1 (e.g. 0.99 to 0.9999,
            1 - rho about N / T by Deligiannidis et al.'s scaling) keeps the acceptance ratio's
            noise small for a one-dimensional state; with several states the sorted resampling
            keeps less of the correlation, the less the longer the record: measure it with
            :func:`log_likelihood_difference_spread` before relying on it.
    """

    builder: Any
    correlation: float

    def __post_init__(self):
        object.__setattr__(self, "correlation", validation.number(
            "correlation", self.correlation, 0.0, 1.0,
            what="a number in (0, 1) (the Crank-Nicolson move's rho)"))
        func, kwargs = validation.builder_options(self.builder)
        if func is not bootstrap_pf:
            raise ValueError(f"builder: the correlated estimate is written for "
                             f"vehjax.filters.bootstrap_pf only, got builder {self.builder!r}; "
                             f"give that builder itself, not Correlated(...)")
        extra = sorted(set(kwargs) - set(CPM_KWARGS))
        if extra or kwargs.get("resampling", _CPM_RESAMPLING) != _CPM_RESAMPLING:
            raise ValueError(f"builder: with correlation the bootstrap PF resamples "
                             f"systematically at every step and takes only {CPM_KWARGS} "
                             f"(resampling=Resampling(scheme='systematic')), got {kwargs!r}")
        validation.integer("n_particles", kwargs.get("n_particles", 1000), 2)

    @property
    def options(self) -> dict:
        """The bootstrap PF's options (``n_particles``, ``resampling``, ``input_noise``)."""
        return validation.builder_options(self.builder)[1]
