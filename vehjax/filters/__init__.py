"""Filters: each builder returns an ``Estimator(init, step)`` of pure functions."""

from . import resampling, sigma
from .adaptive import AckfState, ackf
from .base import Estimator, StepOutput
from .gaussian import GaussianState, SqrtGaussianState, ckf, ekf, masked_update, ukf, validate_prior
from .particle import PFState, bootstrap_pf

__all__ = [
    "Estimator", "StepOutput", "ekf", "ukf", "ckf", "ackf", "bootstrap_pf",
    "GaussianState", "SqrtGaussianState", "AckfState", "PFState",
    "masked_update", "validate_prior", "sigma", "resampling",
]
