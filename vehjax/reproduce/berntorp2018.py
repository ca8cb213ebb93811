"""Berntorp & Di Cairano 2018 (paper 004): noise-statistics learning with the adaptive
marginalized particle filter, in simulation (sec. 4, Fig. 3-7) and on a recorded drive (sec. 5,
Fig. 8-9, Remark 1).

    vehjax reproduce berntorp2018 [--runs 100] [--particles 100] [--duration 180] [--seed 0]
                                  [--out out/berntorp2018]
    vehjax reproduce berntorp2018 --drive [--runs 100] [--particles 500] [--out ...]

Simulation (sec. 4), how the paper's words are read:

* Inputs: "measured input data from an experimental test drive": the speed and steering of the
  shipped comma2k19 RAV4 segment (``drive.inputs(model)``, 60 s of highway), played forward,
  then backwards in time, then forward ... (a palindrome loop, continuous at every joint) up to
  ``--duration`` s (default 180 s, the paper's "about three minutes").
* Truth: :class:`~vehjax.models.SingleTrackBank` (RK4, 10 ms, nominal parameters), driven by
  the true steering delta_m + w_t, w_t ~ N(0.28 deg, (0.02 deg)^2) (the paper's constant
  0.28 deg road-wheel offset, plus a small white steering noise so that sigma_w exists).
* Bank: "the road bank rate is modeled as piecewise linear". :func:`vehjax.simulate` has no
  way to prescribe the bank, so the truth is this module's own ``lax.scan`` of
  ``model.transition``: before every step the bank acceleration state phi_ddot is overwritten
  by a prescribed piecewise-constant value (RK4 integrates the bank chain exactly, so phi_dot is
  exactly piecewise linear and phi piecewise quadratic). The profile repeats every 60 s: 10 s
  level, a 10 s ramp up by 6 deg (triangular bank rate, peak 1.2 deg/s), 20 s at 6 deg, a 10 s
  ramp back down, 10 s level; every other cycle banks the other way.
* Sensors: ay, r, roll_rate (roll_rate reads phi_dot) with fixed white-noise stds (0.2 m/s^2,
  0.3 deg/s, 0.3 deg/s) plus random-walk biases starting at 0 (the paper: "zero initially due
  to averaging"), increments per 10 ms step 1e-3 m/s^2, 3e-4 deg/s, 3e-4 deg/s; a bank-angle
  measurement of known std 0.5 deg and eq. 10's virtual yaw rate of known std 0.5 deg/s, both
  unbiased. The filter models the biases as constant means with forgetting, not as random
  walks (the robustness check the paper intends).
* Filter: :func:`~vehjax.filters.marginalized.marginalized_pf`, N = ``--particles``,
  lambda = 0.995, initial std guesses twice the truth, offset and biases guessed 0, bank jerk
  std 2 deg/s^3 (the truth's jerk is zero except at the ramp corners).
* Steady state: the last third of the drive.

Drive (sec. 5, ``--drive``):

* Filter variant (``--variant``, default ``bank``): the paper's filter with the bank in a
  Kalman filter per particle, sensors ay, yaw gyro and roll gyro with unknown bias and std, the
  bank angle phi as a known-std output that is NaN at every step (the log has no bank sensor:
  the roll gyro and the vehicle model carry the bank), the virtual yaw rate with known std
  0.5 deg/s. ``planar`` is Remark 2's filter (ay, r; r_virt known; no bank states: the
  model's bank states are held at zero by a negligible P0, see ``marginalized_pf``'s
  ``linear_states``). An earlier version gave them a 1e-3 spread and the planar filter drifted
  (offset off by 2 deg after 60 s on flat-road simulated data): the particles' constant bank
  accelerations integrated into a bank that ay read as a bias. With the bank states held, the
  planar filter on that data ends within 0.01 deg of the offset (4 runs, N = 200, 60 s).
* N = 500, lambda = 0.999, 100 executions in one :func:`vehjax.run` call (the same measurements
  tiled over runs, a different key each).
* No steering-offset ground truth exists for this drive (the paper's came from an offline
  PMCMC fit); the table gives the executions' mean and spread after the transient.
* The virtual yaw rate's scale: eq. 10 with linear wheel speeds reads
  r_virt = r + eps vx / l_T when the rear rolling radii differ by the fraction eps
  (v_rr - v_rl gains eps vx). The paper takes r_virt as unbiased; on this car it reads
  -0.24 deg/s off the pose. eps is estimated as a parameter from the sensors alone
  (:func:`virtual_yaw_scale`: least squares of gyro - r_virt on (1, -vx / l_T) over the drive,
  the gyro's constant bias the other unknown; the yaw rate itself cancels), and r_virt is
  corrected by eps vx / l_T before either filter sees it. On the shipped segment
  eps = -3.97e-4 (the pose says -3.92e-4) and the gyro bias +0.039 deg/s (pose: +0.033).
* The yaw gyro: its estimated bias is compared with ``drive.gyro_offset_vs_reference``; the
  bias-corrected yaw rate (gyro minus the estimated bias) and each filter's yaw-rate estimate
  with the pose reference yaw rate, after 15 s; the filters' lateral velocity vy with the
  pose's (the camera's velocity in the car frame; the camera's lever arm times r, < 0.01 m/s
  here, is not removed).
* Remark 1's "common approach": an EKF on the single-track model augmented with the steering
  offset and the ay and yaw-gyro biases as random-walk states, built as a
  :class:`vehjax.models.Model` wrapping SingleTrackBank's transition and observe, with fixed
  noise covariances (the MPF's initial guesses) on the same measurements.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

PAPER = ("K. Berntorp and S. Di Cairano, \"Noise-statistics learning of automotive-grade sensors "
         "using adaptive marginalized particle filtering\", Journal of Dynamic Systems, "
         "Measurement, and Control (MERL TR2018-181) (paper 004)")

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


def parser():
    """The study's options (``vehjax reproduce berntorp2018 --help``); each help states its
    default."""
    from .. import cli as _cli  # one-line user errors, finite numbers in range

    p = _cli.ArgumentParser(
        prog="vehjax reproduce berntorp2018",
        description=f"Adaptive marginalized PF, steering offset and IMU noise statistics: {PAPER}. "
                    "Writes report.md (tables and figures) and results.npz.")
    p.add_argument("--drive", action="store_true",
                   help="the real-drive study (sec. 5) instead of the simulation (default: simulation)")
    p.add_argument("--runs", type=_cli.count, default=100,
                   help="Monte-Carlo runs / executions (default %(default)s)")
    p.add_argument("--particles", type=_cli.count, default=None,
                   help="particles N (default 100 in simulation, 500 with --drive)")
    p.add_argument("--duration", type=_cli.positive, default=None,
                   help="seconds of driving (default 180 in simulation; with --drive the whole "
                        "60 s segment)")
    p.add_argument("--seed", type=_cli.integer, default=0, help="random seed (default %(default)s)")
    p.add_argument("--out", type=_cli.out_folder, default="out/berntorp2018",
                   help="output folder (default %(default)s, with --drive %(default)s_drive)")
    p.add_argument("--variant", choices=("planar", "bank"), default="bank",
                   help="--drive filter: planar (Remark 2) or bank (phi unmeasured) "
                        "(default %(default)s)")
    p.add_argument("--kalman-states", choices=("linear", "all"), default="linear",
                   help="marginalized_pf's kalman_states: linear (the paper's Algorithm 1) or "
                        "all (each particle a Gaussian over all states) (default %(default)s)")
    p.add_argument("--no-plots", action="store_true", help="skip the figures (default: draw them)")
    return p


# ---------------------------------------------------------------------------------------------
# simulation


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


def simulate_truth(model, inputs, acc, runs, key):
    """R runs of the truth: states (R, T, 5), measurements (R, T, 5), biases (R, T, 3)."""
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
            w = OFFSET + STEER_STD * e[0]
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
    from vehjax.filters.marginalized import marginalized_pf

    return marginalized_pf(
        model, n_particles, noisy_input="delta", sensors=SENSORS,
        known_std={"phi": PHI_STD, "r_virt": RVIRT_STD},
        linear_states=("phi", "phi_dot", "phi_ddot"), linear_noise_std=BANK_JERK_STD,
        std0={"delta": 2 * STEER_STD, **{s: 2 * SENSOR_STD[s] for s in SENSORS}},
        forgetting=0.995, kalman_states=kalman_states)


def _rms(a, axis=None):
    return np.sqrt(np.nanmean(np.square(a), axis=axis))


def run_simulation(args, log=print):
    import vehjax as vj

    drive = vj.data.load_comma2k19()
    model = vj.models.SingleTrackBank(dt=drive.dt)
    duration = 180.0 if args.duration is None else args.duration
    N = 100 if args.particles is None else args.particles
    T = int(round(duration / model.dt))
    U = looped_inputs(drive.inputs(model), T)
    t = np.arange(1, T + 1) * model.dt
    acc, phi_path = bank_profile(t, model.dt)
    t0 = time.perf_counter()
    X, Y, B = (np.asarray(a) for a in simulate_truth(model, U, acc, args.runs,
                                                        jax.random.key(args.seed)))
    log(f"truth: {args.runs} runs x {T} steps ({duration:g} s) of SingleTrackBank, "
        f"{time.perf_counter() - t0:.1f} s; max |bank| {np.degrees(np.abs(X[0, :, 2]).max()):.2f} deg")
    est = build_sim_filter(model, N, args.kalman_states)
    P0 = np.diag([0.1, 0.5 * DEG, 0.5 * DEG, 0.2 * DEG, 0.2 * DEG]) ** 2
    t0 = time.perf_counter()
    out = vj.run(est, Y, U, x0=np.zeros(5), P0=P0, key=jax.random.key(args.seed + 1))
    elapsed = time.perf_counter() - t0
    log(f"marginalized PF: N = {N}, {args.runs} runs, {elapsed:.1f} s (compile included), "
        f"diverged runs {int(np.sum(out.diverged))}")
    names = list(est.param_names)
    Pm = np.asarray(out.params)
    ss = slice(int(T * 2 / 3), T)
    rows = []
    # steering offset
    off = Pm[:, :, names.index("delta_offset")]
    err = (off[:, ss] - OFFSET) / DEG
    rows.append(("steering offset error [deg]", np.mean(err), np.max(np.abs(err)),
                 "about ±0.04 deg (Fig. 5)"))
    std_rel = {}
    for s in ("delta",) + SENSORS:
        truth = STEER_STD if s == "delta" else SENSOR_STD[s]
        v = Pm[:, ss, names.index(f"{s}_std")]
        rel = v / truth - 1.0
        std_rel[s] = rel
        rows.append((f"{s} std relative error [-]", np.mean(rel), np.max(np.abs(np.mean(rel, 1))),
                     "converge to truth (Fig. 3)" if s != "delta" else "-"))
    for j, s in enumerate(SENSORS):
        unit, sc = SENSOR_UNIT[s]
        e = (Pm[:, ss, names.index(f"{s}_bias")] - B[:, ss, j]) / sc
        rows.append((f"{s} bias tracking RMS [{unit}]", _rms(e), np.max(_rms(e, 1)),
                     "low-frequency part tracked (Fig. 4)"))
    S = np.asarray(out.states)
    for i, (name, unit, sc) in enumerate((("vy", "m/s", 1.0), ("r", "deg/s", DEG),
                                          ("bank phi", "deg", DEG), ("bank rate", "deg/s", DEG))):
        k = (0, 1, 2, 3)[i]
        e = (S[:, ss, k] - X[:, ss, k]) / sc
        rows.append((f"{name} RMS error [{unit}]", _rms(e), np.max(_rms(e, 1)),
                     "tracked closely (Fig. 6-7)"))
    # raw sensor errors for scale
    raw = {"ay": SENSOR_STD["ay"], "r": SENSOR_STD["r"] / DEG}
    return dict(model=model, t=t, U=U, X=X, Y=Y, B=B, out=out, names=names, rows=rows, T=T,
                N=N, duration=duration, elapsed=elapsed, ss=ss, std_rel=std_rel, raw=raw)


def _table(rows, head=("quantity", "mean over runs", "max over runs", "paper")):
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        cells = [r[0]] + [f"{v:.4g}" if isinstance(v, (float, np.floating)) else str(v)
                          for v in r[1:]]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def sim_figures(out_dir, res):
    from vehjax import plots

    t, Pm, names, X, B = res["t"], np.asarray(res["out"].params), res["names"], res["X"], res["B"]
    S = np.asarray(res["out"].states)
    R = X.shape[0]
    figs = []
    stds = [[Pm[:, :, names.index(f"{s}_std")] / SENSOR_UNIT[s][1]] for s in SENSORS]
    figs.append((plots.plot_band_grid(
        out_dir / "fig3_stds.png", t, stds,
        [f"{s} std [{SENSOR_UNIT[s][0]}]" for s in SENSORS], ["marginalized PF"],
        f"Fig. 3: estimated sensor stds, {R} runs", truth=[SENSOR_STD[s] / SENSOR_UNIT[s][1]
                                                          for s in SENSORS]),
        "Fig. 3: estimated standard deviations of ay, r, roll rate (band over runs) and truth"))
    bias = [[Pm[:, :, names.index(f"{s}_bias")] / SENSOR_UNIT[s][1]] for s in SENSORS]
    figs.append((plots.plot_band_grid(
        out_dir / "fig4_biases.png", t, bias,
        [f"{s} bias [{SENSOR_UNIT[s][0]}]" for s in SENSORS], ["marginalized PF"],
        f"Fig. 4: estimated biases, {R} runs (truth: run 0's random walk)",
        truth=[B[0, :, j] / SENSOR_UNIT[s][1] for j, s in enumerate(SENSORS)],
        truth_label="truth, run 0"),
        "Fig. 4: estimated biases (band over runs; each run has its own random walk, run 0's drawn)"))
    off = [[Pm[:, :, names.index("delta_offset")] / DEG]]
    figs.append((plots.plot_band_grid(
        out_dir / "fig5_offset.png", t, off, ["steering offset [deg]"], ["marginalized PF"],
        f"Fig. 5: estimated steering offset, {R} runs", truth=[OFFSET / DEG]),
        "Fig. 5: estimated steering offset (road wheel) and the true 0.28 deg"))
    bank = [[S[:, :, 2] / DEG], [S[:, :, 3] / DEG]]
    figs.append((plots.plot_band_grid(
        out_dir / "fig6_bank.png", t, bank, ["bank phi [deg]", "bank rate [deg/s]"],
        ["marginalized PF"], f"Fig. 6: estimated bank and bank rate, {R} runs",
        truth=[X[0, :, 2] / DEG, X[0, :, 3] / DEG]),
        "Fig. 6: bank angle and rate (the same bank path in every run)"))
    err = [[S[:, :, 0] - X[:, :, 0]], [(S[:, :, 1] - X[:, :, 1]) / DEG]]
    figs.append((plots.plot_band_grid(
        out_dir / "fig7_states.png", t, err, ["vy error [m/s]", "r error [deg/s]"],
        ["marginalized PF"], f"Fig. 7: lateral velocity and yaw-rate errors, {R} runs",
        truth=[0.0, 0.0], truth_label="zero"),
        "Fig. 7: estimation errors of vy and r (the truth differs per run; errors shown)"))
    return figs


def main_simulation(args, out_dir):
    t_start = time.perf_counter()
    res = run_simulation(args)
    md = _table(res["rows"])
    print()
    print(f"Steady state (last third, t > {res['t'][res['ss'].start]:.0f} s), {args.runs} runs, "
          f"N = {res['N']}, lambda = 0.995")
    print(md)
    np.savez(out_dir / "results.npz", t=res["t"], params=np.asarray(res["out"].params),
             param_names=np.array(res["names"]), states=np.asarray(res["out"].states),
             truth=res["X"], biases=res["B"])
    report = [
        "# vehjax reproduce berntorp2018 (simulation, sec. 4)\n", f"{PAPER}.\n",
        f"{args.runs} Monte-Carlo runs, seed {args.seed}, N = {res['N']} particles, lambda = "
        f"0.995, kalman_states = {args.kalman_states!r}, {res['duration']:g} s at 10 ms. Inputs: speed and steering of the shipped "
        "60 s comma2k19 RAV4 highway segment, looped forward/backward in time (a palindrome, "
        "continuous at the joints) to the duration. Truth: SingleTrackBank with the true "
        "steering = measured + 0.28 deg + N(0, 0.02 deg); bank path prescribed through phi_ddot "
        "in this module's own scan of `model.transition` (piecewise-linear bank rate, 6 deg "
        "ramps every 60 s, alternating sign); sensor biases random walks from 0 (the filter "
        "assumes constant means with forgetting). Initial std guesses twice the truth. All "
        "choices are in the docstring of `vehjax/reproduce/berntorp2018.py`.\n",
        f"True sensor stds: ay {SENSOR_STD['ay']} m/s^2, r and roll rate 0.3 deg/s; bias walk "
        "increments per step: ay 1e-3 m/s^2, gyros 3e-4 deg/s; known stds: bank 0.5 deg, "
        "virtual yaw rate 0.5 deg/s.\n",
        f"Filter run time: {res['elapsed']:.1f} s for all runs, compile included (machine shared "
        "with other jobs).\n",
        "## Steady-state errors (last third of the drive)\n",
        "Offset: mean over runs and time of the error, and max |error| over runs and "
        "steady-state times. Stds: relative error of the estimate, mean, and max over runs of "
        "each run's time mean. Bias, state: RMS over runs and time, and the worst run's RMS.\n",
        md, "",
        "## Against the paper\n", _sim_verdict(res), ""]
    written = [out_dir / "results.npz"]
    if not args.no_plots:
        figs = sim_figures(out_dir, res)
        report += ["## Figures\n"] + [f"![{cap}]({p.name})\n" for p, cap in figs]
        written += [p for p, _ in figs]
    (out_dir / "report.md").write_text("\n".join(report) + "\n")
    print("wrote " + ", ".join(str(p) for p in [out_dir / "report.md"] + written))
    print(f"total {time.perf_counter() - t_start:.1f} s")
    return 0


def _sim_verdict(res):
    r = {row[0]: row for row in res["rows"]}
    off = r["steering offset error [deg]"]
    lines = [f"* Steering offset (Fig. 5): steady-state mean error {off[1]:+.4f} deg, max |error| "
             f"over runs and time {off[2]:.4f} deg; the paper shows about ±0.04 deg. "
             + ("Holds." if off[2] <= 0.06 else "Wider than the paper's.")]
    for s in SENSORS:
        row = r[f"{s} std relative error [-]"]
        lines.append(f"* {s} std (Fig. 3): mean relative error {row[1]:+.3f}, worst run {row[2]:.3f}.")
    for s in SENSORS:
        row = r[f"{s} bias tracking RMS [{SENSOR_UNIT[s][0]}]"]
        lines.append(f"* {s} bias tracking (Fig. 4): RMS {row[1]:.4g} {SENSOR_UNIT[s][0]} "
                     f"(worst run {row[2]:.4g}).")
    for k in ("vy RMS error [m/s]", "r RMS error [deg/s]", "bank phi RMS error [deg]",
              "bank rate RMS error [deg/s]"):
        lines.append(f"* {k}: {r[k][1]:.4g} "
                     f"(worst run {r[k][2]:.4g}).")
    lines.append(f"* For scale: the yaw gyro's noise std is {res['raw']['r']:.2f} deg/s and the "
                 f"bank measurement's 0.5 deg.")
    lines.append("* The inputs are a 60 s highway drive with little steering (road-wheel steering "
                 "std about 0.05 deg), far less excitation than the paper's track loops; the "
                 "offset is identified here mostly through the unbiased virtual yaw rate and the "
                 "speed changes.")
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------
# drive


DRIVE_STD0 = {"delta": 0.2 * DEG, "ay": 0.4, "r": 0.5 * DEG}


def build_drive_filter(model, n_particles, forgetting=0.999, variant="bank",
                       kalman_states="linear"):
    """The drive's filter: ``planar`` (Remark 2: ay, r; r_virt known; no bank) or ``bank``
    (sensors ay, r, roll rate; phi (NaN on this log) and r_virt known; bank in a KF);
    ``kalman_states`` as in ``marginalized_pf`` (no difference for ``planar``)."""
    from vehjax.filters.marginalized import marginalized_pf

    if variant == "bank":
        return marginalized_pf(
            model, n_particles, noisy_input="delta", sensors=("ay", "r", "roll_rate"),
            known_std={"phi": PHI_STD, "r_virt": RVIRT_STD}, linear_noise_std=BANK_JERK_STD,
            std0={**DRIVE_STD0, "roll_rate": DRIVE_STD0["r"]}, forgetting=forgetting,
            kalman_states=kalman_states)
    return marginalized_pf(model, n_particles, noisy_input="delta", sensors=("ay", "r"),
                           known_std={"r_virt": RVIRT_STD}, linear_states=(),
                           std0=DRIVE_STD0, forgetting=forgetting)


def augmented_model(model):
    """Remark 1's common approach: x = (vy, r, steering offset, ay bias, gyro bias), outputs
    (ay, r, r_virt), as a :class:`vehjax.models.Model` wrapping SingleTrackBank."""
    from vehjax.models import Model

    def f(x, u, th):
        full = jnp.concatenate([x[:2], jnp.zeros(3)])
        ut = u.at[1].add(x[2])
        return jnp.concatenate([model.transition(full, ut, th)[:2], x[2:]])

    def h(x, u, th):
        full = jnp.concatenate([x[:2], jnp.zeros(3)])
        y = model.observe(full, u.at[1].add(x[2]), th)
        return jnp.stack([y[0] + x[3], y[1] + x[4], y[4]])

    return Model(f, h, model.dt, ("vy", "r", "delta_offset", "ay_bias", "r_bias"),
                 param_names=model.param_names, input_names=model.input_names,
                 output_names=("ay", "r", "r_virt"), theta=np.asarray(model.theta),
                 units={"vy": "m/s", "r": "rad/s", "delta_offset": "rad", "ay_bias": "m/s^2",
                        "r_bias": "rad/s"})


def virtual_yaw_scale(gyro, r_virt, vx, track):
    """(eps, gyro bias [rad/s]): the rear rolling-radius mismatch and the gyro's constant bias
    from the two yaw-rate sensors alone.

    With r_virt = r + eps vx / l_T + noise (eq. 10 from linear wheel speeds whose rolling radii
    differ by the fraction eps) and gyro = r + b + noise, the difference gyro - r_virt =
    b - eps vx / l_T + noise does not contain r: least squares over the samples where all three
    are finite. Identifiable when vx varies (8 to 20 m/s on the shipped segment).

    Args:
        gyro, r_virt: (T,) yaw rates [rad/s]; vx: (T,) speed [m/s]; track: rear track l_T [m].
    """
    gyro, r_virt, vx = (np.asarray(a, float) for a in (gyro, r_virt, vx))
    ok = np.isfinite(gyro) & np.isfinite(r_virt) & np.isfinite(vx)
    A = np.stack([np.ones(ok.sum()), -vx[ok] / track], axis=1)
    (b, eps), *_ = np.linalg.lstsq(A, gyro[ok] - r_virt[ok], rcond=None)
    return float(eps), float(b)


TRACK = 1.61  # m, the RAV4's rear track (Drive.measurements' default)


def run_drive(args, log=print):
    import vehjax as vj
    from vehjax.filters import gaussian

    drive = vj.data.load_comma2k19()
    model = vj.models.SingleTrackBank(dt=drive.dt)
    U, Y = drive.inputs(model), drive.measurements(model, track=TRACK)
    T = len(U) if args.duration is None else min(len(U), int(round(args.duration / model.dt)))
    U, Y = U[:T], Y[:T].copy()
    eps, gyro_bias_ls = virtual_yaw_scale(Y[:, 1], Y[:, 4], U[:, 0], TRACK)
    rvirt_raw_off = float(np.mean(Y[:, 4] - np.asarray(drive.reference["yaw_rate"])[:T]))
    Y[:, 4] -= eps * U[:, 0] / TRACK  # the virtual yaw rate with its scale error removed
    log(f"virtual yaw rate: rolling-radius mismatch eps = {eps:+.3e}, gyro bias "
        f"{gyro_bias_ls / DEG:+.4f} deg/s (least squares, sensors only)")
    t = drive.t[:T] - drive.t[0]
    ref_r = np.asarray(drive.reference["yaw_rate"])[:T]
    ref_roll = np.asarray(drive.reference["roll"])[:T]
    N = 500 if args.particles is None else args.particles
    R = args.runs
    est = build_drive_filter(model, N, variant=args.variant,
                             kalman_states=args.kalman_states)
    bank_sd = 1e-3 if args.variant == "bank" else 1e-10  # planar: the bank states held at 0
    P0 = np.diag([0.1, 0.5 * DEG, bank_sd, bank_sd, bank_sd]) ** 2
    from vehjax.run import compile_run

    prepared = compile_run(est, np.tile(Y[None], (R, 1, 1)), U, x0=np.zeros(5), P0=P0,
                           key=jax.random.key(args.seed), progress=False)
    t0 = time.perf_counter()
    out = prepared(progress=False)
    mpf_run = time.perf_counter() - t0
    mpf_c = prepared.compile_seconds
    log(f"marginalized PF: N = {N}, {R} executions x {T} steps, compile {mpf_c:.1f} s, "
        f"run {mpf_run:.1f} s")
    names = list(est.param_names)
    Pm = np.asarray(out.params)
    # EKF, Remark 1
    am = augmented_model(model)
    Ya = Y[:, [0, 1, 4]]
    Q = np.array([0.01, 0.01 * DEG, 1e-5 * DEG, 1e-4, 1e-5 * DEG]) ** 2
    Rm = np.array([DRIVE_STD0["ay"], DRIVE_STD0["r"], RVIRT_STD]) ** 2
    ekf = gaussian.ekf(am, Q, Rm)
    P0a = np.array([0.1, 0.5 * DEG, 0.5 * DEG, 0.5, 0.5 * DEG]) ** 2
    prepared = compile_run(ekf, Ya[None], U, x0=np.zeros(5), P0=P0a, progress=False)
    eout = prepared(progress=False)
    ekf_c = prepared.compile_seconds
    ekf_run = math.inf
    for _ in range(3):
        t0 = time.perf_counter()
        prepared(progress=False)
        ekf_run = min(ekf_run, time.perf_counter() - t0)
    log(f"EKF (augmented, Remark 1): compile {ekf_c:.1f} s, run {ekf_run:.3f} s")
    E = np.asarray(eout.states)[0]
    k_tr = min(int(round(25.0 / model.dt)), T // 2)  # transient: 25 s as Fig. 8, or half
    after = slice(k_tr, T)
    off = Pm[:, :, names.index("delta_offset")] / DEG
    rb = Pm[:, :, names.index("r_bias")]
    r_meas = Y[:, 1]
    corr_mpf = (r_meas[None] - rb - ref_r[None]) / DEG  # (R, T)
    corr_ekf = (r_meas - E[:, 4] - ref_r) / DEG
    raw_err = (r_meas - ref_r) / DEG
    rvirt_off = float(np.mean(Y[:, 4] - ref_r))
    res = dict(t=t, T=T, N=N, R=R, names=names, Pm=Pm, E=E, off=off, rb=rb, ref_r=ref_r,
               r_meas=r_meas, corr_mpf=corr_mpf, corr_ekf=corr_ekf, raw_err=raw_err,
               after=after, k_tr=k_tr, mpf_run=mpf_run, mpf_c=mpf_c, ekf_run=ekf_run, ekf_c=ekf_c,
               gyro_ref=float(drive.gyro_offset_vs_reference), rvirt_off=rvirt_off,
               out=out, drive=drive, variant=args.variant, ref_roll=ref_roll,
               phi=np.asarray(out.states)[:, :, 2], eps=eps, gyro_bias_ls=gyro_bias_ls,
               rvirt_raw_off=rvirt_raw_off, k15=min(int(round(15.0 / model.dt)), T // 2),
               r_mpf=np.asarray(out.states)[:, :, 1], vy_mpf=np.asarray(out.states)[:, :, 0],
               ref_vy=np.asarray(drive.reference["vy"])[:T])
    return res


def drive_tables(res):
    after, names, Pm = res["after"], res["names"], res["Pm"]
    off_final = res["off"][:, after].mean(axis=1)
    within = res["off"][:, after] - res["off"][:, after].mean()
    rows_mpf = []
    rows_mpf.append(("steering offset, road wheel [deg]",
                     f"{off_final.mean():+.4f}",
                     f"std {off_final.std():.4f}, range {off_final.min():+.4f}..{off_final.max():+.4f}, "
                     f"max |dev from mean| over time {np.max(np.abs(within)):.4f}",
                     f"{np.mean(res['E'][after, 2]) / DEG:+.4f}"))
    rb_mean = res["rb"][:, after].mean(axis=1) / DEG
    rows_mpf.append(("yaw-gyro bias [deg/s]", f"{rb_mean.mean():+.4f}",
                     f"std {rb_mean.std():.4f}; gyro - pose reference: {res['gyro_ref'] / DEG:+.4f}",
                     f"{np.mean(res['E'][after, 4]) / DEG:+.4f}"))
    ab = Pm[:, after, names.index("ay_bias")].mean(axis=1)
    rows_mpf.append(("ay bias [m/s^2]", f"{ab.mean():+.4f}", f"std {ab.std():.4f}",
                     f"{np.mean(res['E'][after, 3]):+.4f}"))
    for s, (unit, sc) in (("delta", ("deg", DEG)), ("ay", ("m/s^2", 1.0)), ("r", ("deg/s", DEG))):
        v = Pm[:, after, names.index(f"{s}_std")].mean(axis=1) / sc
        rows_mpf.append((f"{s} std [{unit}]", f"{v.mean():.4f}", f"std {v.std():.4f}",
                         "fixed " + (f"{DRIVE_STD0[s] / sc:.3g}" if s != "delta" else "-")))
    if res["variant"] == "bank":
        e = (res["phi"][:, after] - res["ref_roll"][None, after]) / DEG
        rows_mpf.append(("bank angle - pose roll [deg]", f"RMS {_rms(e):.3f}",
                         f"max {np.max(np.abs(e)):.3f}; pose roll RMS "
                         f"{_rms(res['ref_roll'][after]) / DEG:.3f}", "-"))
    k15 = slice(res["k15"], res["T"])  # the issue's yardstick: after 15 s
    ref = res["ref_r"][k15]
    cm, ce, raw = res["corr_mpf"][:, k15], res["corr_ekf"][k15], res["raw_err"][k15]
    em = (res["r_mpf"][:, k15] - ref[None]) / DEG
    ee = (res["E"][k15, 1] - ref) / DEG
    yaw_rows = [
        ("raw gyro", _rms(raw), np.max(np.abs(raw)), np.mean(np.abs(raw) < 0.5)),
        ("gyro - MPF bias", _rms(cm), np.max(np.abs(cm)), np.mean(np.abs(cm) < 0.5)),
        ("gyro - EKF bias", _rms(ce), np.max(np.abs(ce)), np.mean(np.abs(ce) < 0.5)),
        ("MPF yaw-rate estimate", _rms(em), np.max(np.abs(em)), np.mean(np.abs(em) < 0.5)),
        ("EKF yaw-rate estimate", _rms(ee), np.max(np.abs(ee)), np.mean(np.abs(ee) < 0.5)),
    ]
    return rows_mpf, yaw_rows


def vy_rows(res):
    """Lateral velocity against the pose's (after 15 s): RMS and max |error| [m/s]."""
    k15 = slice(res["k15"], res["T"])
    ref = res["ref_vy"][k15]
    em = res["vy_mpf"][:, k15] - ref[None]
    ee = res["E"][k15, 0] - ref
    return [("MPF vy estimate", _rms(em), np.max(np.abs(em))),
            ("EKF vy estimate", _rms(ee), np.max(np.abs(ee))),
            ("vy = 0 (no estimate)", _rms(ref), np.max(np.abs(ref)))]


def drive_figures(out_dir, res):
    import matplotlib.pyplot as plt

    from vehjax import plots

    t, after = res["t"], res["after"]
    figs = []
    fig, axes = plt.subplots(2, 1, figsize=(8, 6))
    ax = axes[0]
    for r in range(res["R"]):
        ax.plot(t, res["off"][r], color="tab:red", lw=0.5, alpha=0.4)
    ax.plot(t, res["E"][:, 2] / DEG, color="tab:blue", lw=1.2, label="EKF (Remark 1)")
    ax.axvline(t[res["k_tr"]], color="0.5", ls=":", label="end of transient")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("steering offset [deg]")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    dev = (res["off"][:, after] - res["off"][:, after].mean()).ravel()
    axes[1].hist(dev, bins=60, color="tab:red", alpha=0.7)
    axes[1].axvline(0.0, color="k", ls="--")
    axes[1].set_xlabel("offset estimate minus its mean after the transient [deg]")
    axes[1].set_ylabel("count")
    fig.suptitle(f"Fig. 8: steering offset, {res['R']} executions, N = {res['N']}")
    fig.tight_layout()
    figs.append((plots.save(fig, out_dir / "fig8_offset.png"),
                 "Fig. 8: steering-offset estimates of every execution (red), the EKF's (blue), "
                 "histogram of the spread after the transient"))
    fig, axes = plt.subplots(3, 1, figsize=(8, 8), sharex=True)
    for r in range(res["R"]):
        axes[0].plot(t, res["rb"][r] / DEG, color="tab:red", lw=0.5, alpha=0.4)
    axes[0].plot(t, res["E"][:, 4] / DEG, color="tab:blue", lw=1.2, label="EKF")
    axes[0].axhline(res["gyro_ref"] / DEG, color="k", ls="--", label="mean gyro - pose reference")
    axes[0].set_ylabel("yaw-gyro bias [deg/s]")
    axes[0].legend(fontsize=8)
    for r in range(res["R"]):
        axes[1].plot(t, res["Pm"][r, :, res["names"].index("r_std")] / DEG, color="tab:red",
                     lw=0.5, alpha=0.4)
    axes[1].set_ylabel("yaw-gyro std [deg/s]")
    axes[2].plot(t, res["r_meas"] / DEG, color="tab:green", lw=0.6, label="gyro")
    axes[2].plot(t, (res["r_meas"] - res["rb"][0]) / DEG, color="tab:red", lw=0.8,
                 label="gyro - MPF bias (execution 0)")
    axes[2].plot(t, res["ref_r"] / DEG, color="k", ls="--", lw=1.0, label="pose reference")
    axes[2].set_ylabel("yaw rate [deg/s]")
    axes[2].set_xlabel("t [s]")
    axes[2].legend(fontsize=8)
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.suptitle(f"Fig. 9: yaw gyro, {res['R']} executions, N = {res['N']}")
    fig.tight_layout()
    figs.append((plots.save(fig, out_dir / "fig9_yaw.png"),
                 "Fig. 9: yaw-gyro bias and std estimates, and the bias-corrected yaw rate against "
                 "the pose reference"))
    if res["variant"] == "bank":
        fig, ax = plt.subplots(figsize=(8, 3.5))
        phi = res["phi"] / DEG
        lo, hi = np.percentile(phi, [2.5, 97.5], axis=0)
        ax.fill_between(t, lo, hi, color="tab:red", alpha=0.3, lw=0,
                        label="MPF bank estimate, 95 % of executions")
        ax.plot(t, phi.mean(axis=0), color="tab:red", lw=0.8, label="MPF, mean")
        ax.plot(t, res["ref_roll"] / DEG, color="k", ls="--", lw=1.0,
                label="pose roll (bank + suspension roll)")
        ax.set_xlabel("t [s]")
        ax.set_ylabel("bank angle [deg]")
        ax.legend(fontsize=8)
        ax.grid(alpha=0.3)
        fig.suptitle("Fig. 10: road bank (no bank sensor: roll gyro and vehicle model)")
        fig.tight_layout()
        figs.append((plots.save(fig, out_dir / "fig10_bank.png"),
                     "Fig. 10: the bank estimate against the car's roll from the pose (which "
                     "also holds the suspension roll)"))
    return figs


def main_drive(args, out_dir):
    t_start = time.perf_counter()
    res = run_drive(args)
    rows_mpf, yaw_rows = drive_tables(res)
    md1 = _table(rows_mpf, head=("quantity", f"MPF mean over {res['R']} executions",
                                 "MPF spread", "EKF (Remark 1)"))
    md2 = _table(yaw_rows, head=("yaw rate vs pose reference", "RMS [deg/s]", "max [deg/s]",
                                 "share within 0.5 deg/s"))
    md3 = _table(vy_rows(res), head=("lateral velocity vs pose", "RMS [m/s]", "max [m/s]"))
    cost = _table([
        ("marginalized PF", f"N = {res['N']}, {res['R']} executions in one call",
         f"{res['mpf_run'] / (res['T'] * res['R']) * 1e3:.4f}", f"{res['mpf_run']:.2f}",
         f"{res['mpf_c']:.1f}"),
        ("EKF, augmented (5 states)", "1 run", f"{res['ekf_run'] / res['T'] * 1e3:.4f}",
         f"{res['ekf_run']:.3f}", f"{res['ekf_c']:.1f}"),
    ], head=("filter", "size", "ms per run-step", "run [s]", "compile [s]"))
    dur = res["T"] * 0.01
    print()
    print(f"Drive: {dur:.1f} s, after the transient (t > {res['t'][res['k_tr']]:.0f} s)")
    print(md1)
    print()
    print(md2)
    print()
    print(md3)
    print()
    print(cost)
    np.savez(out_dir / "results.npz", t=res["t"], params=res["Pm"],
             param_names=np.array(res["names"]), ekf_states=res["E"], ref_yaw_rate=res["ref_r"])
    report = [
        "# vehjax reproduce berntorp2018 --drive (experiments, sec. 5)\n", f"{PAPER}.\n",
        f"The shipped comma2k19 RAV4 segment, {dur:.1f} s of highway at 8-20 m/s with little "
        f"steering. Variant `{res['variant']}` ({_VARIANT_TEXT[res['variant']]}); "
        f"N = {res['N']}, lambda = "
        f"0.999, kalman_states = {args.kalman_states!r}, {res['R']} executions in one `vehjax.run` call (same data, different keys). "
        "Beside it Remark 1's common approach: an EKF "
        "on the single-track model with the steering offset and the ay and gyro biases as "
        "random-walk states, fixed noise covariances (the MPF's initial guesses).\n",
        f"Transient: the first {res['t'][res['k_tr']]:.0f} s are left out of every number.\n",
        "## Offset, biases, stds\n", md1, "",
        "## Virtual yaw rate's scale\n",
        f"Rear rolling-radius mismatch eps = {res['eps']:+.3e} (least squares of gyro - r_virt "
        f"on (1, -vx / l_T), sensors only; the gyro's bias comes out at "
        f"{res['gyro_bias_ls'] / DEG:+.4f} deg/s), so r_virt read "
        f"{res['rvirt_raw_off'] / DEG:+.3f} deg/s off the pose on average before the "
        f"correction eps vx / l_T was removed (l_T = {TRACK} m).\n",
        "## Bias-corrected yaw rate against the pose reference (Fig. 9, 12), after 15 s\n", md2,
        "",
        "## Lateral velocity against the pose (after 15 s)\n",
        "The pose's vy is the camera's lateral velocity in the car frame (mount estimated so "
        "that its mean is zero), so only its variation is a check.\n", md3, "",
        "## Cost\n", "Compiled run time (vehjax.run's path, results copied to host), compile "
        "apart; CPU shared with other jobs, so times are upper bounds. "
        "`vehjax bench marginalized` times the filter properly.\n", cost, "", "## What holds, what cannot be told\n", _drive_verdict(res, yaw_rows),
        ""]
    if not args.no_plots:
        figs = drive_figures(out_dir, res)
        report += ["## Figures\n"] + [f"![{cap}]({p.name})\n" for p, cap in figs]
    (out_dir / "report.md").write_text("\n".join(report) + "\n")
    print(f"wrote {out_dir / 'report.md'}")
    print(f"total {time.perf_counter() - t_start:.1f} s")
    return 0


_VARIANT_TEXT = {
    "planar": "Remark 2: sensors ay and yaw gyro with unknown bias and std, virtual yaw rate with "
              "known std 0.5 deg/s, no bank states",
    "bank": "sensors ay, yaw gyro and roll gyro with unknown bias and std, virtual yaw rate with "
            "known std 0.5 deg/s, the bank in a Kalman filter per particle, phi unmeasured",
}


def _drive_verdict(res, yaw_rows):
    after = res["after"]
    rb = res["rb"][:, after].mean() / DEG
    off_end = res["off"][:, -1]
    lines = []
    if res["R"] > 1 and np.std(off_end) > 0.1:
        lines.append(
            f"* The executions do NOT agree: at the end of the drive their offset estimates "
            f"spread over {off_end.min():+.2f}..{off_end.max():+.2f} deg (std "
            f"{np.std(off_end):.2f} deg) and keep drifting apart, with the ay bias compensating "
            "(ay reads cf/m times the offset). The paper's Fig. 8 spread (about ±0.35 deg at the steering wheel, ±0.02 deg at the "
            "road wheel) is not reproduced.")
    lines += [
        f"* The pose says the gyro reads {res['gyro_ref'] / DEG:+.3f} deg/s above the true yaw "
        f"rate on average. The MPF's bias estimate after the transient averages {rb:+.3f} deg/s, "
        f"the EKF's {np.mean(res['E'][after, 4]) / DEG:+.3f} deg/s. The virtual yaw rate, which "
        f"both filters take as unbiased, read {res['rvirt_raw_off'] / DEG:+.3f} deg/s off the "
        f"pose before its scale was corrected (eps = {res['eps']:+.2e}, estimated from the "
        f"sensors) and {res['rvirt_off'] / DEG:+.3f} deg/s after; without the correction the "
        "gyro bias estimates inherit its offset with the opposite sign (the issue's 0.246 "
        "deg/s against the raw gyro's 0.152, 10 executions, N = 300).",
        f"* Yaw rate vs the pose reference after 15 s: the raw gyro RMS {yaw_rows[0][1]:.3f} "
        f"deg/s; gyro - MPF bias {yaw_rows[1][1]:.3f}, gyro - EKF bias {yaw_rows[2][1]:.3f} "
        "(a constant correction cannot remove the gyro's white noise, which is most of the "
        f"raw error); the filters' yaw-rate estimates: MPF {yaw_rows[3][1]:.3f} "
        f"({yaw_rows[3][1] / yaw_rows[0][1]:.2f}x the raw gyro), EKF {yaw_rows[4][1]:.3f} "
        f"({yaw_rows[4][1] / yaw_rows[0][1]:.2f}x). The pose reference is 20 Hz pose "
        "differentiated, itself noisy at the 0.1 deg/s level.",
        "* The steering offset has no ground truth here (the paper's came from an offline PMCMC "
        "fit on a 3 min track drive). 60 s of highway with road-wheel steering std ~0.05 deg "
        "excites the yaw dynamics very little: the offset is identified only through the "
        "steady-state relation between steering, speed and the virtual yaw rate (scale "
        "corrected, see above), and "
        "the spread over executions measures the filter's Monte-Carlo variability, not its "
        "accuracy. The ay bias and a road bank are indistinguishable here. The sensor stds "
        "absorb model error (tyre parameters are nominal, not this car's).",
    ]
    if res["variant"] == "bank":
        e = (res["phi"][:, after] - res["ref_roll"][None, after]) / DEG
        lines.append(
            f"* Bank (Fig. 10): with no bank sensor the estimate follows the shape of the car's "
            f"roll from the pose (roll gyro and vehicle model), RMS {_rms(e):.2f} deg from it "
            f"against the roll's own RMS {_rms(res['ref_roll'][after]) / DEG:.2f} deg, with a "
            "slowly wandering level that the ay bias takes up: a constant cross-fall and an "
            "accelerometer bias read the same on ay. The pose roll also holds the suspension "
            "roll, so this is a check of shape, not an error.")
    return "\n".join(lines)


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    if args.runs < 1:
        raise ValueError(f"--runs: expected at least 1, got {args.runs}")
    if args.particles is not None and args.particles < 2:
        raise ValueError(f"--particles: expected at least 2, got {args.particles}")
    if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 1.0):
        raise ValueError(f"--duration: expected more than 1 s, got {args.duration}")
    out_dir = Path(args.out)
    if args.drive and args.out == parser().get_default("out"):
        out_dir = Path(args.out + "_drive")
    out_dir.mkdir(parents=True, exist_ok=True)
    print(PAPER)
    return main_drive(args, out_dir) if args.drive else main_simulation(args, out_dir)
