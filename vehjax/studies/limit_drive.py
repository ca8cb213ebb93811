"""Simulated track drives at the friction limit, with a truth none of vehjax's fitted models is.

Why: a saturating tyre model (``vehjax.models.SingleTrack(tyres="brush" | "pacejka")``) fitted to a
drive can only be judged against a truth that is not itself one of the fitted models and whose
friction coefficient is known. :func:`limit_drive` simulates such a drive (issue 47, item 5).

The truth is a planar two-track car (states vy [m/s], r [rad/s]; inputs: road-wheel steer delta
[rad] of both front wheels and the longitudinal speed vx [m/s], a given time series), ISO 8855
axes (x forward, y left; wheels fl (lf, +tf/2), fr (lf, -tf/2), rl (-lr, +tr/2), rr (-lr, -tr/2))::

    m (vy' + vx r) = sum_i Fy_i cos(steer_i)                                   (= m ay)
    iz r'          = sum_i x_i Fy_i cos(steer_i) + y_i Fy_i sin(steer_i)

with steer_i = delta at the front, 0 at the rear, and the lateral force of each wheel in its own
frame from its exact slip angle alpha_i = steer_i - arctan((vy + x_i r) / (vx - y_i r)).

Each tyre follows the magic formula with a curvature factor E != 0 (Bakker, Pacejka & Lidner,
SAE 890087; :func:`vehjax.models.tyres.magic_formula` with no shifts)::

    Fy_i = D_i sin(C arctan(B_i alpha - E (B_i alpha - arctan(B_i alpha)))),
    D_i = mu Fz_i,  B_i = c_i / (C D_i),  c_i = (c_axle / 2) (Fz_i / Fz_static_i)^p

so every wheel's peak friction coefficient is exactly ``mu`` and the cornering stiffness falls
with load (p = 0.8 < 1: the lateral load transfer lowers the axle's stiffness). The vertical
loads are the static ones (m g lr / L, m g lf / L shared equally) plus the lateral load transfer
m ay h / t split between the axles by the roll-stiffness distribution (front share q):
dFz_f = m ay h q / tf, dFz_r = m ay h (1 - q) / tr (no roll dynamics, no roll centres, no
longitudinal load transfer; each load floored at 1 % of its static value, which the drives never
reach: their lightest wheel keeps about 800 N). None of vehjax's fitted models has these curves,
the load transfer or the second track.

Algebraic loop: the loads depend on ay, which depends on the forces. It is solved by plain
fixed-point passes ay <- Fy(loads(ay)) / m, which contract about 20-fold per pass at the limit
(each wheel's force is nearly proportional to its load): :func:`derivative` and the drive's
``ay`` take ``LOAD_PASSES`` = 7 passes from ay = 0 (residual below 1e-7 m/s^2, tested to 1e-6);
:func:`rollout` starts each Runge-Kutta stage's loop from the previous stage's ay and takes
``WARM_PASSES`` = 3 passes (ay moves little in half a sub-step).

The truth's peak friction coefficient, :attr:`LimitDrive.mu`: the two wheels of an axle peak at
slightly different slips when their loads differ, so the axle's peak force over its load falls a
little below mu. ``mu`` is the smaller over the two axles of max over slip of (axle force /
axle load), both wheels at one slip, at the load transfer of the drive's largest |ay|; it lies
within 1 % of the wheels' mu (0.2-0.4 % below it; tested).

Integration: classical RK4 with ``substeps`` equal sub-steps per sample (default: steps of at most
1 ms), the inputs interpolated linearly between samples (the truth's steering and speed are
continuous; a model with sampled, held inputs sees them half a sample late, about 0.01 deg of
steer). Against scipy's DOP853 (rtol 1e-11) on the converged loop, over 2 s at the drive's
peak, the states agree to about 1e-7 (m/s, rad/s; tested to 1e-6).

The drive: a lap of corners left and right at 15-35 m/s with straights between, written as a
schedule of lateral-acceleration targets (fractions of mu g) and speeds joined by half-cosine
ramps (:func:`lap_targets`), repeated to the requested duration. The driver steers open loop by
the truth's own steady-state inverse (:func:`steady_state`: the steer that holds the target ay at
the current speed), plus small smooth corrections (measured); the road wheels also carry a small
unmodelled disturbance (compliance, not measured), so the measured steer differs from the
truth's by about 0.18 deg (the input-noise std a fit would use). The sensors add white Gaussian
noise (:data:`NOISE`).

At the limit the car understeers (the front axle saturates first: the front's larger share of
the roll stiffness, cos(delta), and the yaw moment of the front wheels' unequal forces through
sin(delta)), so that it ploughs rather than spins. For the same reasons the two-track truth's
steady-state limit lies below mu g: at 0.92 mu g at 15 m/s up to 0.97 mu g at 32 m/s. The lap's
corner targets stay 2-5 % below it; the drives peak at about 1.39 g (A) and 1.27 g (B), with
about 15 % of the time above 1 g.

Limits: planar, no roll/pitch dynamics, no longitudinal forces (the speed is given), no aligning
torque, no combined slip; the data approach the tyres' peaks (front axle at 98 % of its peak
force at the drive's largest |ay|) but do not pass them.
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import validation
from ..models.tyres import magic_formula

__all__ = [
    "G", "LOAD_PASSES", "WARM_PASSES", "NOISE", "VARIANTS", "Truth", "LimitDrive", "limit_drive",
    "lap_targets", "wheel_force", "peak_slip", "wheel_loads", "wheel_stiffness", "slip_angles",
    "wheel_forces", "body_forces", "solve_ay", "lateral_acceleration", "derivative", "rollout",
    "steady_residual", "steady_state", "axle_peak_mu",
]

#: Gravitational acceleration [m/s^2] (that of vehjax.models.SingleTrack).
G = 9.81

#: Fixed-point passes of the load loop from ay = 0 (:func:`solve_ay`, :func:`derivative`), and
#: from the previous stage's ay in :func:`rollout` (module docstring).
LOAD_PASSES = 7
WARM_PASSES = 3

#: Default sensor and disturbance standard deviations: ay [m/s^2], r [rad/s], measured steer
#: delta [rad] (white), vx [m/s] (white), and the unmeasured road-wheel steer disturbance [rad]
#: (smooth, 0.05-1 Hz).
NOISE = {"ay": 0.25, "r": np.deg2rad(0.3), "delta": np.deg2rad(0.15), "vx": 0.05,
         "steer_disturbance": np.deg2rad(0.1)}

_DRIVER_STD = np.deg2rad(0.15)  # rad, the driver's smooth steering corrections (measured)


class Truth(NamedTuple):
    """Parameters of the two-track truth (module docstring).

    Attributes:
        m: mass [kg]; iz: yaw inertia [kg m^2]; lf, lr: CoG to front / rear axle [m].
        h: CoG height [m]; track_f, track_r: track widths [m].
        roll_front: front share q of the roll stiffness [-], in (0, 1).
        cf, cr: axle cornering stiffness at the static loads and zero slip [N/rad].
        load_exponent: p of c_i ~ Fz_i^p [-].
        mu: every wheel's peak friction coefficient [-].
        shape: C [-], in (1, 2); curvature: E [-], < 1, != 0.
    """

    m: float
    iz: float
    lf: float
    lr: float
    h: float
    track_f: float
    track_r: float
    roll_front: float
    cf: float
    cr: float
    load_exponent: float
    mu: float
    shape: float
    curvature: float


class LimitDrive(NamedTuple):
    """A simulated limit drive (:func:`limit_drive`); T samples at ``dt``.

    Attributes:
        t: (T,) time [s] of each row, from 0.
        inputs: (T, 2) measured inputs (delta [rad] road-wheel steer, vx [m/s]), the order of
            ``vehjax.models.SingleTrack``'s inputs.
        measurements: (T, 2) measured outputs (ay [m/s^2], r [rad/s]), SingleTrack's output order.
        states: (T, 2) true (vy [m/s], r [rad/s]) at ``t``.
        sideslip: (T,) true sideslip arctan(vy / vx) [rad].
        ay: (T,) true lateral acceleration [m/s^2].
        true_inputs: (T, 2) the truth's (delta [rad] with its disturbance, vx [m/s]).
        x0: (2,) the state at t[0] and before it, for a filter's ``x0`` (zeros: the drive
            starts on a straight).
        mu: the truth's peak friction coefficient (module docstring) [-].
        axle_mu: (front, rear) peak (axle force / axle load) at the drive's largest |ay| [-].
        body: what a data sheet gives: {"m" [kg], "iz" [kg m^2], "lf" [m], "lr" [m]}.
        noise_std: the standard deviations used (keys of :data:`NOISE`, same units).
        truth: every parameter of the truth (:class:`Truth`).
        variant: "A" or "B"; seed: the seed.
    """

    t: np.ndarray
    inputs: np.ndarray
    measurements: np.ndarray
    states: np.ndarray
    sideslip: np.ndarray
    ay: np.ndarray
    true_inputs: np.ndarray
    x0: np.ndarray
    mu: float
    axle_mu: tuple
    body: dict
    noise_std: dict
    truth: Truth
    variant: str
    seed: int


# -- the tyre and the loads --------------------------------------------------------------------

def wheel_force(alpha, stiffness, mu, fz, shape, curvature):
    """Magic-formula lateral force [N] of one wheel: D sin(C arctan(B a - E (B a - arctan(B a))))
    with D = mu fz, C = ``shape``, E = ``curvature`` and B = stiffness / (C D), so that the slope
    at zero slip is ``stiffness`` [N/rad] and the peak is mu fz (for 1 < C < 2, E < 1), at
    :func:`peak_slip`. ``alpha`` [rad], any shape (broadcasts)."""
    peak = mu * fz
    return magic_formula(alpha, stiffness / (shape * peak), shape, peak, curvature, 0.0, 0.0)


def peak_slip(stiffness, mu, fz, shape, curvature, iterations: int = 30):
    """Slip angle [rad] of :func:`wheel_force`'s peak: B alpha = x solves
    (1 - E) x + E arctan(x) = tan(pi / (2 C)) (so that C arctan(...) = pi / 2). Newton from
    the E = 0 root tan(pi / (2 C)), monotone for E < 1 (the left side is increasing, convex for
    E < 0 and concave for E > 0, and the start lies on the side that converges)."""
    target = jnp.tan(jnp.pi / (2.0 * shape))
    x = target
    for _ in range(iterations):
        res = (1.0 - curvature) * x + curvature * jnp.arctan(x) - target
        x = x - res / ((1.0 - curvature) + curvature / (1.0 + x * x))
    return x * shape * mu * fz / stiffness


def _static(truth):
    """(front, rear) static load of one wheel [N]."""
    wheelbase = truth.lf + truth.lr
    return truth.m * G * truth.lr / wheelbase / 2.0, truth.m * G * truth.lf / wheelbase / 2.0


def wheel_loads(truth: Truth, ay):
    """Vertical loads (fl, fr, rl, rr) [N] at lateral acceleration ``ay`` [m/s^2] (> 0 loads the
    right wheels), shape (4,): static plus the lateral transfer (module docstring)."""
    fzf, fzr = _static(truth)
    dzf = truth.m * ay * truth.h * truth.roll_front / truth.track_f
    dzr = truth.m * ay * truth.h * (1.0 - truth.roll_front) / truth.track_r
    static = jnp.stack([fzf, fzf, fzr, fzr])
    return jnp.maximum(static + jnp.stack([-dzf, dzf, -dzr, dzr]), 0.01 * static)


def wheel_stiffness(truth: Truth, fz):
    """Cornering stiffness (fl, fr, rl, rr) [N/rad] at loads ``fz`` (4,): (c_axle / 2)
    (Fz / Fz_static)^p."""
    fzf, fzr = _static(truth)
    static = jnp.stack([fzf, fzf, fzr, fzr])
    half = 0.5 * jnp.stack([truth.cf, truth.cf, truth.cr, truth.cr])
    return half * (fz / static) ** truth.load_exponent


def _geometry(truth: Truth):
    """Wheel positions x_i, y_i [m], (4,) each, in the order fl, fr, rl, rr."""
    px = jnp.stack([truth.lf, truth.lf, -truth.lr, -truth.lr])
    py = 0.5 * jnp.stack([truth.track_f, -truth.track_f, truth.track_r, -truth.track_r])
    return px, py


def slip_angles(truth: Truth, x, u):
    """Exact slip angles (fl, fr, rl, rr) [rad] at state x = (vy, r), input u = (delta, vx)."""
    px, py = _geometry(truth)
    steer = jnp.stack([u[0], u[0], 0.0 * u[0], 0.0 * u[0]])
    return steer - jnp.arctan((x[0] + px * x[1]) / (u[1] - py * x[1]))


def wheel_forces(truth: Truth, alpha, ay):
    """Lateral forces (fl, fr, rl, rr) [N], each in its wheel's frame, at slips ``alpha`` (4,)
    and the loads of lateral acceleration ``ay``."""
    fz = wheel_loads(truth, ay)
    return wheel_force(alpha, wheel_stiffness(truth, fz), truth.mu, fz, truth.shape,
                       truth.curvature)


def body_forces(truth: Truth, forces, delta):
    """(Fy [N], Mz [N m]): lateral force and yaw moment at the CoG of wheel forces (4,)."""
    px, py = _geometry(truth)
    cos, sin = jnp.cos(delta), jnp.sin(delta)
    fy = jnp.stack([forces[0] * cos, forces[1] * cos, forces[2], forces[3]])
    fx = -jnp.stack([forces[0] * sin, forces[1] * sin, 0.0 * forces[2], 0.0 * forces[3]])
    return fy.sum(), (px * fy - py * fx).sum()


def solve_ay(truth: Truth, x, u, ay0=0.0, passes: int = LOAD_PASSES):
    """(ay [m/s^2], wheel forces (4,) [N]) at x, u: the load loop by ``passes`` fixed-point
    passes from ``ay0``; the forces are those at the last pass's loads and ay their body force
    over m. Each pass shrinks the error about 20-fold near the limit (3e-8 m/s^2 after the
    default 7 passes from ay0 = 0 at 1.4 g)."""
    alpha = slip_angles(truth, x, u)
    ay = jnp.zeros_like(x[0]) + ay0
    for _ in range(passes):
        forces = wheel_forces(truth, alpha, ay)
        ay = body_forces(truth, forces, u[0])[0] / truth.m
    return ay, forces


@partial(jax.jit, static_argnames="passes")
def lateral_acceleration(truth: Truth, states, inputs, ay0=0.0, passes: int = LOAD_PASSES):
    """ay [m/s^2] (T,) at states (T, 2) and inputs (T, 2), the load loop by ``passes`` passes
    from ``ay0`` (scalar or (T,)); the loop's residual at ay is
    ``lateral_acceleration(truth, states, inputs, ay, passes=1) - ay``."""
    ay0 = jnp.broadcast_to(ay0, states.shape[:1])
    return jax.vmap(lambda x, u, a: solve_ay(truth, x, u, a, passes)[0])(states, inputs, ay0)


def _derivative(truth: Truth, x, u, ay0, passes: int):
    """((vy', r'), ay) with the load loop started at ``ay0``."""
    ay, forces = solve_ay(truth, x, u, ay0, passes)
    fy, mz = body_forces(truth, forces, u[0])
    return jnp.stack([fy / truth.m - u[1] * x[1], mz / truth.iz]), ay


def derivative(truth: Truth, x, u):
    """(vy', r') [m/s^2, rad/s^2], shape (2,), the load loop converged from ay = 0."""
    return _derivative(truth, x, u, 0.0, LOAD_PASSES)[0]


# -- integration -------------------------------------------------------------------------------

@partial(jax.jit, static_argnames="substeps")
def rollout(truth: Truth, x0, inputs, dt, substeps: int = 10):
    """States (T, 2) at the input samples: row 0 is ``x0`` and row k the RK4 solution at k dt,
    ``substeps`` steps per sample with the inputs (T, 2) interpolated linearly between samples.
    Each stage's load loop starts from the previous stage's ay (``WARM_PASSES`` passes; the
    first from ``LOAD_PASSES`` at x0): ay moves little in half a sub-step. Over 2 s at the
    drive's peak the states stay within about 1e-7 (m/s, rad/s) of the converged loop's
    (DOP853 on :func:`derivative`, tested); RK4's own error at 1 ms is about 1e-11 there."""
    h = dt / substeps

    def f(x, u, ay):
        return _derivative(truth, x, u, ay, WARM_PASSES)

    def sample(carry, pair):
        u0, u1 = pair

        def sub(j, carry):
            x, ay = carry
            ua, um, ub = (u0 + (j + s) / substeps * (u1 - u0) for s in (0.0, 0.5, 1.0))
            k1, ay = f(x, ua, ay)
            k2, ay = f(x + 0.5 * h * k1, um, ay)
            k3, ay = f(x + 0.5 * h * k2, um, ay)
            k4, ay = f(x + h * k3, ub, ay)
            return x + h / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4), ay

        carry = jax.lax.fori_loop(0, substeps, sub, carry)
        return carry, carry[0]

    start = (x0, solve_ay(truth, x0, inputs[0])[0])
    _, xs = jax.lax.scan(sample, start, (inputs[:-1], inputs[1:]))
    return jnp.concatenate([x0[None], xs])


# -- the driver and the peak --------------------------------------------------------------------

def steady_residual(truth: Truth, z, ay, vx):
    """(vy' [m/s^2], r' [rad/s^2]) at z = (vy [m/s], delta [rad]), r = ay / vx and the loads of
    ``ay`` [m/s^2] at speed ``vx`` [m/s]: zero where z holds steady cornering at ay."""
    x, u = jnp.stack([z[0], ay / vx]), jnp.stack([z[1], vx])
    fy, mz = body_forces(truth, wheel_forces(truth, slip_angles(truth, x, u), ay), z[1])
    return jnp.stack([fy / truth.m - ay, mz / truth.iz])


@partial(jax.jit, static_argnames="iterations")
def steady_state(truth: Truth, ay, vx, iterations: int = 3):
    """(vy [m/s], delta [rad]) (T, 2): the lateral velocity and road-wheel steer that hold
    lateral acceleration ``ay`` (T,) [m/s^2] at speed ``vx`` (T,) [m/s] in steady state
    (r = ay / vx, vy' = r' = 0, loads at ay); its delta is the driver of :func:`limit_drive`.
    Newton in (vy, delta), ``iterations`` steps per sample, each sample
    started from the previous one's solution (the first from straight driving, so ``ay[0]``
    should be 0), steps clipped to 0.5 m/s and 0.02 rad. Needs a slowly varying ay below the
    front axle's peak, which the two-track truth reaches below mu g (variant A: 0.93 mu g at
    17 m/s, 0.96 at 28 m/s); check :func:`steady_residual` of the result."""
    limit = jnp.array([0.5, 0.02])

    def sample(z, target):
        def newton(_, z):
            jac = jax.jacfwd(steady_residual, argnums=1)(truth, z, *target)
            step = jnp.linalg.solve(jac, steady_residual(truth, z, *target))
            return z - jnp.clip(step, -limit, limit)

        z = jax.lax.fori_loop(0, iterations, newton, z)
        return z, z

    return jax.lax.scan(sample, jnp.zeros(2), (ay, vx))[1]


def axle_peak_mu(truth: Truth, ay, max_slip: float = 0.6, points: int = 60001):
    """(front, rear): max over slip of (axle force / axle load) [-], both wheels of an axle at one
    slip in [0, ``max_slip``] rad (a grid of ``points``), at the loads of ``ay`` [m/s^2]."""
    front, rear = _axle_peak_mu(truth, ay, max_slip, points)
    return float(front), float(rear)


@partial(jax.jit, static_argnames="points")
def _axle_peak_mu(truth: Truth, ay, max_slip, points: int):
    alpha = jnp.linspace(0.0, max_slip, points)
    fz = wheel_loads(truth, ay)
    c = wheel_stiffness(truth, fz)
    f = wheel_force(alpha[:, None], c, truth.mu, fz, truth.shape, truth.curvature)
    front = (f[:, 0] + f[:, 1]).max() / (fz[0] + fz[1])
    rear = (f[:, 2] + f[:, 3]).max() / (fz[2] + fz[3])
    return front, rear


# -- the drives ----------------------------------------------------------------------------------

_TRUTH_A = Truth(m=1650.0, iz=2900.0, lf=1.15, lr=1.55, h=0.45, track_f=1.62, track_r=1.60,
                 roll_front=0.58, cf=1.85e5, cr=1.65e5, load_exponent=0.8, mu=1.45, shape=1.45,
                 curvature=-0.8)
_TRUTH_B = Truth(m=1420.0, iz=2250.0, lf=1.22, lr=1.43, h=0.46, track_f=1.58, track_r=1.57,
                 roll_front=0.55, cf=1.70e5, cr=1.75e5, load_exponent=0.8, mu=1.30, shape=1.35,
                 curvature=-0.4)

# A lap: the starting (speed [m/s], ay / (mu g)), then (seconds to get there, speed, ay / (mu g))
# joined by half-cosine ramps; a knot equal to the one before is a hold. The last knot equals
# the start so that laps join smoothly. The corner targets stay 2-5 % below the truth's
# steady-state limit at their speed.
_LAP_A = ((25.0, 0.0), (
    (3.0, 33.0, 0.0), (1.5, 33.0, 0.0), (2.0, 20.0, 0.0),                        # straight, brake
    (1.0, 20.0, -0.91), (1.2, 20.0, -0.91), (1.5, 25.0, 0.0),                    # right, 1.32 g
    (2.0, 28.0, 0.0), (1.2, 27.0, 0.5), (1.5, 27.0, 0.5),                        # left sweeper
    (1.5, 27.0, -0.55), (1.2, 27.0, -0.55), (1.2, 29.0, 0.0),                   # chicane right
    (3.5, 35.0, 0.0), (1.0, 35.0, 0.0), (2.5, 17.0, 0.0),                        # straight, brake
    (1.0, 17.0, 0.88), (1.2, 17.0, 0.88), (1.5, 22.0, 0.0),                      # hairpin left
    (2.5, 28.0, 0.0), (1.2, 28.0, -0.72), (1.2, 28.0, -0.72), (1.2, 30.0, 0.0),  # right 1.04 g
    (1.5, 30.0, 0.35), (1.0, 30.0, 0.35), (1.2, 31.0, 0.0), (2.0, 34.0, 0.0),    # left kink
    (2.0, 25.0, 0.0), (1.0, 25.0, -0.935), (1.2, 25.0, -0.935), (1.5, 27.0, 0.0),  # right 1.36 g
    (1.2, 26.0, 0.6), (1.5, 26.0, 0.6), (1.5, 25.0, 0.0),                        # left
))
_LAP_B = ((22.0, 0.0), (
    (2.5, 30.0, 0.0), (1.0, 30.0, 0.0), (1.2, 30.0, 0.45), (1.5, 30.0, 0.45),   # fast left
    (1.2, 31.0, 0.0), (3.0, 34.0, 0.0), (2.5, 18.0, 0.0),                        # straight, brake
    (1.0, 18.0, -0.88), (1.3, 18.0, -0.88), (1.5, 23.0, 0.0),                    # right, 1.14 g
    (1.2, 23.0, 0.8), (1.0, 23.0, 0.8), (1.2, 23.0, -0.75), (1.0, 23.0, -0.75),  # esses
    (1.2, 26.0, 0.0), (3.0, 32.0, 0.0), (2.0, 27.0, 0.0),                        # straight, brake
    (1.0, 27.0, 0.94), (1.4, 27.0, 0.94), (1.5, 29.0, 0.0),                      # left, 1.22 g
    (2.0, 27.0, 0.0), (1.2, 27.0, -0.6), (2.0, 27.0, -0.6), (1.2, 28.0, 0.0),    # long right
    (2.5, 33.0, 0.0), (2.0, 16.0, 0.0), (1.0, 16.0, 0.85), (1.2, 16.0, 0.85),    # hairpin left
    (1.5, 20.0, 0.0), (2.0, 26.0, 0.0), (1.0, 26.0, -0.94), (1.2, 26.0, -0.94),  # right, 1.22 g
    (1.5, 24.0, 0.0), (1.5, 22.0, 0.0),
))

#: variant -> (truth, lap, seed offset): A for tuning, B held back from any tuning.
VARIANTS = {"A": (_TRUTH_A, _LAP_A, 0), "B": (_TRUTH_B, _LAP_B, 1)}


def lap_targets(variant: str, t):
    """(speed vx [m/s], lateral-acceleration target [m/s^2]) of ``variant``'s lap at times ``t``
    [s] (numpy, laps repeating): the driver's plan; the drive's ay follows it within the
    steering corrections and the transients."""
    truth, ((v0, a0), knots), _ = VARIANTS[validation.choice("variant", variant, tuple(VARIANTS))]
    dur = np.array([k[0] for k in knots])
    start = np.concatenate([[0.0], np.cumsum(dur)])
    values = np.array([(v0, a0)] + [(k[1], k[2]) for k in knots])
    tau = np.mod(t, start[-1])
    i = np.clip(np.searchsorted(start, tau, side="right") - 1, 0, len(knots) - 1)
    w = 0.5 * (1.0 - np.cos(np.pi * (tau - start[i]) / dur[i]))
    prof = values[i] + w[:, None] * (values[i + 1] - values[i])
    return prof[:, 0], prof[:, 1] * truth.mu * G


def _smooth_noise(rng, t, std: float, f_lo: float, f_hi: float, n: int = 24):
    """A smooth random signal of standard deviation ``std``: n sinusoids of random frequency in
    [f_lo, f_hi] Hz and random phase, each of amplitude std sqrt(2 / n)."""
    f = rng.uniform(f_lo, f_hi, n)
    phase = rng.uniform(0.0, 2.0 * np.pi, n)
    return std * np.sqrt(2.0 / n) * np.sin(2.0 * np.pi * f * t[:, None] + phase).sum(axis=1)


def limit_drive(variant: str = "A", duration: float = 200.0, dt: float = 0.01, seed: int = 0,
                substeps: int | None = None, noise: dict | None = None) -> LimitDrive:
    """Simulate a track drive at the friction limit (module docstring).

    Variant "A" (for tuning): 1650 kg, mu 1.45, peaks near 1.39 g. Variant "B" (held back from
    any tuning): 1420 kg, mu 1.30, other geometry, tyre shape, lap and speeds, peaks near 1.27 g.
    Deterministic given (variant, seed): the noise, the driver's corrections and the steering
    disturbance come from numpy's generator seeded with (seed, variant); the lap is fixed.

    Args:
        variant: "A" or "B".
        duration: length [s], at least one sample (laps of 51-53 s repeat).
        dt: sampling period [s], in (0, 0.1].
        seed: int >= 0.
        substeps: RK4 steps per sample; None for steps of at most 1 ms.
        noise: overrides of :data:`NOISE` (same keys and units, each >= 0; 0 for none). The
            random draws do not depend on it, so a noise-free drive has the same truth.

    Returns:
        :class:`LimitDrive` of T = round(duration / dt) samples. Cost on 2 CPU cores: a few
        seconds for the 200 s drive, after about 10 s of compilation in the first call (and
        in the first call of each new T or substeps).
    """
    variant = validation.choice("variant", variant, tuple(VARIANTS))
    duration = validation.number("duration", duration, 0.0)
    dt = validation.number("dt", dt, 0.0, 0.1, high_open=False)
    seed = validation.integer("seed", seed, 0)
    substeps = (int(np.ceil(dt / 1e-3 - 1e-9)) if substeps is None
                else validation.integer("substeps", substeps, 1))
    std = {**NOISE, **{k: validation.number(f"noise[{k!r}]", v, 0.0, low_open=False)
                       for k, v in validation.keyed("noise", noise, tuple(NOISE)).items()}}
    truth, _, offset = VARIANTS[variant]
    rng = np.random.default_rng([seed, offset])
    n = validation.integer("duration / dt", int(round(duration / dt)), 1)
    t = np.arange(n) * dt
    vx, ay_target = lap_targets(variant, t)
    command = np.asarray(steady_state(truth, jnp.asarray(ay_target), jnp.asarray(vx)))[:, 1]
    command = command + _smooth_noise(rng, t, _DRIVER_STD, 0.2, 1.5)
    steer = command + _smooth_noise(rng, t, std["steer_disturbance"], 0.05, 1.0)
    true_inputs = np.stack([steer, vx], axis=1)
    x0 = np.zeros(2)
    states = np.asarray(rollout(truth, jnp.asarray(x0), jnp.asarray(true_inputs), dt, substeps))
    ay = np.asarray(lateral_acceleration(truth, states, true_inputs))
    white = rng.standard_normal((len(t), 4))
    inputs = np.stack([command + std["delta"] * white[:, 0], vx + std["vx"] * white[:, 1]], 1)
    meas = np.stack([ay + std["ay"] * white[:, 2], states[:, 1] + std["r"] * white[:, 3]], 1)
    axle = axle_peak_mu(truth, np.abs(ay).max())
    return LimitDrive(
        t=t, inputs=inputs, measurements=meas, states=states,
        sideslip=np.arctan(states[:, 0] / vx), ay=ay, true_inputs=true_inputs, x0=x0,
        mu=min(axle), axle_mu=axle, body={k: getattr(truth, k) for k in ("m", "iz", "lf", "lr")},
        noise_std=std, truth=truth, variant=variant, seed=seed)
