"""Sensor options of the planar single-track models: an accelerometer away from the CoG and
reference outputs (the lateral velocity or the sideslip a reference sensor measures).

Accelerometer lever arm. A lateral accelerometer at (xa, ya) [m] in the body frame (x forward,
y left, origin at the CoG) of a planar rigid body reads the specific force of that point,

    ay_s = ay_cog + xa r' - ya r^2

(the tangential term of the yaw acceleration r' and the centripetal one of the yaw rate r;
e.g. Rajamani, Vehicle Dynamics and Control, 2nd ed., sec. 8.5; any rigid-body kinematics text:
a = a_cog + r' e_z x p - r^2 p for a point p in the plane). A sensor 1 m ahead of the CoG adds
1 m times r', which reaches several rad/s^2 in a quick steer: as much as the accelerometer's
noise or more. The offset ya matters less (ya r^2: 0.3 m at 0.5 rad/s gives 0.075 m/s^2) but is
kept, as a mounting offset of a few decimetres to the side is common; its domain holds zero, so
a fit may leave it there. The vertical offset (roll) is outside the planar model.

Reference outputs. A reference sensor (an INS, an optical speed-over-ground sensor, a dual-antenna
GNSS) measures the lateral velocity vy [m/s] of the CoG or the sideslip beta = arctan(vy / vx)
[rad]; the models append them to their outputs when asked (``references=``), so that a model fitted
on a calibration drive with the reference runs on drives without it, the reference's measurement
column NaN (filters skip NaN components).
"""

from __future__ import annotations

import jax.numpy as jnp

from .. import validation
from . import domains as dom

#: the lever arm's parameters: names, units, nominal values (at the CoG: today's model)
LEVER_ARM = (("xa", "ya"), ("m", "m"), (0.0, 0.0))

#: reference output name -> unit
REFERENCES = {"vy": "m/s", "beta": "rad"}

#: the accelerometer's position in the body frame [m]
LEVER = dom.interval(
    "(-5, 5)", "the accelerometer's position relative to the CoG [m] (x forward, y left) lies "
    "within the car: no road car reaches 5 m from its CoG to a bumper or a side (a long "
    "saloon is 5 m long in all); a value beyond says the lever arm absorbs something else "
    "(a time shift, a wrong yaw inertia)")


def lever_arm_table(lever_arm: bool) -> tuple:
    """(names, units, nominal values) the lever arm appends to theta: ``LEVER_ARM`` or empty."""
    return LEVER_ARM if lever_arm else ((), (), ())


def check_references(references) -> tuple:
    """``references`` as a tuple of unique names among ``REFERENCES``; ValueError naming it."""
    return validation.names("references", references, tuple(REFERENCES), allow_empty=True)


def reference_units(references) -> tuple:
    """The units of ``references`` (names among ``REFERENCES``)."""
    return tuple(REFERENCES[n] for n in references)


def reference_values(vy, vx, references) -> list:
    """The reference outputs for lateral velocity ``vy`` [m/s] and longitudinal speed ``vx``
    [m/s] (> 0): vy itself, beta = arctan(vy / vx) [rad]; one scalar per name."""
    return [vy if n == "vy" else jnp.arctan(vy / vx) for n in references]


def accelerometer_reading(ay, r, r_dot, xa, ya):
    """ay_s = ay + xa r' - ya r^2 [m/s^2]: the lateral specific force at (xa, ya) [m] of a planar
    rigid body whose CoG reads ``ay`` [m/s^2], with yaw rate ``r`` [rad/s] and yaw acceleration
    ``r_dot`` [rad/s^2]."""
    return ay + xa * r_dot - ya * r**2
