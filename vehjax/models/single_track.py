"""Planar single-track (bicycle) model for identification: lateral velocity and yaw rate.

The car is reduced to one front and one rear axle (both tyres of an axle lumped), moving in the
road plane at a known longitudinal speed ``vx`` (an input, e.g. from the wheel speeds). Sign
conventions as in the rest of :mod:`vehjax.models` (ISO 8855, x forward, y left, z up):
``vy`` > 0 moves the car to its left, ``r`` > 0 turns it left, ``delta`` > 0 steers left, and a
positive slip angle gives a positive (leftward) lateral tyre force.

Equations of motion (rigid body in the plane, lateral and yaw balance at the CoG)::

    m (vy' + vx r) = Ff cos(delta) + Fr
    iz r'          = lf Ff cos(delta) - lr Fr
    ay             = (Ff cos(delta) + Fr) / m          (what a lateral accelerometer at the CoG reads)

with the axle forces Ff = F_f(alpha_f), Fr = F_r(alpha_r) from one of three tyre curves
(``tyres=``):

* ``"linear"``: the textbook linear single-track model, small angles throughout:
  alpha_f = delta - (vy + lf r) / vx, alpha_r = (lr r - vy) / vx, Ff = cf alpha_f,
  Fr = cr alpha_r and cos(delta) = 1. For a constant vx it is linear time-invariant in
  (vy, r); its steady-state yaw-rate gain is r / delta = vx / (L + K vx^2) with the understeer
  gradient K = m (lr cr - lf cf) / (L cf cr) [rad s^2/m], L = lf + lr.
* ``"pacejka"``: Pacejka's magic formula per axle, F = D sin(C arctan(B alpha)) (E = 0, no
  shifts; :func:`magic_formula_axle`) with the peak D = mu Fz and the static axle load Fz
  (Fzf = m g lr / L, Fzr = m g lf / L, no load transfer). It is parameterised by its slope at
  zero slip, the cornering stiffness c = B C D [N/rad], so that B = c / (C D): the same cf, cr
  as the linear model (the small-slip slope equals them), plus the friction coefficient mu and
  the shape factors C (``shape_f``, ``shape_r``; 1 < C < 2 gives a peak and a fall-off to
  D sin(C pi / 2)).
* ``"brush"``: Fiala's brush model with a parabolic contact pressure and one friction
  coefficient mu (:func:`brush_axle`): with t = tan(alpha) and the full-sliding slip
  t_sl = 3 mu Fz / c, F = c t - c^2 / (3 mu Fz) |t| t + c^3 / (27 mu^2 Fz^2) t^3 for
  |t| < t_sl, and mu Fz sign(t) beyond; slope c at zero slip, saturating at mu Fz.

For the two saturating curves the slip angles are the exact ones of the axle velocities,
alpha_f = delta - arctan((vy + lf r) / vx), alpha_r = -arctan((vy - lr r) / vx), and the front
force enters the body y axis as Ff cos(delta) (its x component, Ff sin(delta), is taken up by the
speed input). All forms are valid for vx > 0 (the slip angles divide by vx).

Discretisation: ``transition`` integrates the continuous equations over ``dt`` with the input
held (zero-order hold) by ``substeps`` classical Runge-Kutta steps of dt / substeps (default 2,
i.e. RK4 at 5 ms for dt = 0.01 s). The fastest mode of the linear model has a rate of about
(cf + cr) / (m vx) (nominal values: 17 1/s at 10 m/s, 58 1/s at 3 m/s), so at the defaults
|lambda h| <= 0.3 down to 3 m/s, far inside RK4's stability interval (2.78) and with a local
error of order (lambda h)^5 / 120 < 2e-5 relative per step; use more substeps for lower speeds
or larger dt. The elementary functions are jax.numpy's (they compile in a fraction of the time of
:mod:`vehjax.lib.elementary`'s vectorisable ones, which pay off only in large particle filters).
tests/models/test_single_track.py checks the rollout against scipy's ``solve_ivp`` of
these equations.

Options (:mod:`vehjax.models.sensors`; off by default, which is the model above): ``lever_arm``
puts the accelerometer at (xa, ya) [m] in the body frame (two parameters appended to theta; it
reads ay + xa r' - ya r^2), ``references`` appends reference outputs (vy [m/s], beta [rad]) for
a calibration drive with an INS or an optical sensor. The tyre-lag variant, whose axle forces
are states that relax to the curve over a relaxation length, is
:class:`~vehjax.models.SingleTrackLag` (:mod:`vehjax.models.tyre_lag`).
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from jax.numpy import arctan, cos, sin

from .. import validation
from ..lib.priors import LogNormal, Normal
from . import domains as dom
from .base import VehicleModel, _check_dt, _check_integrator, _check_theta, integrate
from .sensors import (LEVER, LEVER_ARM, accelerometer_reading, check_references,
                      lever_arm_table, reference_units, reference_values)

#: Gravitational acceleration [m/s^2].
G = 9.81

TYRES = ("linear", "pacejka", "brush")

_BODY = ("m", "iz", "lf", "lr", "cf", "cr")
_BODY_UNITS = ("kg", "kg m^2", "m", "m", "N/rad", "N/rad")
_BODY_NOMINAL = (1500.0, 2700.0, 1.2, 1.5, 1.2e5, 1.4e5)

#: tyres -> (parameter names, units, nominal values)
_PARAMS = {
    "linear": (_BODY, _BODY_UNITS, _BODY_NOMINAL),
    "pacejka": (_BODY + ("mu", "shape_f", "shape_r"), _BODY_UNITS + ("-", "-", "-"),
                _BODY_NOMINAL + (1.0, 1.3, 1.3)),
    "brush": (_BODY + ("mu",), _BODY_UNITS + ("-",), _BODY_NOMINAL + (1.0,)),
}

#: how well a data sheet gives a parameter that a user cannot weigh: the sigma of a log-normal
#: prior around the given value (``SingleTrack.spec_priors``). The yaw inertia is rarely
#: measured (it needs a swing or a rig); a data sheet's comes from an empirical formula in the
#: mass and the wheelbase whose error for a given car is tens of per cent (a car 2.5 times its
#: sheet's is not unknown). The relaxation lengths: a factor of two between tyres and loads. The
#: mass and the centre of gravity (lf, lr) are not here: wheel-load scales measure them to a per
#: cent or two, and a fit that moves them stands in for a physics the model lacks (a tyre lag
#: or a roll mode moves lr by tens of per cent on a test drive; the sideslip, which the rear
#: slip angle ties to lr, follows it): they are reported when the data reject them, not refitted.
SPEC_UNCERTAINTY = {"iz": 0.3, "sigma_f": 0.7, "sigma_r": 0.7}
#: the std [m] of a normal prior around a given accelerometer position (xa, ya): a mounting
#: position read off a drawing or a tape measure, rarely exact to a decimetre
LEVER_UNCERTAINTY = 0.3

#: the relaxation lengths :class:`~vehjax.models.SingleTrackLag` appends: names, units, nominal
_LAG = (("sigma_f", "sigma_r"), ("m", "m"), (0.5, 0.5))


def param_table(tyres: str, lag: bool = False, lever_arm: bool = False) -> tuple:
    """(names, units, nominal values) of a single-track model's theta: the body's and the tyre
    curve's parameters, then the relaxation lengths (``lag``), then the accelerometer's lever
    arm (xa, ya) [m] (``lever_arm``)."""
    parts = (_PARAMS[tyres], _LAG if lag else ((), (), ()), lever_arm_table(lever_arm))
    return tuple(sum((p[i] for p in parts), ()) for i in range(3))


def body_forces(ff, fr, delta, lf, lr, small_angle: bool):
    """(Fy [N], Mz [N m]): lateral force and yaw moment at the CoG of the axle forces ``ff``,
    ``fr`` [N] (each in its wheel's frame); the front one enters as ff cos(delta) unless
    ``small_angle`` (the linear tyres' cos(delta) = 1)."""
    if not small_angle:
        ff = ff * cos(delta)
    return ff + fr, lf * ff - lr * fr


def axle_loads(m, lf, lr):
    """Static vertical loads (Fzf, Fzr) [N] of a car of mass ``m`` [kg] with its CoG ``lf``,
    ``lr`` [m] behind the front and ahead of the rear axle: m g lr / L and m g lf / L."""
    wheelbase = lf + lr
    return m * G * lr / wheelbase, m * G * lf / wheelbase


def magic_formula_axle(alpha, stiffness, mu, fz, shape):
    """Magic-formula axle force D sin(C arctan(B alpha)) [N] with D = mu fz, C = ``shape`` and
    B = stiffness / (C D), so that the slope at zero slip is ``stiffness``.

    Args:
        alpha: slip angle [rad], any shape (broadcasts with the rest).
        stiffness: cornering stiffness B C D [N/rad], > 0.
        mu: friction coefficient [-], > 0; fz: vertical axle load [N], > 0.
        shape: shape factor C [-], in (0, 2).
    """
    peak = mu * fz
    return peak * sin(shape * arctan(stiffness / (shape * peak) * alpha))


def brush_axle(alpha, stiffness, mu, fz):
    """Fiala's brush-model axle force [N] (parabolic pressure, one friction coefficient).

    With t = tan(alpha) and t_sl = 3 mu fz / stiffness: ``stiffness t - stiffness^2 / (3 mu fz)
    |t| t + stiffness^3 / (27 mu^2 fz^2) t^3`` for |t| < t_sl, ``mu fz sign(t)`` beyond. The
    slope at zero slip is ``stiffness`` [N/rad]; the force reaches mu fz at t_sl with zero slope.

    Args:
        alpha: slip angle [rad], |alpha| < pi / 2, any shape.
        stiffness: cornering stiffness [N/rad]; mu: friction coefficient [-]; fz: load [N].
    """
    return brush_force(sin(alpha) / cos(alpha), stiffness, mu, fz)


def brush_force(t, stiffness, mu, fz):
    """:func:`brush_axle` of the slip's tangent ``t`` = tan(alpha) [-], which the single-track
    model forms from the axle velocities without an arctan (:meth:`SingleTrack.axle_forces`)."""
    peak = mu * fz
    ts = jnp.clip(t, -3.0 * peak / stiffness, 3.0 * peak / stiffness)  # |t| <= t_sl
    # the cubic equals peak sign(t) at |t| = t_sl, so the clip continues it as the sliding branch
    return (stiffness * ts - stiffness**2 / (3.0 * peak) * jnp.abs(ts) * ts
            + stiffness**3 / (27.0 * peak**2) * ts**3)


class SingleTrack(VehicleModel):
    """Planar single-track model: lateral velocity and yaw rate (see the module docstring).

    States x = (vy, r): lateral velocity of the CoG [m/s] and yaw rate [rad/s].
    Inputs u = (delta, vx): road-wheel steering angle [rad] (> 0 left) and longitudinal speed
        [m/s] (> 0).
    Outputs y = (ay, r, *references): lateral acceleration (specific force) at the CoG, or at the
        accelerometer's position with ``lever_arm`` [m/s^2], and yaw rate [rad/s]; then the
        reference outputs asked for (``references``: vy [m/s], beta = arctan(vy / vx) [rad]).
    Parameters theta, by ``tyres``:

    * ``"linear"``: (m, iz, lf, lr, cf, cr) [kg, kg m^2, m, m, N/rad, N/rad];
    * ``"pacejka"``: those and (mu, shape_f, shape_r) [-];
    * ``"brush"``: those and (mu,) [-];
    * then, with ``lever_arm``, the accelerometer's position (xa, ya) [m] in the body frame
      (nominal 0, 0: at the CoG), and ay reads ay + xa r' - ya r^2 (:mod:`vehjax.models.sensors`).

    Nominal values (plausible for a mid-size car, not measured): 1500 kg, 2700 kg m^2, 1.2 m,
    1.5 m, 1.2e5 and 1.4e5 N/rad (understeer gradient 2.2e-3 rad s^2/m), mu = 1, C = 1.3.

    Domains (``PARAM_DOMAINS``, :meth:`~vehjax.models.BaseModel.param_domains`; checked at
    construction, by ``with_theta``, ``simulate`` and ``filter``/``run``):

    * m, iz in (0, inf): a physical necessity (the equations divide by them).
    * lf, lr in (0, inf): the CoG between the axles, a necessity for positive static axle
      loads (which the saturating tyres' peaks mu Fz use).
    * cf, cr in (0, inf): the sign convention of the module docstring (ISO 8855: a positive
      slip angle gives a positive force). Cornering stiffnesses in the SAE convention (y to the
      right, negative stiffnesses) convert by a change of sign; the error says so.
    * mu in (0, 3): positive by necessity; at most 3 by vehjax's convention (road tyres reach
      0.9-1.3, racing slicks about 1.5-2; 3 leaves room for some downforce, which the static
      loads do not model).
    * shape_f, shape_r in (0, 2): C > 0 by necessity (B = c / (C D)); C < 2 keeps the force's
      sign that of the slip angle at every slip (:func:`magic_formula_axle`).
    * xa, ya in (-5, 5) m: the accelerometer within the car (:data:`vehjax.models.sensors.LEVER`).

    State envelope (``STATE_ENVELOPE``, where :func:`vehjax.simulate` flags a run as
    diverged): |vy| <= 300 m/s, |r| <= 20 rad/s.

    Args:
        dt: sampling period [s], > 0.
        integrator: ``"rk4"`` (default) or ``"euler"``, applied ``substeps`` times per step.
        theta: parameter vector in the order above; None for the nominal values.
        tyres: ``"linear"``, ``"pacejka"`` or ``"brush"``.
        substeps: integration steps per sampling period (int >= 1, default 2).
        lever_arm: the accelerometer away from the CoG at (xa, ya), two parameters appended to
            theta (default False: at the CoG).
        references: reference outputs appended to (ay, r), names among ("vy", "beta") (default
            none). A drive without the reference feeds the column as NaN
            (:meth:`vehjax.data.Drive.for_model`'s ``missing_outputs``), which filters skip.
    """

    tyres: str = eqx.field(static=True)
    substeps: int = eqx.field(static=True)
    lever_arm: bool = eqx.field(static=True)
    references: tuple = eqx.field(static=True)
    #: whether the axle forces are lagged states (:class:`~vehjax.models.SingleTrackLag`)
    LAG: ClassVar[bool] = False

    STATE_NAMES = ("vy", "r")
    STATE_UNITS = ("m/s", "rad/s")
    INPUT_NAMES = ("delta", "vx")
    INPUT_UNITS = ("rad", "m/s")
    PARAM_NAMES, PARAM_UNITS, PARAM_NOMINAL = _PARAMS["linear"]  # per instance: ``param_names``
    PARAM_DOMAINS = {"m": dom.MASS, "iz": dom.INERTIA, "lf": dom.AXLE, "lr": dom.AXLE,
                     "cf": dom.CORNERING, "cr": dom.CORNERING, "mu": dom.FRICTION,
                     "shape_f": dom.SHAPE, "shape_r": dom.SHAPE, "xa": LEVER, "ya": LEVER}
    STATE_ENVELOPE = {"vy": dom.SPEED_LIMIT, "r": dom.RATE_LIMIT}

    def __init__(self, dt: float = 0.01, integrator: str = "rk4", theta=None,
                 tyres: str = "linear", substeps: int = 2, lever_arm: bool = False,
                 references=()):
        self.tyres = validation.choice("tyres", tyres, TYRES)
        self.substeps = validation.integer("substeps", substeps, 1)
        self.lever_arm = validation.flag("lever_arm", lever_arm)
        self.references = check_references(references)
        names, _, nominal = param_table(self.tyres, self.LAG, lever_arm)
        self.dt = _check_dt(dt)
        self.integrator = _check_integrator(integrator)
        self.theta = _check_theta(nominal if theta is None else theta, names)
        validation.in_domain("theta", self.theta, self.param_domains())

    param_names = property(lambda self: param_table(self.tyres, self.LAG, self.lever_arm)[0])
    param_units = property(lambda self: param_table(self.tyres, self.LAG, self.lever_arm)[1])
    output_names = property(lambda self: ("ay", "r") + self.references)
    output_units = property(lambda self: ("m/s^2", "rad/s") + reference_units(self.references))

    def axle_forces(self, x, u, theta):
        """(Ff, Fr): front and rear axle lateral forces [N], each in its wheel's frame."""
        vy, r = x[0], x[1]
        delta, vx = u[0], u[1]
        m, _, lf, lr, cf, cr = (theta[i] for i in range(6))
        if self.tyres == "linear":
            return cf * (delta - (vy + lf * r) / vx), cr * (lr * r - vy) / vx
        fzf, fzr = axle_loads(m, lf, lr)
        mu = theta[6]
        qf, qr = (vy + lf * r) / vx, (vy - lr * r) / vx
        if self.tyres == "pacejka":
            return (magic_formula_axle(delta - arctan(qf), cf, mu, fzf, theta[7]),
                    magic_formula_axle(-arctan(qr), cr, mu, fzr, theta[8]))
        # the brush curve reads tan(alpha): tan(delta - arctan(qf)) = (tan(delta) - qf) /
        # (1 + qf tan(delta)), tan(-arctan(qr)) = -qr; no arctan, one tan of the input
        td = sin(delta) / cos(delta)
        return (brush_force((td - qf) / (1.0 + qf * td), cf, mu, fzf),
                brush_force(-qr, cr, mu, fzr))

    def body_forces(self, x, u, theta):
        """(Fy [N], Mz [N m]): lateral force and yaw moment at the CoG (:func:`body_forces`)."""
        ff, fr = self.axle_forces(x, u, theta)
        return body_forces(ff, fr, u[0], theta[2], theta[3], self.tyres == "linear")

    def derivative(self, x, u, theta):
        """(vy', r') [m/s^2, rad/s^2], shape (2,)."""
        fy, mz = self.body_forces(x, u, theta)
        return jnp.stack([fy / theta[0] - u[1] * x[1], mz / theta[1]])

    def transition(self, x, u, theta):
        """State after ``dt`` seconds, input held: ``substeps`` integrator steps, shape (2,)."""
        return integrate(self.derivative, x, u, theta, self.dt, self.integrator, self.substeps)

    def lateral_acceleration(self, x, u, theta):
        """ay = Fy / m = vy' + vx r [m/s^2] at the CoG."""
        return self.body_forces(x, u, theta)[0] / theta[0]

    def observe(self, x, u, theta):
        """(ay [m/s^2], r [rad/s], *references), shape (ny,): ay at the accelerometer (at the
        CoG unless ``lever_arm``), the references in ``references`` order."""
        fy, mz = self.body_forces(x, u, theta)
        ay = fy / theta[0]
        if self.lever_arm:
            ay = accelerometer_reading(ay, x[1], mz / theta[1], theta[-2], theta[-1])
        return jnp.stack([ay, x[1], *reference_values(x[0], u[1], self.references)])

    def nested_model(self):
        """The linear-tyre model with this one's (m, iz, lf, lr, cf, cr) (and lever arm), dt,
        integrator, substeps and outputs; None for the linear tyres. The saturating curves'
        slope at zero slip is (cf, cr), so at a large mu they approach it (exactly so but for
        the small-angle slip angles and cos(delta) = 1 of the linear form)."""
        if self.tyres == "linear":
            return None
        names = param_table("linear", self.LAG, self.lever_arm)[0]
        theta = self.theta[np.array([self.param_names.index(n) for n in names])]
        return type(self)(dt=self.dt, integrator=self.integrator, theta=theta, tyres="linear",
                          substeps=self.substeps, lever_arm=self.lever_arm,
                          references=self.references)

    def data_floors(self, measurements, inputs) -> dict:
        """``{"mu": peak |ay| / g}`` for the saturating tyres (empty for the linear ones).

        The axle forces are at most mu Fz, so |ay| <= mu (Fzf + Fzr) / m = mu g. The peak is
        taken of |ay| averaged over 0.2 s (centred; NaN samples left out), so that sensor
        noise (0.3 m/s^2 per sample: about 0.07 after averaging at 100 Hz) adds little to it;
        the 0.2 s are short against the seconds a car holds a corner. See
        :func:`peak_lateral_acceleration`."""
        if self.tyres == "linear":
            return {}
        ay = np.asarray(measurements, dtype=float)[..., self.output_names.index("ay")]
        return {"mu": peak_lateral_acceleration(ay, self.dt) / G}

    def spec_priors(self) -> dict:
        """``{name: prior}`` for the parameters a user takes from a data sheet and cannot weigh
        (the yaw inertia; the relaxation lengths and the accelerometer's position where the
        model has them), centred at this model's values: log-normal with the relative stds of
        :data:`SPEC_UNCERTAINTY` (iz to 30 %), normal with :data:`LEVER_UNCERTAINTY` [m] for
        (xa, ya). The mass and the centre of gravity have none (scales measure them; see
        :data:`SPEC_UNCERTAINTY`), nor the tyre parameters (what a fit is for). See
        :meth:`vehjax.models.BaseModel.spec_priors`."""
        out = {}
        for j, name in enumerate(self.param_names):
            if name in SPEC_UNCERTAINTY:
                out[name] = LogNormal(float(self.theta[j]), SPEC_UNCERTAINTY[name])
            elif name in LEVER_ARM[0]:
                out[name] = Normal(float(self.theta[j]), LEVER_UNCERTAINTY)
        return out

    def understeer_gradient(self, theta=None):
        """K = m (lr cr - lf cf) / (L cf cr) [rad s^2/m] of the linear tyres (or the saturating
        ones at small slip); > 0 understeer."""
        m, _, lf, lr, cf, cr = (self.theta if theta is None else theta)[:6]
        return m * (lr * cr - lf * cf) / ((lf + lr) * cf * cr)

    # -- used by scenarios' driver model ----------------------------------------------------
    def body_velocity(self, x, u, theta):
        """(vx, vy, r) [m/s, m/s, rad/s]; vx is the input."""
        return u[1], x[0], x[1]

    def pose(self, x):
        return None

    def speed(self, x):
        """None: the speed is the input vx, not a state."""
        return None

    def drive_input(self, x, delta, accel, speed, theta):
        """(delta, vx) = (``delta``, ``speed``)."""
        return jnp.stack([delta, speed])

    def initial_state(self, speed):
        """Straight driving: zeros, shape (2,). ``speed`` enters as the input."""
        return jnp.zeros(2)


def peak_lateral_acceleration(ay, dt: float, window: float = 0.2) -> float:
    """The largest |ay| [m/s^2] of the lateral acceleration ``ay`` (T,) or (R, T) sampled every
    ``dt`` [s], after a centred moving average over ``window`` [s] (at least one sample) that
    leaves NaN samples out; 0.0 when every sample is NaN."""
    ay = np.atleast_2d(np.asarray(ay, dtype=float))
    n = max(1, int(round(window / dt)))
    kernel = np.ones(n)
    ok = np.isfinite(ay)
    sums = np.stack([np.convolve(np.where(o, a, 0.0), kernel, mode="same")
                     for a, o in zip(ay, ok)])
    counts = np.stack([np.convolve(o.astype(float), kernel, mode="same") for o in ok])
    means = np.abs(sums) / np.maximum(counts, 1.0)
    return float(np.max(np.where(counts > 0, means, 0.0)))

