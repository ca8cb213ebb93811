"""Tyre force laws: linear and Pacejka-89 magic formula."""

from __future__ import annotations


def linear_force(stiffness, slip):
    """Linear tyre: F = stiffness * slip (longitudinal slip [-] or slip angle [rad]) [N]."""
    return stiffness * slip
