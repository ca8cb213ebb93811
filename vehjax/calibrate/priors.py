"""The priors of particle MCMC: :mod:`vehjax.lib.priors` (shared with :mod:`vehjax.tune`'s
``priors=``), re-exported here so that ``from vehjax.calibrate.priors import Normal`` keeps
working."""

from __future__ import annotations

from ..lib.priors import (PRIORS, LogNormal, Normal, Uniform, check_priors, describe,
                          log_prior_unconstrained, pull, starting_values, support, to_physical)

__all__ = ["Normal", "LogNormal", "Uniform", "PRIORS", "log_prior_unconstrained",
           "to_physical", "check_priors", "starting_values", "pull", "support", "describe"]
