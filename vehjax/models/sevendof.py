"""7-DOF dual-track model with Pacejka-89 tyres and load transfer (Wang et al. 2016, eq. 1-20).

Frame: ISO 8855 body axes, x forward, y left, z up, as the rest of vehjax; r > 0 turns left and
delta > 0 steers left. The wheels sit at (x_i, y_i) = (a, +tf/2) fl, (a, -tf/2) fr,
(-b, +tr/2) rl, (-b, -tr/2) rr.

How the transcription is read:

* The +/- signs of eq. 5, 7-10 and 13-14 are those of an SAE frame (y to the right, z down, so
  the *left* wheels sit at y = -t/2): e.g. eq. 9 puts u + tf/2 r under the front-left slip angle
  and eq. 7 adds the lateral load transfer to the left wheels for ay > 0. They are consistent in
  that frame. In ISO axes the track terms change sign: u_fl = u - tf/2 r, the left wheels lose
  load for ay > 0, and eq. 5 carries -tf/2 F'x_fl + tf/2 F'x_fr.
* Eq. 5: the yaw moment is sum_i (x_i F'y_i - y_i F'x_i) with F'x, F'y the wheel forces turned
  into body axes by the wheel's steer angle (delta at the front, 0 at the rear), as printed.
  The self-aligning torques Mz_ij are neglected: the paper gives no Mz coefficients, and the
  Pac89 example aligning-moment set peaks at D = c1 Fz^2 + c2 Fz = 35 N m per tyre at 3.16 kN,
  under 1 % of the a Fy ~ 4 kN m yaw moment of one saturated front tyre.
* Eq. 12-14: the slip is s = (re omega - u_w) / u_w with u_w the wheel-centre velocity along
  the wheel heading, vx_i cos(delta_i) + vy_i sin(delta_i), computed exactly. Eq. 13-14 are a
  small-angle approximation of the wheel-centre speed (their front a-beta term has the sign
  flipped against the rear one, a transcription slip). The denominator is
  sqrt(u_w^2 + eps^2), eps = 0.5 m/s: smooth and non-singular at standstill, within 0.03 % of
  |u_w| above 20 m/s.
* Eq. 9-10 use arctan2 so that a sampled state with u <= 0 gives finite numbers; for u > 0 it
  equals the printed arctan.
* Eq. 2 and 4 define ax and ay as the force sums over m (what an accelerometer at the CoG
  reads); u' = ax + v r and v' = ay - u r (eq. 1, 3).

Algebraic loop: the loads (eq. 7-8) depend on ax, ay through the tyre forces; z = (ax, ay) is
solved as a fixed point in a fixed number of steps (one plain pass from the static loads, then two
Newton steps), so the model stays a plain differentiable function; residuals about 1e-5 m/s^2 in
(ax, ay) at up to 0.9 g.

Tyres: Pacejka '89 pure-slip forces of :mod:`vehjax.models.tyres` per wheel, slip angle in
degrees, slip in percent, load in kN. Right-hand tyres use the coefficient sets as given
(camber 0.5 deg; the zero-slip side force of about 107 N then points to the car's centre line, as
static negative camber does); left-hand tyres are their mirror image, Fy_left(alpha) =
-Fy_right(-alpha), so the car is left-right symmetric and drives straight with zero steer.
Longitudinal and lateral forces are computed independently (no combined-slip reduction), as
eq. 15-17 are in the paper: a friction-ellipse clip would put a kink into the model's Jacobian,
and the scenarios' longitudinal slips stay below about 1 %. Loads are floored at 10 N (wheel
lift).

Wheel spin: Iw omega_i' = T_i - re Fx_i (no rolling resistance, no drag: the paper has none).
The wheel-spin modes are stiff (eigenvalues near -re^2 C_s / (Iw u_w), -1100 to -1300 1/s at
20 m/s), so ``transition`` integrates with RK4 in ``substeps`` equal sub-steps (default: at most
1 ms each, 10 for dt = 0.01 s), stable down to about 10 m/s; use more sub-steps for slower
driving, fewer only above about 25 m/s.

Integrators: ``integrator="ros2"`` takes one step of the linearly implicit Rosenbrock W-method
ROS2 per 10 ms, implicit only in the wheel spins (four scalar divisions): the cheap model for
filters (within 0.005 m/s, 3e-4 rad/s and 0.02 m/s^2 of fine RK4 over a double lane change, at
1/14 to 1/20 of RK4's cost); keep RK4 for the truth. ``integrator="etdrk4"`` takes ``substeps``
graded steps (default 3 per 10 ms) of Krogstad's fourth-order exponential Runge-Kutta method
with the wheel rows as its linear part (Krogstad 2005; Cox & Matthews 2002): classical order 4,
stiff order 3 (Hochbruck & Ostermann 2005), but it does not reach RK4-10's accuracy at a third
of its cost.

See docs/sevendof.md for the load loop's convergence, the wheel spins' eigenvalues and RK4's
stability limit, ROS2 and ETDRK4 in full (ETDRK4's stages and order conditions), and the table of
each integrator's errors and cost over the double lane change.
"""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..lib.elementary import arctan2, cos, sin
from . import domains as dom
from .base import VehicleModel
from .tyres import pacejka89_lateral, pacejka89_longitudinal

#: Gravitational acceleration [m/s^2].
G = 9.81

_SLIP_EPS = 0.5  # m/s, regularises the slip denominator near standstill
_FZ_MIN = 10.0  # N, load floor (wheel lift)
_LOAD_NEWTON_STEPS = 2  # Newton steps on the load-transfer loop, after one plain pass
_MAX_SUBSTEP = 1e-3  # s, default longest explicit (Euler, RK4) integration sub-step
_MAX_SUBSTEP_ROS2 = 1e-2  # s, default longest ROS2 sub-step
_MEAN_SUBSTEP_ETD = 1e-2 / 3.0  # s, default mean ETDRK4 sub-step (3 per 10 ms)
#: Integrators of :class:`SevenDOF`: the explicit ones of every vehicle model, ROS2 and ETDRK4.
INTEGRATORS = ("euler", "rk4", "ros2", "etdrk4")
# Per wheel (fl, fr, rl, rr): mirror sign (left tyres are mirror images of the right ones) and
# steered-wheel flag.
_MIRROR = (-1.0, 1.0, -1.0, 1.0)
_FRONT = (1.0, 1.0, 0.0, 0.0)


def _phi_functions(z, kmax):
    """phi_0(z) .. phi_kmax(z) elementwise, stacked on a new leading axis.

    phi_0 = exp, phi_k(z) = (phi_{k-1}(z) - 1/(k-1)!) / z = sum_n z^n / (n + k)!. For |z| >= 1 the
    upward recurrence from exp (it loses at most a factor k! of relative accuracy at |z| = 1);
    below, phi_kmax by its series and the downward recurrence phi_{k-1} = z phi_k + 1/(k-1)!,
    which is stable there. Both branches see safe arguments, so derivatives stay finite.
    """
    small = jnp.abs(z) < 1.0
    zb = jnp.where(small, -1.0, z)
    zs = jnp.where(small, z, 0.0)
    up = [jnp.exp(zb)]
    for k in range(1, kmax + 1):
        up.append((up[-1] - 1.0 / math.factorial(k - 1)) / zb)
    series = jnp.zeros_like(z)
    for n in reversed(range(16)):  # |z| < 1: the tail is below 1/(kmax + 16)! < 1e-17
        series = series * zs + 1.0 / math.factorial(n + kmax)
    down = [series]
    for k in range(kmax, 0, -1):
        down.append(zs * down[-1] + 1.0 / math.factorial(k - 1))
    down = down[::-1]
    return jnp.stack([jnp.where(small, d, u) for d, u in zip(down, up)])


def _per_wheel(values, like):
    return jnp.asarray(values, dtype=like.dtype)


# ETDRK4 (Krogstad's method; see the module docstring) in the form
#   Y_i = x + h (c_i phi_1(c_i h L) f(x) + sum_{1<j<i} a_ij(h L) D_j),
#   x'  = x + h (phi_1(h L) f(x) + sum_{j>1} b_j(h L) D_j),   D_j = f(Y_j) - f(x) - L (Y_j - x),
# c = (0, 1/2, 1/2, 1). Each a_ij, b_j is a combination of phi_k(c h L), k = 1..3, c = 1/2 or 1:
# _ETD_TABLE[row, source, k - 1, c index], rows Y_2, Y_3, Y_4 and x', sources f(x), D_2, D_3,
# D_4.
_ETD_C = (0.0, 0.5, 0.5, 1.0)
_ETD_C_PHI = (0.5, 1.0)
_ETD_GRADING = 1.0  # sub-step k of n is (1 + k) / (n (n + 1) / 2) of dt long


def _etd_table():
    t = np.zeros((4, 4, 3, 2))
    half, one = 0, 1
    t[0, 0, 0, half] = 0.5  # Y_2 = x + h/2 phi_1(h/2 L) f
    t[1, 0, 0, half] = 0.5  # Y_3 = x + h/2 phi_1(h/2 L) f + h phi_2(h/2 L) D_2
    t[1, 1, 1, half] = 1.0
    t[2, 0, 0, one] = 1.0  # Y_4 = x + h phi_1(h L) f + 2 h phi_2(h L) D_3
    t[2, 2, 1, one] = 2.0
    # x' = x + h (phi_1 f + (2 phi_2 - 4 phi_3) (D_2 + D_3) + (4 phi_3 - phi_2) D_4), all at h L
    t[3, 0, 0, one] = 1.0
    t[3, 1:3, 1, one], t[3, 1:3, 2, one] = 2.0, -4.0
    t[3, 3, 1, one], t[3, 3, 2, one] = -1.0, 4.0
    return t


_ETD_TABLE = _etd_table()


@functools.lru_cache(maxsize=None)
def _etd_schedule(dt: float, substeps: int):
    """Per iteration (sub-step t // 4, stage t % 4) of ``_etdrk4_transition``: stage-0 flag, the
    table's column of the stage (row, k - 1, c), the one-hot row that gives the next stage
    point, and the sub-step's length."""
    n_stages = len(_ETD_C)
    grow = 1.0 + _ETD_GRADING * np.arange(substeps)
    t = np.arange(substeps * n_stages)
    stage = t % n_stages
    return (stage == 0, np.moveaxis(_ETD_TABLE, 1, 0)[stage], np.eye(n_stages)[stage],
            (dt * grow / grow.sum())[t // n_stages])


_OUTPUT_SETS = {
    "eq20": (("r", "ay", "u"), ("rad/s", "m/s^2", "m/s")),
    "eq18": (
        ("u", "v", "ax", "ay", "r", "beta", "Gamma"),
        ("m/s", "m/s", "m/s^2", "m/s^2", "rad/s", "rad", "N m"),
    ),
}


class SevenDOF(VehicleModel):
    """Dual-track model: longitudinal, lateral and yaw motion plus the four wheel spins.

    States x = (u, v, r, omega_fl, omega_fr, omega_rl, omega_rr): body-frame velocities of the
        CoG [m/s], yaw rate [rad/s], wheel spin speeds [rad/s].
    Inputs u = (delta, T_fl, T_fr, T_rl, T_rr): front road-wheel steering angle [rad] and wheel
        torques [N m], drive positive, brake negative.
    Parameters theta = (m, iz, a, b, tf, tr, h, re, iw): mass [kg], yaw inertia [kg m^2], CoG to
        front and rear axle [m], front and rear track [m], CoG height [m], effective rolling
        radius [m], spin inertia of one wheel [kg m^2]. Nominal values are the paper's section 4
        (1685, 2580, 1.16, 1.36, 1.54, 1.59, 0.436, 0.36); the paper has no wheel inertia, and
        iw = 1.1 kg m^2 is our estimate for a wheel and tyre of this size (about 20 kg at a
        radius of gyration of 0.235 m). The tyre coefficients are constants of
        :mod:`vehjax.models.tyres`.
    Domains (``PARAM_DOMAINS``, :meth:`~vehjax.models.BaseModel.param_domains`): all nine in
        (0, inf): m, iz, iw by necessity (the equations divide by them), a, b with the CoG
        between the axles (the static loads stay positive), tf, tr, h, re lengths of the car.
        The tyres' signs are those of :mod:`vehjax.models.tyres` (fixed coefficients).
    State envelope: |u|, |v| <= 300 m/s, |r| <= 20 rad/s, |omega_i| <= 3000 rad/s.
    Outputs: ``outputs="eq20"`` gives eq. 20's (r, ay, u); ``outputs="eq18"`` gives eq. 18's
        (u, v, ax, ay, r, beta, Gamma) with beta = arctan(v / u) [rad] and Gamma the yaw
        moment [N m].
    ``integrator``: "rk4" (default), "euler", "ros2" (linearly implicit in the wheel spins) or
        "etdrk4" (exponential in the wheel spins); see the module docstring.
    ``substeps``: integration sub-steps per ``dt`` (default ceil(dt / 1 ms) for RK4 and Euler,
        ceil(dt / 10 ms) for ROS2, ceil(3 dt / 10 ms) for ETDRK4, whose sub-steps grow
        1 : 2 : 3 ...).

    Valid for u well above 0 (about 10 m/s and up with the default sub-steps). See the module
    docstring for the equations and how the transcription's typos are read.
    """

    outputs: str = eqx.field(static=True)
    substeps: int = eqx.field(static=True)

    STATE_NAMES = ("u", "v", "r", "omega_fl", "omega_fr", "omega_rl", "omega_rr")
    STATE_UNITS = ("m/s", "m/s", "rad/s", "rad/s", "rad/s", "rad/s", "rad/s")
    INPUT_NAMES = ("delta", "T_fl", "T_fr", "T_rl", "T_rr")
    INPUT_UNITS = ("rad", "N m", "N m", "N m", "N m")
    PARAM_NAMES = ("m", "iz", "a", "b", "tf", "tr", "h", "re", "iw")
    PARAM_UNITS = ("kg", "kg m^2", "m", "m", "m", "m", "m", "m", "kg m^2")
    PARAM_NOMINAL = (1685.0, 2580.0, 1.16, 1.36, 1.54, 1.59, 0.436, 0.36, 1.1)
    PARAM_DOMAINS = {"m": dom.MASS, "iz": dom.INERTIA, "a": dom.AXLE, "b": dom.AXLE,
                     "tf": dom.LENGTH, "tr": dom.LENGTH, "h": dom.LENGTH, "re": dom.LENGTH,
                     "iw": dom.INERTIA}
    STATE_ENVELOPE = {"u": dom.SPEED_LIMIT, "v": dom.SPEED_LIMIT, "r": dom.RATE_LIMIT,
                      **{w: 3000.0 for w in ("omega_fl", "omega_fr", "omega_rl", "omega_rr")}}

    def __init__(self, dt: float = 0.01, integrator: str = "rk4", theta=None,
                 outputs: str = "eq20", substeps: int | None = None):
        if integrator not in INTEGRATORS:
            raise ValueError(f"integrator: expected one of {INTEGRATORS}, got {integrator!r}")
        super().__init__(dt=dt, integrator="rk4", theta=theta)
        self.integrator = integrator
        if outputs not in _OUTPUT_SETS:
            raise ValueError(f"outputs: expected one of {tuple(_OUTPUT_SETS)}, got {outputs!r}")
        self.outputs = outputs
        if substeps is None:
            per_substep = {"ros2": _MAX_SUBSTEP_ROS2, "etdrk4": _MEAN_SUBSTEP_ETD}.get(
                integrator, _MAX_SUBSTEP)
            substeps = max(1, math.ceil(self.dt / per_substep - 1e-9))
        if isinstance(substeps, bool) or not isinstance(substeps, int) or substeps < 1:
            raise ValueError(f"substeps: expected a positive integer, got {substeps!r}")
        self.substeps = substeps

    output_names = property(lambda self: _OUTPUT_SETS[self.outputs][0])
    output_units = property(lambda self: _OUTPUT_SETS[self.outputs][1])

    # -- the equations ------------------------------------------------------------------------
    @staticmethod
    def _wheel_slips(x, u, theta):
        """Slip angles [rad] (eq. 9-10) and longitudinal slips [-] (eq. 12) of fl, fr, rl, rr,
        and d(slip)/d(omega) [s/rad] of each wheel."""
        vx, vy, r = x[0], x[1], x[2]
        omega = x[3:7]
        delta = u[0]
        a, b, tf, tr, re = theta[2], theta[3], theta[4], theta[5], theta[7]
        px = jnp.stack([a, a, -b, -b])
        py = jnp.stack([tf, -tf, tr, -tr]) / 2.0
        steer = _per_wheel(_FRONT, x) * delta
        wx = vx - r * py  # wheel-centre velocity in body axes
        wy = vy + r * px
        alpha = steer - arctan2(wy, wx)
        u_w = wx * cos(steer) + wy * sin(steer)
        den = jnp.sqrt(u_w**2 + _SLIP_EPS**2)
        return alpha, (re * omega - u_w) / den, re / den

    @staticmethod
    def _tyre_forces(alpha, slip, fz):
        """Wheel-frame forces (Fx, Fy) [N] from eq. 15-17 at loads ``fz`` [N], each (4,)."""
        fz_kn = jnp.maximum(fz, _FZ_MIN) / 1000.0
        mirror = _per_wheel(_MIRROR, alpha)
        fx = pacejka89_longitudinal(100.0 * slip, fz_kn)
        fy = mirror * pacejka89_lateral(mirror * jnp.rad2deg(alpha), fz_kn)
        return fx, fy

    @staticmethod
    def _body_forces(fx, fy, delta, theta):
        """Sum of forces along body x, y [N] and yaw moment Gamma [N m] (eq. 2, 4, 5)."""
        a, b, tf, tr = theta[2], theta[3], theta[4], theta[5]
        steer = _per_wheel(_FRONT, fx) * delta
        c, s = cos(steer), sin(steer)
        fxb = fx * c - fy * s  # F'x of eq. 5
        fyb = fy * c + fx * s  # F'y of eq. 5
        px = jnp.stack([a, a, -b, -b])
        py = jnp.stack([tf, -tf, tr, -tr]) / 2.0
        gamma = jnp.sum(px * fyb - py * fxb)
        return jnp.sum(fxb), jnp.sum(fyb), gamma

    @staticmethod
    def _loads(ax, ay, theta):
        """Vertical loads [N] of fl, fr, rl, rr (eq. 7-8 in ISO axes)."""
        m, a, b, tf, tr, h = theta[0], theta[2], theta[3], theta[4], theta[5], theta[6]
        l = a + b
        lat_f = m * ay * h / tf
        lat_r = m * ay * h / tr
        lon = 0.5 * m * ax * h / l
        half = 0.5 * m * G
        return jnp.stack([
            (half - lat_f) * b / l - lon,
            (half + lat_f) * b / l - lon,
            (half - lat_r) * a / l + lon,
            (half + lat_r) * a / l + lon,
        ])

    def _solve(self, x, u, theta, wheel_jacobian: bool = False):
        """Tyre forces, loads, (ax, ay) and Gamma with the load-transfer loop resolved.

        z = (ax, ay) is the fixed point of z -> (sum of body forces at the loads fz(z)) / m. One
        plain pass from the static loads, then Newton steps: the loads are affine in z,
        fz = fz0 + A z, and each tyre's forces depend on its own load only, so one forward-mode
        pass with a unit tangent on all four loads gives every dF_i/dFz_i and hence the 2x2
        Jacobian of the map.

        With ``wheel_jacobian`` it also returns d(Fx_i)/d(omega_i) [N s/rad] at the solved loads
        (the loads held fixed: their dependence on omega_i through (ax, ay) is left out).
        """
        m = theta[0]
        delta = u[0]
        alpha, slip, dslip = self._wheel_slips(x, u, theta)
        steer = _per_wheel(_FRONT, x) * delta
        c, s = cos(steer), sin(steer)
        zero = jnp.zeros((), dtype=x.dtype)
        fz0 = self._loads(zero, zero, theta)
        dfz = jnp.stack([self._loads(zero + 1.0, zero, theta) - fz0,
                         self._loads(zero, zero + 1.0, theta) - fz0], axis=1)  # A, (4, 2)
        fx, fy = self._tyre_forces(alpha, slip, fz0)
        z = jnp.stack([jnp.sum(fx * c - fy * s), jnp.sum(fy * c + fx * s)]) / m
        ones = jnp.ones_like(fz0)

        def newton(_, z):
            (fx, fy), (dfx, dfy) = jax.jvp(
                lambda f: self._tyre_forces(alpha, slip, f), (fz0 + dfz @ z,), (ones,)
            )
            res = jnp.stack([jnp.sum(fx * c - fy * s), jnp.sum(fy * c + fx * s)]) / m - z
            grad = jnp.stack([dfx * c - dfy * s, dfy * c + dfx * s]) / m  # (2, 4)
            jac = jnp.eye(2, dtype=z.dtype) - grad @ dfz  # d(res)/dz = J - I, negated
            det = jac[0, 0] * jac[1, 1] - jac[0, 1] * jac[1, 0]
            return z + jnp.stack([jac[1, 1] * res[0] - jac[0, 1] * res[1],
                                  jac[0, 0] * res[1] - jac[1, 0] * res[0]]) / det

        # A loop, not unrolled, so that the tyre law is traced once (compile time).
        z = jax.lax.fori_loop(0, _LOAD_NEWTON_STEPS, newton, z)
        fz = fz0 + dfz @ z
        if wheel_jacobian:
            (fx, fy), (dfx, _) = jax.jvp(
                lambda sl: self._tyre_forces(alpha, sl, fz), (slip,), (ones,)
            )
        else:
            fx, fy = self._tyre_forces(alpha, slip, fz)
        sx, sy, gamma = self._body_forces(fx, fy, delta, theta)
        if wheel_jacobian:
            return fx, fz, sx / m, sy / m, gamma, dfx * dslip
        return fx, fz, sx / m, sy / m, gamma

    def derivative(self, x, u, theta):
        """(u', v', r', omega_i') [m/s^2, m/s^2, rad/s^2, rad/s^2 x4], eq. 1-6 plus wheel spin."""
        vx, vy, r = x[0], x[1], x[2]
        iz, re, iw = theta[1], theta[7], theta[8]
        fx, _, ax, ay, gamma = self._solve(x, u, theta)
        omega_dot = (u[1:5] - re * fx) / iw
        return jnp.concatenate([jnp.stack([ax + vy * r, ay - vx * r, gamma / iz]), omega_dot])

    def _wheel_rows(self, x, u, theta):
        """``derivative``, j_i = d(omega_i')/d(omega_i) [1/s] and q_i = d(omega_i)/d(u, v, r) at
        constant slip_i, loads held at their solved values (their dependence on the state
        through (ax, ay) is left out). Returns (xdot (7,), j (4,), q (4, 3))."""
        vx, vy, r = x[0], x[1], x[2]
        iz, re, iw = theta[1], theta[7], theta[8]
        fx, _, ax, ay, gamma, dfx = self._solve(x, u, theta, wheel_jacobian=True)
        omega_dot = (u[1:5] - re * fx) / iw
        xdot = jnp.concatenate([jnp.stack([ax + vy * r, ay - vx * r, gamma / iz]), omega_dot])
        # dfx is dFx/domega = dFx/dslip * dslip/domega.
        j = -re * dfx / iw
        # slip = (re omega - u_w) / den, den = sqrt(u_w^2 + eps^2), with u_w linear in (u, v, r):
        # d(slip)/d(u_w) = -(1 + slip u_w / den) / den and d(slip)/d(omega) = re / den.
        a, b, tf, tr = theta[2], theta[3], theta[4], theta[5]
        px = jnp.stack([a, a, -b, -b])
        py = jnp.stack([tf, -tf, tr, -tr]) / 2.0
        steer = _per_wheel(_FRONT, x) * u[0]
        c, s = cos(steer), sin(steer)
        duw_dbody = jnp.stack([c, s, px * s - py * c], axis=-1)  # (4, 3)
        wx, wy = vx - r * py, vy + r * px
        u_w = wx * c + wy * s
        den = jnp.sqrt(u_w**2 + _SLIP_EPS**2)
        slip = (re * x[3:] - u_w) / den
        return xdot, j, ((1.0 + slip * u_w / den) / re)[:, None] * duw_dbody

    def _derivative_and_wheel_jacobian(self, x, u, theta):
        """``derivative`` and the wheel-spin rows of its Jacobian.

        Returns (xdot (7,), j (4,), g (4, 3)): j_i = d(omega_i')/d(omega_i) [1/s] and
        g_i = d(omega_i')/d(u, v, r) [1/s^2 per m/s, per rad/s], both -re/iw dFx_i/dslip_i times
        d(slip_i)/d(omega_i, u, v, r), with the loads held at their solved values (their
        dependence on the state through (ax, ay) is left out).
        """
        xdot, j, q = self._wheel_rows(x, u, theta)
        return xdot, j, -j[:, None] * q

    def _wheel_linearisation(self, x, u, theta):
        """``derivative`` and the parts of its Jacobian that ETDRK4 uses, loads frozen.

        Returns (xdot (7,), j (4,), bmat (3, 4), q (4, 3)): j and q as ``_wheel_rows``;
        bmat = d(u', v', r')/d(omega) [m/s^2, m/s^2, rad/s^2 per rad/s]: with the loads held,
        u' = ax + v r, v' = ay - u r and r' = Gamma / iz depend on omega_i only through Fx_i,
        turned into body axes by the wheel's steer angle (eq. 2, 4, 5), and
        dFx_i/domega_i = -iw j_i / re.
        """
        m, iz, a, b, tf, tr, re, iw = (theta[0], theta[1], theta[2], theta[3], theta[4], theta[5],
                                       theta[7], theta[8])
        xdot, j, q = self._wheel_rows(x, u, theta)
        steer = _per_wheel(_FRONT, x) * u[0]
        c, s = cos(steer), sin(steer)
        px = jnp.stack([a, a, -b, -b])
        py = jnp.stack([tf, -tf, tr, -tr]) / 2.0
        bmat = jnp.stack([c / m, s / m, (px * s - py * c) / iz]) * (-iw * j / re)
        return xdot, j, bmat, q

    def derived(self, x, u, theta):
        """Eq. 18's vector (u, v, ax, ay, r, beta, Gamma), shape (7,).

        ax, ay [m/s^2] are the force sums over m (eq. 2, 4), beta = arctan(v / u) [rad] (eq. 11),
        Gamma [N m] the yaw moment (eq. 5).
        """
        _, _, ax, ay, gamma = self._solve(x, u, theta)
        beta = arctan2(x[1], x[0])
        return jnp.stack([x[0], x[1], ax, ay, x[2], beta, gamma])

    def wheel_loads(self, x, u, theta):
        """Vertical tyre loads (fl, fr, rl, rr) [N] after the load-transfer iteration."""
        return self._solve(x, u, theta)[1]

    def observe(self, x, u, theta):
        d = self.derived(x, u, theta)
        if self.outputs == "eq18":
            return d
        return jnp.stack([d[4], d[3], d[0]])

    def transition(self, x, u, theta):
        """State after ``dt`` seconds, ``substeps`` integrator steps with ``u`` held, (7,)."""
        if self.integrator == "etdrk4":
            return self._etdrk4_transition(x, u, theta)
        h = self.dt / self.substeps
        return jax.lax.fori_loop(0, self.substeps, lambda _, xk: self._step(xk, u, theta, h), x)

    def _step(self, x, u, theta, h):
        """One Euler, classic RK4 or ROS2 step of length ``h``. The RK4 stages run as a loop so
        that the derivative is traced once, which keeps compile times (jit, jacfwd) down."""
        if self.integrator == "euler":
            return x + h * self.derivative(x, u, theta)
        if self.integrator == "ros2":
            return self._ros2_step(x, u, theta, h)
        offsets = jnp.array([0.0, 0.5, 0.5, 1.0], dtype=x.dtype)
        weights = jnp.array([1.0, 2.0, 2.0, 1.0], dtype=x.dtype) / 6.0

        def stage(carry, cw):
            k_prev, acc = carry
            k = self.derivative(x + cw[0] * h * k_prev, u, theta)
            return (k, acc + cw[1] * k), None

        zero = jnp.zeros_like(x)
        (_, acc), _ = jax.lax.scan(stage, (zero, zero), jnp.stack([offsets, weights], axis=1))
        return x + h * acc

    def _ros2_step(self, x, u, theta, h):
        """One step of the two-stage Rosenbrock W-method ROS2 (Verwer, Spee, Blom & Hundsdorfer,
        SIAM J. Sci. Comput. 20(4), 1999), gamma = 1 + 1/sqrt(2)::

            W k1 = f(x),   W k2 = f(x + h k1) - 2 k1,   x' = x + h (3/2 k1 + 1/2 k2),

        W = I - gamma h J. J keeps the wheel-spin rows of the Jacobian (d omega_i' / d omega_i
        and d omega_i' / d(u, v, r)) and is zero in the body rows, so W is block lower
        triangular with a diagonal wheel block: each solve is four scalar divisions. ROS2 is
        second order for any J (a W-method); with the wheel rows exact the stiff wheel-spin
        modes are damped (not resolved) and the wheel speeds stay on their quasi-steady slip
        at every step. Without the d(u, v, r) coupling they would lag it by about 0.7 h and
        the method would drop to first order.
        """
        gamma = 1.0 + 1.0 / math.sqrt(2.0)
        dtype = x.dtype

        # The two stages run as a loop so that the derivative is traced once (compile time);
        # W is formed from the first stage's Jacobian rows and kept for the second.
        def stage(carry, coef):
            k_prev, scale, g, acc = carry
            first = coef[0] == 0.0
            f, j_new, g_new = self._derivative_and_wheel_jacobian(x + coef[0] * h * k_prev, u, theta)
            scale = jnp.where(first, 1.0 / (1.0 - gamma * h * j_new), scale)
            g = jnp.where(first, g_new, g)
            rhs = f - coef[1] * k_prev
            body = rhs[:3]
            k = jnp.concatenate([body, scale * (rhs[3:] + gamma * h * (g @ body))])
            return (k, scale, g, acc + coef[2] * k), None

        coefs = jnp.array([[0.0, 0.0, 1.5], [1.0, 2.0, 0.5]], dtype=dtype)
        carry0 = (jnp.zeros_like(x), jnp.ones(4, dtype), jnp.zeros((4, 3), dtype), jnp.zeros_like(x))
        (_, _, _, acc), _ = jax.lax.scan(stage, carry0, coefs)
        return x + h * acc

    def _etdrk4_transition(self, x, u, theta):
        """``substeps`` steps of Krogstad's ETDRK4 over ``dt``, sub-step lengths in the ratio
        1 : 2 : 3 ..., the linear part L formed once, at x (see docs/sevendof.md, ETDRK4)."""
        dtype = x.dtype
        first, cols, pick, hs = (jnp.asarray(a) for a in _etd_schedule(self.dt, self.substeps))
        cols, pick, hs = cols.astype(dtype), pick.astype(dtype), hs.astype(dtype)
        c_phi = jnp.asarray(_ETD_C_PHI, dtype)
        inv_fact = jnp.asarray([1.0, 0.5, 1.0 / 6.0], dtype)  # 1/k!, k = 1..3
        n_rows = cols.shape[1]
        f0, j, bmat, q = self._wheel_linearisation(x, u, theta)

        # Slip-aligned coordinates z = (u, v, r, w), w = omega - q (u, v, r), in which
        # L = [[0, B], [0, diag(j)]] and phi_k(c h L) = [[I / k!, c h B diag(phi_{k+1}(c h j))],
        # [0, diag(phi_k(c h j))]]. Products of two state-dependent arrays are written as
        # broadcasts and sums: tiny batched dot products are slow on CPU.
        def aligned(v):
            return jnp.concatenate([v[:3], v[3:] - jnp.sum(q * v[:3], axis=-1)])

        def unaligned(v):
            return jnp.concatenate([v[:3], v[3:] + jnp.sum(q * v[:3], axis=-1)])

        def couple(w):  # B w
            return jnp.sum(bmat * w, axis=-1)

        # Iteration (sub-step k, stage i) takes g = f (aligned) at its stage point z; stage 0
        # starts the sub-step, z_k = z. D_i (g itself at stage 0) adds, weighted by the table's
        # column i, into each row: rows 0-2 give the next stage points, row 3 gives z_{k+1}.
        # A row of acc holds 11 numbers: its body part's I / k! terms (3), the wheel vector
        # that reaches its body part through B (4), and its wheel part (4).
        def update(carry, coef, g):
            zk, z, g1, acc = carry
            first, col, pick, h = coef  # col: (row, k - 1, c)
            ch = h * c_phi
            phi = _phi_functions(ch[:, None] * j, 4)  # (k = 0..4, c, wheel)
            zk = jnp.where(first, z, zk)
            g1 = jnp.where(first, 0.0, g1)
            dw = z[3:] - zk[3:]
            d = g - g1 - jnp.concatenate([couple(dw), j * dw])
            weights = jnp.concatenate([
                jnp.broadcast_to(jnp.einsum("rkc,k->r", col, inv_fact)[:, None], (n_rows, 3)),
                jnp.einsum("rkc,c,kcw->rw", col, ch, phi[2:5]),
                jnp.einsum("rkc,kcw->rw", col, phi[1:4])], axis=1)
            acc = jnp.where(first, 0.0, acc) + weights * jnp.concatenate([d, d[3:]])
            row = jnp.sum(pick[:, None] * acc, axis=0)
            step = jnp.concatenate([row[:3] + couple(row[3:7]), row[7:]])
            return zk, zk + h * step, jnp.where(first, g, g1), acc

        def stage(carry, coef):
            g = aligned(self.derivative(unaligned(carry[1]), u, theta))
            return update(carry, coef, g), None

        coefs = (first, cols, pick, hs)
        z0 = aligned(x)
        # Sub-step 0's stage 0 needs no evaluation: f(x) came with the linear part. The other
        # stages run as one loop, so the derivative is traced once there (and once above).
        carry = update((z0, z0, z0, jnp.zeros((n_rows, 11), dtype)),
                       jax.tree_util.tree_map(lambda c: c[0], coefs), aligned(f0))
        (_, z, _, _), _ = jax.lax.scan(stage, carry, jax.tree_util.tree_map(lambda c: c[1:], coefs))
        return unaligned(z)

    # -- used by scenarios' driver model ----------------------------------------------------
    def body_velocity(self, x, u, theta):
        """(u, v, r) of the CoG in the body frame [m/s, m/s, rad/s]."""
        return x[0], x[1], x[2]

    def pose(self, x):
        return None

    def speed(self, x):
        return x[0]

    def drive_input(self, x, delta, accel, speed, theta):
        """Steer ``delta`` [rad] and wheel torques [N m] for longitudinal acceleration ``accel``.

        Feed-forward torque (m re + 4 iw / re) accel (body plus spin-up of all four wheels; the
        model has no rolling or air resistance), shared by all four wheels in proportion to
        the static axle loads, front b / l, rear a / l: all-wheel drive and four-wheel braking.
        """
        m, a, b, re, iw = theta[0], theta[2], theta[3], theta[7], theta[8]
        l = a + b
        total = (m * re + 4.0 * iw / re) * accel
        front = 0.5 * total * b / l
        rear = 0.5 * total * a / l
        return jnp.stack([delta, front, front, rear, rear])

    def initial_state(self, speed):
        """Straight driving at ``speed`` [m/s], wheels rolling freely (omega = speed / re)."""
        speed = jnp.asarray(speed, dtype=self.theta.dtype)
        w = speed / self.theta[7]
        zero = 0.0 * speed
        return jnp.stack([speed, zero, zero, w, w, w, w])
