"""A simulated second car: a front-wheel-drive saloon whose truth is richer than any fitted model.

Why: on a second real car (200 Hz, up to 1.2 g, an accelerometer with heavy 40-100 Hz
vibration) the documented fit of ``vehjax.models.SingleTrack`` with the data sheet's yaw
inertia, 2.5 times too small, gave sideslip errors several times those of an untuned textbook
linear Kalman filter. :func:`second_car` simulates such a car, so that the documented path, its
variants and a textbook observer can be compared against a known sideslip.

The truth builds on :mod:`vehjax.studies.limit_drive`'s planar two-track car (its magic-formula tyres
with load-sensitive stiffness, exact slip angles, body forces; ISO 8855 axes) and adds:

* first-order tyre lag: each wheel's lateral force Fy_i is a state and follows its steady-state
  value with the relaxation length sigma of its axle (default 0.6 m front, 0.8 m rear)::

      Fy_i' = (vx / sigma_i) (Fy_ss_i(alpha_i, Fz_i) - Fy_i)

  (Pacejka, *Tyre and Vehicle Dynamics*, 3rd ed., sec. 7.2: the straight-tangent relaxation
  model);
* roll: the sprung body rolls about a roll axis parallel to the road at height ``roll_height``
  (CoG ``h`` above the road, arm hs = h - roll_height). Roll angle phi (> 0: the right side
  down, ISO 8855; it follows ay > 0) and rate p::

      ixx p' = m ay hs + m g hs phi - k phi - c p

  and the lateral load transfer of each axle is dynamic: the suspension's share (front share q
  of the roll stiffness k and damping c) plus the roll centre's part,
  dFz_f = (q (k phi + c p) + m ay (lr / L) roll_height) / track_f, the rear alike with 1 - q
  and lf / L (Milliken & Milliken, *Race Car Vehicle Dynamics*, ch. 18). ay is that of the
  lagged forces, so there is no algebraic loop (unlike limit_drive's quasi-static loads).

States (8): (vy [m/s], r [rad/s], phi [rad], p [rad/s], Fy_fl, Fy_fr, Fy_rl, Fy_rr [N]); inputs
(delta [rad] road-wheel steer, vx [m/s] given). In steady state the loads equal
:mod:`vehjax.studies.limit_drive`'s with an equivalent CoG height and front share (:func:`planar`), so
the driver steers by limit_drive's steady-state inverse of that planar truth.

Sensors at 200 Hz: the road-wheel steer (white noise), the speed (white), the yaw rate (white)
and the lateral accelerometer at the CoG: ay plus white noise plus vibration, Gaussian noise
whose spectrum is flat in 40-100 Hz and zero elsewhere (:func:`vibration`; for dt = 5 ms the
band ends at the Nyquist frequency), so that consecutive samples are negatively correlated
(lag-1 autocorrelation about -0.5 at 200 Hz). The accelerometer reads the road-plane ay: it
does not see gravity through the roll angle (a limit).

The spec sheet (:func:`spec_sheet`) is what a user is given: the truth's m, lf, lr, a yaw
inertia 2.5 times below the truth's (:data:`SPEC_IZ_RATIO`), and textbook cornering stiffnesses
from the static axle loads times typical cornering coefficients (:data:`CORNERING_COEFFICIENT`).

Runs (:data:`RUNS`): three drives of different speed profiles and steering (corners up to
1.2 g, slaloms, straights), each from a schedule drawn by its own seed: run 1 to fit, runs 2
and 3 held out. Integration: classical RK4 with substeps of at most 1 ms, inputs linearly
interpolated between samples, checked against scipy's DOP853 in tests/studies/test_second_car.py.

Limits: planar apart from roll; no pitch, no longitudinal forces or load transfer (the speed is
given), no aligning torque or combined slip; the roll axis is level and the unsprung masses
are lumped into the body.
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from . import limit_drive as ld
from .. import validation

__all__ = ["G", "NOISE", "RUNS", "SPEC_IZ_RATIO", "CORNERING_COEFFICIENT", "VIBRATION_BAND",
           "Truth", "SecondCarRun", "TRUTH", "planar", "spec_sheet", "textbook_stiffness", "wheel_loads",
           "derivative", "lateral_acceleration", "rollout", "vibration", "schedule",
           "second_car"]

G = ld.G

#: Sensor standard deviations: ay white [m/s^2], ay vibration [m/s^2], r [rad/s], measured steer
#: delta [rad], vx [m/s], and the unmeasured road-wheel steer disturbance [rad] (0.05-1 Hz).
NOISE = {"ay": 0.15, "vibration": 1.0, "r": np.deg2rad(0.2), "delta": np.deg2rad(0.1),
         "vx": 0.05, "steer_disturbance": np.deg2rad(0.1)}

#: Frequency band [Hz] of the accelerometer's vibration.
VIBRATION_BAND = (40.0, 100.0)

#: The spec sheet's yaw inertia is the truth's divided by this.
SPEC_IZ_RATIO = 2.5

#: Textbook cornering coefficients (front, rear) [1/rad]: axle stiffness over static axle load.
#: The rear's is higher (its tyres carry less load, and a tyre's coefficient falls with load).
CORNERING_COEFFICIENT = (16.0, 20.0)

_DRIVER_STD = np.deg2rad(0.1)  # rad, the driver's smooth corrections (measured)


class Truth(NamedTuple):
    """Parameters of the second car's truth (module docstring).

    Attributes:
        body: the planar two-track car (:class:`vehjax.studies.limit_drive.Truth`): m [kg], iz
            [kg m^2], lf, lr [m], h the CoG height [m], track widths [m], roll_front the front
            share q of the roll stiffness and damping [-], the tyres (cf, cr at the static loads
            [N/rad], load exponent, mu, shape C, curvature E).
        roll_height: roll axis height [m], < body.h.
        roll_stiffness [N m/rad], roll_damping [N m s/rad], roll_inertia [kg m^2] (about the
            roll axis).
        relax_f, relax_r: relaxation lengths [m].
    """

    body: ld.Truth
    roll_height: float
    roll_stiffness: float
    roll_damping: float
    roll_inertia: float
    relax_f: float
    relax_r: float


#: The second car: a front-wheel-drive mid-size saloon (61 % of its weight on the front axle,
#: wheelbase 2.7 m) with a large real yaw inertia; steady roll gradient about 3.9 deg/g, roll
#: frequency about 2 Hz, damping ratio about 0.4.
TRUTH = Truth(
    body=ld.Truth(m=1600.0, iz=6900.0, lf=1.05, lr=1.65, h=0.55, track_f=1.56, track_r=1.54,
                  roll_front=0.62, cf=1.45e5, cr=1.30e5, load_exponent=0.8, mu=1.40,
                  shape=1.40, curvature=-0.5),
    roll_height=0.10, roll_stiffness=1.1e5, roll_damping=6.0e3, roll_inertia=550.0,
    relax_f=0.6, relax_r=0.8)


class SecondCarRun(NamedTuple):
    """A simulated drive of the second car (:func:`second_car`); T samples at ``dt``.

    Attributes:
        t: (T,) time [s]. inputs: (T, 2) measured (delta [rad], vx [m/s]).
        measurements: (T, 2) measured (ay [m/s^2], r [rad/s]), SingleTrack's order.
        states: (T, 2) true (vy [m/s], r [rad/s]); full_states: (T, 8) every truth state.
        sideslip: (T,) true arctan(vy / vx) [rad]; ay: (T,) true lateral acceleration [m/s^2].
        vibration: (T,) the accelerometer's vibration [m/s^2] (its white noise not included).
        true_inputs: (T, 2) the truth's (delta with its disturbance, vx).
        x0: (2,) zeros, the state before the first step (a straight).
        spec: the spec sheet {"m", "iz", "lf", "lr", "cf", "cr"} (:func:`spec_sheet`).
        truth: :class:`Truth`; noise_std: the standard deviations used; run, seed, dt.
    """

    t: np.ndarray
    inputs: np.ndarray
    measurements: np.ndarray
    states: np.ndarray
    full_states: np.ndarray
    sideslip: np.ndarray
    ay: np.ndarray
    vibration: np.ndarray
    true_inputs: np.ndarray
    x0: np.ndarray
    spec: dict
    truth: Truth
    noise_std: dict
    run: int
    seed: int
    dt: float


# -- the truth ----------------------------------------------------------------------------------

def _roll_gain(truth: Truth) -> float:
    """k / (k - m g hs) [-]: the suspension's steady roll moment over m ay hs."""
    hs = truth.body.h - truth.roll_height
    return truth.roll_stiffness / (truth.roll_stiffness - truth.body.m * G * hs)


def planar(truth: Truth) -> ld.Truth:
    """The :class:`vehjax.studies.limit_drive.Truth` with this car's steady-state loads: its body with
    the equivalent CoG height h_eq = hs k / (k - m g hs) + roll_height and front share
    q_eq = (q hs k / (k - m g hs) + roll_height lr / L) / h_eq, so that limit_drive's
    dFz_f = m ay h_eq q_eq / track_f is this car's steady front transfer (the rear alike)."""
    b = truth.body
    susp = (b.h - truth.roll_height) * _roll_gain(truth)
    h_eq = susp + truth.roll_height
    q_eq = (b.roll_front * susp + truth.roll_height * b.lr / (b.lf + b.lr)) / h_eq
    return b._replace(h=h_eq, roll_front=q_eq)


def spec_sheet(truth: Truth = TRUTH) -> dict:
    """What the data sheet gives {"m" [kg], "iz" [kg m^2], "lf", "lr" [m], "cf", "cr" [N/rad]}:
    the truth's m, lf, lr; its iz over :data:`SPEC_IZ_RATIO`; textbook stiffnesses
    :data:`CORNERING_COEFFICIENT` times the static axle loads m g lr / L, m g lf / L."""
    b = truth.body
    cf, cr = textbook_stiffness(b.m, b.lf, b.lr)
    return {"m": b.m, "iz": b.iz / SPEC_IZ_RATIO, "lf": b.lf, "lr": b.lr, "cf": cf, "cr": cr}


def textbook_stiffness(m: float, lf: float, lr: float, coefficient=CORNERING_COEFFICIENT):
    """(cf, cr) [N/rad] of a data sheet: the cornering coefficients (front, rear) [1/rad] times
    the static axle loads m g lr / L, m g lf / L [N] of mass ``m`` [kg], CoG ``lf``, ``lr`` [m]
    behind the front and ahead of the rear axle."""
    wheelbase = lf + lr
    return (coefficient[0] * m * G * lr / wheelbase, coefficient[1] * m * G * lf / wheelbase)


def wheel_loads(truth: Truth, phi, p, ay):
    """Vertical loads (fl, fr, rl, rr) [N], (4,), at roll angle ``phi`` [rad], roll rate ``p``
    [rad/s] and lateral acceleration ``ay`` [m/s^2]: static plus the dynamic transfer (module
    docstring), each floored at 1 % of its static value."""
    b = truth.body
    static = ld.wheel_loads(b, 0.0)
    moment = truth.roll_stiffness * phi + truth.roll_damping * p
    centre = b.m * ay * truth.roll_height / (b.lf + b.lr)
    dzf = (b.roll_front * moment + centre * b.lr) / b.track_f
    dzr = ((1.0 - b.roll_front) * moment + centre * b.lf) / b.track_r
    return jnp.maximum(static + jnp.stack([-dzf, dzf, -dzr, dzr]), 0.01 * static)


def lateral_acceleration(truth: Truth, x, u):
    """ay [m/s^2] of state x (8,) (its lagged forces) at input u = (delta, vx)."""
    return ld.body_forces(truth.body, x[4:], u[0])[0] / truth.body.m


def derivative(truth: Truth, x, u):
    """x' (8,) of state x (8,) at input u = (delta [rad], vx [m/s]) (module docstring)."""
    b = truth.body
    fy, mz = ld.body_forces(b, x[4:], u[0])
    ay = fy / b.m
    hs = b.h - truth.roll_height
    roll_acc = (b.m * hs * (ay + G * x[2]) - truth.roll_stiffness * x[2]
                - truth.roll_damping * x[3]) / truth.roll_inertia
    fz = wheel_loads(truth, x[2], x[3], ay)
    steady = ld.wheel_force(ld.slip_angles(b, x[:2], u), ld.wheel_stiffness(b, fz), b.mu, fz,
                            b.shape, b.curvature)
    relax = jnp.stack([truth.relax_f, truth.relax_f, truth.relax_r, truth.relax_r])
    return jnp.concatenate([jnp.stack([ay - u[1] * x[1], mz / b.iz, x[3], roll_acc]),
                            u[1] / relax * (steady - x[4:])])


@partial(jax.jit, static_argnames="substeps")
def rollout(truth: Truth, x0, inputs, dt, substeps: int = 5):
    """States (T, 8) at the input samples: row 0 is ``x0`` (8,), row k the RK4 solution at k dt
    with ``substeps`` steps per sample and the inputs (T, 2) interpolated linearly."""
    h = dt / substeps

    def sample(x, pair):
        u0, u1 = pair

        def sub(j, x):
            ua, um, ub = (u0 + (j + s) / substeps * (u1 - u0) for s in (0.0, 0.5, 1.0))
            k1 = derivative(truth, x, ua)
            k2 = derivative(truth, x + 0.5 * h * k1, um)
            k3 = derivative(truth, x + 0.5 * h * k2, um)
            k4 = derivative(truth, x + h * k3, ub)
            return x + h / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)

        x = jax.lax.fori_loop(0, substeps, sub, x)
        return x, x

    _, xs = jax.lax.scan(sample, x0, (inputs[:-1], inputs[1:]))
    return jnp.concatenate([x0[None], xs])


# -- the sensors and the drives -------------------------------------------------------------------

def vibration(rng, n: int, dt: float, std: float, band=VIBRATION_BAND) -> np.ndarray:
    """(n,) Gaussian noise of standard deviation ``std`` with a flat spectrum in ``band`` [Hz]
    (clipped to the Nyquist frequency 1 / (2 dt)) and none outside: white noise from ``rng``
    (numpy Generator) with its Fourier coefficients outside the band set to zero. Its lag-1
    autocorrelation is the band's mean of cos(2 pi f dt): about -0.50 for 40-100 Hz at 200 Hz."""
    spec = np.fft.rfft(rng.standard_normal(n))
    f = np.fft.rfftfreq(n, dt)
    spec[(f < band[0]) | (f > band[1])] = 0.0
    out = np.fft.irfft(spec, n)
    return std * out / max(float(np.std(out)), 1e-300)


#: run -> (seed offset, speed range [m/s], corner ay range [g], share of slaloms): run 1 to fit,
#: runs 2 and 3 held out.
RUNS = {1: (0, (15.0, 30.0), (0.3, 1.2), 0.35), 2: (1, (10.0, 24.0), (0.3, 1.1), 0.5),
        3: (2, (20.0, 34.0), (0.2, 1.2), 0.25)}


def _segment(rng, kind: str, v: float, speeds, ay_range) -> list:
    """Knots (seconds, speed [m/s], ay [g]) of one segment from speed ``v``."""
    lo, hi = ay_range
    if kind == "straight":
        return [(rng.uniform(2.0, 4.0), rng.uniform(*speeds), 0.0)]
    if kind == "corner":
        a = rng.choice([-1.0, 1.0]) * rng.uniform(lo, hi)
        return [(rng.uniform(1.0, 1.5), v, a), (rng.uniform(1.0, 3.0), v, a),
                (rng.uniform(1.0, 1.5), v, 0.0)]
    a, half = rng.uniform(lo, 0.8 * hi), rng.uniform(0.5, 1.0)
    sign = rng.choice([-1.0, 1.0])
    return [(half, v, sign * a * (-1) ** k) for k in range(int(rng.integers(3, 7)))] + [
        (half, v, 0.0)]


def schedule(run: int, duration: float):
    """Knots ((speed [m/s], ay [g]) at t = 0, ((seconds, speed, ay [g]), ...)) of ``run``'s
    drive, covering ``duration`` [s]: a straight, a corner at the range's top (the drive's
    peak), then straights, corners and slaloms drawn by the run's seed."""
    offset, speeds, ay_range, slalom = RUNS[run]
    rng = np.random.default_rng([53, offset])
    v0 = 0.5 * (speeds[0] + speeds[1])
    knots = [(2.0, v0, 0.0), (1.5, v0, ay_range[1]), (1.5, v0, ay_range[1]), (1.5, v0, 0.0)]
    total = sum(k[0] for k in knots)
    while total < duration:
        kind = rng.choice(["straight", "corner", "slalom"], p=[0.35, 0.65 - slalom, slalom])
        seg = _segment(rng, "straight", knots[-1][1], speeds, ay_range) + _segment(
            rng, str(kind), 0.0, speeds, ay_range)
        seg = seg[:1] + [(s, seg[0][1], a) for s, _, a in seg[1:]]
        knots += seg
        total += sum(k[0] for k in seg)
    return (v0, 0.0), tuple(knots)


def _targets(start, knots, t):
    """(vx [m/s], ay [g]) at times ``t``: the knots joined by half-cosine ramps."""
    dur = np.array([k[0] for k in knots])
    begin = np.concatenate([[0.0], np.cumsum(dur)])
    values = np.array([start] + [(k[1], k[2]) for k in knots])
    i = np.clip(np.searchsorted(begin, t, side="right") - 1, 0, len(knots) - 1)
    w = 0.5 * (1.0 - np.cos(np.pi * np.clip((t - begin[i]) / dur[i], 0.0, 1.0)))
    prof = values[i] + w[:, None] * (values[i + 1] - values[i])
    return prof[:, 0], prof[:, 1]


def _smooth(rng, t, std: float, f_lo: float, f_hi: float, n: int = 24):
    """A smooth random signal of standard deviation ``std``: n sinusoids in [f_lo, f_hi] Hz."""
    f, phase = rng.uniform(f_lo, f_hi, n), rng.uniform(0.0, 2.0 * np.pi, n)
    return std * np.sqrt(2.0 / n) * np.sin(2.0 * np.pi * f * t[:, None] + phase).sum(axis=1)


def second_car(run: int = 1, duration: float = 88.0, dt: float = 0.005, seed: int | None = None,
               substeps: int | None = None, noise: dict | None = None,
               truth: Truth = TRUTH) -> SecondCarRun:
    """Simulate one drive of the second car (module docstring).

    Deterministic given (run, duration, seed): the schedule comes from the run, the noise, the
    driver's corrections and the steering disturbance from numpy's generator seeded with
    (seed, run).

    Args:
        run: 1, 2 or 3 (:data:`RUNS`): run 1 to fit, 2 and 3 held out.
        duration: length [s] (the default 88 s is 17,600 samples at 200 Hz).
        dt: sampling period [s], in (0, 0.02].
        seed: int >= 0; None for the run's number.
        substeps: RK4 steps per sample; None for steps of at most 1 ms.
        noise: overrides of :data:`NOISE` (same keys and units, each >= 0).
        truth: the car (:class:`Truth`); its spec sheet follows from it.

    Returns:
        :class:`SecondCarRun` of T = round(duration / dt) samples. Cost on 2 CPU cores: a few
        seconds for the 88 s drive, compilation (once per new T or substeps) included.
    """
    if isinstance(run, (bool, np.bool_)) or run not in RUNS:
        raise ValueError(f"run: expected one of {tuple(RUNS)}, got {run!r}")
    duration = validation.number("duration", duration, 0.0)
    dt = validation.number("dt", dt, 0.0, 0.02, high_open=False)
    seed = run if seed is None else validation.integer("seed", seed, 0)
    substeps = (int(np.ceil(dt / 1e-3 - 1e-9)) if substeps is None
                else validation.integer("substeps", substeps, 1))
    std = {**NOISE, **{k: validation.number(f"noise[{k!r}]", v, 0.0, low_open=False)
                       for k, v in validation.keyed("noise", noise, tuple(NOISE)).items()}}
    n = validation.integer("duration / dt", int(round(duration / dt)), 2)
    rng = np.random.default_rng([seed, run])
    t = np.arange(n) * dt
    vx, ay_target = _targets(*schedule(run, duration), t)
    command = np.asarray(ld.steady_state(planar(truth), jnp.asarray(ay_target * G),
                                         jnp.asarray(vx)))[:, 1]
    command = command + _smooth(rng, t, _DRIVER_STD, 0.2, 1.5)
    true_inputs = np.stack([command + _smooth(rng, t, std["steer_disturbance"], 0.05, 1.0), vx],
                           axis=1)
    full = np.asarray(rollout(truth, jnp.zeros(8), jnp.asarray(true_inputs), dt, substeps))
    ay = np.asarray(jax.vmap(lambda x, u: lateral_acceleration(truth, x, u))(full, true_inputs))
    vib = vibration(rng, n, dt, std["vibration"])
    white = rng.standard_normal((n, 4))
    inputs = np.stack([command + std["delta"] * white[:, 0], vx + std["vx"] * white[:, 1]], 1)
    meas = np.stack([ay + vib + std["ay"] * white[:, 2], full[:, 1] + std["r"] * white[:, 3]], 1)
    return SecondCarRun(
        t=t, inputs=inputs, measurements=meas, states=full[:, :2], full_states=full,
        sideslip=np.arctan(full[:, 0] / vx), ay=ay, vibration=vib, true_inputs=true_inputs,
        x0=np.zeros(2), spec=spec_sheet(truth), truth=truth, noise_std=std, run=run, seed=seed,
        dt=dt)
