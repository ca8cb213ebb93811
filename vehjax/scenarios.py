"""Manoeuvres: input sequences (T, nu) and initial states for a given vehicle model.

Every scenario is driven in closed loop through the model at its nominal parameters, without
noise: a speed-holding longitudinal controller and, for the double lane change, a pure-pursuit
driver that steers along the ISO 3888-1 course; the other manoeuvres apply an open-loop
road-wheel steering profile. The resulting inputs are then replayed open loop by
:func:`vehjax.simulate`, so the truth of every Monte-Carlo run sees the same inputs.

    scn = double_lane_change(model, speed=20.0)
    scn.inputs   # (T, nu) in the model's input units
    scn.x0       # (nx,)
    scn.t        # (T,) seconds, the time at which each input is applied
"""

from __future__ import annotations

import inspect
from typing import Callable, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import validation
from .models.base import DrivableModel

__all__ = [
    "Scenario",
    "double_lane_change",
    "sine_steer",
    "step_steer",
    "chirp",
    "sine_with_dwell",
    "slip_and_steer",
    "from_inputs",
    "iso3888_centreline",
    "default_steps",
    "REGISTRY",
]

#: ISO 3888-1 course: section lengths [m] (lane 1, transition, lane 2, transition, lane 3).
_ISO_SECTIONS = (15.0, 30.0, 25.0, 25.0, 15.0)
_RUN_IN = 20.0  # m of straight road before the first cone
_MAX_STEER = 0.5  # rad, road-wheel steering limit of the driver
_SPEED_GAIN = 1.0  # 1/s, speed-hold controller gain
_MAX_ACCEL = 3.0  # m/s^2
_PREVIEW = 0.5  # s, pure-pursuit look-ahead time


class Scenario(NamedTuple):
    """A manoeuvre for one model.

    Attributes:
        name: manoeuvre label.
        t: (T,) time [s] at which each input row is applied.
        inputs: (T, nu) inputs in the model's input units.
        x0: (nx,) initial state.
        input_names: the model's input names.
        path: (T, 3) pose (X [m], Y [m], psi [rad]) of the nominal closed-loop drive.
    """

    name: str
    t: np.ndarray
    inputs: jnp.ndarray
    x0: jnp.ndarray
    input_names: tuple
    path: np.ndarray


def iso3888_centreline(X, offset: float = 3.5):
    """Centre line of the ISO 3888-1 double-lane-change course, Y [m] at distance X [m].

    The course starts at X = 0: 15 m entry lane, 30 m transition, 25 m offset lane at ``offset``
    metres to the left, 25 m transition, 15 m exit lane, then straight road. The lane centres are
    joined by half-cosine transitions, which a driver can follow with bounded curvature.
    """
    l1, t1, l2, t2, _ = _ISO_SECTIONS
    X = jnp.asarray(X)
    s_in = jnp.clip((X - l1) / t1, 0.0, 1.0)
    s_out = jnp.clip((X - (l1 + t1 + l2)) / t2, 0.0, 1.0)
    return offset * (0.5 * (1.0 - jnp.cos(jnp.pi * s_in)) - 0.5 * (1.0 - jnp.cos(jnp.pi * s_out)))


def _wheelbase(model) -> float:
    names = tuple(model.param_names)
    theta = np.asarray(model.theta)
    for front, rear in (("lf", "lr"), ("a", "b")):
        if front in names and rear in names:
            return float(theta[names.index(front)] + theta[names.index(rear)])
    return 2.7


def _check_model(model):
    if not isinstance(model, DrivableModel):
        raise ValueError(
            f"model: {type(model).__name__} has no driver interface (vehjax.models.base."
            "DrivableModel: drive_input, body_velocity, pose, speed, initial_state); "
            "scenarios drive the built-in vehicle models. For your own model build the inputs "
            "yourself and wrap them with vehjax.scenarios.from_inputs(model, inputs, x0)."
        )


def _check_positive(name, value):
    return validation.number(name, value, 0.0)


def _check_finite(name, value):
    return validation.number(name, value)


def _drive(model, name: str, speed: float, duration: float, steer: Callable | None, offset=3.5):
    """Closed-loop drive at the nominal parameters; ``steer(t)`` (a function of time only,
    evaluated on the whole time grid) or, if None, the ISO course."""
    _check_model(model)
    dt = model.dt
    n_steps = int(round(duration / dt))
    if n_steps < 1:
        raise ValueError(f"duration: expected at least one step of dt = {dt} s, got {duration} s")
    t = np.arange(n_steps) * dt
    dtype = model.theta.dtype
    x0 = jnp.asarray(model.initial_state(speed), dtype=dtype)
    zero = jnp.zeros((), dtype=dtype)
    X_start = zero - _RUN_IN if steer is None else zero
    if model.pose(x0) is not None and steer is None:
        x0 = x0.at[0].set(-_RUN_IN)
    ts = jnp.asarray(t, dtype=dtype)
    delta = ts if steer is None else jnp.broadcast_to(jnp.asarray(steer(ts), dtype), ts.shape)
    gains = jnp.asarray([speed, offset, max(6.0, _PREVIEW * speed), _wheelbase(model)], dtype)
    inputs, path = _rollout(model, steer is None, (x0, X_start, zero, zero), delta, gains)
    if not bool(jnp.all(jnp.isfinite(inputs))):
        raise ValueError(
            f"{name}: the nominal closed-loop drive went non-finite at speed {speed} m/s; "
            "try a lower speed or a smaller amplitude"
        )
    return Scenario(name, t, inputs, x0, tuple(model.input_names), np.asarray(path))


@eqx.filter_jit
def _rollout(model, pursuit: bool, carry0, delta_open, gains):
    """The drive's scan, compiled once per model, driver kind and length (every open-loop
    profile of a model and length shares one program). ``pursuit``: the pure-pursuit driver on
    the ISO course, else the road-wheel angles ``delta_open`` (T,) [rad]; ``gains``: the
    speed target [m/s], the centre-lane offset [m], the look-ahead distance [m] and the
    wheelbase [m]. Returns inputs (T, nu) and the pose (T, 3)."""
    speed, offset, lookahead, wheelbase = gains
    theta, dt = model.theta, model.dt

    def step(carry, d_open):
        x, X, Y, psi = carry
        pose = model.pose(x)
        if pose is not None:
            X, Y, psi = pose
        v = model.speed(x)
        v = speed if v is None else v
        if pursuit:
            Xt = X + lookahead
            Yt = iso3888_centreline(Xt, offset)
            alpha = jnp.arctan2(Yt - Y, Xt - X) - psi
            delta = jnp.arctan(2.0 * wheelbase * jnp.sin(alpha) / lookahead)
        else:
            delta = d_open
        delta = jnp.clip(delta, -_MAX_STEER, _MAX_STEER)
        accel = jnp.clip(_SPEED_GAIN * (speed - v), -_MAX_ACCEL, _MAX_ACCEL)
        u = model.drive_input(x, delta, accel, speed, theta)
        vx, vy, r = model.body_velocity(x, u, theta)
        x_next = model.transition(x, u, theta)
        psi_next = psi + r * dt
        X_next = X + (vx * jnp.cos(psi) - vy * jnp.sin(psi)) * dt
        Y_next = Y + (vx * jnp.sin(psi) + vy * jnp.cos(psi)) * dt
        return (x_next, X_next, Y_next, psi_next), (u, jnp.stack([X, Y, psi]))

    return jax.lax.scan(step, carry0, delta_open)[1]


def double_lane_change(model, speed: float = 20.0, duration: float | None = None, offset: float = 3.5):
    """ISO 3888-1 double lane change at ``speed`` [m/s], driven by a pure-pursuit driver.

    The driver aims at the course centre line 0.5 s ahead. It keeps the centre of gravity inside
    the lanes at 20 m/s; it is not a race driver: with the 3-DOF model it overshoots the centre
    lane by about 0.6 m, so a 1.8 m wide body would touch the cones.

    The car starts 20 m before the course on its centre line. ``duration`` [s] defaults to the
    time to cover the run-in, the 110 m course and 20 m beyond. ``offset`` [m] is the lateral
    shift of the centre lane.
    """
    speed = _check_positive("speed", speed)
    _check_finite("offset", offset)
    if duration is None:
        duration = _course_duration(speed)
    duration = _check_positive("duration", duration)
    return _drive(model, "double_lane_change", speed, duration, None, offset)


def _course_duration(speed: float) -> float:
    """Seconds to drive the run-in, the ISO course and 20 m beyond at ``speed`` [m/s]."""
    return (_RUN_IN + sum(_ISO_SECTIONS) + 20.0) / speed


def default_steps(builder, model, speed: float = 20.0) -> int:
    """How many steps ``builder`` (a manoeuvre of :data:`REGISTRY`, or another builder with a
    ``duration`` argument) drives ``model`` for at ``speed`` [m/s] with its default duration,
    found without driving: so that a caller can check the size of a long study
    (:func:`vehjax.simulate.check_size`) before building its scenario."""
    speed = _check_positive("speed", speed)
    duration = inspect.signature(builder).parameters["duration"].default
    if duration is None:  # the double lane change: the course at this speed
        duration = _course_duration(speed)
    return int(round(duration / model.dt))


def sine_steer(model, speed: float = 20.0, amplitude: float = 0.05, frequency: float = 0.5,
               duration: float = 10.0):
    """Continuous sine steer: delta = amplitude [rad] * sin(2 pi frequency [Hz] t)."""
    speed = _check_positive("speed", speed)
    amplitude = _check_finite("amplitude", amplitude)
    frequency = _check_positive("frequency", frequency)
    duration = _check_positive("duration", duration)
    return _drive(model, "sine_steer", speed, duration,
                  lambda t: amplitude * jnp.sin(2.0 * jnp.pi * frequency * t))


def step_steer(model, speed: float = 20.0, amplitude: float = 0.03, t_step: float = 1.0,
               duration: float = 6.0):
    """Step steer of ``amplitude`` [rad] at ``t_step`` [s], ramped over 0.1 s as a driver would."""
    speed = _check_positive("speed", speed)
    amplitude = _check_finite("amplitude", amplitude)
    t_step = _check_finite("t_step", t_step)
    duration = _check_positive("duration", duration)
    return _drive(model, "step_steer", speed, duration,
                  lambda t: amplitude * jnp.clip((t - t_step) / 0.1, 0.0, 1.0))


def chirp(model, speed: float = 20.0, amplitude: float = 0.03, f0: float = 0.1, f1: float = 2.0,
          duration: float = 10.0):
    """Linear chirp steer from ``f0`` to ``f1`` [Hz] over ``duration`` [s], ``amplitude`` [rad]."""
    speed = _check_positive("speed", speed)
    amplitude = _check_finite("amplitude", amplitude)
    f0 = _check_positive("f0", f0)
    f1 = _check_positive("f1", f1)
    duration = _check_positive("duration", duration)
    rate = (f1 - f0) / duration
    return _drive(model, "chirp", speed, duration,
                  lambda t: amplitude * jnp.sin(2.0 * jnp.pi * (f0 * t + 0.5 * rate * t**2)))


def sine_with_dwell(model, speed: float = 22.0, amplitude: float = 0.08, frequency: float = 0.7,
                    dwell: float = 0.5, t0: float = 1.0, duration: float = 6.0):
    """Sine with dwell (FMVSS 126 style): a 0.7 Hz sine, held for ``dwell`` [s] at its second peak.

    delta = A sin(2 pi f (t - t0)) for the first three quarters of the cycle, then -A for
    ``dwell`` seconds, then the last quarter back to zero, then straight.
    """
    speed = _check_positive("speed", speed)
    amplitude = _check_finite("amplitude", amplitude)
    frequency = _check_positive("frequency", frequency)
    dwell = _check_finite("dwell", dwell)
    if dwell < 0:
        raise ValueError(f"dwell: expected a non-negative duration in seconds, got {dwell}")
    duration = _check_positive("duration", duration)
    t_hold = 0.75 / frequency

    def steer(t):
        s = t - t0
        phase = jnp.where(s < t_hold, s, jnp.where(s < t_hold + dwell, t_hold, s - dwell))
        active = (s >= 0.0) & (phase < 1.0 / frequency)
        return jnp.where(active, amplitude * jnp.sin(2.0 * jnp.pi * frequency * phase), 0.0)

    return _drive(model, "sine_with_dwell", speed, duration, steer)


def slip_and_steer(model, speed: float = 20.0, duration: float = 60.0):
    """Open-loop wheel-slip and steering inputs (s_fl, s_fr, s_rl, s_rr, delta) for
    :class:`~vehjax.models.Dynamic3DOF` (or a model with its parameters m, cx, ca and inputs),
    in the style of MATLAB's recorded ``vehicledata``, which cannot ship: front slips that
    balance air drag at ``speed`` [m/s] and swing the speed between about 14 and 23 m/s at 20 m/s
    (+-0.6 m/s^2 of longitudinal acceleration, 20 s period), a two-tone steering signal (0.04 rad
    at 0.25 Hz plus 0.02 rad at 0.9 Hz, up to about 0.45 rad/s of yaw rate), rear slips zero.
    The excitation of Dutta et al. (2019)'s dynamic stage as ``vehjax reproduce dutta2019``
    reads it. Open loop: the inputs are not driven through the model."""
    speed = _check_positive("speed", speed)
    duration = _check_positive("duration", duration)
    m, cx, ca = (float(model.theta[model.param_index(n)[0]]) for n in ("m", "cx", "ca"))
    t = np.arange(int(round(duration / model.dt))) * model.dt
    hold = ca * speed**2 / (2 * cx)  # slip per front wheel that balances drag
    swing = 0.6 * m / (2 * cx)  # +-0.6 m/s^2 of longitudinal acceleration
    slip = hold + swing * np.sin(2 * np.pi * t / 20.0)
    delta = 0.04 * np.sin(2 * np.pi * 0.25 * t) + 0.02 * np.sin(2 * np.pi * 0.9 * t + 1.0)
    zero = np.zeros_like(t)
    return from_inputs(model, np.stack([slip, slip, zero, zero, delta], 1), [speed, 0.0, 0.0],
                       name="slip_and_steer")


def from_inputs(model, inputs, x0, name: str = "custom"):
    """Wrap an input sequence (T, nu) and initial state (nx,) of your own as a Scenario.

    Checked by the rules every entry point shares (:mod:`vehjax.validation`): real, finite,
    T >= 1; ValueError naming ``inputs`` or ``x0`` and the first bad index."""
    validation.model(model)
    nu, nx = len(model.input_names), len(model.state_names)
    inputs = np.asarray(validation.array("inputs", inputs), dtype=float)
    if inputs.ndim != 2 or inputs.shape[1] != nu or inputs.shape[0] == 0:
        raise ValueError(
            f"inputs: expected shape (T, {nu}) with T >= 1 for inputs "
            f"{tuple(model.input_names)}, got {inputs.shape}"
        )
    x0 = np.asarray(validation.per_run("x0", x0, (nx,), what=f"nx = {nx} states"), dtype=float)
    t = np.arange(inputs.shape[0]) * model.dt
    path = np.full((inputs.shape[0], 3), np.nan)
    return Scenario(name, t, jnp.asarray(inputs), jnp.asarray(x0), tuple(model.input_names), path)


#: name -> builder, for the CLI.
REGISTRY = {
    "double_lane_change": double_lane_change,
    "sine_steer": sine_steer,
    "step_steer": step_steer,
    "chirp": chirp,
    "sine_with_dwell": sine_with_dwell,
}
