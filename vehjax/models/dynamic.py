"""3-DOF dual-track model with linear tyres (Dutta et al. 2019, eq. 6-10).

The model is the one of MATLAB's System Identification example "Modeling a Vehicle Dynamics
System" that the paper cites as [16].
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from ..lib.elementary import arctan, cos, sin
from . import domains as dom
from .base import VehicleModel
from .tyres import linear_force

_OUTPUT_SETS = {
    "states": (("vx", "vy", "r"), ("m/s", "m/s", "rad/s")),
    "matlab": (("vx", "ay", "r"), ("m/s", "m/s^2", "rad/s")),
}


class Dynamic3DOF(VehicleModel):
    """Planar dual-track model: longitudinal, lateral and yaw motion, front-wheel drive.

    States x = (vx, vy, r): body-frame velocities at the CoG [m/s] and yaw rate [rad/s].
    Inputs u = (s_fl, s_fr, s_rl, s_rr, delta): longitudinal wheel slips [-] and front steering
        angle [rad]. Rear slips are zero in the paper's front-wheel-drive set-up.
    Parameters theta = (m, cx, cy, lf, lr, iz, ca): mass [kg], longitudinal and cornering tyre
        stiffness [N], [N/rad], CoG to axles [m], yaw inertia [kg m^2], air drag [N s^2/m^2].
        The yaw inertia is its own parameter (MATLAB ties it to m), so that m, cx, cy are
        identifiable from the states.
    Domains (``PARAM_DOMAINS``, :meth:`~vehjax.models.BaseModel.param_domains`): m, iz in
        (0, inf) (necessity); lf, lr in (0, inf) (the CoG between the axles); cx, cy in
        (0, inf), the sign convention of ISO 8855 used throughout (a positive slip or slip angle
        gives a positive force; stiffnesses in the SAE convention, negative, convert by a
        change of sign); ca in [0, inf) (drag opposes the motion; zero allowed).
    State envelope: |vx|, |vy| <= 300 m/s, |r| <= 20 rad/s.
    Outputs: ``outputs="states"`` gives (vx, vy, r), the paper's H = I; ``outputs="matlab"``
        gives (vx, ay, r) as in the MATLAB example, ay the lateral acceleration [m/s^2].

    The transcription's eq. 6-8 write F_xFL where F_yFL is meant and lose the bracket of 1/m.
    Read from rigid-body mechanics (and MATLAB's example):

        m (vx' - vy r) = (Fx_fl + Fx_fr) cos d - (Fy_fl + Fy_fr) sin d + Fx_rl + Fx_rr - ca vx^2
        m (vy' + vx r) = (Fx_fl + Fx_fr) sin d + (Fy_fl + Fy_fr) cos d + Fy_rl + Fy_rr
        iz r'          = lf ((Fx_fl + Fx_fr) sin d + (Fy_fl + Fy_fr) cos d) - lr (Fy_rl + Fy_rr)

    with Fx = cx s and Fy = cy alpha per wheel, alpha_f = d - arctan((vy + lf r) / vx) and
    alpha_r = -arctan((vy - lr r) / vx) (eq. 9-10). Valid for vx > 0.
    """

    outputs: str = eqx.field(static=True)

    STATE_NAMES = ("vx", "vy", "r")
    STATE_UNITS = ("m/s", "m/s", "rad/s")
    INPUT_NAMES = ("s_fl", "s_fr", "s_rl", "s_rr", "delta")
    INPUT_UNITS = ("-", "-", "-", "-", "rad")
    PARAM_NAMES = ("m", "cx", "cy", "lf", "lr", "iz", "ca")
    PARAM_UNITS = ("kg", "N", "N/rad", "m", "m", "kg m^2", "N s^2/m^2")
    PARAM_NOMINAL = (1700.0, 1.5e5, 4.0e4, 1.5, 1.5, 1700.0 * 1.5**2, 0.5)
    PARAM_DOMAINS = {"m": dom.MASS, "cx": dom.SLIP_STIFFNESS, "cy": dom.CORNERING,
                     "lf": dom.AXLE, "lr": dom.AXLE, "iz": dom.INERTIA, "ca": dom.DRAG}
    STATE_ENVELOPE = {"vx": dom.SPEED_LIMIT, "vy": dom.SPEED_LIMIT, "r": dom.RATE_LIMIT}

    def __init__(self, dt: float = 0.01, integrator: str = "rk4", theta=None, outputs: str = "states"):
        super().__init__(dt=dt, integrator=integrator, theta=theta)
        if outputs not in _OUTPUT_SETS:
            raise ValueError(f"outputs: expected one of {tuple(_OUTPUT_SETS)}, got {outputs!r}")
        self.outputs = outputs

    output_names = property(lambda self: _OUTPUT_SETS[self.outputs][0])
    output_units = property(lambda self: _OUTPUT_SETS[self.outputs][1])

    def _forces(self, x, u, theta):
        """Sum of forces along body x and y [N] and yaw moment [N m] at the CoG."""
        vx, vy, r = x
        s_fl, s_fr, s_rl, s_rr, delta = u
        m, cx, cy, lf, lr, iz, ca = theta
        alpha_f = delta - arctan((vy + lf * r) / vx)
        alpha_r = -arctan((vy - lr * r) / vx)
        fx_front = linear_force(cx, s_fl) + linear_force(cx, s_fr)
        fx_rear = linear_force(cx, s_rl) + linear_force(cx, s_rr)
        fy_front = 2.0 * linear_force(cy, alpha_f)
        fy_rear = 2.0 * linear_force(cy, alpha_r)
        c, s = cos(delta), sin(delta)
        fx = fx_front * c - fy_front * s + fx_rear - ca * vx**2
        fy = fx_front * s + fy_front * c + fy_rear
        mz = lf * (fx_front * s + fy_front * c) - lr * fy_rear
        return fx, fy, mz

    def derivative(self, x, u, theta):
        vx, vy, r = x
        m, iz = theta[0], theta[5]
        fx, fy, mz = self._forces(x, u, theta)
        return jnp.stack([vy * r + fx / m, -vx * r + fy / m, mz / iz])

    def lateral_acceleration(self, x, u, theta):
        """ay = vy' + vx r = Fy / m [m/s^2], what a lateral accelerometer at the CoG reads."""
        _, fy, _ = self._forces(x, u, theta)
        return fy / theta[0]

    def observe(self, x, u, theta):
        if self.outputs == "states":
            return x
        return jnp.stack([x[0], self.lateral_acceleration(x, u, theta), x[2]])

    # -- used by scenarios' driver model ----------------------------------------------------
    def body_velocity(self, x, u, theta):
        return x[0], x[1], x[2]

    def pose(self, x):
        return None

    def speed(self, x):
        return x[0]

    def drive_input(self, x, delta, accel, speed, theta):
        """Front slips that give longitudinal acceleration ``accel`` against drag, and ``delta``."""
        m, cx, ca = theta[0], theta[1], theta[6]
        slip = (m * accel + ca * x[0] ** 2) / (2.0 * cx * cos(delta))
        slip = jnp.clip(slip, -0.1, 0.1)
        return jnp.stack([slip, slip, 0.0 * slip, 0.0 * slip, delta])

    def initial_state(self, speed):
        return jnp.array([speed, 0.0, 0.0])
