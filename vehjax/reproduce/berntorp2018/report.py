"""Paper 004's reports: markdown tables, the drive study's rows, figures and verdicts (what
holds, what cannot be told). Reads the result dicts of :mod:`.study` and :mod:`.drive`; computes
no estimate of its own."""

from __future__ import annotations

import math

import numpy as np

from vehjax.studies.banked_road import DEG, DRIVE_STD0
from vehjax.models.bank_scale import TRACK

from .pmmh import PMMH_UNITS, SAMPLER

PAPER = ("K. Berntorp and S. Di Cairano, \"Noise-statistics learning of automotive-grade sensors "
         "using adaptive marginalized particle filtering\", Journal of Dynamic Systems, "
         "Measurement, and Control (MERL TR2018-181) (paper 004)")


def _rms(a, axis=None):
    return np.sqrt(np.nanmean(np.square(a), axis=axis))


def _table(rows, head=("quantity", "mean over runs", "max over runs", "paper")):
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        cells = [r[0]] + [f"{v:.4g}" if isinstance(v, (float, np.floating)) else str(v)
                          for v in r[1:]]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def drive_tables(res):
    """The drive's rows: offset, biases, stds (MPF over executions beside the EKF) and the yaw
    rates against the pose after 15 s."""
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
    k15 = slice(res["k15"], res["T"])  # the yardstick: after 15 s
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
    if "Es" in res:
        cs = res["r_meas"][k15] - res["Es"][k15, 4] - ref
        es = res["Es"][k15, 1] - ref
        yaw_rows += [
            ("gyro - smoothed EKF bias", _rms(cs / DEG), np.max(np.abs(cs / DEG)),
             np.mean(np.abs(cs / DEG) < 0.5)),
            ("smoothed yaw rate (extended RTS)", _rms(es / DEG), np.max(np.abs(es / DEG)),
             np.mean(np.abs(es / DEG) < 0.5))]
    if res.get("mpf_smooth") is not None:  # the paper's filter's own smoother (state 1: r)
        ms = (np.asarray(res["mpf_smooth"]["states"])[k15, 1] - ref) / DEG
        yaw_rows.append(("MPF-smoothed yaw rate (ancestor paths)", _rms(ms), np.max(np.abs(ms)),
                         np.mean(np.abs(ms) < 0.5)))
    return rows_mpf, yaw_rows


def scale_rows(res):
    """The rolling-radius mismatch eps [1e-4] by every estimator: (source, value, note)."""
    after = res["after"]
    e_end = res["eps_mpf"][:, -1] / 1e-4
    e_after = res["eps_mpf"][:, after].mean(axis=1) / 1e-4
    rows = [("pose (least squares of r_virt - pose yaw rate on vx / l_T)",
             f"{res['eps_pose'] / 1e-4:+.3f}", "reference"),
            ("sensors only, offline (virtual_yaw_scale, whole run)", f"{res['eps'] / 1e-4:+.3f}",
             "applied before the filters" if res["mode"] == "offline" else "not applied"),
            (_MPF_EPS[res["mode"]], f"{e_end.mean():+.3f}",
             f"std over executions {e_end.std():.3f}; mean after the transient "
             f"{e_after.mean():+.3f}; at 15 s {res['eps_mpf'][:, res['k15']].mean() / 1e-4:+.3f}"),
            ("augmented EKF online, eps a state, end of run", f"{res['E'][-1, 5] / 1e-4:+.3f}",
             f"at 15 s {res['E'][res['k15'], 5] / 1e-4:+.3f}"),
            ("extended RTS of the augmented EKF", f"{res['Es'][0, 5] / 1e-4:+.3f}",
             f"+- {2 * math.sqrt(res['Ps'][0, 5, 5]) / 1e-4:.3f} (2 std); a constant state: "
             "the whole run's value")]
    for lik, (pr, _, n, _) in res.get("pmmh", {}).items():
        k = pr.names.index("eps")
        rows.append((f"{SAMPLER[lik]}, posterior mean, first {n * 0.01:.0f} s",
                     f"{pr.mean[k] / 1e-4:+.3f}", f"posterior std {pr.std[k] / 1e-4:.3f}"))
    if res["mode"] in ("offline", "none"):
        rows[3] = (rows[3][0], "held at 0", f"--rvirt-scale {res['mode']}")
        rows[4] = (rows[4][0], "held at 0", f"--rvirt-scale {res['mode']}")
    return rows


_MPF_EPS = {
    "online": "online, causal recursive least squares (online_virtual_scale), end of run",
    "state": "MPF online, eps in each particle's Kalman filter, end of run",
    "offline": "offline value used by the MPF",
    "none": "none (the paper), used by the MPF",
}


def smoothed_rows(res):
    """The augmented EKF's extended-RTS estimates over the drive: (quantity, smoothed mean over
    the drive, its range over time, 2 std at the middle of the drive, the online EKF at the
    end)."""
    rows = []
    names = list(res["ekf_names"])
    mid = res["T"] // 2
    items = [("smoothed steering offset [deg]", "delta_offset", DEG),
             ("smoothed ay bias [m/s^2]", "ay_bias", 1.0),
             ("smoothed yaw-gyro bias [deg/s]", "r_bias", DEG), ("smoothed eps [1e-4]", "eps", 1e-4)]
    if "phi" in names:
        items += [("smoothed bank angle [deg]", "phi", DEG),
                  ("smoothed roll-gyro bias [deg/s]", "roll_rate_bias", DEG)]
    for label, name, sc in items:
        k = names.index(name)
        v = res["Es"][:, k] / sc
        rows.append((label, f"{v.mean():+.4f}", f"{v.min():+.4f}..{v.max():+.4f}",
                     f"{2 * math.sqrt(res['Ps'][mid, k, k]) / sc:.4f}",
                     f"{res['E'][-1, k] / sc:+.4f}"))
    return rows


def mpf_smoothed_rows(res):
    """The MPF smoother's estimates over the drive (one execution, M ancestral paths): (quantity,
    smoothed mean over the drive, its range over time, 2 std at the middle of the drive, the
    filter at the end, mean over the executions). Noise statistics: the paths' NiW estimates at
    each time (:mod:`vehjax.smoothers.marginalized`: conditioned on the data up to t along
    paths drawn with all of it); bank: each path's RTS mixed over the paths."""
    sm = res["mpf_smooth"]
    names = list(res["names"])
    mid = res["T"] // 2
    rows = []
    items = [("MPF-smoothed steering offset [deg]", "delta_offset", DEG),
             ("MPF-smoothed ay bias [m/s^2]", "ay_bias", 1.0),
             ("MPF-smoothed yaw-gyro bias [deg/s]", "r_bias", DEG),
             ("MPF-smoothed roll-gyro bias [deg/s]", "roll_rate_bias", DEG),
             ("MPF-smoothed steering std [deg]", "delta_std", DEG),
             ("MPF-smoothed ay std [m/s^2]", "ay_std", 1.0),
             ("MPF-smoothed yaw-gyro std [deg/s]", "r_std", DEG),
             ("MPF-smoothed roll-gyro std [deg/s]", "roll_rate_std", DEG)]
    for label, name, sc in items:
        if name not in names:
            continue
        k = names.index(name)
        v = sm["params"][:, k] / sc
        rows.append((label, f"{v.mean():+.4f}", f"{v.min():+.4f}..{v.max():+.4f}",
                     f"{2 * math.sqrt(max(sm['params_cov'][mid, k, k], 0.0)) / sc:.4f}",
                     f"{res['Pm'][:, -1, k].mean() / sc:+.4f}"))
    states = [("MPF-smoothed bank angle [deg]", 2, DEG)] if res["variant"] == "bank" else []
    if res["mode"] == "state":
        states.append(("MPF-smoothed eps [1e-4]", 5, 1e-4))
    S_end = np.asarray(res["out"].states)[:, -1]
    for label, k, sc in states:
        v = sm["states"][:, k] / sc
        rows.append((label, f"{v.mean():+.4f}", f"{v.min():+.4f}..{v.max():+.4f}",
                     f"{2 * math.sqrt(max(sm['cov'][mid, k, k], 0.0)) / sc:.4f}",
                     f"{S_end[:, k].mean() / sc:+.4f}"))
    if res["variant"] == "bank":
        e = (sm["states"][res["k15"]:, 2] - res["ref_roll"][res["k15"]:]) / DEG
        rows.append(("MPF-smoothed bank - pose roll after 15 s [deg]", f"RMS {_rms(e):.3f}",
                     f"max {np.max(np.abs(e)):.3f}", "-", "-"))
    return rows


#: what the offline reference's report checks: split R-hat below this and ESS at least this for
#: every quantity (the chains have mixed and the posterior summaries are to about 10 % of a std)
RHAT_MAX, ESS_MIN = 1.1, 100
#: Doucet, Pitt, Deligiannidis & Kohn (2015): the bootstrap PF's log-likelihood std [nats] for
#: which PMMH is most efficient for its cost
LOGLIK_STD_BAND = (1.0, 1.5)


def pmmh_check(pr, info, lik="bootstrap"):
    """The report's sentence on one sampler: whether every quantity has split R-hat <
    :data:`RHAT_MAX` and ESS >= :data:`ESS_MIN` (naming those that do not), and for a
    particle likelihood (``lik`` "bootstrap" or "mpf") its log-likelihood estimate's std
    against :data:`LOGLIK_STD_BAND`; for the correlated chain (``info`` with
    ``loglik_diff_std``) the std of the difference its acceptance ratio sees beside two
    independent estimates'."""
    bad = [f"{n} (R-hat {r:.2f}, ESS {e:.0f})" for n, r, e in zip(pr.names, pr.rhat, pr.ess)
           if not (r < RHAT_MAX and e >= ESS_MIN)]
    text = (f"Check: split R-hat < {RHAT_MAX} and ESS >= {ESS_MIN} for every quantity: "
            + ("met (max R-hat {:.3f}, min ESS {:.0f}).".format(np.max(pr.rhat), np.min(pr.ess))
               if not bad else "NOT met for " + ", ".join(bad)
               + ": these chains have not mixed, their numbers are not yet a posterior."))
    if "loglik_diff_std" in info:
        d, sd = info["loglik_diff_std"], info["loglik_std"]
        text += (f" The correlated estimates (N = {info['particles']}, rho = "
                 f"{info.get('correlation')}) differ by a log-likelihood std of {d:.2f} nats "
                 f"between an estimate and its Crank-Nicolson move at the Kalman chain's "
                 f"posterior mean, against {math.sqrt(2.0) * sd:.2f} for two independent "
                 f"estimates (each of std {sd:.2f}); "
                 + ("small enough for the acceptance ratio (about 1-2 nats)."
                    if d <= 2.0 else
                    "far above the 1-2 nats an efficient chain needs: with two states the "
                    "sorted resampling keeps little of the correlation (module vehjax.calibrate.correlated), "
                    "so this chain sticks as the independent one does."))
        return text
    if "loglik_std" in info:
        lo, hi = LOGLIK_STD_BAND
        sd = info["loglik_std"]
        who = {"mpf": "marginalized PF's"}.get(lik, "bootstrap PF's")
        text += (f" The {who} log-likelihood estimate (N = {info['particles']}) has std "
                 f"{sd:.2f} nats at the Kalman chain's posterior mean (Doucet et al. 2015: "
                 f"{lo:g}-{hi:g} for an efficient PMMH)"
                 + ("." if sd <= hi else
                    "; above it, so the chain sticks more than an efficient PMMH would."
                    if lik == "mpf" else
                    f"; far above it, so the chain sticks: the std falls only slowly with N "
                    f"here (a precise gyro against the bootstrap proposal), and this chain "
                    f"is a check of the particle machinery, not the reference."))
    return text


def pmmh_rows(pr):
    """One table row per PMMH quantity: name [unit], mean, std, 2.5 %, 97.5 %, R-hat, ESS."""
    flat = pr.samples.reshape(-1, len(pr.names))
    rows = []
    for k, name in enumerate(pr.names):
        unit, sc = PMMH_UNITS[name]
        lo, hi = np.percentile(flat[:, k], [2.5, 97.5]) / sc
        rows.append((f"{name} [{unit}]", f"{pr.mean[k] / sc:+.4g}", f"{pr.std[k] / sc:.3g}",
                     f"{lo:+.4g}..{hi:+.4g}", f"{pr.rhat[k]:.3f}", f"{pr.ess[k]:.0f}"))
    return rows


def posterior_agreement(pr, ref):
    """Rows comparing one chain's posterior with the reference chain's (same names): name
    [unit], the two means, mean difference / its Monte-Carlo std (sqrt(s_a^2 / ESS_a + s_b^2 /
    ESS_b): |z| < 2-3 when both chains target the same posterior and have mixed), and the std
    ratio."""
    rows = []
    for k, name in enumerate(pr.names):
        j = ref.names.index(name)
        unit, sc = PMMH_UNITS[name]
        se = math.sqrt(pr.std[k] ** 2 / max(pr.ess[k], 1.0)
                       + ref.std[j] ** 2 / max(ref.ess[j], 1.0))
        rows.append((f"{name} [{unit}]", f"{pr.mean[k] / sc:+.4g}", f"{ref.mean[j] / sc:+.4g}",
                     f"{(pr.mean[k] - ref.mean[j]) / se:+.2f}",
                     f"{pr.std[k] / ref.std[j]:.3f}"))
    return rows


def vy_rows(res):
    """Lateral velocity against the pose's (after 15 s): RMS and max |error| [m/s]."""
    k15 = slice(res["k15"], res["T"])
    ref = res["ref_vy"][k15]
    em = res["vy_mpf"][:, k15] - ref[None]
    ee = res["E"][k15, 0] - ref
    rows = [("MPF vy estimate", _rms(em), np.max(np.abs(em))),
            ("EKF vy estimate", _rms(ee), np.max(np.abs(ee)))]
    if "Es" in res:
        es = res["Es"][k15, 0] - ref
        rows.append(("smoothed vy (extended RTS)", _rms(es), np.max(np.abs(es))))
    rows.append(("vy = 0 (no estimate)", _rms(ref), np.max(np.abs(ref))))
    return rows


def drive_figures(out_dir, res):
    """Fig. 8 (offset), 9 (yaw gyro) and, for the bank variant, 10 (bank against the pose roll)."""
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


_SMOOTHED_GIVEN_PATH = {
    "linear": "the sampled states (vy, r) are the path itself and the Kalman states (the bank "
              "and eps, eps held with --rvirt-scale offline or none)",
    "all": "all states (each particle's Gaussian over them)",
}


def _given_path(res):
    text = _SMOOTHED_GIVEN_PATH[res["kalman_states"]]
    return text.replace("the bank and eps", "eps") if res["variant"] == "planar" else text


def _mpf_smooth_text(res, md):
    """The report's paragraph and table on the MPF's smoother (none when it was skipped)."""
    msm = res["mpf_smooth"]
    if msm is None:
        return ["The MPF's own smoother was skipped (`--mpf-smooth-paths 0`).\n"]
    T = res["T"]
    mid = T // 2
    if msm.get("method", "ancestor") == "ffbsi":
        how = (f"M = {msm['M']} trajectories drawn backwards over all the filter's particles "
               "(Rao-Blackwellised backward simulation, method 'ffbsi': weights from each "
               "particle's predictive of the next sampled state and measurement; the data "
               "after that step are not used in the weights), each trajectory's Kalman filter "
               "and noise statistics re-run along it. Given a trajectory, ")
        spread = (f"they pass through {int(msm['n_distinct'][0])} distinct particles at t = 0 "
                  f"and {int(msm['n_distinct'][mid])} at the middle (backward ESS "
                  f"{float(np.mean(msm['backward_ess'])):.1f} of {res['N']} on average)")
        stats = ("The noise statistics in each row are the trajectories' re-run estimates at "
                 "that time: with lambda = 0.999 each looks back about 10 s along a trajectory "
                 "drawn given the whole drive, not a backward pass over the statistics. ")
    else:
        how = (f"M = {msm['M']} paths followed back through its resampling genealogy "
               "(method 'ancestor'). Given a path, ")
        spread = (f"the paths coalesce going back in time (they pass through "
                  f"{int(msm['n_unique'][0])} distinct particles at t = 0, "
                  f"{int(msm['n_unique'][mid])} at the middle), so the early rows rest on few "
                  "particles")
        stats = ("The noise statistics in each row are the paths' NiW estimates at that time: "
                 "with lambda = 0.999 each looks back about 10 s along a path drawn given the "
                 "whole drive, not a backward pass over the statistics. ")
    return [
        f"The marginalized PF's own smoother (`vehjax.smooth` on the drive's filter, "
        f"kalman_states = {res['kalman_states']!r}; `vehjax.smoothers.marginalized`): one "
        f"more execution of the filter, {how}{_given_path(res)} "
        "are smoothed by an RTS of the trajectory's own Kalman filter: the exact conditional "
        "Gaussian given it of the model that filter runs (affine in those states, the "
        f"plug-in noise statistics at each step); {spread}. {stats}"
        f"Diverged: {msm['diverged']}.\n",
        md, ""]


_SCALE_TEXT = {
    "online": "eps is learnt online: a causal recursive least squares from the two yaw "
              "sensors (`online_virtual_scale`: a Kalman filter on (gyro bias, eps) fed "
              "gyro - r_virt, which holds no yaw rate) corrects each r_virt sample by its "
              "estimate so far before the MPF sees it; the augmented EKF sees the raw r_virt "
              "and carries eps as a state; prior N(0, 1e-3^2).",
    "state": "The filters see the raw r_virt and learn eps online: in the MPF as a constant "
             "state in each particle's Kalman filter (no process noise, no forgetting), in the "
             "augmented EKF as a state; prior N(0, 1e-3^2).",
    "offline": "eps from the offline least squares below is removed from r_virt before the "
               "filters, which take r_virt as unbiased (eps held at 0).",
    "none": "r_virt taken as unbiased, as in the paper (eps held at 0).",
}

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
        f"the EKF's {np.mean(res['E'][after, 4]) / DEG:+.3f} deg/s, the smoothed EKF's "
        f"{np.mean(res['Es'][:, 4]) / DEG:+.3f} deg/s. The raw virtual yaw rate read "
        f"{res['rvirt_raw_off'] / DEG:+.3f} deg/s off the pose (rolling radii "
        f"{abs(res['eps_pose']) * 100:.3f} % apart by the pose); taken as unbiased, the gyro "
        "bias estimates inherit that offset with the opposite sign (0.246 deg/s "
        f"against the raw gyro's 0.152, 10 executions, N = 300). Here (`--rvirt-scale "
        f"{res['mode']}`) r_virt minus the MPF's eps vx / l_T read "
        f"{res['rvirt_off'] / DEG:+.3f} deg/s off the pose on average.",
        f"* Yaw rate vs the pose reference after 15 s: the raw gyro RMS {yaw_rows[0][1]:.3f} "
        f"deg/s; gyro - MPF bias {yaw_rows[1][1]:.3f}, gyro - EKF bias {yaw_rows[2][1]:.3f} "
        "(a constant correction cannot remove the gyro's white noise, which is most of the "
        f"raw error); the filters' yaw-rate estimates: MPF {yaw_rows[3][1]:.3f} "
        f"({yaw_rows[3][1] / yaw_rows[0][1]:.2f}x the raw gyro), EKF {yaw_rows[4][1]:.3f} "
        f"({yaw_rows[4][1] / yaw_rows[0][1]:.2f}x)"
        + "".join(f", the {r[0]} {r[1]:.3f} ({r[1] / yaw_rows[0][1]:.2f}x)"
                  for r in yaw_rows[6:] if "smoothed yaw rate" in r[0])
        + ". Target: at most 0.8x the raw gyro ("
        f"{0.8 * yaw_rows[0][1]:.3f} deg/s): "
        + ", ".join(f"{r[0]} {'meets it' if r[1] <= 0.8 * yaw_rows[0][1] else 'does NOT'}"
                    for r in yaw_rows[1:])
        + ". The pose reference is 20 Hz pose differentiated, itself noisy at the 0.1 deg/s "
        "level.",
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


def _sampler_text(lik, info):
    """What an offline sampler's report paragraph says it ran, by --pmmh-likelihood value."""
    return {"bootstrap": f"PMMH likelihood: bootstrap PF, N = {info['particles']}",
            "kalman": "PMMH likelihood: EKF, exact Kalman likelihood on this linear "
                      "model, plain MH",
            "cpm": f"PMMH likelihood: bootstrap PF, N = {info['particles']}, with "
                   f"correlated random numbers (correlated pseudo-marginal, Deligiannidis, "
                   f"Doucet & Pitt 2018: each proposal moves the filter's standard normals "
                   f"by a Crank-Nicolson step, rho = {info.get('correlation')}, particles "
                   f"Hilbert-sorted before systematic resampling at every step)",
            "mpf": f"PMMH likelihood: marginalized PF (paper 004's filter, "
                   f"kalman_states='all', every state in each particle's Kalman filter), "
                   f"N = {info['particles']}, its noise statistics held at the chain's "
                   f"values (vehjax.calibrate.fixed_noise_mpf: the EKF's model, so an "
                   f"unbiased estimate of the same likelihood and the same posterior)",
            "pg": f"particle Gibbs with ancestor sampling (ref. [29]), conditional PF with "
                  f"N = {info['particles']}, steering noise as additive process noise "
                  f"(Q[vy], Q[r]; their correlation dropped)"}[lik]


def pmmh_markdown(res):
    """The offline reference's paragraphs and tables, one sampler after another (lines)."""
    md_pmmh = []
    for lik, (pr, sec, n, info) in res["pmmh"].items():
        what = _sampler_text(lik, info)
        md_pmmh += [f"{what}; {pr.samples.shape[0]} chains x "
                    f"{info['iters']} iterations (half warm-up), the first {n * 0.01:.0f} s, "
                    f"{sec:.1f} s (compile included), acceptance "
                    f"{np.mean(pr.acceptance):.2f} (tuned toward "
                    f"{info.get('acceptance_target', 0.255):.3f}). " + pmmh_check(pr, info, lik) + "\n",
                    _table(pmmh_rows(pr), head=("quantity", "posterior mean", "std",
                                                 "95 % interval", "split R-hat", "ESS")), ""]
        if lik in ("mpf", "cpm") and "kalman" in res["pmmh"]:
            md_pmmh += ["Against the exact-likelihood chain (the same model and posterior): "
                        "z = difference of the means over its Monte-Carlo std (from both "
                        "chains' ESS), |z| < 3 expected where both have mixed.\n",
                        _table(posterior_agreement(pr, res["pmmh"]["kalman"][0]),
                               head=("quantity", {"mpf": "mean (MPF likelihood)",
                                                  "cpm": "mean (correlated PMMH)"}[lik],
                                     "mean (Kalman likelihood)", "z", "std ratio")), ""]
    return md_pmmh


def cost_table(res):
    """Run and compile times of every estimator of the drive study (markdown)."""
    msm = res["mpf_smooth"]
    return _table([
        ("marginalized PF", f"N = {res['N']}, {res['R']} executions in one call",
         f"{res['mpf_run'] / (res['T'] * res['R']) * 1e3:.4f}", f"{res['mpf_run']:.2f}",
         f"{res['mpf_c']:.1f}"),
        (f"EKF, augmented ({len(res['ekf_names'])} states)", "1 run",
         f"{res['ekf_run'] / res['T'] * 1e3:.4f}", f"{res['ekf_run']:.3f}", f"{res['ekf_c']:.1f}"),
        ("extended RTS smoother (filter + backward pass)", "1 run", "-", "-",
         f"{res['rts_s']:.1f} (with run)"),
    ] + ([] if msm is None else [(
          "MPF smoother (filter + " + {"ffbsi": "backward simulation + re-run + RTS)",
                                       "ancestor": "ancestor paths + per-path RTS)"}[
                                           msm.get("method", "ancestor")],
          f"1 run, N = {res['N']}, M = {msm['M']}", "-", "-",
          f"{msm['seconds']:.1f} (with run)")]) + [(
          SAMPLER[lik], f"{pr.samples.shape[0]} chains x {info['iters']} iter. x {n} steps",
          "-", "-", f"{sec:.1f} (with run)")
         for lik, (pr, sec, n, info) in res["pmmh"].items()], head=("filter", "size", "ms per run-step", "run [s]", "compile [s]"))


def drive_markdown(res):
    """Every table of the drive study, by name (markdown strings; ``pmmh`` a list of lines)."""
    rows_mpf, yaw_rows = drive_tables(res)
    md1 = _table(rows_mpf, head=("quantity", f"MPF mean over {res['R']} executions",
                                 "MPF spread", "EKF (Remark 1)"))
    md2 = _table(yaw_rows, head=("yaw rate vs pose reference", "RMS [deg/s]", "max [deg/s]",
                                 "share within 0.5 deg/s"))
    md3 = _table(vy_rows(res), head=("lateral velocity vs pose", "RMS [m/s]", "max [m/s]"))
    md_scale = _table(scale_rows(res), head=("rolling-radius mismatch eps", "[1e-4]", "note"))
    md_smooth = _table(smoothed_rows(res), head=(
        "smoothed over the drive (extended RTS, augmented EKF)", "mean over the drive",
        "range over time", "2 std (middle of the drive)", "online EKF, end"))
    msm = res["mpf_smooth"]
    md_mpf_smooth = "" if msm is None else _table(mpf_smoothed_rows(res), head=(
        f"smoothed over the drive (MPF, N = {res['N']}, M = {msm['M']}, "
        f"{msm.get('method', 'ancestor')})",
        "mean over the drive", "range over time", "2 std (middle of the drive)",
        "MPF, end (mean over executions)"))
    return dict(yaw_rows=yaw_rows, md1=md1, md2=md2, md3=md3, scale=md_scale, smooth=md_smooth,
                mpf_smooth=md_mpf_smooth, pmmh=pmmh_markdown(res), cost=cost_table(res))


def print_drive(res, tables):
    """The drive study's tables on stdout."""
    dur = res["T"] * 0.01
    print()
    print(f"Drive: {dur:.1f} s, after the transient (t > {res['t'][res['k_tr']]:.0f} s)")
    for key in ("md1", "md2", "md3", "scale", "smooth", "mpf_smooth"):
        print(tables[key])
        print()
    print("\n".join(tables["pmmh"]))
    print(tables["cost"])


def _pmmh_intro(res):
    """The offline reference's opening paragraph (or the line saying it was skipped)."""
    if not res["pmmh"]:
        return "Skipped (`--pmmh-iters 0`).\n"
    return ("`vehjax.calibrate.pmmh` on the planar single-track model (`pmmh_model`: the steering "
            "offset and eps as parameters, ay and gyro biases, the three sensor stds and the "
            "steering-noise std; priors in `pmmh_priors`), raw r_virt; chains vmapped, split "
            "R-hat and ESS over the kept draws. All chains start at the online estimates (the "
            "smoothed EKF's offset and biases, the causal eps, the MPF's stds, r_virt's residual "
            "std). Each chain's random walk is adapted over its warm-up (the covariance of "
            "the pooled draws in windows of doubling length, a scale tuned toward the optimal "
            "acceptance rate; `vehjax.calibrate.pmmh`) and fixed after it. Each sampler's line "
            f"states whether split R-hat < {RHAT_MAX} and ESS >= {ESS_MIN} for every quantity; "
            "where not, its numbers are not yet a posterior. The exact-likelihood chain is the "
            "reference on this linear model.\n")


def _scale_paragraph(args, res):
    """The report's paragraph on the virtual yaw rate's scale and gate."""
    return (f"Mode `--rvirt-scale {res['mode']}`. " + _SCALE_TEXT[res["mode"]] +
            f" {res['n_gated']} r_virt samples more than {args.rvirt_gate:g} deg/s from the gyro "
            "(wheel-speed bursts) are treated as missing by every filter."
            f" The raw r_virt reads {res['rvirt_raw_off'] / DEG:+.3f} deg/s off the pose on "
            f"average; offline least squares of gyro - r_virt on (1, -vx / l_T) (sensors only) "
            f"gives eps = {res['eps']:+.3e} and the gyro's bias {res['gyro_bias_ls'] / DEG:+.4f} "
            f"deg/s (l_T = {TRACK} m).\n")


def drive_report(args, res, tables):
    """report.md's lines for the drive study, figures apart."""
    dur = res["T"] * 0.01
    return [
        "# vehjax reproduce berntorp2018 --drive (experiments, sec. 5)\n", f"{PAPER}.\n",
        f"The shipped comma2k19 RAV4 segment, {dur:.1f} s of highway at 8-20 m/s with little "
        f"steering. Variant `{res['variant']}` ({_VARIANT_TEXT[res['variant']]}); "
        f"N = {res['N']}, lambda = "
        f"0.999, kalman_states = {args.kalman_states!r}, {res['R']} executions in one `vehjax.run` call (same data, different keys). "
        "Beside it Remark 1's common approach: an EKF "
        "on the single-track model with the steering offset and the ay and gyro biases as "
        "random-walk states, fixed noise covariances (the MPF's initial guesses).\n",
        f"Transient: the first {res['t'][res['k_tr']]:.0f} s are left out of every number.\n",
        "## Offset, biases, stds\n", tables["md1"], "",
        "## Virtual yaw rate's scale\n", _scale_paragraph(args, res), tables["scale"], "",
        "## Smoothed offset, biases and bank over the drive\n",
        "`vehjax.smooth` (extended RTS) of the augmented EKF, whose offset, biases and eps are "
        "random-walk states: the estimate of each at every time given the whole drive.\n",
        tables["smooth"], "",
        *_mpf_smooth_text(res, tables["mpf_smooth"]),
        "## Offline reference: particle marginal Metropolis-Hastings (sec. 5, ref. [28])\n",
        _pmmh_intro(res), *tables["pmmh"],
        "## Bias-corrected yaw rate against the pose reference (Fig. 9, 12), after 15 s\n",
        tables["md2"], "",
        "## Lateral velocity against the pose (after 15 s)\n",
        "The pose's vy is the camera's lateral velocity in the car frame (mount estimated so "
        "that its mean is zero), so only its variation is a check.\n", tables["md3"], "",
        "## Cost\n", "Compiled run time (vehjax.run's path, results copied to host), compile "
        "apart; CPU shared with other jobs, so times are upper bounds. "
        "`vehjax bench marginalized` times the filter properly.\n", tables["cost"], "",
        "## What holds, what cannot be told\n", _drive_verdict(res, tables["yaw_rows"]), ""]
