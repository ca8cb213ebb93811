"""Online noise learning compared: Sage-Husa ACKF, the variational adaptive Kalman filters, the
marginalized PF of paper 004 and Remark 1's augmented-state EKF, on paper 004's simulation
study and on the shipped RAV4 drive.

    vehjax reproduce noise-learning [--runs 100] [--duration 180] [--particles 100]
                                    [--drive-executions 10] [--drive-particles 500]
                                    [--no-drive] [--seed 0] [--out out/noise_learning]

Simulation: exactly ``vehjax reproduce berntorp2018``'s (:mod:`vehjax.studies.banked_road`'s
``simulate_truth``, ``bank_profile``, ``looped_inputs``): SingleTrackBank, steering offset 0.28 deg plus white
steering noise 0.02 deg, the piecewise-linear bank, ay / yaw-gyro / roll-gyro with random-walk
biases from 0 and white noise of stds 0.2 m/s^2, 0.3 deg/s, 0.3 deg/s; the bank measurement
(0.5 deg) and the virtual yaw rate (0.5 deg/s) unbiased with known stds. Drive: the shipped
comma2k19 segment as berntorp2018 --drive reads it (:func:`vehjax.data.prepare_drive`: the
virtual yaw rate's bursts gated at 5 deg/s, its scale error removed; no truth for offset,
biases or stds; the pose gives the yaw rate, vy and the gyro's offset from it).

The methods (one row each; nothing tuned per method beyond what is written here):

* **Sage-Husa ACKF** (:func:`vehjax.filters.ackf`): R adapted alone, every output in R, Q at the
  MPF's initial guess; no offset or bias states (its R absorbs them), no coverage.
* **VB-R (CKF)**, **VB-R (EKF)**: :func:`vehjax.filters.vbakf_r` (Särkkä & Nummenmaa 2009),
  **VB-PR (CKF)**: :func:`vehjax.filters.vbakf_pr` (Huang et al. 2017, tau = 3): the three
  sensors' variances learnt from twice the true stds, the offset and the biases as Kalman
  states; they do not learn the steering noise (fixed at ``--steer-factor`` times the truth).
* **MPF (paper)**: :mod:`vehjax.studies.banked_road`'s ``build_sim_filter`` (N = ``--particles``,
  lambda = 0.995, initial stds twice the truth) and ``build_drive_filter`` (lambda = 0.999).
* **MPF (consistent)**: ``marginalized_pf_grid`` (not the paper's): the offset and the biases as
  Kalman states, the steering std on a fixed grid (``--grid-points``, default 25) a decade
  either side of the guess under Jeffreys' prior, the sensor variances scored; no forgetting in
  simulation, 0.999 on the drive; no random numbers (one execution on the drive).
* **MPF (inverse-Wishart)**: MPF (consistent) with ``sensor_variances="inverse-wishart"``.
* **augmented EKF** (Remark 1, :func:`vehjax.models.bank_scale.augmented_model`): (vy, r, offset,
  ay bias, gyro bias) on (ay, r, r_virt), fixed Q and R (the MPF's initial guesses).

See docs/noise_learning.md for each row in full: the settings, the measurements behind them
(the steering factor, the grid's size and prior, forgetting, the early NEES, timing, the drive's
yaw rate) and what was tried first.

What is measured (simulation; steady state = the last third):

* offset: mean of the error over runs and steady-state times, and its RMS [deg];
* biases: RMS error of the estimate against each run's random walk [sensor units];
* stds: the mean relative error of the estimate (estimate / truth - 1) per sensor, and of
  the steering std where a method learns it (the MPF rows);
* coverage: per learnt parameter, the fraction of runs whose final 95 % interval (estimate
  +- 1.96 reported std) holds the truth; the table gives offset / biases (worst) / stds (worst);
* NEES of (vy, r) (2 degrees of freedom, the states every method has) and NIS: the share of
  steps whose run-average lies in the 95 % chi-square band (:func:`vehjax.metrics.consistency`)
  and the mean per degree of freedom (1 consistent, > 1 over-confident);
* time per run-step: the compiled ``vehjax.run`` call (compile apart) divided by runs x steps;
  CPU shared with other jobs, so an upper bound.

Verdicts are computed from the numbers (:func:`verdict`): "learns" the offset when its mean
error is within 0.05 deg and its RMS within 0.1 deg; the biases when each RMS error is below a
quarter of the sensor's noise std; the stds when each mean relative error is within 10 %;
"honest" when the NEES share in the band is >= 0.9 and every learnt parameter's coverage is
>= 0.9; otherwise the NEES is called over-confident above 1.1 per
dof, under-confident below 0.9, and between them only its share in the band is given.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import vehjax as vj
from vehjax.studies import banked_road as road
from vehjax.data import prepare_drive
from vehjax.models.bank_scale import augmented_model

PAPER = ("Online noise learning compared: Sage-Husa ACKF, variational adaptive "
         "Kalman filters (Särkkä & Nummenmaa 2009; Huang et al. 2017), the marginalized PF of "
         "Berntorp & Di Cairano 2018 (paper 004) and its Remark 1 augmented EKF")

DEG = road.DEG
SENSORS = road.SENSORS
METHODS = ("Sage-Husa ACKF", "VB-R (CKF)", "VB-R (EKF)", "VB-PR (CKF)", "MPF (paper)",
           "MPF (consistent)", "MPF (inverse-Wishart)", "augmented EKF")


def parser():
    """The study's options (``vehjax reproduce noise-learning --help``)."""
    from .. import cli as _cli

    p = _cli.ArgumentParser(
        prog="vehjax reproduce noise-learning",
        description=f"{PAPER}. Writes report.md (one table per data set, one figure).")
    p.add_argument("--runs", type=_cli.count, default=100,
                   help="simulation Monte-Carlo runs (default %(default)s)")
    p.add_argument("--duration", type=_cli.positive, default=180.0,
                   help="simulated seconds (default %(default)s)")
    p.add_argument("--particles", type=_cli.count, default=100,
                   help="MPF particles in simulation (default %(default)s)")
    p.add_argument("--drive-executions", type=_cli.count, default=10,
                   help="executions of the paper's MPF on the drive (the consistent MPF draws "
                        "nothing: one) (default %(default)s)")
    p.add_argument("--drive-particles", type=_cli.count, default=500,
                   help="MPF particles on the drive (default %(default)s)")
    p.add_argument("--grid-points", type=_cli.count, default=25,
                   help="MPF (consistent): its particles, a fixed grid of steering stds, in "
                        "simulation and on the drive (default %(default)s)")
    p.add_argument("--forgetting", type=_cli.positive, default=0.995,
                   help="forgetting of the ACKF and the VB filters, in (0, 1] "
                        "(default %(default)s)")
    p.add_argument("--iterations", type=_cli.count, default=5,
                   help="VB fixed-point iterations (default %(default)s)")
    p.add_argument("--methods", default=",".join(METHODS),
                   help="comma-separated methods to run (default: all: %(default)s)")
    p.add_argument("--steer-factor", type=_cli.positive, default=2.0,
                   help="simulation: the fixed steering-noise std of the ACKF and VB filters as "
                        "a multiple of the truth's 0.02 deg (default %(default)s, the MPF's "
                        "initial guess)")
    p.add_argument("--no-drive", action="store_true", help="skip the drive (default: run it)")
    p.add_argument("--seed", type=_cli.integer, default=0, help="random seed (default %(default)s)")
    p.add_argument("--out", type=_cli.out_folder, default="out/noise_learning",
                   help="output folder (default %(default)s)")
    p.add_argument("--no-plots", action="store_true", help="skip the figure (default: draw it)")
    return p


# ---------------------------------------------------------------------------------------------
# the filters


def _q_bank(model):
    """Process noise of the model's states: the bank jerk through ``bank_noise_gain`` (PSD)."""
    g = np.asarray(model.bank_noise_gain(), float)
    return road.BANK_JERK_STD ** 2 * np.outer(g, g)


def ackf_with_R(est, idx, names, R0):
    """The Sage-Husa ACKF reporting sqrt(diag R^)[idx] as its parameters ``names`` (with a
    negligible reported variance: the ACKF gives no uncertainty of R^)."""
    from vehjax.filters.base import Dims, Estimator, ParamSpec, Runtime

    p = len(idx)
    tiny = 1e-30

    def init(x0, P0, theta0=None, P_theta0=None, key=None):
        return est.init(x0, P0, None, None, key)

    def step(state, y, u):
        state, out = est.step(state, y, u)
        sd = jnp.sqrt(jnp.diagonal(state.R)[np.asarray(idx)])
        return state, out._replace(params=sd, params_cov=jnp.eye(p, dtype=sd.dtype) * tiny)

    prior = (np.sqrt(np.diag(R0)[np.asarray(idx)]), np.eye(p) * tiny)
    return Estimator(
        init=init,
        step=step,
        name=est.name,
        dims=Dims(nx=est.nx, ny=est.ny, nu=est.nu),
        params=ParamSpec(names=tuple(names), prior=prior),
        runtime=Runtime(workload=est.workload),
    )


def _mpf_consistent(model, args, drive, variances=None):
    """The MPF (paper)'s model in :func:`vehjax.filters.marginalized_pf_grid`
    (:func:`vehjax.studies.banked_road.build_consistent_filter`): the biases as Kalman states with the
    truth's random-walk stds (as the VB rows), the statistics averaged over the offset's
    conditional, Gaussian particle states; ``variances``, its ``sensor_variances``."""
    if drive:
        std0 = {**road.DRIVE_STD0, "roll_rate": road.DRIVE_STD0["r"]}
        return road.build_consistent_filter(model, args.grid_points, std0, 0.999,
                                            sensor_variances=variances)
    steer0 = args.steer_factor * road.STEER_STD
    std0 = {"delta": steer0, **{s: 2 * road.SENSOR_STD[s] for s in SENSORS}}
    return road.build_consistent_filter(model, args.grid_points, std0, 1.0,
                                        sensor_variances=variances)


def build(method, model, args, drive=False):
    """(estimator, output columns it reads, P0) of one method; the drive uses the drive's MPF
    and the drive stds of berntorp2018 as initial guesses."""
    from vehjax import filters

    std0 = ({"ay": road.DRIVE_STD0["ay"], "r": road.DRIVE_STD0["r"],
             "roll_rate": road.DRIVE_STD0["r"]} if drive
            else {s: 2 * road.SENSOR_STD[s] for s in SENSORS})
    steer0 = road.DRIVE_STD0["delta"] if drive else args.steer_factor * road.STEER_STD
    R0 = np.array([std0[s] ** 2 for s in SENSORS])
    Q = _q_bank(model)
    known = {"phi": road.PHI_STD, "r_virt": road.RVIRT_STD}
    all5 = [0, 1, 2, 3, 4]
    P0 = road.P0_SIM
    if method == "Sage-Husa ACKF":
        Rall = np.diag(np.r_[R0, road.PHI_STD ** 2, road.RVIRT_STD ** 2])
        est = filters.ackf(model, Q, Rall, forgetting=args.forgetting, adapt=("R",),
                           prior_steps=200, input_noise={"delta": steer0})
        return ackf_with_R(est, [0, 1, 2], [f"{s}_std" for s in SENSORS], Rall), all5, P0
    if method.startswith("VB-"):
        kw = dict(form="ckf" if "CKF" in method else "ekf", forgetting=args.forgetting,
                  iterations=args.iterations, sensors=SENSORS, known_std=known,
                  augment=filters.Augmentation(
                      biases=SENSORS, input_offsets=("delta",),
                      bias_walk={s: road.BIAS_WALK[s] for s in SENSORS},
                      bias_std0=road.BIAS_STD0, offset_std0=road.OFFSET_STD0),
                  input_noise={"delta": steer0})
        if method.startswith("VB-R"):
            return filters.vbakf_r(model, Q, R0, dof0=10.0, **kw), all5, P0
        return filters.vbakf_pr(model, Q, R0, tau=3.0, **kw), all5, P0
    if method == "MPF (paper)":
        if drive:
            est = road.build_drive_filter(model, args.drive_particles, variant="bank")
        else:
            est = road.build_sim_filter(model, args.particles)
        return est, all5, P0
    if method == "MPF (consistent)":
        return _mpf_consistent(model, args, drive), all5, P0
    if method == "MPF (inverse-Wishart)":
        return _mpf_consistent(model, args, drive, "inverse-wishart"), all5, P0
    if method == "augmented EKF":
        am = augmented_model(model)
        # by state name: (vy, r, offset, ay bias, gyro bias) and, where berntorp2018's model
        # has it, the rolling-radius mismatch eps held at 0 (r_virt taken as unbiased)
        q = {"vy": 0.01, "r": 0.01 * DEG, "delta_offset": 1e-5 * DEG, "ay_bias": 1e-4,
             "r_bias": 1e-5 * DEG, "eps": 0.0}
        p0 = {"vy": 0.1, "r": 0.5 * DEG, "delta_offset": road.OFFSET_STD0,
              "ay_bias": road.BIAS_STD0["ay"], "r_bias": road.BIAS_STD0["r"], "eps": 1e-9}
        Qa = np.array([q[n] for n in am.state_names]) ** 2
        P0a = np.diag(np.array([p0[n] for n in am.state_names]) ** 2)
        Ra = np.array([std0["ay"], std0["r"], road.RVIRT_STD]) ** 2
        return filters.ekf(am, Qa, Ra), [0, 1, 4], P0a
    raise ValueError(f"method: unknown {method!r}; expected one of {METHODS}")


def run_method(method, model, Y, U, args, key, drive=False):
    """Run one method on measurements Y (R, T, 5): its estimates as a dict of arrays (offset,
    biases, stds with their reported stds, (vy, r) and their covariance, NIS) and timings."""
    from vehjax.run import compile_run

    est, cols, P0 = build(method, model, args, drive)
    x0 = np.zeros(P0.shape[0])
    t0 = time.perf_counter()
    prepared = compile_run(est, Y[..., cols], U, x0=x0, P0=P0, key=key,
                           return_covariances=True, progress=False)
    t1 = time.perf_counter()
    out = prepared(progress=False)
    run_s = time.perf_counter() - t1
    R, T = Y.shape[:2]
    S, C = np.asarray(out.states), np.asarray(out.covariances)
    res = dict(method=method, vr=S[..., :2], vr_cov=C[..., :2, :2], nis=np.asarray(out.nis),
               n_obs=np.asarray(out.n_obs), diverged=int(np.sum(out.diverged)),
               ms_per_step=run_s / (R * T) * 1e3, compile_s=t1 - t0, est=None, sd=None)
    est_, sd_ = {}, {}
    if method == "augmented EKF":
        for i, nm in ((2, "delta_offset"), (3, "ay_bias"), (4, "r_bias")):
            est_[nm], sd_[nm] = S[..., i], np.sqrt(C[..., i, i])
    else:
        Pm = np.asarray(out.params)
        Pc = np.asarray(out.params_cov)
        names = list(est.param_names)
        for nm in (["delta_offset", "delta_std"] + [f"{s}_bias" for s in SENSORS]
                   + [f"{s}_std" for s in SENSORS]):
            if nm in names:
                j = names.index(nm)
                est_[nm] = Pm[..., j]
                sd_[nm] = (None if method == "Sage-Husa ACKF"
                           else np.sqrt(np.maximum(Pc[..., j, j], 0.0)))
    res["est"], res["sd"] = est_, sd_
    return res


# ---------------------------------------------------------------------------------------------
# metrics and verdicts


def _rms(a, axis=None):
    return float(np.sqrt(np.nanmean(np.square(a), axis=axis)))


def sim_metrics(res, X, B, ss):
    """The simulation's numbers of one method (module docstring); None where it has none."""
    from vehjax import metrics

    est, sd = res["est"], res["sd"]
    m = dict(method=res["method"], diverged=res["diverged"], ms=res["ms_per_step"],
             compile_s=res["compile_s"])
    truth = {"delta_offset": np.full(X.shape[:2], road.OFFSET),
             "delta_std": np.full(X.shape[:2], road.STEER_STD)}
    for j, s in enumerate(SENSORS):
        truth[f"{s}_bias"] = B[..., j]
        truth[f"{s}_std"] = np.full(X.shape[:2], road.SENSOR_STD[s])
    if "delta_offset" in est:
        e = (est["delta_offset"][:, ss] - road.OFFSET) / DEG
        m["offset_mean"], m["offset_rms"] = float(np.nanmean(e)), _rms(e)
    if "delta_std" in est:
        m["delta_std"] = float(np.nanmean(est["delta_std"][:, ss] / road.STEER_STD - 1.0))
    for s in SENSORS:
        k = f"{s}_bias"
        if k in est:
            m[k] = _rms(est[k][:, ss] - B[:, ss, SENSORS.index(s)]) / road.SENSOR_UNIT[s][1]
        k = f"{s}_std"
        if k in est:
            m[k] = float(np.nanmean(est[k][:, ss] / road.SENSOR_STD[s] - 1.0))
    cov = {}
    for k, v in est.items():
        if sd.get(k) is not None:
            cov[k] = float(np.mean(np.abs(v[:, -1] - truth[k][:, -1]) <= 1.96 * sd[k][:, -1]))
    m["coverage"] = cov
    nees = metrics.nees(res["vr"], res["vr_cov"], X[..., :2])
    c = metrics.consistency(nees, 2)
    m["nees_in"], m["nees_dof"] = c.inside, float(np.nanmean(nees)) / 2.0
    ci = metrics.consistency(res["nis"], res["n_obs"])
    m["nis_in"] = ci.inside
    m["nis_dof"] = float(np.nansum(res["nis"]) / max(np.sum(res["n_obs"]), 1))
    return m


def verdict(m):
    """One line from a method's numbers (rules in the module docstring)."""
    parts = []
    if "offset_mean" in m:
        ok = abs(m["offset_mean"]) <= 0.05 and m["offset_rms"] <= 0.1
        parts.append(("learns" if ok else "misses") + " the offset")
    else:
        parts.append("no offset")
    bk = [s for s in SENSORS if f"{s}_bias" in m]
    if bk:
        bad = [s for s in bk
               if m[f"{s}_bias"] > 0.25 * road.SENSOR_STD[s] / road.SENSOR_UNIT[s][1]]
        parts.append("biases " + ("tracked" if not bad else "off on " + ", ".join(bad))
                     + ("" if len(bk) == 3 else f" ({len(bk)} of 3 sensors)"))
    else:
        parts.append("no biases")
    sk = [s for s in SENSORS if f"{s}_std" in m]
    if sk:
        bad = [s for s in sk if abs(m[f"{s}_std"]) > 0.10]
        parts.append("stds " + ("within 10 %" if not bad else "off on " + ", ".join(bad)))
    else:
        parts.append("stds fixed")
    cov = m.get("coverage", {})
    honest = m["nees_in"] >= 0.9 and (not cov or min(cov.values()) >= 0.9)
    if honest:
        parts.append("honest (NEES, coverage)")
    else:
        why = []
        if m["nees_in"] < 0.9:
            lean = ("over-confident" if m["nees_dof"] > 1.1 else "under-confident"
                    if m["nees_dof"] < 0.9 else f"{m['nees_dof']:.2f} per dof")
            why.append(f"NEES in band {m['nees_in']:.2f}, {lean}")
        if cov and min(cov.values()) < 0.9:
            worst = min(cov, key=cov.get)
            why.append(f"{worst} interval holds in {cov[worst]:.2f} of runs")
        parts.append("not honest: " + "; ".join(why))
    if m.get("diverged"):
        parts.append(f"{m['diverged']} runs diverged")
    return "; ".join(parts)


def _f(v, fmt="{:.3g}"):
    return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else fmt.format(v)


def _cov_cell(cov):
    if not cov:
        return "-"
    off = cov.get("delta_offset")
    b = [v for k, v in cov.items() if k.endswith("_bias")]
    s = [v for k, v in cov.items() if k.endswith("_std")]
    return " / ".join(_f(x, "{:.2f}") for x in (off, min(b) if b else None, min(s) if s else None))


def sim_table(ms):
    head = ("method", "offset err mean / RMS [deg]", "bias RMS ay [m/s^2] / r / roll [deg/s]",
            "std rel. err ay / r / roll", "steering std rel. err",
            "coverage offset / biases / stds",
            "NEES (vy, r) in band / per dof", "NIS in band / per dof", "ms per run-step",
            "verdict")
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for m in ms:
        off = (f"{m['offset_mean']:+.3f} / {m['offset_rms']:.3f}" if "offset_mean" in m else "-")
        bias = " / ".join(_f(m.get(f"{s}_bias"), "{:.3g}") for s in SENSORS)
        std = " / ".join(_f(m.get(f"{s}_std"), "{:+.3f}") for s in SENSORS)
        lines.append("| " + " | ".join([
            m["method"], off, bias, std, _f(m.get("delta_std"), "{:+.3f}"),
            _cov_cell(m["coverage"]),
            f"{m['nees_in']:.2f} / {m['nees_dof']:.2f}", f"{m['nis_in']:.2f} / {m['nis_dof']:.2f}",
            f"{m['ms']:.4f}", verdict(m)]) + " |")
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------
# simulation


def run_simulation(args, methods=METHODS, log=print):
    import vehjax as vj

    drive = vj.data.load_comma2k19()
    model = vj.models.SingleTrackBank(dt=drive.dt)
    T = int(round(args.duration / model.dt))
    U = road.looped_inputs(drive.inputs(model), T)
    t = np.arange(1, T + 1) * model.dt
    acc, _ = road.bank_profile(t, model.dt)
    X, Y, B = (np.asarray(a) for a in road.simulate_truth(model, U, acc, args.runs,
                                                          jax.random.key(args.seed)))
    ss = slice(int(T * 2 / 3), T)
    results, ms = [], []
    for i, meth in enumerate(methods):
        res = run_method(meth, model, Y, U, args, jax.random.key(args.seed + 1 + i))
        m = sim_metrics(res, X, B, ss)
        log(f"sim {meth}: compile {res['compile_s']:.1f} s, {m['ms']:.4f} ms per run-step, "
            f"diverged {res['diverged']}")
        results.append(res)
        ms.append(m)
    return dict(t=t, X=X, B=B, ss=ss, results=results, metrics=ms, T=T)


# ---------------------------------------------------------------------------------------------
# drive


def run_drive(args, methods=METHODS, log=print):
    # berntorp2018 --drive's data: r_virt's bursts gated at 5 deg/s, its scale error removed
    drive = vj.data.load_comma2k19()
    model = vj.models.SingleTrackBank(dt=drive.dt)
    U, Y = prepare_drive(drive, model, seconds=args.duration, gate=5.0 * road.DEG)
    T = len(U)
    ref_r = np.asarray(drive.reference["yaw_rate"])[:T]
    ref_vy = np.asarray(drive.reference["vy"])[:T]
    gyro_ref = float(drive.gyro_offset_vs_reference)
    k_tr = min(int(round(25.0 / model.dt)), T // 2)
    after = slice(k_tr, T)
    rows = []
    results = []
    for i, meth in enumerate(methods):
        # the consistent MPF draws nothing (a fixed grid): one execution is all of them
        R = args.drive_executions if meth == "MPF (paper)" else 1
        res = run_method(meth, model, np.tile(Y[None], (R, 1, 1)), U, args,
                         jax.random.key(args.seed + 100 + i), drive=True)
        est = res["est"]
        m = dict(method=meth, ms=res["ms_per_step"], R=R, diverged=res["diverged"])
        if "delta_offset" in est:
            o = est["delta_offset"][:, after] / DEG
            m["offset"], m["offset_spread"] = float(np.mean(o)), float(np.std(o))
        if "r_bias" in est:
            m["r_bias_err"] = float(np.mean(est["r_bias"][:, after]) - gyro_ref) / DEG
        if "ay_bias" in est:
            m["ay_bias"] = float(np.mean(est["ay_bias"][:, after]))
        for s in ("ay", "r"):
            if f"{s}_std" in est:
                m[f"{s}_std"] = float(np.mean(est[f"{s}_std"][:, after])) / road.SENSOR_UNIT[s][1]
        from vehjax import metrics

        ci = metrics.consistency(res["nis"][:, after], res["n_obs"][:, after])
        m["nis_in"] = ci.inside
        m["nis_dof"] = float(np.nansum(res["nis"][:, after])
                             / max(np.sum(res["n_obs"][:, after]), 1))
        m["r_rms"] = _rms((res["vr"][:, after, 1] - ref_r[None, after]) / DEG)
        m["vy_rms"] = _rms(res["vr"][:, after, 0] - ref_vy[None, after])
        log(f"drive {meth}: {m['ms']:.4f} ms per run-step, diverged {res['diverged']}")
        rows.append(m)
        results.append(res)
    return dict(rows=rows, results=results, t=drive.t[:T] - drive.t[0], T=T, k_tr=k_tr,
                gyro_ref=gyro_ref, raw_r_rms=_rms((Y[after, 1] - ref_r[after]) / DEG),
                vy_ref_rms=_rms(ref_vy[after]))


def drive_verdict(m, d):
    parts = []
    if "r_bias_err" in m:
        parts.append("gyro bias " + ("agrees with" if abs(m["r_bias_err"]) <= 0.05 else "off")
                     + f" the pose's ({m['r_bias_err']:+.3f} deg/s)")
    else:
        parts.append("no gyro bias")
    parts.append(f"yaw rate {m['r_rms'] / d['raw_r_rms']:.2f}x the raw gyro's error")
    parts.append("innovations " + ("consistent" if m["nis_in"] >= 0.9 else
                                   ("too large" if m["nis_dof"] > 1 else "too small"))
                 + f" (NIS in band {m['nis_in']:.2f})")
    if m.get("diverged"):
        parts.append(f"{m['diverged']} diverged")
    return "; ".join(parts)


def drive_table(d):
    head = ("method", "executions", "offset after 25 s [deg] (spread)",
            "gyro bias - pose offset [deg/s]", "ay bias [m/s^2]", "std ay [m/s^2] / r [deg/s]",
            "NIS in band / per dof", "yaw rate RMS vs pose [deg/s]", "vy RMS vs pose [m/s]",
            "ms per run-step", "verdict")
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for m in d["rows"]:
        off = (f"{m['offset']:+.3f} ({m['offset_spread']:.3f})" if "offset" in m else "-")
        lines.append("| " + " | ".join([
            m["method"], str(m["R"]), off, _f(m.get("r_bias_err"), "{:+.3f}"),
            _f(m.get("ay_bias"), "{:+.3f}"),
            " / ".join(_f(m.get(f"{s}_std"), "{:.3f}") for s in ("ay", "r")),
            f"{m['nis_in']:.2f} / {m['nis_dof']:.2f}", f"{m['r_rms']:.3f}", f"{m['vy_rms']:.3f}",
            f"{m['ms']:.4f}", drive_verdict(m, d)]) + " |")
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------
# figure, report


def figure(path, sim, drive):
    import matplotlib.pyplot as plt

    from vehjax import plots

    fig, axes = plt.subplots(2, 2, figsize=(11, 7.5))
    t = sim["t"]
    color = {m: f"C{i}" for i, m in enumerate(METHODS)}  # one colour per method everywhere
    for res in sim["results"]:
        est = res["est"]
        lab = res["method"]
        kw = dict(lw=1, label=lab, color=color[lab])
        axes[0, 0].plot([], [], **kw)  # every method in the legend
        if "delta_offset" in est:
            axes[0, 0].plot(t, np.nanmean(est["delta_offset"], 0) / DEG, **{**kw, "label": None})
        if "ay_std" in est:
            axes[0, 1].plot(t, np.nanmean(est["ay_std"], 0) / road.SENSOR_STD["ay"], **kw)
        if "r_bias" in est:
            e = (est["r_bias"] - sim["B"][..., 1]) / DEG
            axes[1, 0].plot(t, np.sqrt(np.nanmean(e ** 2, 0)), **kw)
    axes[0, 0].axhline(road.OFFSET / DEG, color="k", ls="--", label="truth")
    axes[0, 0].set_ylabel("steering offset, mean over runs [deg]")
    axes[0, 1].axhline(1.0, color="k", ls="--")
    axes[0, 1].set_ylabel("ay std estimate / truth, mean over runs")
    axes[1, 0].set_ylabel("yaw-gyro bias RMS error [deg/s]")
    for ax in axes[0, 0], axes[0, 1], axes[1, 0]:
        ax.set_xlabel("t [s] (simulation)")
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=7)
    ax = axes[1, 1]
    if drive is not None:
        td = drive["t"]
        for res in drive["results"]:
            if "delta_offset" in res["est"]:
                ax.plot(td, np.mean(res["est"]["delta_offset"], 0) / DEG, lw=1,
                        label=res["method"], color=color[res["method"]])
        ax.set_xlabel("t [s] (RAV4 drive)")
        ax.set_ylim(-1.0, 1.0)  # a method that swings wider leaves the frame (table: spread)
        ax.set_ylabel("steering offset, mean over executions [deg]\n(axis clipped at +-1)")
        ax.grid(alpha=0.3)
    else:
        ax.axis("off")
    handles, labels = axes[0, 0].get_legend_handles_labels()
    axes[0, 0].get_legend().remove()
    fig.legend(handles, labels, loc="lower center", ncol=len(labels), fontsize=8)
    fig.suptitle("Online noise learning: offset, ay std, gyro bias (simulation), offset (drive)")
    fig.tight_layout(rect=(0, 0.05, 1, 1))
    return plots.save(fig, path)


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    if not (0.0 < args.forgetting <= 1.0):
        raise ValueError(f"--forgetting: expected a number in (0, 1], got {args.forgetting}")
    if min(args.particles, args.drive_particles, args.grid_points) < 2:
        raise ValueError("--particles / --drive-particles / --grid-points: expected at least 2")
    methods = tuple(m.strip() for m in args.methods.split(",") if m.strip())
    bad = [m for m in methods if m not in METHODS]
    if bad or not methods:
        raise ValueError(f"--methods: unknown {bad}; expected names from {METHODS}")
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    print(PAPER)
    sim = run_simulation(args, methods)
    md_sim = sim_table(sim["metrics"])
    print(md_sim)
    drive = None
    md_drive = ""
    if not args.no_drive:
        drive = run_drive(args, methods)
        md_drive = drive_table(drive)
        print(md_drive)
    report = [
        "# vehjax reproduce noise-learning\n", f"{PAPER}.\n",
        f"Command: `vehjax reproduce noise-learning --runs {args.runs} --duration "
        f"{args.duration:g} --particles {args.particles} --drive-executions "
        f"{args.drive_executions} --drive-particles {args.drive_particles} --grid-points "
        f"{args.grid_points} --forgetting "
        f"{args.forgetting:g} --iterations {args.iterations} --seed {args.seed}"
        + ("" if methods == METHODS else f" --methods '{','.join(methods)}'")
        + ("" if args.steer_factor == 2.0 else f" --steer-factor {args.steer_factor:g}")
        + (" --no-drive" if args.no_drive else "") + "`. Every choice is in the docstring of "
        "`vehjax/reproduce/noise_learning.py`.\n",
        f"## Simulation (paper 004 sec. 4): {args.runs} runs, {args.duration:g} s, steady "
        f"state t > {sim['t'][sim['ss'].start]:.0f} s\n",
        "Coverage: fraction of runs whose final 95 % interval holds the truth (offset, the "
        "worst bias, the worst std); '-' where the method gives no uncertainty or does not "
        "learn the quantity. NEES over (vy, r); NIS over the outputs each method reads. "
        "Times: CPU shared with other jobs.\n",
        md_sim, ""]
    if drive is not None:
        report += [
            f"## RAV4 drive (comma2k19 segment, {drive['T'] * 0.01:.0f} s)\n",
            "No ground truth for offset, biases or stds; the gyro's offset from the pose "
            f"reference is {drive['gyro_ref'] / DEG:+.3f} deg/s; raw gyro RMS vs the pose yaw "
            f"rate {drive['raw_r_rms']:.3f} deg/s; the pose vy's own RMS "
            f"{drive['vy_ref_rms']:.3f} m/s. Numbers after the 25 s transient.\n",
            md_drive, ""]
    if not args.no_plots:
        p = figure(out_dir / "noise_learning.png", sim, drive)
        report += ["## Figure\n", f"![offset, ay std, gyro bias, drive offset]({p.name})\n"]
    report.append(f"Total time {time.perf_counter() - t_start:.0f} s.\n")
    (out_dir / "report.md").write_text("\n".join(report) + "\n")
    print(f"wrote {out_dir / 'report.md'}")
    return 0
