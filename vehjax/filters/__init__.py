"""Filters: each builder returns an ``Estimator(init, step)`` of pure functions."""

from . import resampling, sigma
from .adaptive import AckfState, ackf
from .base import Estimator, StepOutput
from .dual import DualState, JointState, dual_ekf, dual_ukf, joint_ekf, joint_ukf
from .gaussian import GaussianState, SqrtGaussianState, ckf, ekf, masked_update, ukf, validate_prior
from .liu_west import LiuWestState, liu_west_ukf
from .particle import PFState, bootstrap_pf

__all__ = [
    "Estimator", "StepOutput", "ekf", "ukf", "ckf", "ackf", "bootstrap_pf",
    "dual_ekf", "dual_ukf", "joint_ekf", "joint_ukf", "liu_west_ukf",
    "DualState", "JointState", "LiuWestState",
    "GaussianState", "SqrtGaussianState", "AckfState", "PFState",
    "masked_update", "validate_prior", "sigma", "resampling",
]
