"""Paper 004 on a recorded drive (sec. 5, Fig. 8-9, Remark 1): ``vehjax reproduce berntorp2018
--drive``. The study in named steps: :func:`load_drive` (data, the virtual yaw rate's bursts and
scale), :func:`run_mpf` (the adaptive marginalized PF, many executions in one call),
:func:`run_ekf` (Remark 1's augmented EKF and its extended RTS smoother),
:func:`run_mpf_smoother` (the MPF's own smoother), the offline reference
(:func:`.pmmh.run_samplers`) and :func:`collect`; :func:`main_drive` prints and writes the
report (:mod:`.report`). The reading of the paper is in the package's docstring.
"""

from __future__ import annotations

import math
import time

import jax
import numpy as np

import vehjax as vj
from vehjax.studies.banked_road import BANK_JERK_STD, DEG, DRIVE_STD0, RVIRT_STD, build_drive_filter
from vehjax.data.prepare import (gate_virtual_yaw, online_virtual_scale, pose_virtual_scale,
                                 remove_virtual_scale, virtual_yaw_scale)
from vehjax.filters import gaussian
from vehjax.models import SingleTrackBank
from vehjax.models.bank_scale import TRACK, VirtualScaleBank, augmented_model
from vehjax.run import compile_run

from . import report
from .pmmh import run_samplers

#: ancestral paths of the drive's MPF smoother (at most N; ``--mpf-smooth-paths``)
MPF_SMOOTH_PATHS = 100


def ekf_noise(bank):
    """The augmented EKF's fixed Q (per step) and R (the MPF's initial guesses), SI units."""
    q = [0.01, 0.01 * DEG, 1e-5 * DEG, 1e-4, 1e-5 * DEG, 0.0]
    r = [DRIVE_STD0["ay"], DRIVE_STD0["r"], RVIRT_STD]
    Q = np.diag(np.array(q + ([0.0] * 4 if bank else [])) ** 2)
    if bank:
        B = np.asarray(SingleTrackBank().bank_noise_gain())[2:5]
        Q[6:9, 6:9] = BANK_JERK_STD**2 * np.outer(B, B)
        Q[9, 9] = (1e-5 * DEG) ** 2
        r.append(DRIVE_STD0["r"])
    return Q, np.array(r) ** 2


def load_drive(args, log=print):
    """The shipped drive cut to ``--duration``, its virtual yaw rate's scale estimated three
    ways (the pose's, least squares from the sensors, the causal one), its bursts gated
    (``--rvirt-gate``) and its scale removed per ``--rvirt-scale``. Returns a dict: drive,
    model, U, Y (what the MPF sees), Y_raw (gated, scale kept), and the estimates."""
    drive = vj.data.load_comma2k19()
    model = vj.models.SingleTrackBank(dt=drive.dt)
    U, Y = drive.inputs(model), drive.measurements(model, track=TRACK)
    T = len(U) if args.duration is None else min(len(U), int(round(args.duration / model.dt)))
    U, Y = U[:T], Y[:T].copy()
    ref_r = np.asarray(drive.reference["yaw_rate"])[:T]
    rvirt_raw_off = float(np.nanmean(Y[:, 4] - ref_r))
    eps_pose = pose_virtual_scale(Y[:, 4], ref_r, U[:, 0], TRACK)
    # eps by least squares from all samples (gating biases it: the bursts are one-sided), then
    # the gate
    eps, gyro_bias_ls = virtual_yaw_scale(Y[:, 1], Y[:, 4], U[:, 0], TRACK)
    eps_rls, _ = online_virtual_scale(Y[:, 1], Y[:, 4], U[:, 0], TRACK)
    resid = Y[:, 1] - Y[:, 4] - gyro_bias_ls + eps * U[:, 0] / TRACK
    Y[:, 4], n_gated = gate_virtual_yaw(Y[:, 1], Y[:, 4], getattr(args, "rvirt_gate", 5.0) * DEG)
    rvirt_sd = float(np.sqrt(np.nanmean(np.square(resid[np.isfinite(Y[:, 4])]))))
    Y_raw = Y.copy()
    mode = getattr(args, "rvirt_scale", "offline")
    if mode == "offline":  # the virtual yaw rate with its scale error removed
        Y[:, 4] = remove_virtual_scale(Y[:, 4], eps, U[:, 0], TRACK)
    elif mode == "online":  # ... by the causal estimate up to each step
        Y[:, 4] = remove_virtual_scale(Y[:, 4], eps_rls, U[:, 0], TRACK)
    log(f"virtual yaw rate: rolling-radius mismatch eps = {eps:+.3e}, gyro bias "
        f"{gyro_bias_ls / DEG:+.4f} deg/s (least squares, sensors only); scale {mode}")
    return dict(drive=drive, model=model, U=U, Y=Y, Y_raw=Y_raw, T=T, ref_r=ref_r, mode=mode,
                rvirt_raw_off=rvirt_raw_off, eps_pose=eps_pose, eps=eps,
                gyro_bias_ls=gyro_bias_ls, eps_rls=eps_rls, rvirt_sd=rvirt_sd, n_gated=n_gated)


def run_mpf(args, d, log=print):
    """The drive's marginalized PF (:class:`VirtualScaleBank`, ``--variant``), ``--runs``
    executions of the same data in one compiled call. Returns (est, P0, out, run s, compile s)."""
    N = 500 if args.particles is None else args.particles
    R, T, mode = args.runs, d["T"], d["mode"]
    eps_sd = 1e-3 if mode == "state" else 1e-12  # prior std of the MPF's eps state
    smodel = VirtualScaleBank(dt=d["drive"].dt)
    est = build_drive_filter(smodel, N, variant=args.variant,
                             kalman_states=args.kalman_states)
    bank_sd = 1e-3 if args.variant == "bank" else 1e-10  # planar: the bank states held at 0
    P0 = np.diag([0.1, 0.5 * DEG, bank_sd, bank_sd, bank_sd, eps_sd]) ** 2
    prepared = compile_run(est, np.tile(d["Y"][None], (R, 1, 1)), d["U"], x0=np.zeros(6),
                           P0=P0, key=jax.random.key(args.seed), progress=False)
    t0 = time.perf_counter()
    out = prepared(progress=False)
    mpf_run = time.perf_counter() - t0
    mpf_c = prepared.compile_seconds
    log(f"marginalized PF: N = {N}, {R} executions x {T} steps, compile {mpf_c:.1f} s, "
        f"run {mpf_run:.1f} s")
    return est, P0, out, mpf_run, mpf_c


def run_ekf(args, d, log=print):
    """Remark 1's EKF (:func:`~vehjax.models.bank_scale.augmented_model`, eps as a state) on one
    run, timed best of three, and its extended RTS smoother. Returns a dict."""
    U, mode = d["U"], d["mode"]
    bank = args.variant == "bank"
    eps_sd_ekf = 1e-3 if mode in ("online", "state") else 1e-12
    am = augmented_model(d["model"], bank=bank)
    Ya = d["Y_raw"] if mode in ("online", "state", "none") else d["Y"]
    Ya = Ya[:, [0, 1, 4] + ([2] if bank else [])]
    Q, Rm = ekf_noise(bank)
    ekf = gaussian.ekf(am, Q, Rm)
    P0a = np.array([0.1, 0.5 * DEG, 0.5 * DEG, 0.5, 0.5 * DEG, eps_sd_ekf]
                   + ([1e-3, 1e-3, 1e-3, 0.5 * DEG] if bank else [])) ** 2
    prepared = compile_run(ekf, Ya[None], U, x0=np.zeros(am.nx), P0=P0a, progress=False)
    eout = prepared(progress=False)
    ekf_c = prepared.compile_seconds
    ekf_run = math.inf
    for _ in range(3):
        t0 = time.perf_counter()
        prepared(progress=False)
        ekf_run = min(ekf_run, time.perf_counter() - t0)
    log(f"EKF (augmented, Remark 1): compile {ekf_c:.1f} s, run {ekf_run:.3f} s")
    E = np.asarray(eout.states)[0]
    t0 = time.perf_counter()
    sm = jax.jit(lambda y, u: vj.smooth(ekf, y, u, x0=np.zeros(am.nx), P0=P0a))(Ya, U)
    Es, Ps = np.asarray(sm.states), np.asarray(sm.covariances)
    rts_s = time.perf_counter() - t0
    log(f"extended RTS smoother of the augmented EKF: {rts_s:.1f} s (compile included), "
        f"diverged {bool(sm.diverged)}")
    return dict(E=E, Es=Es, Ps=Ps, rts_s=rts_s, ekf_run=ekf_run, ekf_c=ekf_c,
                ekf_names=am.state_names)


def run_mpf_smoother(args, d, est, P0, N, log=print):
    """The MPF's own smoother: one more execution of the same filter, M trajectories
    (``--mpf-smooth-paths``, at most N; 0: skipped, None returned), each trajectory's bank
    (and eps) by an RTS given it (:mod:`vehjax.smoothers.marginalized`)."""
    M = min(N, getattr(args, "mpf_smooth_paths", MPF_SMOOTH_PATHS))
    if not M:
        return None
    method = getattr(args, "mpf_smoother", "ffbsi")
    if getattr(args, "kalman_states", "linear") != "linear":
        method = "ancestor"  # FFBSi is built for the paper's kalman_states="linear"
    t0 = time.perf_counter()
    record = vj.smoothers.methods.BY_NAME[method](n_trajectories=M)
    msm = jax.jit(lambda y, u, k: vj.smooth(est, y, u, x0=np.zeros(6), P0=P0, key=k,
                                            method=record))(
        d["Y"], d["U"], jax.random.fold_in(jax.random.key(args.seed), 29))
    mpf_smooth = dict(states=np.asarray(msm.states), cov=np.asarray(msm.covariances),
                      params=np.asarray(msm.params), params_cov=np.asarray(msm.params_cov),
                      n_unique=np.asarray(msm.n_unique),
                      n_distinct=np.asarray(msm.n_distinct),
                      backward_ess=np.asarray(msm.backward_ess),
                      diverged=bool(msm.diverged), M=M, method=method)
    mpf_smooth["seconds"] = time.perf_counter() - t0
    log(f"MPF smoother ({method}): N = {N}, M = {M}, "
        f"{mpf_smooth['seconds']:.1f} s (compile included), diverged "
        f"{mpf_smooth['diverged']}")
    return mpf_smooth


def collect(args, d, out, names, ekf, timing, mpf_smooth, pm_res):
    """The drive study's results for the report: a dict of arrays and numbers (yaw rates against
    the pose, the transient's end, eps by every estimator)."""
    T, R, mode, U, Y = d["T"], args.runs, d["mode"], d["U"], d["Y"]
    drive, model, ref_r, E = d["drive"], d["model"], d["ref_r"], ekf["E"]
    Pm, S = np.asarray(out.params), np.asarray(out.states)
    k_tr = min(int(round(25.0 / model.dt)), T // 2)  # transient: 25 s as Fig. 8, or half
    off = Pm[:, :, names.index("delta_offset")] / DEG
    rb = Pm[:, :, names.index("r_bias")]
    r_meas = Y[:, 1]
    rvirt_off = float(np.nanmean(Y[:, 4] - S[:, :, 5].mean(0) * U[:, 0] / TRACK - ref_r))
    eps, eps_rls = d["eps"], d["eps_rls"]
    eps_mpf = S[:, :, 5] if mode == "state" else np.tile(
        (eps_rls if mode == "online" else np.full(T, eps if mode == "offline" else 0.0))[None],
        (R, 1))
    return dict(t=drive.t[:T] - drive.t[0], T=T, N=timing["N"], R=R, names=names, Pm=Pm, E=E,
                off=off, rb=rb, ref_r=ref_r, r_meas=r_meas,
                corr_mpf=(r_meas[None] - rb - ref_r[None]) / DEG,  # (R, T)
                corr_ekf=(r_meas - E[:, 4] - ref_r) / DEG, raw_err=(r_meas - ref_r) / DEG,
                after=slice(k_tr, T), k_tr=k_tr, mpf_run=timing["mpf_run"],
                mpf_c=timing["mpf_c"], ekf_run=ekf["ekf_run"], ekf_c=ekf["ekf_c"],
                gyro_ref=float(drive.gyro_offset_vs_reference), rvirt_off=rvirt_off,
                out=out, drive=drive, variant=args.variant,
                ref_roll=np.asarray(drive.reference["roll"])[:T], phi=S[:, :, 2], eps=eps,
                gyro_bias_ls=d["gyro_bias_ls"], rvirt_raw_off=d["rvirt_raw_off"],
                k15=min(int(round(15.0 / model.dt)), T // 2), r_mpf=S[:, :, 1],
                vy_mpf=S[:, :, 0], eps_mpf=eps_mpf, mode=mode, n_gated=d["n_gated"],
                ref_vy=np.asarray(drive.reference["vy"])[:T], Es=ekf["Es"], Ps=ekf["Ps"],
                rts_s=ekf["rts_s"], ekf_names=ekf["ekf_names"], pmmh=pm_res, vx=U[:, 0],
                eps_pose=d["eps_pose"], mpf_smooth=mpf_smooth,
                kalman_states=getattr(args, "kalman_states", "linear"))


def run_drive(args, log=print):
    """The drive study (sec. 5): every step in order; returns :func:`collect`'s dict."""
    d = load_drive(args, log)
    N = 500 if args.particles is None else args.particles
    est, P0, out, mpf_run, mpf_c = run_mpf(args, d, log)
    names = list(est.param_names)
    ekf = run_ekf(args, d, log)
    mpf_smooth = run_mpf_smoother(args, d, est, P0, N, log)
    pm_res = run_samplers(args, d, ekf["Es"], np.asarray(out.params), names, log)
    timing = dict(N=N, mpf_run=mpf_run, mpf_c=mpf_c)
    return collect(args, d, out, names, ekf, timing, mpf_smooth, pm_res)


def main_drive(args, out_dir):
    """Runs the drive study, prints its tables and writes report.md, results.npz and the
    figures to ``out_dir``."""
    t_start = time.perf_counter()
    res = run_drive(args)
    tables = report.drive_markdown(res)
    report.print_drive(res, tables)
    np.savez(out_dir / "results.npz", t=res["t"], params=res["Pm"],
             param_names=np.array(res["names"]), ekf_states=res["E"], ref_yaw_rate=res["ref_r"])
    lines = report.drive_report(args, res, tables)
    if not args.no_plots:
        figs = report.drive_figures(out_dir, res)
        lines += ["## Figures\n"] + [f"![{cap}]({p.name})\n" for p, cap in figs]
    (out_dir / "report.md").write_text("\n".join(lines) + "\n")
    print(f"wrote {out_dir / 'report.md'}")
    print(f"total {time.perf_counter() - t_start:.1f} s")
    return 0
