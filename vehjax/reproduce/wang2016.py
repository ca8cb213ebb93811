"""Wang et al. 2016 (paper 001): EKF, UKF, CKF and ACKF on the 7-DOF model in a double lane change.

    vehjax reproduce wang2016 [--runs 100] [--seed 0] [--out out/wang2016] [--filters ekf,ukf,ckf,ackf]

What the paper specifies and how it is read here (section 4):

* Manoeuvre: double lane change, 10 s at 0.01 s. The paper drives an ADAMS vehicle "under
  extreme condition" at "high speed" without giving the speed; here the 7-DOF model itself is
  the truth, driven through the ISO 3888-1 course by :func:`vehjax.scenarios.double_lane_change`
  at 80 km/h (22.2 m/s), the ISO 3888-1 test speed (``--speed``).
* Noise, eq. 31-32: "covariance" 0.01 |max - min| sin(pi t / 10) per state and
  0.05 |max - min| sin(pi t / 10) per measurement, the ranges taken over the noise-free drive.
  Read as variances the numbers are unphysical (a yaw-rate range of 0.6 rad/s would give a
  process-noise std of 0.08 rad/s per 10 ms step), so they are read as standard deviations
  scaled by sin(pi t / 10). The process noise is added to the model's own states
  (u, v, r and the four wheel speeds), whose ranges are taken; the paper's eq. 18 state
  (u, v, ax, ay, r, beta, Gamma) has no wheel speeds, and most of it is not a state of the
  7-DOF ODE at all.
* The non-adaptive filters are given the constant peak noise (sin = 1) as Q and R; ACKF starts
  from the same Q0, R0 and re-estimates both (eq. 29-30, forgetting factor b = 0.98, inside the
  paper's [0.95, 0.995]).
* "Inaccurate initial parameters": the paper does not say which; here the filters' model has
  mass and yaw inertia 10 % too large (``--param-error``).
* Measurements: eq. 20's (r, ay, u). The Table 1 quantities (u, v, ax, ay, r, beta) come from
  :meth:`SevenDOF.derived`: on the true states with the true parameters, and on the estimates
  with the filter's parameters (ax, ay are the tyre-force sums over m, beta = arctan(v/u)).
* Truth: RK4 with 1 ms sub-steps (the model's reference integrator). Filters: the same model
  integrated by ROS2 with one 10 ms step (``integrator="ros2"``), 12-20 times cheaper, whose
  own error over this drive is at most 0.008 m/s^2 in ay and 0.003 m/s in u (see
  tests/test_sevendof.py), far below the measurement noise.
* The truth's ax carries white noise: eq. 31's process noise on the wheel speeds moves the
  slips, hence the tyre forces, from step to step. No filter can follow it, and it sets most
  of the ax error.

Table: per quantity and filter, MAE and RMSE over time of each run, mean over runs with its 95 %
Student-t interval, beside the paper's Table 1. "meas." is the raw sensor's error for the three
measured quantities.
"""

from __future__ import annotations

import argparse
import csv
import math
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

PAPER = ("W. Wang, S. Bei, K. Zhu, L. Zhang, Y. Wang, Vehicle state and parameter estimation based "
         "on adaptive cubature Kalman filter, ICIC Express Letters 10(8), 2016 (paper 001)")

QUANTITIES = ("u", "v", "ax", "ay", "r", "beta")


def _quantity_units():
    """Units of QUANTITIES, from SevenDOF's eq. 18 output set."""
    from vehjax.models.sevendof import SevenDOF

    m = SevenDOF(outputs="eq18")
    units = dict(zip(m.output_names, m.output_units))
    return tuple(units[q] for q in QUANTITIES)


UNITS = _quantity_units()
FILTERS = ("ekf", "ukf", "ckf", "ackf")

#: Table 1 of the paper: metric -> quantity -> (EKF, UKF, ACKF).
PAPER_TABLE = {
    "MAE": {
        "u": (0.00452, 0.0035, 0.00136),
        "v": (0.0687, 0.0463, 0.0261),
        "ax": (0.0669, 0.0345, 0.0105),
        "ay": (0.226, 0.192, 0.145),
        "r": (0.126, 0.0115, 0.00765),
        "beta": (0.00304, 0.00211, 0.00109),
    },
    "RMSE": {
        "u": (0.0047, 0.00325, 0.0018),
        "v": (0.099, 0.0664, 0.0278),
        "ax": (0.0657, 0.0352, 0.0165),
        "ay": (0.339, 0.247, 0.147),
        "r": (0.256, 0.0212, 0.0128),
        "beta": (0.00436, 0.00299, 0.00129),
    },
}
_PAPER_COLUMNS = ("ekf", "ukf", "ackf")
_MEASURED = {"r": 0, "ay": 1, "u": 2}  # quantity -> column of eq. 20's (r, ay, u)

_PROCESS_FRACTION = 0.01  # eq. 31
_MEAS_FRACTION = 0.05  # eq. 32
_FORGETTING = 0.98
# Prior std of the filters' initial state (u, v, r, four wheel speeds); x0 is the true start.
_P0_STD = (0.1, 0.05, 0.01, 0.1, 0.1, 0.1, 0.1)


def parser():
    """The study's options (``vehjax reproduce wang2016 --help``); each help states its default."""
    p = argparse.ArgumentParser(
        prog="vehjax reproduce wang2016",
        description=f"EKF, UKF, CKF and ACKF on the 7-DOF model in a double lane change: {PAPER}. "
                    "Writes report.md (table and figures), table1.md, table1.csv, results.npz.")
    p.add_argument("--runs", type=int, default=100, help="Monte-Carlo runs (default %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default %(default)s)")
    p.add_argument("--out", default="out/wang2016", help="output folder (default %(default)s)")
    p.add_argument("--filters", default=",".join(FILTERS),
                   help="comma-separated subset of the filters (default all: %(default)s)")
    p.add_argument("--duration", type=float, default=10.0,
                   help="manoeuvre length, s (default %(default)g, the paper's)")
    p.add_argument("--speed", type=float, default=80.0 / 3.6,
                   help="m/s (default 22.2 = 80 km/h, the ISO 3888-1 test speed)")
    p.add_argument("--param-error", type=float, default=0.1,
                   help="relative error of the filters' m and iz (default %(default)g)")
    p.add_argument("--no-plots", action="store_true", help="skip the figures (default: draw them)")
    return p


_parser = parser


def _check(args):
    if args.runs < 2:
        raise ValueError(f"--runs: expected at least 2 (intervals over runs), got {args.runs}")
    names = tuple(f.strip().lower() for f in args.filters.split(",") if f.strip())
    bad = [f for f in names if f not in FILTERS]
    if bad or not names:
        raise ValueError(f"--filters: expected a comma-separated subset of {FILTERS}, got {args.filters!r}")
    if not (math.isfinite(args.duration) and args.duration > 0):
        raise ValueError(f"--duration: expected a positive number of seconds, got {args.duration}")
    if not (math.isfinite(args.speed) and args.speed >= 10.0):
        raise ValueError(f"--speed: expected at least 10 m/s (the model's range), got {args.speed}")
    if not (math.isfinite(args.param_error) and -0.5 < args.param_error < 1.0):
        raise ValueError(f"--param-error: expected a relative error in (-0.5, 1), got {args.param_error}")
    return tuple(dict.fromkeys(names))


def setup(runs, seed=0, duration=10.0, speed=80.0 / 3.6, param_error=0.1):
    """Truth, measurements and filter settings of the study (see the module docstring).

    Returns a dict with ``sim`` (:class:`vehjax.Simulation`, truth by RK4 1 ms), ``truth_model``,
    ``filter_model`` (ROS2, m and iz scaled by 1 + param_error), ``Q`` (7,) and ``R`` (3,)
    peak variances, ``x0`` (7,), ``P0`` (7, 7), ``process_std`` (7,), ``meas_std`` (3,),
    ``truth_derived`` (R, T, 6) true (u, v, ax, ay, r, beta).
    """
    import vehjax as vj
    from vehjax.models.sevendof import SevenDOF

    truth_model = SevenDOF(dt=0.01)
    scn = vj.scenarios.double_lane_change(truth_model, speed=speed, duration=duration)
    x_nom = _rollout(truth_model, scn.x0, scn.inputs)
    y_nom = jax.vmap(lambda x, u: truth_model.observe(x, u, truth_model.theta))(x_nom, scn.inputs)
    process_std = _PROCESS_FRACTION * np.ptp(np.asarray(x_nom), axis=0)
    meas_std = _MEAS_FRACTION * np.ptp(np.asarray(y_nom), axis=0)
    sim = vj.simulate(truth_model, scn, runs=runs, key=jax.random.key(seed),
                      process_std=process_std, meas_std=meas_std,
                      process_scale=_sine, meas_scale=_sine)
    th = np.asarray(truth_model.theta, dtype=float).copy()
    th[[0, 1]] *= 1.0 + param_error
    filter_model = SevenDOF(dt=0.01, integrator="ros2", theta=th)
    truth_derived = _derived(truth_model, sim.states, sim.inputs, truth_model.theta)
    return dict(
        sim=sim, truth_model=truth_model, filter_model=filter_model,
        Q=process_std**2, R=meas_std**2, x0=np.asarray(scn.x0), P0=np.diag(np.square(_P0_STD)),
        process_std=process_std, meas_std=meas_std, truth_derived=truth_derived,
    )


def _sine(t):
    return np.sin(np.pi * np.asarray(t) / 10.0)


def _rollout(model, x0, inputs):
    @jax.jit
    def roll(x0, us):
        def step(x, u):
            xn = model.transition(x, u, model.theta)
            return xn, xn

        return jax.lax.scan(step, x0, us)[1]

    return roll(x0, inputs)


def _derived(model, states, inputs, theta):
    """(R, T, 6) of (u, v, ax, ay, r, beta) from states (R, T, 7), inputs (T, 5), theta (9,)."""
    from vehjax.models.sevendof import SevenDOF

    # A default-integrator model every time, theta an argument: one compilation serves the
    # truth and every filter (``derived`` does not depend on the integrator).
    same = SevenDOF(dt=model.dt)
    return np.asarray(_derived_all(same, jnp.asarray(states), jnp.asarray(inputs), jnp.asarray(theta)))


@eqx.filter_jit
def _derived_all(model, states, inputs, theta):
    one = lambda x, u: model.derived(x, u, theta)[:6]
    return jax.vmap(jax.vmap(one), in_axes=(0, None))(states, inputs)


def build_filter(name, model, Q, R):
    """The estimator ``name`` (one of FILTERS) on ``model`` with peak noise variances Q, R."""
    import vehjax as vj

    Q, R = np.diag(Q), np.diag(R)
    if name == "ekf":
        return vj.filters.ekf(model, Q, R)
    if name == "ukf":
        return vj.filters.ukf(model, Q, R)
    if name == "ckf":
        return vj.filters.ckf(model, Q, R)
    return vj.filters.ackf(model, Q, R, forgetting=_FORGETTING)


def run_filter(name, study, log=print):
    """Run filter ``name`` over every run in one ``vehjax.run`` call; returns a result dict."""
    import vehjax as vj

    sim, model = study["sim"], study["filter_model"]
    est = build_filter(name, model, study["Q"], study["R"])
    t0 = time.perf_counter()
    prepared = vj.compile_run(est, sim.measurements, sim.inputs, x0=study["x0"], P0=study["P0"],
                              progress=False)
    t1 = time.perf_counter()
    out = prepared()
    t2 = time.perf_counter()
    derived = _derived(model, out.states, sim.inputs, model.theta)
    ok = ~np.asarray(out.diverged)
    log(f"  {name.upper():5s} compile {t1 - t0:6.1f} s, run {t2 - t1:6.1f} s "
        f"({len(ok)} runs x {sim.measurements.shape[1]} steps), {int((~ok).sum())} diverged")
    return dict(name=name, out=out, derived=derived, mask=ok, compile_s=t1 - t0, run_s=t2 - t1)


def error_table(results, study):
    """{metric: {quantity: {column: Interval}}} with columns the filters and "meas."."""
    from vehjax import metrics

    truth = study["truth_derived"]
    table = {"MAE": {}, "RMSE": {}}
    meas = np.asarray(study["sim"].measurements)
    for metric, fn in (("MAE", metrics.mae), ("RMSE", metrics.rmse)):
        for i, q in enumerate(QUANTITIES):
            row = {}
            for res in results:
                per_run = fn(res["derived"][..., i:i + 1], truth[..., i:i + 1], axis="run",
                             mask=res["mask"])[:, 0]
                row[res["name"]] = metrics.confidence_interval(per_run)
            if q in _MEASURED:
                per_run = fn(meas[..., _MEASURED[q]:_MEASURED[q] + 1], truth[..., i:i + 1],
                             axis="run")[:, 0]
                row["meas."] = metrics.confidence_interval(per_run)
            table[metric][q] = row
    return table


def _fmt(iv):
    m, h = float(iv.mean), float(iv.half_width)
    if not math.isfinite(m):
        return "-"
    return f"{m:.3g} ± {h:.2g}" if math.isfinite(h) else f"{m:.3g}"


def format_table(table, filters):
    """Markdown table: rows metric x quantity, our columns then the paper's."""
    cols = [f.upper() for f in filters] + ["meas."]
    paper_cols = [f"paper {c.upper()}" for c in _PAPER_COLUMNS]
    head = ["metric", "quantity"] + cols + paper_cols
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for metric in ("MAE", "RMSE"):
        for q, unit in zip(QUANTITIES, UNITS):
            row = table[metric][q]
            ours = [_fmt(row[f]) for f in filters] + [_fmt(row["meas."]) if "meas." in row else "-"]
            paper = [f"{v:.3g}" for v in PAPER_TABLE[metric][q]]
            lines.append("| " + " | ".join([metric, f"{q} [{unit}]"] + ours + paper) + " |")
    return "\n".join(lines)


def _write_csv(path, table, filters):
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["metric", "quantity", "unit", "column", "mean", "ci95_low", "ci95_high", "paper"])
        for metric in ("MAE", "RMSE"):
            for q, unit in zip(QUANTITIES, UNITS):
                for col, iv in table[metric][q].items():
                    paper = ""
                    if col in _PAPER_COLUMNS:
                        paper = PAPER_TABLE[metric][q][_PAPER_COLUMNS.index(col)]
                    w.writerow([metric, q, unit, col.upper() if col != "meas." else col,
                                float(iv.mean), float(iv.low), float(iv.high), paper])


def _runs(study, results) -> str:
    n = study["sim"].measurements.shape[0]
    div = sum(int((~r["mask"]).sum()) for r in results)
    return f"{n} runs" + (f", {div} diverged run(s) left out" if div else "")


def plot_fig3(path, study, results, run=0):
    """Fig. 3 of the paper: truth and each filter's estimate of u, v, ax, ay, r, beta, one run;
    the measurement under everything, the truth on top."""
    from vehjax import plots
    from vehjax.plots import plt

    t = np.asarray(study["sim"].t)
    truth = study["truth_derived"][run]
    meas = np.asarray(study["sim"].measurements)[run]
    n = study["sim"].measurements.shape[0]
    fig, axes = plt.subplots(3, 2, figsize=(11, 9.4), sharex=True)
    cyc = plots.colors()
    labels = _labels(study, results)
    for i, (ax, q, unit) in enumerate(zip(axes.flat, QUANTITIES, UNITS)):
        if q in _MEASURED:
            ax.plot(t, meas[:, _MEASURED[q]], color="0.75", lw=0.5, label="measured", zorder=1)
        for k, res in enumerate(results):  # first filters thickest: identical lines stay visible
            ax.plot(t, res["derived"][run, :, i], lw=_width(k, len(results)),
                    color=cyc[k % len(cyc)], label=labels[k])
        plots.truth_line(ax, t, truth[:, i])
        ax.set_ylabel(plots.label(q, unit))
        ax.grid(alpha=0.3)
    for ax in axes[-1]:
        ax.set_xlabel("t [s]")
    plots.figure_legend(fig, axes, f"Double lane change, run {run} of {n}: truth and estimates "
                                   "(cf. Wang et al. 2016, Fig. 3)", ncol=8)
    return plots.save(fig, path)


def _labels(study, results, rel: float = 0.03):
    """Legend label per filter; a filter whose estimates of every quantity differ from an earlier
    filter's by an RMS of at most ``rel`` times the quantity's spread is marked
    "(≈ EARLIER)": at the figures' scale the lines coincide."""
    scale = np.std(study["truth_derived"], axis=(0, 1))
    labels = []
    for k, res in enumerate(results):
        lab = res["name"].upper()
        for prev in results[:k]:
            both = res["mask"] & prev["mask"]
            diff = res["derived"][both] - prev["derived"][both]
            if both.any() and np.all(np.sqrt(np.mean(diff**2, axis=(0, 1))) <= rel * scale):
                lab += f" (≈ {prev['name'].upper()})"
                break
        labels.append(lab)
    return labels


def _width(k, n):
    """Line width of the k-th of n overlapping lines: the first thickest."""
    return 0.8 + 1.4 * (n - 1 - k) / max(1, n - 1)


def plot_errors(path, study, results, window_s: float = 0.2):
    """RMSE over runs and a moving ``window_s`` window against time of each quantity, one line
    per filter; the raw sensor's (grey) on the measured quantities."""
    from vehjax import metrics, plots
    from vehjax.plots import plt

    t = np.asarray(study["sim"].t)
    truth = study["truth_derived"]
    meas = np.asarray(study["sim"].measurements)
    w = max(1, int(round(window_s / (t[1] - t[0])))) if len(t) > 1 else 1
    skip = max(1, len(t) // 100)  # the first steps start at the true state: keep them off the scale
    fig, axes = plt.subplots(3, 2, figsize=(11, 9.4), sharex=True)
    cyc = plots.colors()
    labels = _labels(study, results)
    for i, (ax, q, unit) in enumerate(zip(axes.flat, QUANTITIES, UNITS)):
        shown = []
        if q in _MEASURED:
            j = _MEASURED[q]
            e = plots.moving_rms(metrics.rmse(meas[..., j:j + 1], truth[..., i:i + 1],
                                              axis="time")[:, 0], w)
            ax.semilogy(t, e, lw=1.0, color="0.6", label="raw sensor (meas.)", zorder=1)
            shown.append(e[skip:])
        for k, res in enumerate(results):
            e = plots.moving_rms(metrics.rmse(res["derived"][..., i:i + 1], truth[..., i:i + 1],
                                              axis="time", mask=res["mask"])[:, 0], w)
            ax.semilogy(t, e, lw=_width(k, len(results)), color=cyc[k % len(cyc)],
                        label=labels[k])
            shown.append(e[skip:])
        vals = np.concatenate(shown)
        vals = vals[np.isfinite(vals) & (vals > 0)]
        if vals.size:
            ax.set_ylim(np.percentile(vals, 1) / 2, vals.max() * 1.5)
        ax.set_ylabel(plots.label(f"RMSE {q}", unit))
        ax.grid(alpha=0.3, which="both")
    for ax in axes[-1]:
        ax.set_xlabel("t [s]")
    plots.figure_legend(fig, axes, f"RMSE over runs and a {window_s:g} s window against time, "
                                   f"{_runs(study, results)}", ncol=8)
    return plots.save(fig, path)


def plot_error_bands(path, study, results):
    """Small multiples: rows the quantities, one column per filter; the estimation error's mean
    and 5-95 % band over runs, zero on top."""
    from vehjax import plots

    truth = study["truth_derived"]
    series = [[(r["derived"][r["mask"], :, i] - truth[r["mask"], :, i]) if r["mask"].any() else None
               for r in results] for i in range(len(QUANTITIES))]
    rows = [plots.label(f"error {q}", u) for q, u in zip(QUANTITIES, UNITS)]
    return plots.plot_band_grid(path, study["sim"].t, series, rows,
                                [r["name"].upper() for r in results],
                                f"Estimation error over runs, double lane change, {_runs(study, results)}",
                                truth=[0.0] * len(QUANTITIES), truth_label="zero error",
                                panel_height=1.7)


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    filters = _check(args)
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    print(PAPER)
    t0 = time.perf_counter()
    study = setup(args.runs, args.seed, args.duration, args.speed, args.param_error)
    T = study["sim"].measurements.shape[1]
    print(f"truth: {args.runs} runs x {T} steps of SevenDOF (RK4, 1 ms), DLC at {args.speed:.1f} m/s, "
          f"{time.perf_counter() - t0:.1f} s")
    tm = study["truth_model"]
    noise_text = tuple(
        ", ".join(f"{n} {s:.3g} {u}" for n, s, u in zip(names, std, units))
        for names, std, units in ((tm.state_names, study["process_std"], tm.state_units),
                                  (tm.output_names, study["meas_std"], tm.output_units)))
    print(f"process noise std per step (peak) {noise_text[0]}")
    print(f"measurement noise std (peak) {noise_text[1]}")
    print(f"filters: SevenDOF (ROS2, 10 ms) with m, iz x {1 + args.param_error:g}")
    results = [run_filter(name, study) for name in filters]
    table = error_table(results, study)
    md = format_table(table, filters)
    print()
    print("Table 1: mean over runs of each run's error, ± 95 % interval; paper values right")
    print(md)
    (out_dir / "table1.md").write_text(
        f"{PAPER}\n\n{args.runs} runs, seed {args.seed}, speed {args.speed:.2f} m/s, "
        f"m and iz x {1 + args.param_error:g}\n\n{md}\n")
    _write_csv(out_dir / "table1.csv", table, filters)
    np.savez(out_dir / "results.npz", t=np.asarray(study["sim"].t),
             quantities=np.array(QUANTITIES), truth=study["truth_derived"],
             measurements=np.asarray(study["sim"].measurements),
             **{r["name"]: r["derived"] for r in results},
             **{f"{r['name']}_diverged": ~r["mask"] for r in results})
    written = [out_dir / "table1.md", out_dir / "table1.csv", out_dir / "results.npz"]
    report = [f"# vehjax reproduce wang2016\n\n{PAPER}.\n",
              f"{args.runs} Monte-Carlo runs, seed {args.seed}, double lane change at "
              f"{args.speed:.1f} m/s for {args.duration:g} s; truth SevenDOF (RK4, 1 ms), filters "
              f"SevenDOF (ROS2, 10 ms) with m and iz x {1 + args.param_error:g}. Every choice the "
              "paper leaves open is listed in the docstring of `vehjax/reproduce/wang2016.py`.\n",
              f"Process noise std per step (peak): {noise_text[0]}.",
              f"Measurement noise std (peak): {noise_text[1]}.\n",
              "## Table 1\n",
              "Per quantity and filter: each run's MAE and RMSE over time, mean over runs ± 95 % "
              "interval; the paper's values right; \"meas.\": the raw sensor's error on the "
              "measured quantities. Also in `table1.csv`.\n", md, ""]
    if not args.no_plots:
        figures = [
            (plot_fig3(out_dir / "fig3.png", study, results),
             "Fig. 3: truth, measurement and each filter's estimate, run 0"),
            (plot_errors(out_dir / "rmse_time.png", study, results),
             "RMSE over runs (and a 0.2 s window) against time, each filter and the raw sensor"),
            (plot_error_bands(out_dir / "error_bands.png", study, results),
             "Estimation error against time, each filter's mean and 5-95 % band over runs"),
        ]
        report += ["## Figures\n",
                   "The true ax carries white noise: eq. 31's process noise on the wheel speeds "
                   "moves the tyre forces from step to step (see the module docstring); no filter "
                   "follows it.\n"] + [f"![{cap}]({p.name})\n" for p, cap in figures]
        written += [p for p, _ in figures]
    (out_dir / "report.md").write_text("\n".join(report) + "\n")
    written.insert(0, out_dir / "report.md")
    print("wrote " + ", ".join(str(p) for p in written))
    print(f"total {time.perf_counter() - t0:.1f} s")
    return 0
