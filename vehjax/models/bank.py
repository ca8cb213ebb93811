"""Single-track model with road bank and steering offset (Berntorp & Di Cairano 2018, eq. 1-10).

Sign conventions (ISO 8855-like body frame, x forward, y left, z up):

* ``vy`` > 0 moves the car to its left, ``r`` > 0 turns it left (counter-clockwise seen from above),
  ``delta`` > 0 steers the front wheel left.
* ``phi`` > 0 is the road plane rolled by +phi about the car's forward x axis (right-hand rule),
  i.e. the car's left side is higher than its right side. Gravity then pulls the car to its
  right, down the slope, with the in-plane component ``-m g sin(phi) ~ -m g phi`` along y.

Reading of the transcription's typos:

* Eq. 2a prints the bank term as ``- g / v^x phi``; that has units of m/s^3 and cannot be a force.
  It is the in-plane gravity component ``- m g sin(phi) ~ - m g phi`` (the paper states the small
  angle approximation sin(phi) ~ phi right below eq. 2), kept with the printed minus sign, which
  fixes the bank convention above.
* Eq. 3 prints A_phi as the identity. For z = (phi, phi', phi'') driven by a jerk w_phi held over
  the step, the exact discretisation of z' = [[0, 1, 0], [0, 0, 1], [0, 0, 0]] z + [0, 0, 1] w is
  A_phi = [[1, T, T^2/2], [0, 1, T], [0, 0, 1]], B_phi = (T^3/6, T^2/2, T), which is the printed
  B_phi and the "(nearly) constant acceleration model" named in the text; the identity is a typo.
  ``derivative`` writes the noise-free chain (phi' = phi_dot, phi_dot' = phi_ddot,
  phi_ddot' = 0); its solution is a quadratic in time, which RK4 (exact up to degree 4)
  reproduces to rounding, so ``transition`` with ``integrator="rk4"`` applies A_phi exactly
  (explicit Euler does not: it drops the T^2/2 term).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from . import domains as dom
from .base import VehicleModel

#: Gravitational acceleration [m/s^2].
G = 9.81

_OUTPUT_NAMES = ("ay", "r", "roll_rate", "phi", "r_virt")
_OUTPUT_UNITS = ("m/s^2", "rad/s", "rad/s", "rad", "rad/s")


class SingleTrackBank(VehicleModel):
    """Lateral single-track (bicycle) model on a banked road, linear tyres, known speed.

    States x = (vy, r, phi, phi_dot, phi_ddot): lateral velocity of the CoG [m/s], yaw rate
        [rad/s], road-bank angle [rad], its rate [rad/s] and acceleration [rad/s^2].
    Inputs u = (vx, delta): longitudinal speed [m/s] (> 0; the paper takes it from the wheel
        speeds) and the *measured* road-wheel steering angle delta_m [rad]. The true angle is
        delta_m + w with w the steering offset of eq. 4-5, which enters as process noise through
        ``steering_noise_gain`` (and ``measurement_noise_gain`` for ay).
    Parameters theta = (m, iz, lf, lr, cf, cr): mass [kg], yaw inertia [kg m^2], CoG to front
        and rear axle [m], cornering stiffness per axle (both tyres lumped) [N/rad]. The paper
        gives no vehicle data; the nominal values (1500 kg, 2700 kg m^2, 1.2 m, 1.5 m,
        1.2e5 N/rad, 1.4e5 N/rad) are plausible for a mid-size sedan (iz ~ m lf lr, understeer
        gradient m (lr cr - lf cf) / (L cf cr) ~ 2.2e-3 rad/(m/s^2) ~ 1.2 deg/g), not measured.
        Domains (``PARAM_DOMAINS``, :meth:`~vehjax.models.BaseModel.param_domains`): all six
        in (0, inf): m, iz by necessity, lf, lr with the CoG between the axles, cf, cr in the
        sign convention above (a positive slip angle gives a positive force; a stiffness in
        the SAE convention, negative, converts by a change of sign).
    State envelope: |vy| <= 300 m/s, |r|, |phi_dot| <= 20 rad/s, |phi| <= pi/2 (a road
        banked beyond vertical is none), |phi_ddot| <= 1000 rad/s^2.
    Outputs y = (ay, r, roll_rate, phi, r_virt):

    * ay [m/s^2], the lateral accelerometer in the road plane. An accelerometer reads specific
      force, i.e. everything but gravity: (Fyf + Fyr) / m = vy' + vx r + g phi. Its derivative
      with respect to delta is cf / m, the d = [Cf/m, 0, 0] of eq. 8.
    * r [rad/s], the yaw-rate gyro.
    * roll_rate [rad/s], the roll gyro; the paper neglects the body roll rate relative to the
      road, so it reads the bank rate phi_dot.
    * phi [rad], the bank angle (suspension or differential GPS, per the paper).
    * r_virt [rad/s], eq. 10's virtual yaw rate (omega_rr - omega_rl) r_w / l_T from the rear
      wheel speeds. In the model it equals r; its error is measurement noise. Use
      :func:`virtual_yaw_rate` to form it from recorded wheel speeds.

    Equations (eq. 1-2, linear slip angles at the CoG velocity as in the paper):

        alpha_f = delta - (vy + lf r) / vx,     alpha_r = (lr r - vy) / vx
        m vy'   = -m vx r + cf alpha_f + cr alpha_r - m g phi
        iz r'   = lf cf alpha_f - lr cr alpha_r

    Valid for vx > 0 (the slip angles divide by vx).
    """

    STATE_NAMES = ("vy", "r", "phi", "phi_dot", "phi_ddot")
    STATE_UNITS = ("m/s", "rad/s", "rad", "rad/s", "rad/s^2")
    INPUT_NAMES = ("vx", "delta")
    INPUT_UNITS = ("m/s", "rad")
    PARAM_NAMES = ("m", "iz", "lf", "lr", "cf", "cr")
    PARAM_UNITS = ("kg", "kg m^2", "m", "m", "N/rad", "N/rad")
    PARAM_NOMINAL = (1500.0, 2700.0, 1.2, 1.5, 1.2e5, 1.4e5)
    PARAM_DOMAINS = {"m": dom.MASS, "iz": dom.INERTIA, "lf": dom.AXLE, "lr": dom.AXLE,
                     "cf": dom.CORNERING, "cr": dom.CORNERING}
    STATE_ENVELOPE = {"vy": dom.SPEED_LIMIT, "r": dom.RATE_LIMIT, "phi": np.pi / 2,
                      "phi_dot": dom.RATE_LIMIT, "phi_ddot": 1000.0}

    output_names = property(lambda self: _OUTPUT_NAMES)
    output_units = property(lambda self: _OUTPUT_UNITS)

    def _tyre_forces(self, x, u, theta):
        """Lumped front and rear lateral tyre forces [N]."""
        vy, r = x[0], x[1]
        vx, delta = u[0], u[1]
        _, _, lf, lr, cf, cr = theta
        alpha_f = delta - (vy + lf * r) / vx
        alpha_r = (lr * r - vy) / vx
        return cf * alpha_f, cr * alpha_r

    def derivative(self, x, u, theta):
        vx = u[0]
        m, iz, lf, lr = theta[0], theta[1], theta[2], theta[3]
        phi, phi_dot, phi_ddot = x[2], x[3], x[4]
        fyf, fyr = self._tyre_forces(x, u, theta)
        vy_dot = -vx * x[1] + (fyf + fyr) / m - G * phi
        r_dot = (lf * fyf - lr * fyr) / iz
        return jnp.stack([vy_dot, r_dot, phi_dot, phi_ddot, 0.0 * phi_ddot])

    def lateral_acceleration(self, x, u, theta):
        """Specific force along the road-plane y axis, (Fyf + Fyr) / m [m/s^2]."""
        fyf, fyr = self._tyre_forces(x, u, theta)
        return (fyf + fyr) / theta[0]

    def observe(self, x, u, theta):
        """(ay, r, roll_rate, phi, r_virt), shape (5,), units ``output_units``."""
        ay = self.lateral_acceleration(x, u, theta)
        return jnp.stack([ay, x[1], x[3], x[2], x[1]])

    # -- the steering offset as noise (eq. 6 and 8) --------------------------------------------
    def steering_noise_gain(self, x, u, theta):
        """g of eq. 6: d transition / d delta, shape (nx,) [state units per rad].

        The model is affine in delta, so ``transition(x, u + (0, w), theta)`` equals
        ``transition(x, u, theta) + w * g`` exactly (for either integrator); the bank entries
        are zero.
        """
        return _d_ddelta(self.transition, x, u, theta)

    def measurement_noise_gain(self, x, u, theta):
        """d of eq. 8: d observe / d delta = (cf / m, 0, 0, 0, 0), shape (ny,)."""
        return _d_ddelta(self.observe, x, u, theta)

    def bank_noise_gain(self):
        """B_phi of eq. 3 on the full state, (0, 0, T^3/6, T^2/2, T), shape (nx,).

        The response over one step to a bank jerk w_phi [rad/s^3] held over the step; the bank
        process-noise covariance is sigma_phi^2 B B^T. As in eq. 3 and 6 the jerk's O(T^4)
        effect on (vy, r) within the step is neglected.
        """
        t = self.dt
        return jnp.array([0.0, 0.0, t**3 / 6.0, t**2 / 2.0, t])

    # -- used by scenarios' driver model ----------------------------------------------------
    def body_velocity(self, x, u, theta):
        """(vx, vy, r) [m/s, m/s, rad/s]; vx is the input."""
        return u[0], x[0], x[1]

    def pose(self, x):
        return None

    def speed(self, x):
        """None: the speed is the input vx, not a state; a driver uses its reference speed."""
        return None

    def drive_input(self, x, delta, accel, speed, theta):
        """(vx, delta) = (``speed``, ``delta``); ``accel`` is already in the reference ``speed``."""
        return jnp.stack([speed, delta])

    def initial_state(self, speed):
        """Straight driving on a flat road: zeros, shape (5,). ``speed`` enters as the input."""
        return jnp.zeros(5)


def _d_ddelta(fn, x, u, theta):
    """Forward-mode derivative of ``fn(x, u, theta)`` with respect to u[1] (delta)."""
    u = jnp.asarray(u)
    tangent = jnp.zeros_like(u).at[1].set(1.0)
    return jax.jvp(lambda uu: fn(x, uu, theta), (u,), (tangent,))[1]


def virtual_yaw_rate(omega_rl, omega_rr, wheel_radius, track):
    """Eq. 10: yaw rate from the rear wheel speeds, (omega_rr - omega_rl) r_w / l_T [rad/s].

    Args:
        omega_rl, omega_rr: rear-left and rear-right wheel rotation rates [rad/s], any
            broadcastable shapes.
        wheel_radius: effective rolling radius r_w [m], > 0.
        track: rear track width l_T [m], > 0.

    In a left turn (r > 0) the right wheel is on the outside and spins faster, so the result is
    positive, matching the model's sign of r. Wheel-radius errors scale the result (the paper
    does not model them).
    """
    for name, value in (("wheel_radius", wheel_radius), ("track", track)):
        if not isinstance(value, jax.core.Tracer):
            v = np.asarray(value, dtype=float)
            if not np.all(np.isfinite(v)) or np.any(v <= 0.0):
                raise ValueError(f"{name}: expected a positive length in metres, got {value!r}")
    return (jnp.asarray(omega_rr) - jnp.asarray(omega_rl)) * wheel_radius / track
