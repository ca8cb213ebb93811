"""Filters: each builder returns an ``Estimator(init, step)`` of pure functions."""

from .base import Estimator, StepOutput

__all__ = ["Estimator", "StepOutput"]
