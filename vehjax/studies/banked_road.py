"""Paper 004's banked-road problem (Berntorp & Di Cairano 2018, sec. 4-5): the simulated
scenario, with its truth and biased IMU, and the adaptive marginalized PF set-ups for
:class:`~vehjax.models.SingleTrackBank`, shared by ``vehjax reproduce berntorp2018``,
``vehjax reproduce noise-learning`` and the marginalized-PF benchmarks.

The simulated scenario (sec. 4), how the paper's words are read:

* Inputs: "measured input data from an experimental test drive": a recorded drive's speed and
  steering played forward, then backwards in time, then forward ... (:func:`looped_inputs`, a
  palindrome loop, continuous at every joint) up to the wanted length.
* Truth: SingleTrackBank (RK4, 10 ms, nominal parameters), driven by the true steering
  delta_m + w_t, w_t ~ N(:data:`OFFSET` = 0.28 deg, (:data:`STEER_STD` = 0.02 deg)^2) (the
  paper's constant road-wheel offset, plus a small white steering noise so that sigma_w exists).
* Bank: "the road bank rate is modeled as piecewise linear". :func:`vehjax.simulate` has no way
  to prescribe the bank, so :func:`simulate_truth` is its own ``lax.scan`` of
  ``model.transition``: before every step the bank acceleration state phi_ddot is overwritten
  by a prescribed piecewise-constant value (:func:`bank_profile`; RK4 integrates the bank chain
  exactly, so phi_dot is exactly piecewise linear and phi piecewise quadratic). The profile
  repeats every 60 s: 10 s level, a 10 s ramp up by :data:`BANK_DEG` = 6 deg (triangular bank
  rate, peak 1.2 deg/s), 20 s at 6 deg, a 10 s ramp back down, 10 s level; every other cycle
  banks the other way.
* Sensors :data:`SENSORS`: ay, r, roll_rate (roll_rate reads phi_dot) with fixed white-noise
  stds :data:`SENSOR_STD` (0.2 m/s^2, 0.3 deg/s, 0.3 deg/s) plus random-walk biases starting at
  0 (the paper: "zero initially due to averaging"), increments per 10 ms step
  :data:`BIAS_WALK` (1e-3 m/s^2, 3e-4 deg/s, 3e-4 deg/s); a bank-angle measurement of known std
  :data:`PHI_STD` = 0.5 deg and eq. 10's virtual yaw rate of known std :data:`RVIRT_STD` =
  0.5 deg/s, both unbiased.

The filters (:func:`~vehjax.filters.marginalized.marginalized_pf`): :func:`build_sim_filter`
(sec. 4: lambda = 0.995, initial std guesses twice the truth, offset and biases guessed 0, bank
jerk std :data:`BANK_JERK_STD` = 2 deg/s^3; it models the biases as constant means with
forgetting, not as random walks, the robustness check the paper intends) and
:func:`build_drive_filter` (sec. 5 and Remark 2: lambda = 0.999, initial guesses
:data:`DRIVE_STD0`); and, not the paper's, the consistent filter
(:func:`~vehjax.filters.marginalized.marginalized_pf_grid`) on the same problem,
:func:`build_consistent_filter` (the offset and the biases as Kalman states, prior stds
:data:`OFFSET_STD0`, :data:`BIAS_STD0`), which ``vehjax reproduce noise-learning`` and the
consistent filter's benchmarks share with :data:`P0_SIM`, the simulation's state prior.

The consistency study's banked road (``vehjax reproduce consistency``'s MPF rows, not the
paper's scenario): the data follow the filter's own noise model (paper 004 eq. 3-10), the true
steering the measured one plus white N(offset, steer_std^2), a white bank jerk, constant sensor
biases and white sensor noises of fixed stds (:class:`MatchedNoise`, the study's values its
defaults), two steering sines at 20 m/s (:func:`matched_inputs`); :func:`simulate_matched`
draws it, :func:`matched_truth` gives the filters' true parameters and
:func:`build_matched_filter` / :func:`matched_setup` the study's filters, given the true
statistics as their prior. The steering std (or any other noise) is an argument, so a study of
another steering noise needs no module state changed.

Limits: the bank path is the same in every run; the truth's steering noise is white.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..filters.marginalized import (InputStdGrid, MeanStates, NiW, marginalized_pf,
                                   marginalized_pf_grid)
from ..models import with_output_biases

__all__ = ["DEG", "OFFSET", "STEER_STD", "SENSORS", "SENSOR_STD", "SENSOR_UNIT", "BIAS_WALK",
           "PHI_STD", "RVIRT_STD", "BANK_JERK_STD", "BANK_DEG", "DRIVE_STD0", "OFFSET_STD0",
           "BIAS_STD0", "P0_SIM", "looped_inputs", "bank_profile", "simulate_truth",
           "build_sim_filter", "build_drive_filter", "build_consistent_filter",
           "MatchedNoise", "MATCHED", "matched_inputs", "simulate_matched", "matched_truth",
           "build_matched_filter", "matched_setup"]

DEG = math.pi / 180.0
OFFSET = 0.28 * DEG  # rad, road wheel
STEER_STD = 0.02 * DEG
SENSORS = ("ay", "r", "roll_rate")
SENSOR_STD = {"ay": 0.2, "r": 0.3 * DEG, "roll_rate": 0.3 * DEG}
SENSOR_UNIT = {"ay": ("m/s^2", 1.0), "r": ("deg/s", DEG), "roll_rate": ("deg/s", DEG),
               "delta": ("deg", DEG)}
BIAS_WALK = {"ay": 1e-3, "r": 3e-4 * DEG, "roll_rate": 3e-4 * DEG}
PHI_STD = 0.5 * DEG
RVIRT_STD = 0.5 * DEG
BANK_JERK_STD = 2.0 * DEG
BANK_DEG = 6.0
#: the drive filter's initial std guesses (steering, ay, yaw gyro; the roll gyro as the yaw's)
DRIVE_STD0 = {"delta": 0.2 * DEG, "ay": 0.4, "r": 0.5 * DEG}
#: prior stds of the steering offset and of the sensor biases where a filter holds them as
#: Gaussian states (the consistent filter's ``MeanStates.mean_std0``, the VB filters')
OFFSET_STD0 = 0.5 * DEG
BIAS_STD0 = {"ay": 0.5, "r": 0.5 * DEG, "roll_rate": 0.5 * DEG}
#: the simulation's state prior covariance P0 of (vy, r, phi, phi_dot, phi_ddot)
P0_SIM = np.diag([0.1, 0.5 * DEG, 0.5 * DEG, 0.2 * DEG, 0.2 * DEG]) ** 2


def looped_inputs(U: np.ndarray, n_steps: int) -> np.ndarray:
    """``U`` forward, backward, forward ... (continuous at the joints), cut to ``n_steps``."""
    pieces, n, fwd = [], 0, True
    while n < n_steps:
        pieces.append(U if fwd else U[::-1])
        n += len(U)
        fwd = not fwd
    return np.concatenate(pieces)[:n_steps]


def bank_profile(t: np.ndarray, dt: float):
    """(phi_ddot per step [rad/s^2], phi [rad]): the piecewise-linear bank rate of the module
    docstring (cycles of 60 s, 6 deg, alternating sign)."""
    amp = BANK_DEG * DEG
    D = 5.0  # half ramp [s]; a ramp of 2 D raises phi by a D^2
    a = amp / D**2
    tc = np.mod(t, 60.0)
    sign = np.where(np.mod(np.floor(t / 60.0), 2) == 0, 1.0, -1.0)
    acc = np.zeros_like(t)
    acc[(tc >= 10) & (tc < 15)] = a
    acc[(tc >= 15) & (tc < 20)] = -a
    acc[(tc >= 40) & (tc < 45)] = -a
    acc[(tc >= 45) & (tc < 50)] = a
    acc = sign * acc
    # the value each step applies over [t_k, t_k + dt]: steps start at t - dt
    phi_dot = np.concatenate([[0.0], np.cumsum(acc * dt)])
    phi = np.concatenate([[0.0], np.cumsum(0.5 * (phi_dot[1:] + phi_dot[:-1]) * dt)])
    return acc, phi[1:]


def simulate_truth(model, inputs, acc, runs, key, steer_std=None):
    """R runs of the truth: states (R, T, 5), measurements (R, T, 5), biases (R, T, 3).
    ``steer_std``: the white steering noise's std [rad] (default :data:`STEER_STD`)."""
    steer_std = STEER_STD if steer_std is None else steer_std
    nx = 5
    s_std = jnp.array([SENSOR_STD[s] for s in SENSORS])
    walk = jnp.array([BIAS_WALK[s] for s in SENSORS])
    theta = jnp.asarray(model.theta)
    U = jnp.asarray(inputs)
    A = jnp.asarray(acc)

    def one(k):
        eps = jax.random.normal(k, (U.shape[0], 1 + 3 + 3 + 2))

        def step(carry, xs):
            x, b = carry
            u, a, e = xs
            w = OFFSET + steer_std * e[0]
            ut = u.at[1].add(w)
            x = x.at[4].set(a)
            xn = model.transition(x, ut, theta)
            b = b + walk * e[1:4]
            h = model.observe(xn, ut, theta)
            y = jnp.concatenate([h[:3] + b + s_std * e[4:7],
                                 jnp.stack([h[3] + PHI_STD * e[7], h[4] + RVIRT_STD * e[8]])])
            return (xn, b), (xn, y, b)

        _, out = jax.lax.scan(step, (jnp.zeros(nx), jnp.zeros(3)), (U, A, eps))
        return out

    return jax.jit(jax.vmap(one))(jax.random.split(key, runs))


def build_sim_filter(model, n_particles, kalman_states="linear"):
    """The simulation study's filter (sec. 4): N = ``n_particles``, lambda = 0.995, initial
    std guesses twice the truth; ``kalman_states`` as in ``marginalized_pf``."""
    return marginalized_pf(
        model, n_particles, noisy_input="delta", sensors=SENSORS,
        known_std={"phi": PHI_STD, "r_virt": RVIRT_STD},
        linear_states=("phi", "phi_dot", "phi_ddot"), Q=BANK_JERK_STD ** 2,
        niw=NiW(std0={"delta": 2 * STEER_STD, **{s: 2 * SENSOR_STD[s] for s in SENSORS}},
                forgetting=0.995), kalman_states=kalman_states)


def build_drive_filter(model, n_particles, forgetting=0.999, variant="bank",
                       kalman_states="linear"):
    """The drive's filter: ``planar`` (Remark 2: ay, r; r_virt known; no bank) or ``bank``
    (sensors ay, r, roll rate; phi (NaN on a log without a bank sensor) and r_virt known; bank
    in a KF); ``kalman_states`` as in ``marginalized_pf`` (no difference for ``planar``). With a
    :class:`~vehjax.models.VirtualScaleBank` model the rolling-radius mismatch eps joins each
    particle's Kalman filter (no process noise: a constant learnt online)."""
    scale = ("eps",) if "eps" in model.state_names else ()
    if variant == "bank":
        return marginalized_pf(
            model, n_particles, noisy_input="delta", sensors=("ay", "r", "roll_rate"),
            known_std={"phi": PHI_STD, "r_virt": RVIRT_STD},
            linear_states=("phi", "phi_dot", "phi_ddot") + scale, Q=BANK_JERK_STD ** 2,
            niw=NiW(std0={**DRIVE_STD0, "roll_rate": DRIVE_STD0["r"]}, forgetting=forgetting),
            kalman_states=kalman_states)
    return marginalized_pf(model, n_particles, noisy_input="delta", sensors=("ay", "r"),
                           known_std={"r_virt": RVIRT_STD}, linear_states=scale,
                           Q=0.0 if scale else None,
                           niw=NiW(std0=DRIVE_STD0, forgetting=forgetting),
                           kalman_states=kalman_states)


def build_consistent_filter(model, points, std0, forgetting=1.0, nu0=None, grid=None,
                            sensor_variances=None):
    """The consistent marginalized PF (:func:`~vehjax.filters.marginalized.marginalized_pf_grid`,
    not the paper's) on this problem: ``points`` grid points of the steering std, the offset and
    the biases as Kalman states (prior stds :data:`OFFSET_STD0`, :data:`BIAS_STD0`; the biases'
    random walks :data:`BIAS_WALK`, the truth's), phi and r_virt known, the bank chain (and the
    rolling-radius mismatch eps where the model has it) in each particle's Kalman filter.
    ``std0``, ``forgetting``, ``nu0``: its :class:`~vehjax.filters.marginalized.NiW`; ``grid``
    (an :class:`~vehjax.filters.marginalized.InputStdGrid` or None) and ``sensor_variances`` as
    in ``marginalized_pf_grid``."""
    scale = ("eps",) if "eps" in model.state_names else ()
    return marginalized_pf_grid(
        model, points, noisy_input="delta", sensors=SENSORS,
        known_std={"phi": PHI_STD, "r_virt": RVIRT_STD},
        linear_states=("phi", "phi_dot", "phi_ddot") + scale, Q=BANK_JERK_STD ** 2,
        niw=NiW(std0=std0, forgetting=forgetting, nu0=nu0),
        means=MeanStates(bias_walk={s: BIAS_WALK[s] for s in SENSORS},
                         mean_std0={"delta": OFFSET_STD0, **BIAS_STD0}),
        grid=InputStdGrid() if grid is None else grid, sensor_variances=sensor_variances)


# ---------------------------------------------------------------------------------------------
# the consistency study's banked road (module docstring)


class MatchedNoise(NamedTuple):
    """The noise of the consistency study's banked road, which the filters are given as their
    prior: speed vx [m/s]; the steering offset and std [rad]; the bank jerk's std
    [rad/s^3] (through ``bank_noise_gain``, eq. 3); the sensors' constant biases and white
    noises' stds (:data:`SENSORS`); the known stds of phi and the virtual yaw rate."""

    speed: float = 20.0
    offset: float = math.radians(0.28)
    steer_std: float = math.radians(0.3)
    bank_jerk_std: float = 0.05
    bias: dict = {"ay": 0.1, "r": math.radians(0.3), "roll_rate": math.radians(-0.2)}
    sensor_std: dict = {"ay": 0.2, "r": math.radians(0.6), "roll_rate": math.radians(0.6)}
    known_std: dict = {"phi": math.radians(0.5), "r_virt": math.radians(0.3)}


#: the consistency study's noise
MATCHED = MatchedNoise()


def matched_inputs(T, noise=MATCHED):
    """(T, 2) inputs (vx, delta) at 100 Hz: two steering sines (0.02 rad at 0.4 Hz, 0.015 rad
    at 0.11 Hz), vx = ``noise.speed``."""
    t = np.arange(T) * 0.01
    delta = 0.02 * np.sin(2 * np.pi * 0.4 * t) + 0.015 * np.sin(2 * np.pi * 0.11 * t + 1.0)
    return np.stack([np.full(T, noise.speed), delta], 1)


def simulate_matched(model, runs, T, seed, noise=MATCHED):
    """Truth (R, T, 5), measurements (R, T, 5) and inputs (T, 2) of ``runs`` runs of
    :func:`matched_inputs` on ``model`` (SingleTrackBank) with ``noise``, drawn from numpy's
    generator seeded ``[seed, 2018]``; the observation at step t sees the same steering error
    as the transition into it, as in eq. 9."""
    U = matched_inputs(T, noise)
    rng = np.random.default_rng([seed, 2018])
    W = noise.offset + noise.steer_std * rng.standard_normal((T, runs))
    J = noise.bank_jerk_std * rng.standard_normal((T, runs))
    B = model.bank_noise_gain()
    th = model.theta

    def body(X, k):
        delta, w, jerk = k
        uu = jnp.stack([jnp.full(runs, noise.speed), delta + w], 1)
        Xn = jax.vmap(lambda x, u: model.transition(x, u, th))(X, uu) + jerk[:, None] * B
        Y = jax.vmap(lambda x, u: model.observe(x, u, th))(Xn, uu)
        return Xn, (Xn, Y)

    X0 = jnp.zeros((runs, len(model.state_names)))
    _, (Xs, Ys) = jax.jit(lambda X0, xs: jax.lax.scan(body, X0, xs))(
        X0, (jnp.asarray(U[:, 1]), jnp.asarray(W), jnp.asarray(J)))
    Xs, Ys = np.moveaxis(np.asarray(Xs), 0, 1), np.moveaxis(np.asarray(Ys), 0, 1)
    names = model.output_names
    bias = np.array([noise.bias.get(n, 0.0) for n in names])
    std = np.array([noise.sensor_std.get(n, noise.known_std.get(n, 0.0)) for n in names])
    return Xs, Ys + bias + std * rng.standard_normal(Ys.shape), U


def matched_truth(param_names, noise=MATCHED):
    """The true values of a marginalized PF's parameters (its ``param_names``) under
    ``noise``: the steering offset and std, then the sensors' biases and stds."""
    value = {"delta_offset": noise.offset, "delta_std": noise.steer_std}
    for s in SENSORS:
        value[f"{s}_bias"], value[f"{s}_std"] = noise.bias[s], noise.sensor_std[s]
    return np.array([value[n] for n in param_names])


def build_matched_filter(model, n_particles, options=None, noise=MATCHED):
    """A marginalized PF with ``noise``'s true statistics as its prior (NiW gamma0 = 1,
    forgetting 1; the bank chain in each particle's Kalman filter). ``options``:
    ``marginalized_pf``'s keywords, with ``builder="grid"`` for ``marginalized_pf_grid``'s
    (then ``input_std_range``, ``input_std_prior`` go into its ``InputStdGrid``); ``nu0``,
    ``gamma0`` go into the ``NiW``; ``bias_states=True``: ``model`` has a bias state per
    sensor (:func:`matched_setup`) that the Kalman filters estimate, and the NiW's bias means
    are not given (with gamma0 = 1e-9 they are pinned at zero, and the steering offset at its
    prior mean too: the NiW has one gamma for both)."""
    opts = dict(options or {})
    kalman = opts.pop("bias_states", False)
    grid = opts.pop("builder", None) == "grid"
    niw = NiW(std0={"delta": noise.steer_std, **noise.sensor_std},
              mean0={"delta": noise.offset} if kalman else {"delta": noise.offset, **noise.bias},
              forgetting=1.0, **{k: opts.pop(k) for k in ("nu0", "gamma0") if k in opts})
    common = dict(sensors=SENSORS, known_std=noise.known_std,
                  Q=noise.bank_jerk_std ** 2, niw=niw,
                  linear_states=("phi", "phi_dot", "phi_ddot")
                  + (tuple(f"{s}_bias" for s in SENSORS) if kalman else ()))
    if grid:
        std_grid = InputStdGrid(**{k: opts.pop(k) for k in ("input_std_range", "input_std_prior")
                                   if k in opts})
        return marginalized_pf_grid(model, n_particles, grid=std_grid, **common, **opts)
    return marginalized_pf(model, n_particles, **common, **opts)


def matched_setup(model, n_particles, options, P0, noise=MATCHED):
    """(estimator, x0, P0, state_params) of :func:`build_matched_filter` with ``options``,
    ``P0`` the truth's. With ``bias_states`` the filter runs on the model with bias states
    (:func:`vehjax.models.with_output_biases`), starting them from the bias prior of the other
    filters (mean the truth, variance gamma0 = 1 times the noise's); ``state_params`` maps each
    bias parameter to the state that estimates it (None without)."""
    x0 = np.zeros(len(model.state_names))
    if not (options or {}).get("bias_states", False):
        return build_matched_filter(model, n_particles, options, noise), x0, P0, None
    nx = len(x0)
    est = build_matched_filter(with_output_biases(model, SENSORS), n_particles, options, noise)
    return (est, np.r_[x0, [noise.bias[s] for s in SENSORS]],
            np.r_[P0, [noise.sensor_std[s] ** 2 for s in SENSORS]],
            {f"{s}_bias": nx + j for j, s in enumerate(SENSORS)})
