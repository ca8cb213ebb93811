"""Filters: each builder returns an ``Estimator(init, step)`` of pure functions.

Shared algebra: :mod:`~vehjax.filters.sigma` (sigma-point rules and the one sigma-point
predict/update), :mod:`~vehjax.filters.kalman` (the masked Kalman update and the Jacobian forms),
:mod:`~vehjax.filters.smc` (the one particle core), :mod:`~vehjax.filters.resampling`.
"""

from . import kalman, resampling, sigma, smc
from .adaptive import AckfState, ackf
from .base import Backward, Dims, Estimator, ParamSpec, Runtime, StepOutput
from .dual import DualState, JointState, dual_ekf, dual_ukf, joint_ekf, joint_ukf
from .gaussian import GaussianState, SqrtGaussianState, ckf, ekf, masked_update, ukf, validate_prior
from .sigma import SigmaPoints
from .smc import Resampling
from .liu_west import LiuWestKernel, LiuWestState, liu_west_ukf
from .marginalized import (InputStdGrid, MeanStates, MPFState, NiW, marginalized_pf,
                           marginalized_pf_grid)
from .particle import PFState, bootstrap_pf
from .vb import Augmentation, VBPRState, VBState, vbakf_pr, vbakf_r

__all__ = [
    "Estimator", "StepOutput", "Dims", "ParamSpec", "Runtime", "Backward", "ekf", "ukf", "ckf", "ackf", "bootstrap_pf",
    "dual_ekf", "dual_ukf", "joint_ekf", "joint_ukf", "liu_west_ukf", "marginalized_pf",
    "marginalized_pf_grid", "NiW", "MeanStates", "InputStdGrid", "MPFState",
    "DualState", "JointState", "LiuWestState",
    "GaussianState", "SqrtGaussianState", "AckfState", "PFState",
    "vbakf_r", "vbakf_pr", "VBState", "VBPRState",
    "SigmaPoints", "Resampling", "LiuWestKernel", "Augmentation",
    "masked_update", "validate_prior", "sigma", "kalman", "smc", "resampling",
]
