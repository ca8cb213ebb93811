"""Kinematic bicycle referenced at the centre of gravity (Dutta et al. 2019, eq. 1-5; Kong et al. 2015)."""

from __future__ import annotations

import jax.numpy as jnp

from ..lib.elementary import arctan, cos, sin, tan
from . import domains as dom
from .base import VehicleModel


class KinematicBicycle(VehicleModel):
    """Kinematic single-track model, CoG-referenced.

    States x = (x, y, psi, v): position in the inertial frame [m], heading [rad], speed [m/s].
    Inputs u = (a, delta): acceleration along the velocity [m/s^2], front steering angle [rad].
    Parameters theta = (lf, lr): CoG to front and rear axle [m], nominal 1.5 m each.
    Outputs: all four states (the paper's H_s = I).

    Domains (``PARAM_DOMAINS``, :meth:`~vehjax.models.BaseModel.param_domains`): lf, lr in
    (0, inf), the CoG between the axles (lr > 0 is a necessity: the yaw rate divides by it).
    State envelope: |v| <= 300 m/s; the pose is unbounded.

    Eq. 1 of the transcription reads ``beta = tan^-1(lr / (lr + lf)) tan(delta)``; a bracket is
    misplaced, the slip angle at the CoG is ``beta = arctan(lr / (lf + lr) * tan(delta))``.
    """

    STATE_NAMES = ("x", "y", "psi", "v")
    STATE_UNITS = ("m", "m", "rad", "m/s")
    INPUT_NAMES = ("a", "delta")
    INPUT_UNITS = ("m/s^2", "rad")
    PARAM_NAMES = ("lf", "lr")
    PARAM_UNITS = ("m", "m")
    PARAM_NOMINAL = (1.5, 1.5)
    PARAM_DOMAINS = {"lf": dom.AXLE, "lr": dom.AXLE}
    STATE_ENVELOPE = {"v": dom.SPEED_LIMIT}

    output_names = property(lambda self: self.STATE_NAMES)
    output_units = property(lambda self: self.STATE_UNITS)

    def derivative(self, x, u, theta):
        _, _, psi, v = x
        a, delta = u
        lf, lr = theta
        beta = arctan(lr / (lf + lr) * tan(delta))
        return jnp.stack(
            [v * cos(psi + beta), v * sin(psi + beta), v / lr * sin(beta), a]
        )

    def observe(self, x, u, theta):
        return x

    # -- used by scenarios' driver model ----------------------------------------------------
    def body_velocity(self, x, u, theta):
        """(vx, vy, r) of the CoG in the body frame [m/s, m/s, rad/s]."""
        _, _, _, v = x
        return v, 0.0 * v, 0.0 * v  # the driver integrates pose from the states themselves

    def pose(self, x):
        """(X, Y, psi) when the model carries its own pose, else None."""
        return x[0], x[1], x[2]

    def speed(self, x):
        return x[3]

    def drive_input(self, x, delta, accel, speed, theta):
        """Inputs that steer ``delta`` [rad] and accelerate at ``accel`` [m/s^2]."""
        return jnp.stack([accel, delta])

    def initial_state(self, speed):
        return jnp.array([0.0, 0.0, 0.0, speed])
