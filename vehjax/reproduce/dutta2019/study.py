"""Reproduce Dutta, Singh & Alam (2019): dual state and parameter estimation, Tables I-III.

``vehjax reproduce dutta2019`` runs the paper's two-model scheme as Monte-Carlo studies, one
jitted :func:`vehjax.run` call per filter and stage:

1. Kinematic stage (Table I, Fig. 4-5): lf and lr estimated on :class:`KinematicBicycle` from
   noisy (x, y, psi, v) by Dual EKF, Dual UKF and Liu-West Particle+UKF (and the joint EKF/UKF
   the paper compared against in its text).
2. Input-frequency study (Fig. 6): the Dual UKF of stage 1 under steering sines of several
   frequencies.
3. Dynamic stage (Tables II-III, Fig. 7-12): m, cx and cy estimated on :class:`Dynamic3DOF`
   from noisy (vx, vy, r). Each run's filter uses the lf, lr that the same filter estimated for
   that run in stage 1 (fed in as two extra, constant inputs, so all runs are still one call).

How the paper is read (it leaves these open; each choice is ours and printed with the results):

* Notation: the paper follows Thrun et al., R = process noise and Q = measurement noise; in
  vehjax Q is the process noise and R the measurement noise. Its Sigma_s, Sigma_p are taken as
  the initial covariances P0, P_theta0 exactly as printed (variances), R_p as Q_theta.
* "Simulation noise N(0, 0.1)": measurement noise of standard deviation 0.1 on every measured
  component, and process noise of 0.1 per square-root second (0.1 sqrt(dt) per step).
* The sampling period is not given: dt = 0.02 s (50 Hz). The paper's noise covariances are used per
  step as printed.
* The parameter noise decay gamma (R_p <- gamma R_p) is not given: 0.99 per step.
* Three filter settings are run (``--settings``): "paper", section III as printed; "matched",
  the covariances a user who knows the sensors would set: Q and R equal to the simulation's
  process and measurement noise, Q_theta = (1e-3 |truth|)^2 per step with the same decay, and
  P_theta0 the variance of the uniform box the initial guesses are drawn from; and "tuned", the
  covariances a user who knows neither the sensors nor the parameters would get from data:
  Q and R fitted by :func:`vehjax.tune.fit`, everything else (P0, Q_theta, its decay,
  P_theta0) as in "matched". The paper's process noise is 100-10^4 times the simulated one, so
  its filters follow the measurements and learn the parameters slowly or not at all.
* How "tuned" is made (:func:`tuned_settings`), per stage: a training set of 3 runs of the
  stage's model, noise and excitation, at most 20 s long (the stage's length when shorter),
  simulated from a random stream of their own (``fold_in`` of the stage's key), so they are
  never the study's runs. vehjax.tune rejects the dual, joint and Liu-West filters, so the fit
  uses a plain UKF on the same model: maximum likelihood (adam, at most 150 iterations) of
  diagonal Q and R, started from the paper's Q and R, jointly with the unknown parameters
  (lf, lr; m, cx, cy), started from one guess drawn from the prior box, since Q fitted with
  wrong parameters would absorb the model error. The fitted parameters are not passed on: the
  study's filters start from the same guesses as in the other settings and learn them from the
  study's runs. The dynamic fit holds lf, lr at the kinematic fit's values, as the study's
  dynamic stage uses the kinematic stage's estimates. The Fig. 6 study uses the Q and R
  tuned on the 0.5 Hz training runs for every steering frequency.
* Initial parameter guesses are not given: per run, uniform in the box the Particle+UKF uses
  as its prior (lf, lr in [0.5, 2.5] m; m, cx, cy within +-30 % of truth), the same guesses for
  every filter.
* Excitation. Kinematic: 5 m/s (the kinematic model's domain, Kong et al. 2015), steering
  0.3 rad sine at 0.5 Hz, acceleration 0.5 m/s^2 sine at 0.05 Hz. With 0.1 rad at 10 m/s the
  side-slip angle that separates lf from lr is a third as large and even the joint filters end
  0.1-0.2 m off after 60 s: the data do not hold the information. Dynamic: the paper uses MATLAB's recorded ``vehicledata``, which cannot ship; vehjax
  generates inputs of the same character with :class:`Dynamic3DOF` itself: front-wheel slips
  around the one that holds 20 m/s, swinging the speed between about 14 and 23 m/s, and a
  two-tone steering signal (0.04 rad at 0.25 Hz plus 0.02 rad at 0.9 Hz, up to about 0.45 rad/s
  of yaw rate), rear slips zero. Half these amplitudes leave m, cx, cy off by about 7 % after
  60 s even for the joint EKF.
* ``--excitation chirp``: a second dynamic excitation with other true values, for checking
  the filters on data they were not tuned to: a linear steering chirp from 0.1 to
  1.5 Hz over the stage (0.03 rad), 15 m/s with the speed swinging by about +-0.8 m/s^2 of
  acceleration at a 12 s period, and the true m, cx, cy at 1.10, 0.92 and 1.06 times the
  nominal values; the box (the initial guesses and the Particle+UKF's prior) stays +-30 %
  around the nominal values, so it is not centred on the truth. The kinematic stage is
  unchanged.

The paper's settings, the matched ones and the simulation noise are
:mod:`vehjax.studies.dual_settings`'s, the dynamic excitation :func:`vehjax.scenarios.slip_and_steer`.
This module is the study: the paper's settings and ours, the excitations, the simulated runs,
the "tuned" fit, the filters and the two stages (:func:`kinematic_study`,
:func:`dynamic_study`). How its results are read and shown (tables, the written summaries,
figures, ``report.md``) and the command line (:func:`main`, :func:`parser`) are in
:mod:`vehjax.reproduce.dutta2019.report`; the package lends both modules' names.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import numpy as np

from ... import scenarios
from ...studies.dual_settings import (DYNAMIC_SETTINGS, KINEMATIC_SETTINGS, SIM_STD,  # noqa: F401
                              matched_settings, simulate_runs)
from .. import reporting

PAPER = "Dutta, Singh, Alam (2019), Dual state and parameter estimation of a four wheel vehicle"

_DECAY = 0.99

#: The paper's numbers: Table I (lf, lr m), II (RMS error vx, vy m/s, r rad/s), III (m, cx, cy).
PAPER_TABLE1 = {"Dual EKF": (1.56, 1.43), "Dual UKF": (1.58, 1.39), "Particle+UKF": (1.67, 1.36)}
PAPER_TABLE2 = {"Dual UKF": (1.3197, 0.636, 0.1277), "Particle+UKF": (0.1727, 0.1566, 0.0630)}
PAPER_TABLE3 = {"Dual UKF": (1620.0, 13.2e4, 4.75e4), "Particle+UKF": (1715.0, 14.6e4, 3.85e4)}

_KIN_BOX = ((0.5, 2.5), (0.5, 2.5))
_DYN_REL_BOX = 0.3
_FILTERS = ("Dual EKF", "Dual UKF", "Particle+UKF", "Joint EKF", "Joint UKF")
_SETTINGS = ("paper", "matched", "tuned")
# tuned settings: training runs and the fit (vehjax.tune.fit, adam on log standard deviations)
_TUNE_RUNS = 3  # training runs per stage
_TUNE_DURATION = 20.0  # s, longest training run (the stage's duration when shorter)
_TUNE_LR = 0.3  # adam's peak step on the unconstrained (log) scale
_TUNE_STEPS = 150  # adam iterations at most
_TUNE_PATIENCE = 20  # iterations without improvement before the fit stops
_TRAINING_STREAM = 1  # jax.random.fold_in data of the training runs' random stream
_FREQUENCIES = (0.1, 0.25, 0.5, 1.0)  # Hz, input-frequency study
#: label of a filter's smoothed row: its own RTS smoother (extended RTS for the joint EKF,
#: unscented RTS for the joint UKF, parameters smoothed as constant states) on the same runs
SMOOTHED = "RTS-smoothed"


class Stage(NamedTuple):
    """One stage's study: the simulation, each filter's result and the truth."""

    sim: object
    results: dict  # filter name -> RunResult
    truth: np.ndarray  # (p,) true values of the estimated parameters
    names: tuple  # estimated parameter names
    seconds: dict  # filter name -> wall time of its run call, s
    theta0: np.ndarray  # (R, p) initial guesses of the estimated parameters (BOX_PRIOR aside)
    param_units: tuple  # units of the estimated parameters
    state_units: tuple  # units of the states
    box: np.ndarray  # (p, 2) the box theta0 is drawn from, the prior of the BOX_PRIOR filters
    tuning: object = None  # Tuning of the "tuned" setting; None for the others
    smoothed: dict | None = None  # filter name -> RunResult smoothed (RTS) on the same runs
    model: object = None  # the stage's true model (``theta`` the truth, names, units, dt)


#: filters whose parameter prior is the uniform box itself (theta0 unused): their initial
#: estimate is the box centre in every run
BOX_PRIOR = ("Particle+UKF",)


def initial_estimates(stage: Stage, name: str) -> np.ndarray:
    """(R, p) initial parameter estimate of filter ``name`` in each run: ``theta0``, or the box
    centre for the BOX_PRIOR filters."""
    if name in BOX_PRIOR:
        return np.broadcast_to(np.asarray(stage.box, float).mean(axis=1), np.shape(stage.theta0))
    return np.asarray(stage.theta0)


def _final(params, window: int):
    """Per-run final estimate: mean over the last ``window`` steps, (R, p)."""
    return params[:, -window:].mean(axis=1)


def _window(res):
    """Steps of a result's final estimate: the last 10 % (at least one)."""
    return max(1, res.params.shape[1] // 10)


def _ok(res):
    """(R,) the runs that did not diverge."""
    return ~np.asarray(res.diverged)


# ----------------------------------------------------------------------------------------------
# Excitation


def kinematic_scenario(model, duration: float = 60.0, frequency: float = 0.5,
                       amplitude: float = 0.3, speed: float = 5.0):
    """Open-loop inputs (a, delta) for KinematicBicycle: a steering sine and a slow speed swing."""
    from ... import scenarios

    t = np.arange(int(round(duration / model.dt))) * model.dt
    a = 0.5 * np.sin(2 * np.pi * 0.05 * t)
    delta = amplitude * np.sin(2 * np.pi * frequency * t)
    return scenarios.from_inputs(model, np.stack([a, delta], 1), [0.0, 0.0, 0.0, speed],
                                 name=f"sine {frequency:g} Hz")


def _slip_and_steer(model, duration):
    """The dynamic stage's excitation (module docstring): :func:`vehjax.scenarios.slip_and_steer`
    at 20 m/s."""
    return scenarios.slip_and_steer(model, duration=duration)


#: ``--excitation chirp``: true m, cx, cy relative to the nominal values
CHIRP_TRUTH = (1.10, 0.92, 1.06)


def chirp_scenario(model, duration: float = 60.0, speed: float = 15.0):
    """The second dynamic excitation (``--excitation chirp``, module docstring): front slips that
    hold ``speed`` against drag with a +-0.8 m/s^2 swing of 12 s period, a 0.03 rad steering
    chirp from 0.1 to 1.5 Hz, rear slips zero."""
    from ... import scenarios

    m, cx, ca = (float(model.theta[model.param_index(n)[0]]) for n in ("m", "cx", "ca"))
    t = np.arange(int(round(duration / model.dt))) * model.dt
    slip = ca * speed**2 / (2 * cx) + 0.8 * m / (2 * cx) * np.sin(2 * np.pi * t / 12.0)
    f0, f1 = 0.1, 1.5
    delta = 0.03 * np.sin(2 * np.pi * (f0 * t + 0.5 * (f1 - f0) / duration * t**2))
    zero = np.zeros_like(t)
    return scenarios.from_inputs(model, np.stack([slip, slip, zero, zero, delta], 1),
                                 [speed, 0.0, 0.0], name="chirp excitation")


def _with_axle_inputs(dyn):
    """Dynamic3DOF with lf, lr taken from two extra inputs (per-run values from stage 1)."""
    from ...models import Model

    i_lf, i_lr = dyn.param_index(("lf", "lr"))

    def theta_of(u, theta):
        return theta.at[i_lf].set(u[5]).at[i_lr].set(u[6])

    return Model(
        transition=lambda x, u, th: dyn.transition(x, u[:5], theta_of(u, th)),
        observe=lambda x, u, th: dyn.observe(x, u[:5], theta_of(u, th)),
        dt=dyn.dt,
        state_names=dyn.state_names,
        param_names=dyn.param_names,
        input_names=tuple(dyn.input_names) + ("lf_hat", "lr_hat"),
        output_names=dyn.output_names,
        theta=dyn.theta,
        units={**dict(zip(dyn.state_names, dyn.state_units)),
               **dict(zip(dyn.param_names, dyn.param_units)),
               **dict(zip(dyn.input_names, dyn.input_units)), "lf_hat": "m", "lr_hat": "m",
               **dict(zip(dyn.output_names, dyn.output_units))},
    )


def study_runs(model, scn, runs: int, key):
    """The study's runs of a stage, on which the filters of every setting are evaluated.

    Parameters
    ----------
    model : vehjax model
        The true model (``model.theta``).
    scn : vehjax.scenarios.Scenario
        The excitation, T steps of ``model.dt`` s.
    runs : int
        Number of runs R.
    key : jax.random.key
        The stage's key (the one :func:`_stage` is given).

    Returns
    -------
    vehjax.Simulation
        (R, T, nx) states, (R, T, ny) measurements.
    """
    return simulate_runs(model, scn, runs, jax.random.split(key, 3)[0])


def _training_keys(key):
    """(simulation, starting guess) keys of the training runs of the stage whose key is ``key``:
    a random stream of their own (``fold_in``), never one the study draws from."""
    return tuple(jax.random.split(jax.random.fold_in(key, _TRAINING_STREAM), 2))


def training_runs(model, scn, runs: int, key):
    """The training runs of the "tuned" setting: the same model, noise and excitation as the
    study's runs, simulated from a random stream of their own.

    Parameters
    ----------
    model, scn, runs
        As for :func:`study_runs` (``scn`` may be shorter than the study's).
    key : jax.random.key
        The stage's key, the same one :func:`study_runs` is given; the training stream is
        ``fold_in(key, _TRAINING_STREAM)``, which the study never draws from.

    Returns
    -------
    vehjax.Simulation
        (R, T, nx) states, (R, T, ny) measurements.
    """
    return simulate_runs(model, scn, runs, _training_keys(key)[0])


class Tuning(NamedTuple):
    """How the "tuned" settings of one stage were made."""

    settings: dict  # the filter settings (P0, P_theta0, Q, Q_theta, R as diagonals)
    fit: object  # vehjax.tune.TuneResult of the fit on the training runs
    sim: object  # the training runs, a vehjax Simulation with (runs, T, ny) measurements
    names: tuple  # the model parameters fitted with Q and R
    start: np.ndarray  # (p,) their starting values in the fit
    fixed: dict  # model parameters held at given values in the fit (name -> value)


def tuned_settings(paper: dict, model, scn, estimate, truth, box, key, runs: int = _TUNE_RUNS,
                   fixed=None, steps: int = _TUNE_STEPS) -> Tuning:
    """The "tuned" settings: Q and R fitted by :func:`vehjax.tune.fit` on training runs.

    ``runs`` training runs of ``scn`` (:func:`training_runs`, a random stream the study does not
    use) are filtered by a UKF on ``model``; Q and R (diagonal, from the paper's ``paper["Q"]``,
    ``paper["R"]``) and the unknown parameters ``estimate`` (from one guess drawn uniformly from
    ``box`` with the training stream) are fitted jointly by maximum likelihood (adam). P0 is the
    paper's; Q_theta and P_theta0 are those of :func:`matched_settings`.

    Parameters
    ----------
    paper : dict
        The paper's settings (``KINEMATIC_SETTINGS`` or ``DYNAMIC_SETTINGS``): diagonals of P0
        (nx,), Q (nx,) [state units^2 per step], R (ny,) [output units^2].
    model : vehjax model
        The true model; ``model.theta`` simulates the training runs.
    scn : vehjax.scenarios.Scenario
        Excitation of the training runs (T steps).
    estimate : sequence of str
        The parameters fitted with Q and R, (p,) names.
    truth : array_like
        (p,) true values of ``estimate`` (for the matched Q_theta only).
    box : array_like
        (p, 2) low and high ends of the box the starting guess is drawn from, parameter units.
    key : jax.random.key
        The stage's key; the training stream is derived from it.
    runs : int
        Number of training runs.
    fixed : dict, optional
        Model parameters (name -> value) to hold at values other than the truth in the fit.
    steps : int
        Most adam iterations.

    Returns
    -------
    Tuning
    """
    from ... import tune
    from ...filters import ukf

    sim = training_runs(model, scn, runs, key)
    low, high = np.asarray(box, dtype=float).T
    start = np.asarray(jax.random.uniform(_training_keys(key)[1], (len(estimate),),
                                          minval=low, maxval=high), dtype=float)
    fixed = {k: float(v) for k, v in (fixed or {}).items()}
    guess = model.with_theta(**fixed, **{n: float(v) for n, v in zip(estimate, start)})
    fit = tune.fit(ukf, guess, np.asarray(paper["Q"], float), np.asarray(paper["R"], float),
                   sim.measurements, sim.inputs, x0=np.asarray(scn.x0, float),
                   P0=np.diag(np.asarray(paper["P0"], float)), params=tuple(estimate),
                   options=tune.Options(optimizer=tune.Adam(learning_rate=_TUNE_LR, steps=steps,
                                                            patience=_TUNE_PATIENCE),
                                        progress=False))
    cfg = matched_settings(paper, model, truth, box)
    cfg.update(Q=tuple(float(v) for v in np.diag(fit.Q)), R=tuple(float(v) for v in np.diag(fit.R)))
    return Tuning(cfg, fit, sim, tuple(estimate), start, fixed)


# ----------------------------------------------------------------------------------------------
# Filters


def _builders(model, s, estimate, box, particles: int):
    from ...filters.dual import dual_ekf, dual_ukf, joint_ekf, joint_ukf
    from ...filters.liu_west import liu_west_ukf

    common = dict(estimate=estimate, theta_decay=_DECAY)
    low, high = np.asarray(box).T
    return {
        "Dual EKF": lambda: dual_ekf(model, s["Q"], s["R"], Q_theta=s["Q_theta"], **common),
        "Dual UKF": lambda: dual_ukf(model, s["Q"], s["R"], Q_theta=s["Q_theta"], **common),
        "Particle+UKF": lambda: liu_west_ukf(
            model, s["Q"], s["R"], n_particles=particles, estimate=estimate, theta_low=low,
            theta_high=high),
        "Joint EKF": lambda: joint_ekf(model, s["Q"], s["R"], Q_theta=s["Q_theta"], **common),
        "Joint UKF": lambda: joint_ukf(model, s["Q"], s["R"], Q_theta=s["Q_theta"], **common),
    }


def _stage(model, scn, estimate, settings, box, runs, key, estimators, inputs=None,
           progress=None, tuning=None, smooth: bool = False) -> Stage:
    """Simulate ``runs`` runs of ``scn`` and run each of ``estimators`` (name -> Estimator);
    with ``smooth`` each one with a Gaussian smoother (``Estimator.smoother``: the joint
    EKF/UKF) also smoothed on the same runs (``vehjax.run(..., smooth=True)``, its own RTS),
    in ``Stage.smoothed``."""
    from ... import run

    _, k_guess, k_run = jax.random.split(key, 3)
    sim = study_runs(model, scn, runs, key)
    truth = np.asarray(model.theta)[list(model.param_index(estimate))]
    low, high = np.asarray(box).T
    theta0 = np.asarray(jax.random.uniform(k_guess, (runs, len(estimate)), minval=low, maxval=high))
    x0 = np.asarray(scn.x0)
    results, seconds, smoothed = {}, {}, {}

    def timed(label, est, us, **kw):
        """One study of ``est``, its seconds in ``seconds[label]``, progress around it."""
        if progress:
            progress(f"  {label}: {runs} runs x {len(scn.t)} steps ...")
        out, seconds[label] = reporting.timed(
            run, est, sim.measurements, us, x0=x0, P0=np.diag(settings["P0"]), theta0=theta0,
            P_theta0=np.diag(settings["P_theta0"]), key=k_run, **kw)
        if progress:
            n_div = int(np.sum(out.diverged))
            progress(f" {seconds[label]:.1f} s" + (f", {n_div} diverged" if n_div else "") + "\n")
        return out

    for name, est in estimators.items():
        us = sim.inputs if inputs is None else inputs[name]
        results[name] = timed(name, est, us, return_covariances=True)
        if smooth and est.smoother is not None:
            smoothed[name] = timed(f"{name} {SMOOTHED}", est, us, smooth=True)
    p_units = tuple(model.param_units[i] for i in model.param_index(estimate))
    return Stage(sim, results, truth, tuple(estimate), seconds, theta0, p_units,
                 tuple(model.state_units), np.asarray(box, dtype=float), tuning, smoothed,
                 model)



# ----------------------------------------------------------------------------------------------
# The two stages


def _config(setting: str, paper: dict, model, truth, box, make_tuning):
    """(filter settings, Tuning or None) of ``setting``; ``make_tuning()`` makes the Tuning of
    the "tuned" setting (only called for it)."""
    if setting == "paper":
        return paper, None
    if setting == "matched":
        return matched_settings(paper, model, truth, box), None
    tuning = make_tuning()
    return tuning.settings, tuning


def _tuned(stage_name: str, make_tuning, progress=None):
    """``make_tuning()`` with a progress line."""
    if progress:
        progress(f"[tuned] {stage_name}: fitting Q, R on {_TUNE_RUNS} training runs ...")
    tuning = make_tuning()
    if progress:
        progress(f" {tuning.fit.iterations} iterations, {tuning.fit.seconds:.1f} s\n")
    return tuning


def kinematic_study(filters, setting: str, key, *, runs: int, particles: int,
                    duration: float = 60.0, dt: float = 0.02, frequency_study: bool = True,
                    progress=None):
    """Stage 1 (Table I, Fig. 4-6): lf, lr on :class:`KinematicBicycle`, and the input-frequency
    study of the Dual UKF.

    Parameters
    ----------
    filters : sequence of str
        Names of the filters run (of ``_FILTERS``).
    setting : str
        "paper", "matched" or "tuned" (module docstring).
    key : jax.random.key
        The stage's key: the study's runs, the initial guesses, the filters' keys, the
        training runs (a stream of their own) and the frequency study's runs.
    runs, particles : int
        Monte-Carlo runs; the Particle+UKF's particles.
    duration, dt : float
        The stage's length and sampling period, s.
    frequency_study : bool
        Whether to run the Fig. 6 study (only when the Dual UKF is among ``filters``).
    progress : callable, optional
        Called with progress text (no newline added); None: silent.

    Returns
    -------
    (Stage, dict or None)
        The stage, and the frequency study: steering frequency [Hz] -> the Dual UKF's RunResult
        (None when not run).
    """
    from ...models import KinematicBicycle

    kin = KinematicBicycle(dt=dt)
    scn = kinematic_scenario(kin, duration)
    truth = np.asarray(kin.theta)
    k_main, k_freq = jax.random.split(key)
    train = kinematic_scenario(kin, min(duration, _TUNE_DURATION))
    cfg, tuning = _config(setting, KINEMATIC_SETTINGS, kin, truth, _KIN_BOX, lambda: _tuned(
        "kinematic model", lambda: tuned_settings(KINEMATIC_SETTINGS, kin, train, ("lf", "lr"),
                                                  truth, _KIN_BOX, k_main), progress))
    builders = _builders(kin, cfg, ("lf", "lr"), _KIN_BOX, particles)
    ests = {name: builders[name]() for name in filters}
    if progress:
        progress(f"[{setting}] kinematic model, {scn.name} steering at 5 m/s, {len(scn.t)} "
                 "steps:\n")
    st = _stage(kin, scn, ("lf", "lr"), cfg, _KIN_BOX, runs, k_main, ests, progress=progress,
                tuning=tuning)
    if not frequency_study or "Dual UKF" not in ests:
        return st, None
    if progress:
        progress(f"[{setting}] input-frequency study (Dual UKF):")
    freq = {}
    for f in _FREQUENCIES:
        scn_f = kinematic_scenario(kin, duration, frequency=f)
        freq[f] = _stage(kin, scn_f, ("lf", "lr"), cfg, _KIN_BOX, runs, k_freq,
                         {"Dual UKF": ests["Dual UKF"]}).results["Dual UKF"]
        if progress:
            progress(f" {f:g} Hz")
    if progress:
        progress("\n")
    return st, freq


def dynamic_study(filters, setting: str, key, kinematic: Stage, *, runs: int, particles: int,
                  duration: float = 60.0, dt: float = 0.02, excitation: str = "paper",
                  smooth: bool = True, progress=None) -> Stage:
    """Stage 2 (Tables II-III, Fig. 7-12): m, cx, cy on :class:`Dynamic3DOF`, each run's filter
    with the lf, lr that the same filter estimated for that run in ``kinematic``.

    Parameters
    ----------
    filters, setting, runs, particles, duration, dt, progress
        As for :func:`kinematic_study`.
    key : jax.random.key
        The stage's key.
    kinematic : Stage
        Stage 1 of the same setting (its filters' final lf, lr per run; for "tuned", the lf, lr
        its training fit found, which the dynamic fit holds).
    excitation : str
        "paper" or "chirp" (module docstring).
    smooth : bool
        Also run the filters that have a Gaussian smoother (the joint EKF/UKF) smoothed
        (``Stage.smoothed``).

    Returns
    -------
    Stage
        ``Stage.model`` is the dynamic model with lf, lr as two extra inputs; its ``theta`` the
        truth.
    """
    from ...models import Dynamic3DOF

    dyn = Dynamic3DOF(dt=dt)
    nominal = np.asarray(dyn.theta)[list(dyn.param_index(("m", "cx", "cy")))]
    excite = _slip_and_steer
    if excitation == "chirp":  # other true values; the box stays around the nominal ones
        th = np.asarray(dyn.theta, float).copy()
        th[list(dyn.param_index(("m", "cx", "cy")))] = nominal * np.asarray(CHIRP_TRUTH)
        dyn, excite = Dynamic3DOF(dt=dt, theta=th), chirp_scenario
    model = _with_axle_inputs(dyn)
    scn_d = excite(dyn, duration)
    base = np.asarray(scn_d.inputs)
    T = len(base)
    lf_lr_true = np.asarray(dyn.theta)[list(dyn.param_index(("lf", "lr")))]
    scn_m = scn_d._replace(inputs=np.concatenate([base, np.tile(lf_lr_true, (T, 1))], 1),
                           input_names=model.input_names)
    inputs = {}
    for name, res in kinematic.results.items():
        lf_lr = _final(res.params, _window(res))
        lf_lr = np.where(np.isfinite(lf_lr) & (lf_lr > 0), lf_lr, lf_lr_true)
        inputs[name] = np.concatenate(
            [np.broadcast_to(base, (runs,) + base.shape),
             np.broadcast_to(lf_lr[:, None, :], (runs, T, 2))], 2)
    truth = np.asarray(dyn.theta)[list(dyn.param_index(("m", "cx", "cy")))]
    box = [(v * (1 - _DYN_REL_BOX), v * (1 + _DYN_REL_BOX)) for v in nominal]
    # the training fit holds lf, lr at what the kinematic training fit found, as the study's
    # dynamic stage uses the kinematic stage's estimates
    train = excite(dyn, min(duration, _TUNE_DURATION))
    cfg, tuning = _config(setting, DYNAMIC_SETTINGS, dyn, truth, box, lambda: _tuned(
        "dynamic model", lambda: tuned_settings(DYNAMIC_SETTINGS, dyn, train, ("m", "cx", "cy"),
                                                truth, box, key,
                                                fixed=kinematic.tuning.fit.params), progress))
    builders = _builders(model, cfg, ("m", "cx", "cy"), box, particles)
    ests = {name: builders[name]() for name in filters}
    if progress:
        progress(f"[{setting}] dynamic model, {T} steps (each run uses its own lf, lr from "
                 "above):\n")
    return _stage(model, scn_m, ("m", "cx", "cy"), cfg, box, runs, key, ests, inputs=inputs,
                  progress=progress, tuning=tuning, smooth=smooth)
