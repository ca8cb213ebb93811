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
* Two filter settings are run (``--settings``): "paper", section III as printed, and "matched",
  the covariances a user who knows the sensors would set: Q and R equal to the simulation's
  process and measurement noise, Q_theta = (1e-3 |truth|)^2 per step with the same decay, and
  P_theta0 the variance of the uniform box the initial guesses are drawn from. The paper's
  process noise is 100-10^4 times the simulated one, so its filters follow the measurements
  and learn the parameters slowly or not at all.
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
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import NamedTuple

import jax
import numpy as np

PAPER = "Dutta, Singh, Alam (2019), Dual state and parameter estimation of a four wheel vehicle"

_DECAY = 0.99
_SIM_STD = 0.1

# Section III, in vehjax's naming (Q process, R measurement); diagonals.
KINEMATIC_SETTINGS = dict(
    P0=(1.0, 1.0, 0.2, 2.0),
    P_theta0=(3.0, 3.0),
    Q=(0.5**2, 0.5**2, 0.2**2, 1.0**2),
    Q_theta=(1.25**2, 1.25**2),
    R=(1.0**2, 1.0**2, 1.5**2, 0.1**2),
)
DYNAMIC_SETTINGS = dict(
    P0=(1.0, 1.0, 0.2),
    P_theta0=(200.0, 2.0e4, 1.5e4),
    Q=(1.2**2, 1.2**2, 0.45**2),
    Q_theta=(20.0**2, 175.0**2, 150.0**2),
    R=(0.2**2, 0.2**2, 0.15**2),
)

#: The paper's numbers: Table I (lf, lr m), II (RMS error vx, vy m/s, r rad/s), III (m, cx, cy).
PAPER_TABLE1 = {"Dual EKF": (1.56, 1.43), "Dual UKF": (1.58, 1.39), "Particle+UKF": (1.67, 1.36)}
PAPER_TABLE2 = {"Dual UKF": (1.3197, 0.636, 0.1277), "Particle+UKF": (0.1727, 0.1566, 0.0630)}
PAPER_TABLE3 = {"Dual UKF": (1620.0, 13.2e4, 4.75e4), "Particle+UKF": (1715.0, 14.6e4, 3.85e4)}

_KIN_BOX = ((0.5, 2.5), (0.5, 2.5))
_DYN_REL_BOX = 0.3
_FILTERS = ("Dual EKF", "Dual UKF", "Particle+UKF", "Joint EKF", "Joint UKF")
_SETTINGS = ("paper", "matched")
_Q_THETA_REL = 1e-3  # matched settings: parameter random-walk std per step, relative to truth
_FREQUENCIES = (0.1, 0.25, 0.5, 1.0)  # Hz, input-frequency study


class Stage(NamedTuple):
    """One stage's study: the simulation, each filter's result and the truth."""

    sim: object
    results: dict  # filter name -> RunResult
    truth: np.ndarray  # (p,) true values of the estimated parameters
    names: tuple  # estimated parameter names
    seconds: dict  # filter name -> wall time of its run call, s


# ----------------------------------------------------------------------------------------------
# Excitation


def kinematic_scenario(model, duration: float = 60.0, frequency: float = 0.5,
                       amplitude: float = 0.3, speed: float = 5.0):
    """Open-loop inputs (a, delta) for KinematicBicycle: a steering sine and a slow speed swing."""
    from .. import scenarios

    t = np.arange(int(round(duration / model.dt))) * model.dt
    a = 0.5 * np.sin(2 * np.pi * 0.05 * t)
    delta = amplitude * np.sin(2 * np.pi * frequency * t)
    return scenarios.from_inputs(model, np.stack([a, delta], 1), [0.0, 0.0, 0.0, speed],
                                 name=f"sine {frequency:g} Hz")


def dynamic_scenario(model, duration: float = 60.0, speed: float = 20.0):
    """Open-loop inputs (s_fl, s_fr, s_rl, s_rr, delta) for Dynamic3DOF, in the style of MATLAB's
    vehicledata: front slips that balance air drag at ``speed`` and swing the speed between
    about 14 and 23 m/s, two-tone steering, rear slips zero."""
    from .. import scenarios

    m, cx, ca = (float(model.theta[model.param_index(n)[0]]) for n in ("m", "cx", "ca"))
    t = np.arange(int(round(duration / model.dt))) * model.dt
    hold = ca * speed**2 / (2 * cx)  # slip per front wheel that balances drag
    swing = 0.6 * m / (2 * cx)  # +-0.6 m/s^2 of longitudinal acceleration
    slip = hold + swing * np.sin(2 * np.pi * t / 20.0)
    delta = 0.04 * np.sin(2 * np.pi * 0.25 * t) + 0.02 * np.sin(2 * np.pi * 0.9 * t + 1.0)
    zero = np.zeros_like(t)
    return scenarios.from_inputs(model, np.stack([slip, slip, zero, zero, delta], 1),
                                 [speed, 0.0, 0.0], name="dynamic excitation")


def _with_axle_inputs(dyn):
    """Dynamic3DOF with lf, lr taken from two extra inputs (per-run values from stage 1)."""
    from ..models import Model

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
    )


def matched_settings(paper: dict, model, truth, box) -> dict:
    """The "matched" settings: Q, R of the simulation, small Q_theta, P_theta0 of the box."""
    nx, ny, dt = len(model.state_names), len(model.output_names), model.dt
    width = np.diff(np.asarray(box, float), axis=1)[:, 0]
    return dict(
        P0=paper["P0"],
        P_theta0=tuple(width**2 / 12.0),
        Q=(_SIM_STD**2 * dt,) * nx,
        Q_theta=tuple((_Q_THETA_REL * np.abs(truth)) ** 2),
        R=(_SIM_STD**2,) * ny,
    )


# ----------------------------------------------------------------------------------------------
# Filters


def _builders(model, s, estimate, box, particles: int):
    from ..filters.dual import dual_ekf, dual_ukf, joint_ekf, joint_ukf
    from ..filters.liu_west import liu_west_ukf

    common = dict(estimate=estimate, theta_decay=_DECAY)
    low, high = np.asarray(box).T
    return {
        "Dual EKF": lambda: dual_ekf(model, s["Q"], s["R"], s["Q_theta"], **common),
        "Dual UKF": lambda: dual_ukf(model, s["Q"], s["R"], s["Q_theta"], **common),
        "Particle+UKF": lambda: liu_west_ukf(
            model, s["Q"], s["R"], particles, estimate=estimate, theta_low=low, theta_high=high
        ),
        "Joint EKF": lambda: joint_ekf(model, s["Q"], s["R"], s["Q_theta"], **common),
        "Joint UKF": lambda: joint_ukf(model, s["Q"], s["R"], s["Q_theta"], **common),
    }


def _stage(model, scn, estimate, settings, box, runs, key, estimators, inputs=None,
           progress=None) -> Stage:
    """Simulate ``runs`` runs of ``scn`` and run each of ``estimators`` (name -> Estimator)."""
    from .. import run, simulate

    k_sim, k_guess, k_run = jax.random.split(key, 3)
    dt = model.dt
    sim = simulate(model, scn, runs=runs, key=k_sim,
                   process_std=_SIM_STD * np.sqrt(dt), meas_std=_SIM_STD)
    truth = np.asarray(model.theta)[list(model.param_index(estimate))]
    low, high = np.asarray(box).T
    theta0 = np.asarray(jax.random.uniform(k_guess, (runs, len(estimate)), minval=low, maxval=high))
    x0 = np.asarray(scn.x0)
    results, seconds = {}, {}
    for name, est in estimators.items():
        if progress:
            progress(f"  {name}: {runs} runs x {len(scn.t)} steps ...")
        t0 = time.perf_counter()
        results[name] = run(
            est, sim.measurements, sim.inputs if inputs is None else inputs[name],
            x0=x0, P0=np.diag(settings["P0"]), theta0=theta0,
            P_theta0=np.diag(settings["P_theta0"]), key=k_run,
        )
        seconds[name] = time.perf_counter() - t0
        if progress:
            n_div = int(np.sum(results[name].diverged))
            progress(f" {seconds[name]:.1f} s" + (f", {n_div} diverged" if n_div else "") + "\n")
    return Stage(sim, results, truth, tuple(estimate), seconds)


# ----------------------------------------------------------------------------------------------
# Tables


def _final(params, window: int):
    """Per-run final estimate: mean over the last ``window`` steps, (R, p)."""
    return params[:, -window:].mean(axis=1)


def _ok(res):
    return ~np.asarray(res.diverged)


def _fmt_pm(mean, std, digits):
    return f"{mean:.{digits}f} +- {std:.{digits}f}"


def table_parameters(stage: Stage, paper: dict, dt: float, tol, digits, scale=None, window=None):
    """Markdown table: final estimate mean +- std over runs, convergence time, the paper's value."""
    from .. import metrics

    names = stage.names
    scale = np.ones(len(names)) if scale is None else np.asarray(scale)
    unit = [f" (x{s:g})" if s != 1 else "" for s in scale]
    head = "| filter | " + " | ".join(f"{n}{u}" for n, u in zip(names, unit))
    head += " | " + " | ".join(f"t_conv {n} [s]" for n in names) + " | diverged |"
    lines = [head, "|" + "---|" * (2 * len(names) + 2)]
    lines.append("| truth | " + " | ".join(f"{v / s:.{d}f}" for v, s, d in zip(stage.truth, scale, digits))
                 + " |" + " |" * len(names) + " |")
    for name, res in stage.results.items():
        ok = _ok(res)
        T = res.params.shape[1]
        w = window or max(1, T // 10)
        fin = _final(res.params, w)[ok] / scale
        conv = metrics.convergence_time(res.params, stage.truth[None, None, :], tol, dt, mask=ok)
        conv_s = []
        for j in range(len(names)):
            c = conv[ok, j]
            n_conv = int(np.sum(np.isfinite(c)))
            med = np.median(c[np.isfinite(c)]) if n_conv else np.inf
            conv_s.append(f"{med:.1f} ({n_conv}/{ok.sum()})" if n_conv else f"never (0/{ok.sum()})")
        err = np.abs(fin - stage.truth / scale)
        cells = [f"{_fmt_pm(fin[:, j].mean(), fin[:, j].std(), d)} ({err[:, j].mean():.{d}f})"
                 if len(fin) else "-" for j, d in enumerate(digits)]
        lines.append(f"| {name} (vehjax) | " + " | ".join(cells) + " | " + " | ".join(conv_s)
                     + f" | {int((~ok).sum())}/{len(ok)} |")
        if name in paper:
            lines.append(f"| {name} (paper) | "
                         + " | ".join(f"{v / s:.{d}f}" for v, s, d in zip(paper[name], scale, digits))
                         + " |" + " |" * len(names) + " |")
    return "\n".join(lines)


def table_states(stage: Stage, paper: dict):
    """Markdown table: state RMSE over all runs and steps with its 95 % interval over runs."""
    from .. import metrics

    names = stage.sim.state_names
    lines = ["| filter | " + " | ".join(f"RMSE {n}" for n in names) + " |",
             "|" + "---|" * (len(names) + 1)]
    for name, res in stage.results.items():
        ok = _ok(res)
        per_run = metrics.rmse(res.states, stage.sim.states, axis="run", mask=ok)
        ci = metrics.confidence_interval(per_run, mask=ok)
        total = metrics.rmse(res.states, stage.sim.states, mask=ok) if ok.any() else [np.nan] * 3
        lines.append(f"| {name} (vehjax) | "
                     + " | ".join(f"{v:.4f} [{lo:.4f}, {hi:.4f}]"
                                  for v, lo, hi in zip(total, ci.low, ci.high)) + " |")
        if name in paper:
            lines.append(f"| {name} (paper) | " + " | ".join(f"{v:.4f}" for v in paper[name]) + " |")
    return "\n".join(lines)


def frequency_table(freq_results: dict, truth, dt: float, tol: float):
    from .. import metrics

    lines = ["| steering frequency [Hz] | final lf [m] | final lr [m] | t_conv lf [s] | t_conv lr [s] |",
             "|---|---|---|---|---|"]
    for f, res in freq_results.items():
        ok = _ok(res)
        fin = _final(res.params, max(1, res.params.shape[1] // 10))[ok]
        conv = metrics.convergence_time(res.params, np.asarray(truth)[None, None], tol, dt, mask=ok)[ok]
        med = [np.median(c) if np.all(np.isfinite(c)) else
               (np.median(c[np.isfinite(c)]) if np.isfinite(c).any() else np.inf) for c in conv.T]
        err = np.abs(fin - np.asarray(truth)).mean(axis=0)
        lines.append(f"| {f:g} | {_fmt_pm(fin[:, 0].mean(), fin[:, 0].std(), 3)} ({err[0]:.3f}) | "
                     f"{_fmt_pm(fin[:, 1].mean(), fin[:, 1].std(), 3)} ({err[1]:.3f}) | "
                     f"{med[0]:.1f} | {med[1]:.1f} |")
    return "\n".join(lines)


# ----------------------------------------------------------------------------------------------
# Figures


def _band(ax, t, values, label, color):
    """Mean over runs with a shaded 5-95 % band."""
    lo, hi = np.nanpercentile(values, [5, 95], axis=0)
    ax.fill_between(t, lo, hi, color=color, alpha=0.2, lw=0)
    ax.plot(t, np.nanmean(values, axis=0), color=color, lw=1.2, label=label)


def plot_parameters(stage: Stage, path, title: str, scale=None):
    """One panel per parameter: each filter's mean and 5-95 % band over runs, and the truth."""
    from ..plots import plt

    t = np.asarray(stage.sim.t)
    n = len(stage.names)
    scale = np.ones(n) if scale is None else np.asarray(scale)
    fig, axes = plt.subplots(n, 1, figsize=(8, 2.6 * n), sharex=True, squeeze=False)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for j, ax in enumerate(axes[:, 0]):
        for k, (name, res) in enumerate(stage.results.items()):
            ok = _ok(res)
            if ok.any():
                _band(ax, t, res.params[ok, :, j] / scale[j], name, colors[k % len(colors)])
        ax.axhline(stage.truth[j] / scale[j], color="k", ls="--", lw=1, label="truth")
        ax.set_ylabel(stage.names[j] + (f" (x{scale[j]:g})" if scale[j] != 1 else ""))
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=7, ncol=3)
    axes[-1, 0].set_xlabel("t [s]")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def plot_states(stage: Stage, path, title: str):
    """One panel per state: truth of run 0 and each filter's estimate error band over runs."""
    from ..plots import plt

    t = np.asarray(stage.sim.t)
    names = stage.sim.state_names
    fig, axes = plt.subplots(len(names), 2, figsize=(11, 2.6 * len(names)), sharex=True, squeeze=False)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    truth = np.asarray(stage.sim.states)
    for i, n in enumerate(names):
        axes[i, 0].plot(t, truth[0, :, i], "k", lw=1, label="truth (run 0)")
        for k, (name, res) in enumerate(stage.results.items()):
            c = colors[k % len(colors)]
            axes[i, 0].plot(t, res.states[0, :, i], color=c, lw=0.8, label=name)
            ok = _ok(res)
            if ok.any():
                _band(axes[i, 1], t, res.states[ok, :, i] - truth[ok, :, i], name, c)
        axes[i, 0].set_ylabel(n)
        axes[i, 1].set_ylabel(f"error {n}")
        for ax in axes[i]:
            ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=7)
    axes[0, 1].legend(fontsize=7)
    for ax in axes[-1]:
        ax.set_xlabel("t [s]")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def plot_frequency(freq_results: dict, t, truth, path):
    from ..plots import plt

    fig, axes = plt.subplots(2, 1, figsize=(8, 5.5), sharex=True)
    for j, ax in enumerate(axes):
        for f, res in freq_results.items():
            ok = _ok(res)
            if ok.any():
                ax.plot(t, res.params[ok, :, j].mean(axis=0), lw=1.2, label=f"{f:g} Hz")
        ax.axhline(truth[j], color="k", ls="--", lw=1)
        ax.set_ylabel(("lf", "lr")[j] + " [m]")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8, title="steering sine")
    axes[-1].set_xlabel("t [s]")
    fig.suptitle("Dual UKF on the kinematic model: effect of input frequency (mean over runs)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


# ----------------------------------------------------------------------------------------------
# Entry point


def _parser():
    p = argparse.ArgumentParser(
        prog="vehjax reproduce dutta2019",
        description="Dual EKF, Dual UKF and Liu-West Particle+UKF on the kinematic and the 3-DOF "
                    "dynamic model (Dutta et al. 2019, Tables I-III, Fig. 4-12).",
    )
    p.add_argument("--runs", type=int, default=100, help="Monte-Carlo runs per filter (default 100)")
    p.add_argument("--particles", type=int, default=1000, help="Particle+UKF particles M (default 1000)")
    p.add_argument("--kinematic-duration", type=float, default=60.0, help="s (default 60)")
    p.add_argument("--dynamic-duration", type=float, default=60.0, help="s (default 60)")
    p.add_argument("--dt", type=float, default=0.02, help="sampling period, s (default 0.02)")
    p.add_argument("--filters", default=",".join(_FILTERS),
                   help=f"comma-separated subset of {', '.join(_FILTERS)}")
    p.add_argument("--settings", default=",".join(_SETTINGS),
                   help="filter settings: paper (section III as printed), matched (noise "
                        "covariances of the simulation), or both (default paper,matched)")
    p.add_argument("--no-frequency-study", action="store_true", help="skip the Fig. 6 study")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="out/dutta2019", help="folder for tables and figures")
    return p


def _say(msg):
    sys.stdout.write(msg)
    sys.stdout.flush()


def _check_args(args):
    filters = tuple(f.strip() for f in args.filters.split(",") if f.strip())
    unknown = [f for f in filters if f not in _FILTERS]
    if unknown or not filters:
        raise ValueError(f"--filters: unknown {unknown}; expected a subset of {list(_FILTERS)}")
    settings = tuple(x.strip() for x in args.settings.split(",") if x.strip())
    if not settings or any(x not in _SETTINGS for x in settings):
        raise ValueError(f"--settings: expected a subset of {list(_SETTINGS)}, got {args.settings!r}")
    if args.runs < 2:
        raise ValueError(f"--runs: expected at least 2 runs (spread over runs), got {args.runs}")
    if args.particles < 1:
        raise ValueError(f"--particles: expected at least 1, got {args.particles}")
    for name in ("kinematic_duration", "dynamic_duration", "dt"):
        if not getattr(args, name) > 0:
            raise ValueError(f"--{name.replace('_', '-')}: expected a positive number of seconds")
    return filters, settings


def _kinematic(args, filters, setting, key, out, report):
    from ..models import KinematicBicycle

    kin = KinematicBicycle(dt=args.dt)
    scn = kinematic_scenario(kin, args.kinematic_duration)
    truth = np.asarray(kin.theta)
    cfg = KINEMATIC_SETTINGS if setting == "paper" else matched_settings(
        KINEMATIC_SETTINGS, kin, truth, _KIN_BOX)
    builders = _builders(kin, cfg, ("lf", "lr"), _KIN_BOX, args.particles)
    ests = {name: builders[name]() for name in filters}
    k_main, k_freq = jax.random.split(key)
    _say(f"[{setting}] kinematic model, {scn.name} steering at 5 m/s, {len(scn.t)} steps:\n")
    st = _stage(kin, scn, ("lf", "lr"), cfg, _KIN_BOX, args.runs, k_main, ests, progress=_say)
    report += [f"### Table I: lf, lr from the kinematic model ({setting} settings)",
               "Final estimate (mean of the last 10 % of steps) as mean +- std over runs, "
               "(mean absolute error over runs); the initial guesses are spread evenly around "
               "the truth, so the std and the absolute error, not the mean, show what was "
               "learned. t_conv: median time after which the error stays within 0.05 m (runs "
               "that converged). Target: every filter within 0.05 m.\n",
               table_parameters(st, PAPER_TABLE1, args.dt, tol=0.05, digits=(3, 3)), ""]
    plot_parameters(st, out / f"fig4_5_kinematic_lf_lr_{setting}.png",
                    f"lf, lr on the kinematic model ({setting} settings): mean and 5-95 % band")
    if not args.no_frequency_study and "Dual UKF" in ests:
        _say(f"[{setting}] input-frequency study (Dual UKF):")
        freq = {}
        for f in _FREQUENCIES:
            scn_f = kinematic_scenario(kin, args.kinematic_duration, frequency=f)
            res = _stage(kin, scn_f, ("lf", "lr"), cfg, _KIN_BOX, args.runs, k_freq,
                         {"Dual UKF": ests["Dual UKF"]}).results["Dual UKF"]
            freq[f] = res
            _say(f" {f:g} Hz")
        _say("\n")
        report += [f"### Fig. 6: Dual UKF and the steering frequency ({setting} settings)\n",
                   frequency_table(freq, truth, args.dt, 0.05), ""]
        plot_frequency(freq, np.asarray(scn.t), truth,
                       out / f"fig6_input_frequency_{setting}.png")
    return st


def _dynamic(args, filters, setting, key, out, report, kinematic: Stage):
    from ..models import Dynamic3DOF

    dyn = Dynamic3DOF(dt=args.dt)
    model = _with_axle_inputs(dyn)
    scn_d = dynamic_scenario(dyn, args.dynamic_duration)
    base = np.asarray(scn_d.inputs)
    T = len(base)
    lf_lr_true = np.asarray(dyn.theta)[list(dyn.param_index(("lf", "lr")))]
    scn_m = scn_d._replace(inputs=np.concatenate([base, np.tile(lf_lr_true, (T, 1))], 1),
                           input_names=model.input_names)
    inputs = {}
    for name, res in kinematic.results.items():
        lf_lr = _final(res.params, max(1, res.params.shape[1] // 10))
        lf_lr = np.where(np.isfinite(lf_lr) & (lf_lr > 0), lf_lr, lf_lr_true)
        inputs[name] = np.concatenate(
            [np.broadcast_to(base, (args.runs,) + base.shape),
             np.broadcast_to(lf_lr[:, None, :], (args.runs, T, 2))], 2)
    truth = np.asarray(dyn.theta)[list(dyn.param_index(("m", "cx", "cy")))]
    box = [(v * (1 - _DYN_REL_BOX), v * (1 + _DYN_REL_BOX)) for v in truth]
    cfg = DYNAMIC_SETTINGS if setting == "paper" else matched_settings(
        DYNAMIC_SETTINGS, dyn, truth, box)
    builders = _builders(model, cfg, ("m", "cx", "cy"), box, args.particles)
    ests = {name: builders[name]() for name in filters}
    _say(f"[{setting}] dynamic model, {T} steps (each run uses its own lf, lr from above):\n")
    st = _stage(model, scn_m, ("m", "cx", "cy"), cfg, box, args.runs, key, ests, inputs=inputs,
                progress=_say)
    report += [f"### Table II: state RMSE on the dynamic model ({setting} settings)",
               "RMSE over all runs and steps, [95 % interval of the per-run RMSE mean]. Target: "
               "Dual UKF at or below the paper's Particle+UKF row.\n",
               table_states(st, PAPER_TABLE2), ""]
    report += [f"### Table III: m, cx, cy from the dynamic model ({setting} settings)",
               "As Table I (initial guesses uniform within +-30 % of truth); t_conv: error within "
               "3 % of truth. Targets: Dual UKF within 3 %, "
               "Particle+UKF within 2 %.\n",
               table_parameters(st, PAPER_TABLE3, args.dt, tol=0.03 * truth, digits=(1, 3, 3),
                                scale=(1.0, 1e4, 1e4)), ""]
    plot_states(st, out / f"fig7_9_dynamic_states_{setting}.png",
                f"Dynamic model states ({setting} settings): run 0, and error mean with 5-95 % band")
    plot_parameters(st, out / f"fig10_12_dynamic_m_cx_cy_{setting}.png",
                    f"m, cx, cy on the dynamic model ({setting} settings): mean and 5-95 % band",
                    scale=(1.0, 1e4, 1e4))
    return st


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    filters, settings = _check_args(args)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    report = [f"# vehjax reproduce dutta2019\n\n{PAPER}.\n",
              f"{args.runs} Monte-Carlo runs per filter, M = {args.particles} particles, "
              f"dt = {args.dt} s, seed {args.seed}. The dynamic model's excitation is generated "
              "with Dynamic3DOF (MATLAB's vehicledata, which the paper used, cannot ship). "
              "Every choice the paper leaves open is listed in the docstring of "
              "`vehjax/reproduce/dutta2019.py`.\n"]
    times = {}
    for setting in settings:
        key = jax.random.key(args.seed)  # the same data and guesses for both settings
        k_kin, k_dyn = jax.random.split(key)
        report.append(f"## {setting} settings\n")
        st1 = _kinematic(args, filters, setting, k_kin, out, report)
        st2 = _dynamic(args, filters, setting, k_dyn, out, report, st1)
        times.update({f"{setting}, kinematic, {k}": v for k, v in st1.seconds.items()})
        times.update({f"{setting}, dynamic, {k}": v for k, v in st2.seconds.items()})
    report += ["## Wall time per call (compile included)\n"]
    report += [f"- {k}: {v:.1f} s" for k, v in times.items()]
    report += [f"\nTotal: {time.perf_counter() - t_start:.0f} s"]
    text = "\n".join(report) + "\n"
    (out / "report.md").write_text(text)
    print()
    print(text)
    print(f"wrote {out / 'report.md'} and figures in {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
