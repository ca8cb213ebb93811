"""``vehjax reproduce dutta2019``'s presentation: how the study's results are read and shown
(tables, the summaries written from the numbers, figures, ``report.md``) and its command line.

The study itself (settings, excitations, runs, filters, the two stages) is
:mod:`vehjax.reproduce.dutta2019.study`; the package lends both modules' names. What the
reproductions' reports share (markdown rows, figure links, report.md, run counts, timings) is
:mod:`vehjax.reproduce.reporting`.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import jax
import numpy as np

from .. import reporting
from . import study as _study
from .study import (
    _FILTERS,
    _FREQUENCIES,
    _SETTINGS,
    _TUNE_DURATION,
    _TUNE_RUNS,
    BOX_PRIOR,
    CHIRP_TRUTH,
    DYNAMIC_SETTINGS,
    KINEMATIC_SETTINGS,
    PAPER,
    PAPER_TABLE1,
    PAPER_TABLE2,
    PAPER_TABLE3,
    SIM_STD,
    SMOOTHED,
    Stage,
    Tuning,
    _final,
    _ok,
    _window,
    initial_estimates,
)

SMOOTHED_NOTE = ("Rows \"RTS-smoothed (vehjax, offline)\": the same filter's own RTS smoother "
                 "(`vehjax.run(..., smooth=True)`) on the same runs, each estimate from all of "
                 "the run's data, past and future: an offline estimate, not comparable with the "
                 "paper's filters, which use the data up to each step only.")


# ----------------------------------------------------------------------------------------------
# Tables and the summaries written from the numbers


def table_consistency(stage: Stage) -> str:
    """Markdown table: is each filter's reported uncertainty right?

    Per filter: the share of steps at which the run-averaged NEES of the states (truth from the
    simulation, nx degrees of freedom) and the NIS (``n_obs`` degrees of freedom) lie in their
    95 % chi-square band (:func:`vehjax.metrics.consistency`), the mean NEES / nx and NIS per
    degree of freedom (1 = consistent; > 1 over-confident, < 1 under-confident), and per
    parameter the share of runs whose true value lies in the final 95 % interval
    (estimate +- 1.96 sqrt(params_cov)); diverged runs are left out.
    """
    from ...metrics import consistency, nees

    names = ", ".join(stage.names)
    lines = [f"| filter | NEES in band | mean NEES / nx | NIS in band | mean NIS / dof | "
             f"truth in 95 % interval ({names}) |", "|---|---|---|---|---|---|"]
    X = np.asarray(stage.sim.states)
    nx = X.shape[-1]
    for name, res in stage.results.items():
        keep = ~np.asarray(res.diverged, bool)
        e = nees(res.states, res.covariances, X)
        ce = consistency(e, nx, mask=keep)
        cn = consistency(res.nis, res.n_obs, mask=keep)
        dof = np.where(res.n_obs > 0, res.n_obs, np.nan)
        nis_rate = np.nanmean((res.nis / dof)[keep]) if keep.any() else np.nan
        sd = np.sqrt(np.diagonal(res.params_cov[:, -1], axis1=-2, axis2=-1))
        inside = np.abs(res.params[:, -1] - stage.truth) <= 1.96 * sd
        cover = ", ".join(f"{v:.2f}" for v in inside[keep].mean(axis=0)) if keep.any() else "-"
        lines.append(f"| {name} | {ce.inside:.2f} | {np.nanmean(e[keep]) / nx:.3g} | "
                     f"{cn.inside:.2f} | {nis_rate:.3g} | {cover} |")
    return "\n".join(lines)


def _report_consistency(report: list, stage: Stage, what: str, setting: str) -> None:
    report += [f"### Consistency, {what} ({setting} settings)",
               "Share of steps with the run-averaged NEES / NIS inside the 95 % chi-square "
               "band (a consistent filter: about 0.95), their mean per degree of freedom "
               "(1 = consistent, > 1 over-confident, < 1 under-confident), and the share of runs "
               "whose true parameter lies in the final 95 % interval (about 0.95 if the "
               "parameter covariance is right).\n", table_consistency(stage), ""]


#: "not learned": on average over runs the final estimate lies within this fraction of the
#: initial guesses' spread (std over runs) of the run's own guess; its mean and spread over runs
#: are then the guesses' mean and spread to within the same fraction.
NOT_LEARNED_FRACTION = 0.1
#: state-RMSE rows that agree to this relative tolerance are "the same"
SAME_RMSE_RTOL = 0.01



def _unit(u, s=1.0):
    """The unit of a column, ``[m]`` or ``[1e4 N]``."""
    from ...plots import label

    return label("", u, s).strip()


def _names_and(names) -> str:
    names = list(names)
    return names[0] if len(names) == 1 else ", ".join(names[:-1]) + " and " + names[-1]


def table_parameters(stage: Stage, paper: dict, dt: float, tol, digits, scale=None, window=None):
    """Markdown table: the initial guesses and each filter's final estimate as mean +- std over
    runs (mean absolute error), convergence time, the paper's value."""
    from ... import metrics

    names = stage.names
    scale = np.ones(len(names)) if scale is None else np.asarray(scale)
    cols = [f"{n} {_unit(u, s)}" for n, u, s in zip(names, stage.param_units, scale)]
    head = "| filter | " + " | ".join(cols)
    head += " | " + " | ".join(f"t_conv {n} [s]" for n in names) + " | diverged |"
    blank = " |" * len(names) + " |"
    lines = [head, reporting.md_rule(2 * len(names) + 2)]
    lines.append("| truth | " + " | ".join(f"{v / s:.{d}f}" for v, s, d in zip(stage.truth, scale, digits))
                 + " |" + blank)
    g = np.asarray(stage.theta0) / scale
    g_err = np.abs(g - stage.truth / scale).mean(axis=0)
    lines.append("| initial guess | " + " | ".join(
        f"{reporting.pm(g[:, j].mean(), g[:, j].std(), d)} ({g_err[j]:.{d}f})"
        for j, d in enumerate(digits)) + " |" + blank)
    for name in (n for n in BOX_PRIOR if n in stage.results):
        c = np.asarray(stage.box, float).mean(axis=1) / scale
        lines.append(f"| {name} prior mean (box centre) | " + " | ".join(
            f"{c[j]:.{d}f} ({abs(c[j] - stage.truth[j] / scale[j]):.{d}f})"
            for j, d in enumerate(digits)) + " |" + blank)
    for name, res in stage.results.items():
        ok = _ok(res)
        w = window or _window(res)
        fin = _final(res.params, w)[ok] / scale
        conv = metrics.convergence_time(res.params, stage.truth[None, None, :], tol, dt, mask=ok)
        conv_s = []
        for j in range(len(names)):
            c = conv[ok, j]
            n_conv = int(np.sum(np.isfinite(c)))
            med = np.median(c[np.isfinite(c)]) if n_conv else np.inf
            conv_s.append(f"{med:.1f} ({n_conv}/{ok.sum()})" if n_conv else f"never (0/{ok.sum()})")
        err = np.abs(fin - stage.truth / scale)
        cells = [f"{reporting.pm(fin[:, j].mean(), fin[:, j].std(), d)} ({err[:, j].mean():.{d}f})"
                 if len(fin) else "-" for j, d in enumerate(digits)]
        lines.append(f"| {name} (vehjax) | " + " | ".join(cells) + " | " + " | ".join(conv_s)
                     + f" | {int((~ok).sum())}/{len(ok)} |")
        if name in paper:
            lines.append(f"| {name} (paper) | "
                         + " | ".join(f"{v / s:.{d}f}" for v, s, d in zip(paper[name], scale, digits))
                         + " |" + blank)
    return "\n".join(lines)


def learning(stage: Stage, tol, window=None) -> dict:
    """Per parameter and filter, what the filter made of its initial guesses.

    Returns {parameter: {filter: (verdict, guess error, final error, moved)}} with verdict one of
    "learned" (final mean absolute error within ``tol``), "drifted" (a BOX_PRIOR filter whose
    prior centre, its initial estimate, is the truth, ending farther than ``tol``), "not
    learned" (each run's final
    estimate within NOT_LEARNED_FRACTION of the prior's spread, the std of the box the guesses
    are drawn from, of the filter's own initial estimate in that run, on average),
    "partly" (error reduced, not to ``tol``), "worse" (error grew); errors are mean absolute
    errors over the filter's converged runs, ``moved`` the mean |final - guess| over runs, all
    in the parameter's units. Filters whose every run diverged are left out.
    """
    tol = np.broadcast_to(np.asarray(tol, dtype=float), (len(stage.names),))
    out = {}
    for j, pname in enumerate(stage.names):
        verdicts = {}
        for fname, res in stage.results.items():
            ok = _ok(res)
            if not ok.any():
                continue
            fin = _final(res.params, window or _window(res))[ok, j]
            guess = initial_estimates(stage, fname)[ok, j]
            spread = max(float(np.diff(np.asarray(stage.box, float)[j])[0]) / np.sqrt(12.0),
                         1e-12 * abs(stage.truth[j]))
            e0 = float(np.mean(np.abs(guess - stage.truth[j])))
            e1 = float(np.mean(np.abs(fin - stage.truth[j])))
            moved = float(np.mean(np.abs(fin - guess)))
            # a box-prior filter whose prior centre is the truth starts at the truth: staying
            # there is not a sign of not learning, and its point estimates cannot show learning
            at_truth = np.all(np.abs(guess - stage.truth[j]) <= 1e-9 * max(1.0, abs(stage.truth[j])))
            if moved <= NOT_LEARNED_FRACTION * spread and not at_truth:
                verdict = "not learned"
            elif e1 <= tol[j]:
                verdict = "learned"
            elif at_truth:
                verdict = "drifted"
            elif e1 < e0:
                verdict = "partly"
            else:
                verdict = "worse"
            verdicts[fname] = (verdict, e0, e1, moved)
        out[pname] = verdicts
    return out


def learning_summary(stage: Stage, tol, tol_text: str, scale=None, digits=None, window=None) -> str:
    """Markdown paragraph, written from the numbers: which parameter each filter learned, which
    it only moved part of the way, and which it left at its initial guess."""
    n = len(stage.names)
    scale = np.ones(n) if scale is None else np.asarray(scale)
    digits = (3,) * n if digits is None else digits
    verdicts = learning(stage, tol, window)
    lines = [f"**What is learned and what is not.** Per parameter, the mean absolute error over "
             f"runs of the initial guesses and of the final estimates (learned: within "
             f"{tol_text}; not learned: the final estimate stays, on average, within "
             f"{100 * NOT_LEARNED_FRACTION:.0f} % of the prior's spread (the std of the box the "
             "guesses are drawn from) of the run's own initial estimate)."]
    box = np.asarray(stage.box, float)
    centre_is_truth = np.allclose(box.mean(axis=1), stage.truth, rtol=1e-9, atol=0.0)
    box_filters = [f for f in BOX_PRIOR if f in stage.results]
    if box_filters and centre_is_truth:
        lines[-1] += (f" {_names_and(box_filters)} starts from the centre of its prior box, not "
                      "from the guesses; that centre is the truth here, so its error can only "
                      "grow and its point estimates cannot show what it learned.")
    lines[-1] += "\n"
    for j, pname in enumerate(stage.names):
        s, d, u = scale[j], digits[j], _unit(stage.param_units[j], scale[j])
        v = verdicts[pname]
        if not v:
            lines.append(f"- {pname}: every run of every filter diverged.")
            continue
        g_all = np.asarray(stage.theta0)[:, j]
        e0 = float(np.mean(np.abs(g_all - stage.truth[j]))) / s
        by = {k: [f for f, x in v.items() if x[0] == k]
              for k in ("learned", "partly", "worse", "drifted", "not learned")}
        parts = []
        if by["learned"]:
            parts.append("learned by " + _names_and(
                f"{f} ({v[f][2] / s:.{d}f})" for f in by["learned"]))
        if by["partly"]:
            parts.append("partly learned by " + _names_and(
                f"{f} ({v[f][2] / s:.{d}f}, {100 * (1 - v[f][2] / v[f][1]):.0f} % of the error "
                "removed)"
                for f in by["partly"]))
        if by["worse"]:
            parts.append("moved away from the truth by " + _names_and(
                f"{f} ({v[f][2] / s:.{d}f})" for f in by["worse"]))
        if by["drifted"]:
            parts.append("drifted off the truth it started from by " + _names_and(
                f"{f} ({v[f][2] / s:.{d}f})" for f in by["drifted"]))
        if by["not learned"]:
            moved = max(v[f][3] for f in by["not learned"]) / s
            every = len(by["not learned"]) == len(v)
            who = ("any filter" if every and len(v) > 1 else _names_and(by["not learned"]))
            spread = float(np.diff(np.asarray(stage.box, float)[j])[0]) / np.sqrt(12.0) / s
            guessed = [f for f in by["not learned"] if f not in BOX_PRIOR]
            text = (f"**not learned by {who}**: the final estimates stay at the initial "
                    f"estimates (moved {moved:.{d}f} on average, against a prior spread of "
                    f"{spread:.{d}f})")
            if guessed:
                g = g_all / s
                text += (f", so the mean +- std over runs in the table for {_names_and(guessed)} "
                         f"is essentially the initial guesses' {reporting.pm(g.mean(), g.std(), d)}, "
                         "not a result of the data")
            parts.append(text)
        notes = []
        for f in (f for f in BOX_PRIOR if f in v and not centre_is_truth):
            c = float(np.asarray(stage.box, float)[j].mean())
            notes.append(f"{f} starts from its prior's centre {c / s:.{d}f}, not from the guesses")
        lines.append(f"- **{pname}** {u} (guess error {e0:.{d}f}): " + "; ".join(parts) + "."
                     + (" " + "; ".join(notes) + "." if notes else ""))
    return "\n".join(lines)


def _raw_rmse(stage: Stage):
    """RMSE of the raw measurements against the true states, when each output is a state."""
    from ... import metrics

    sim = stage.sim
    if tuple(sim.output_names) != tuple(sim.state_names):
        return None
    return np.asarray(metrics.rmse(sim.measurements, sim.states))


def table_states(stage: Stage, paper: dict):
    """Markdown table: state RMSE over all runs and steps with its 95 % interval over runs, and
    the raw measurements' RMSE when the states are measured."""
    from ... import metrics

    names = stage.sim.state_names
    lines = ["| filter | " + " | ".join(f"RMSE {n} {_unit(u)}" for n, u in zip(names, stage.state_units))
             + " |", reporting.md_rule(len(names) + 1)]
    raw = _raw_rmse(stage)
    if raw is not None:
        lines.append("| raw measurements | " + " | ".join(f"{v:.4f}" for v in raw) + " |")
    def row(label, res):
        ok = _ok(res)
        per_run = metrics.rmse(res.states, stage.sim.states, axis="run", mask=ok)
        ci = metrics.confidence_interval(per_run, mask=ok)
        total = metrics.rmse(res.states, stage.sim.states, mask=ok) if ok.any() else [np.nan] * 3
        lines.append(f"| {label} | " + " | ".join(f"{v:.4f} [{lo:.4f}, {hi:.4f}]"
                                                  for v, lo, hi in zip(total, ci.low, ci.high))
                     + " |")

    for name, res in stage.results.items():
        row(f"{name} (vehjax)", res)
        if name in (stage.smoothed or {}):
            row(f"{name} {SMOOTHED} (vehjax, offline)", stage.smoothed[name])
        if name in paper:
            lines.append(f"| {name} (paper) | " + " | ".join(f"{v:.4f}" for v in paper[name]) + " |")
    return "\n".join(lines)


def state_rmse(stage: Stage) -> dict:
    """Filter -> (nx,) state RMSE over its converged runs and all steps (filters with any)."""
    from ... import metrics

    return {name: np.asarray(metrics.rmse(res.states, stage.sim.states, mask=_ok(res)))
            for name, res in stage.results.items() if _ok(res).any()}


def smoothed_summary(stage: Stage) -> str:
    """One sentence from the numbers: for each smoothed filter, its smoothed state RMSE over its
    filtered one (both over the runs where both converged)."""
    from ... import metrics

    parts = []
    for name, sm in (stage.smoothed or {}).items():
        res = stage.results[name]
        ok = _ok(res) & _ok(sm)
        if not ok.any():
            parts.append(f"{name}: every run diverged")
            continue
        ratio = (np.asarray(metrics.rmse(sm.states, stage.sim.states, mask=ok))
                 / np.asarray(metrics.rmse(res.states, stage.sim.states, mask=ok)))
        parts.append(f"{name} " + ", ".join(f"{n} {r:.2f}"
                                             for n, r in zip(stage.sim.state_names, ratio)))
    return "Smoothed over filtered state RMSE: " + "; ".join(parts) + "."


def same_rmse_groups(rmse: dict, rtol: float = SAME_RMSE_RTOL) -> list:
    """Groups (lists of two or more filter names) whose state RMSE rows agree within ``rtol``."""
    groups, left = [], list(rmse)
    while left:
        first = left.pop(0)
        same = [f for f in left if np.allclose(rmse[f], rmse[first], rtol=rtol, atol=0.0)]
        left = [f for f in left if f not in same]
        if same:
            groups.append([first] + same)
    return groups


def states_summary(stage: Stage, tol=None) -> str:
    """Markdown paragraph, written from the numbers: which filters' state RMSE rows are the same
    and how the estimates compare with the raw measurements. With ``tol`` (the parameters'
    "learned" tolerance) it also says when equal rows come from filters that learned the
    parameters differently."""
    rmse = state_rmse(stage)
    if not rmse:
        return "**State RMSE.** Every run of every filter diverged."
    names = stage.sim.state_names
    out = []
    groups = same_rmse_groups(rmse)
    differ = False
    if tol is not None:
        verdicts = learning(stage, tol)
        differ = any(len({v[0] for v in per.values()}) > 1 for per in verdicts.values())
    if len(groups) == 1 and len(groups[0]) == len(rmse) and len(rmse) > 1:
        out.append(f"**State RMSE: every filter alike.** All {len(rmse)} filters have the same "
                   f"state RMSE (within {100 * SAME_RMSE_RTOL:g} %)"
                   + (f", although they learned {_names_and(stage.names)} differently (below): "
                      "in these settings the state estimates do not depend on the parameter "
                      "estimates" if differ else "")
                   + "; this table does not tell the filters apart.")
    elif groups:
        out.append("**State RMSE.** " + "; ".join(
            f"{_names_and(g)} have the same state RMSE (within {100 * SAME_RMSE_RTOL:g} %)"
            for g in groups)
            + ": this table does not tell them apart.")
    else:
        out.append("**State RMSE.** The filters' state RMSE rows differ.")
    raw = _raw_rmse(stage)
    if raw is not None:
        ratios = np.array(list(rmse.values())) / raw
        spans = [f"{n} {lo:.2f}" if abs(hi - lo) < 0.005 else f"{n} {lo:.2f}-{hi:.2f}"
                 for n, lo, hi in zip(names, ratios.min(0), ratios.max(0))]
        out.append("Estimate RMSE over raw-measurement RMSE (1: no better than the sensors): "
                   + ", ".join(spans) + ".")
    return " ".join(out)


def frequency_table(freq_results: dict, truth, dt: float, tol: float, units=("m", "m")):
    from ... import metrics

    lines = [f"| steering frequency [Hz] | final lf {_unit(units[0])} | final lr {_unit(units[1])} "
             "| t_conv lf [s] | t_conv lr [s] |",
             "|---|---|---|---|---|"]
    for f, res in freq_results.items():
        ok = _ok(res)
        fin = _final(res.params, _window(res))[ok]
        conv = metrics.convergence_time(res.params, np.asarray(truth)[None, None], tol, dt, mask=ok)[ok]
        med = [np.median(c) if np.all(np.isfinite(c)) else
               (np.median(c[np.isfinite(c)]) if np.isfinite(c).any() else np.inf) for c in conv.T]
        err = np.abs(fin - np.asarray(truth)).mean(axis=0)
        conv_s = [f"{c:.1f}" if np.isfinite(c) else "never" for c in med]
        lines.append(f"| {f:g} | {reporting.pm(fin[:, 0].mean(), fin[:, 0].std(), 3)} ({err[0]:.3f}) | "
                     f"{reporting.pm(fin[:, 1].mean(), fin[:, 1].std(), 3)} ({err[1]:.3f}) | "
                     f"{conv_s[0]} | {conv_s[1]} |")
    return "\n".join(lines)


def table_noise(tuning: Tuning, paper: dict, model) -> str:
    """Markdown table: per component the paper's, the tuned and the simulation's (matched)
    variance of Q (process, per step) and R (measurement), and tuned over simulation.

    Parameters
    ----------
    tuning : Tuning
        The tuned setting of the stage (:func:`tuned_settings`).
    paper : dict
        The paper's settings of the stage; ``paper["Q"]`` (nx,), ``paper["R"]`` (ny,).
    model : vehjax model
        The stage's model (names; ``dt`` [s] for the simulation's Q per step).

    Returns
    -------
    str
        One row per state (Q) and per output (R), variances in the component's unit squared.
    """
    fit = tuning.fit
    lines = ["| covariance | paper | tuned | simulation (matched) | tuned / simulation |",
             "|---|---|---|---|---|"]
    sim_var = {"Q": SIM_STD**2 * model.dt, "R": SIM_STD**2}
    for which, names in (("Q", model.state_names), ("R", model.output_names)):
        for i, n in enumerate(names):
            key = f"{which}[{n},{n}]"
            tuned = float(tuning.settings[which][i])
            lines.append(f"| {which} {n} [{fit.units[key]}] | {paper[which][i]:.3g} | "
                         f"{tuned:.3g} | {sim_var[which]:.3g} | {tuned / sim_var[which]:.2f} |")
    return "\n".join(lines)


def tuning_summary(tuning: Tuning, truth, units, scale=None, digits=None, fixed_note="") -> str:
    """Markdown paragraph: the training set and what the fit did (parameters from their start
    to their fitted values, the loss, iterations, time).

    Parameters
    ----------
    tuning : Tuning
        The tuned setting of the stage.
    truth : array_like
        (p,) true values of ``tuning.names``.
    units : sequence of str
        (p,) their units.
    scale : array_like, optional
        (p,) divisors for printing (e.g. 1e4 for N); default ones.
    digits : sequence of int, optional
        (p,) decimals printed; default 3.
    fixed_note : str
        Where the values of ``tuning.fixed`` come from.

    Returns
    -------
    str
    """
    fit, sim = tuning.fit, tuning.sim
    n_runs, T = np.shape(sim.measurements)[:2]
    n = len(tuning.names)
    scale = np.ones(n) if scale is None else np.asarray(scale, float)
    digits = (3,) * n if digits is None else digits
    params = ", ".join(
        f"{p} {_unit(u, s)} {a / s:.{d}f} -> {fit.params[p] / s:.{d}f} (truth {t / s:.{d}f})"
        for p, u, s, d, a, t in zip(tuning.names, units, scale, digits, tuning.start, truth))
    held = ""
    if tuning.fixed:
        held = (" Held fixed in the fit: "
                + ", ".join(f"{k} {v:.3f}" for k, v in tuning.fixed.items())
                + (f" ({fixed_note})" if fixed_note else "") + ".")
    loss_end = -fit.loglik / (n_runs * T)
    return (f"**How Q and R were tuned.** Training set: {n_runs} runs x {T} steps "
            f"({T * fit.model.dt:g} s) of the same model, noise "
            "and excitation as the study, simulated from a random stream of their own (not the "
            "study's runs). vehjax.tune.fit (UKF, maximum likelihood, adam) started from the "
            "paper's Q and R and fitted them (diagonal) jointly with the unknown parameters, "
            f"started from a guess drawn from the prior box: {params}.{held} Loss (negative "
            f"log-likelihood per step) {fit.history[0]:.3f} -> {loss_end:.3f} in "
            f"{fit.iterations} iterations ({'stopped early' if fit.converged else 'at the limit'}"
            f"), {fit.seconds:.0f} s. The study's filters then run with the tuned Q and R on the "
            "study's runs; P0 is the paper's, Q_theta and P_theta0 as in the matched setting.")


def _mean_abs_error(stage: Stage, name: str) -> np.ndarray:
    """(p,) mean absolute error over the filter's converged runs of its final estimates."""
    res = stage.results[name]
    ok = _ok(res)
    if not ok.any():
        return np.full(len(stage.names), np.nan)
    return np.abs(_final(res.params, _window(res))[ok] - stage.truth).mean(axis=0)


def table_settings(stages: dict, scale=None, digits=None) -> str:
    """Markdown table: per filter and setting, the final estimates' mean absolute error over
    runs (converged runs) and how many runs diverged.

    Parameters
    ----------
    stages : dict
        Setting name -> Stage, all on the same runs with the same filters.
    scale : array_like, optional
        (p,) divisors of the parameters for printing; default ones.
    digits : sequence of int, optional
        (p,) decimals printed; default 3.

    Returns
    -------
    str
        Rows (filter, setting), errors in the parameters' units divided by ``scale``.
    """
    first = next(iter(stages.values()))
    n = len(first.names)
    scale = np.ones(n) if scale is None else np.asarray(scale, float)
    digits = (3,) * n if digits is None else digits
    lines = ["| filter | setting | " + " | ".join(
        f"error {p} {_unit(u, s)}" for p, u, s in zip(first.names, first.param_units, scale))
        + " | diverged |", reporting.md_rule(n + 3)]
    for name in first.results:
        for setting, st in stages.items():
            err = _mean_abs_error(st, name) / scale
            div = np.asarray(st.results[name].diverged)
            lines.append(f"| {name} | {setting} | " + " | ".join(
                "-" if not np.isfinite(e) else f"{e:.{d}f}" for e, d in zip(err, digits))
                + f" | {int(div.sum())}/{len(div)} |")
    return "\n".join(lines)


def table_settings_states(stages: dict) -> str:
    """Markdown table: per filter and setting, the state RMSE over its converged runs and all
    steps, in the states' units.

    Parameters
    ----------
    stages : dict
        Setting name -> Stage, all on the same runs with the same filters.

    Returns
    -------
    str
    """
    first = next(iter(stages.values()))
    names = first.sim.state_names
    lines = ["| filter | setting | " + " | ".join(
        f"RMSE {n} {_unit(u)}" for n, u in zip(names, first.state_units)) + " |",
        reporting.md_rule(len(names) + 2)]
    for name in first.results:
        for setting, st in stages.items():
            r = state_rmse(st).get(name)
            cells = ["-"] * len(names) if r is None else [f"{v:.4f}" for v in r]
            lines.append(f"| {name} | {setting} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


# ----------------------------------------------------------------------------------------------
# Figures


def _runs_text(results: dict) -> str:
    """'10 runs' or '10 runs, 2 diverged run(s) left out' over a dict of results."""
    runs = max(len(np.asarray(r.diverged)) for r in results.values())
    return reporting.runs_text(runs, sum(int(np.sum(r.diverged)) for r in results.values()))


def plot_parameters(stage: Stage, path, title: str, scale=None, tol=None):
    """Small multiples: one row per parameter, one column per filter; mean and 5-95 % band of
    the estimate over runs, the truth on top. With ``tol`` each panel names the verdict of
    :func:`learning` when it is not "learned"."""
    from ... import plots

    n = len(stage.names)
    scale = np.ones(n) if scale is None else np.asarray(scale)
    filters = list(stage.results)
    series = [[(res.params[_ok(res), :, j] / scale[j]) if _ok(res).any() else None
               for res in stage.results.values()] for j in range(n)]
    rows = [plots.label(p, u, s) for p, u, s in zip(stage.names, stage.param_units, scale)]
    notes = None
    if tol is not None:
        verdicts = learning(stage, tol)
        text = {"not learned": "not learned: stays at its guess", "partly": "partly learned",
                "worse": "moved away from truth",
                "drifted": "starts at truth (prior centre), drifts off"}
        notes = [[text.get(verdicts[p].get(f, ("",))[0], "") for f in filters] for p in stage.names]
    return plots.plot_band_grid(path, stage.sim.t, series, rows, filters,
                                f"{title}, {_runs_text(stage.results)}",
                                truth=[v / s for v, s in zip(stage.truth, scale)], notes=notes)


def plot_states(stage: Stage, path, title: str, window_s: float = 1.0):
    """Row per state. Left: the truth of run 0 (on top) and each filter's estimate of it. Then
    one column per filter: its RMS error over a moving ``window_s`` window, mean and 5-95 %
    band over runs, with the raw measurements' RMS error (grey) when the state is measured."""
    from ... import plots
    from ...plots import plt

    t = np.asarray(stage.sim.t)
    names = stage.sim.state_names
    filters = list(stage.results)
    n_rows, n_cols = len(names), 1 + len(filters)
    fig, axes = plt.subplots(n_rows, n_cols, figsize=(1.2 + 3.0 * n_cols, 1.4 + 2.3 * n_rows),
                             sharex=True, squeeze=False)
    cyc = plots.colors()
    truth = np.asarray(stage.sim.states)
    window = reporting.window_steps(t, window_s)
    raw = None
    if tuple(stage.sim.output_names) == tuple(names):
        raw = plots.moving_rms(np.moveaxis(np.asarray(stage.sim.measurements) - truth, -1, 1), window)
    for i, (n, u) in enumerate(zip(names, stage.state_units)):
        ax = axes[i, 0]
        n_f = len(filters)
        for k, (name, res) in enumerate(stage.results.items()):  # first thickest: overlaps show
            ax.plot(t, res.states[0, :, i], color=cyc[k % len(cyc)], label=name,
                    lw=reporting.line_width(k, n_f, 0.7, 1.3))
        plots.truth_line(ax, t, truth[0, :, i], label="truth")
        ax.set_ylabel(plots.label(n, u))
        for k, (name, res) in enumerate(stage.results.items()):
            ax = axes[i, 1 + k]
            if k:
                ax.sharey(axes[i, 1])
            ok = _ok(res)
            if raw is not None:
                ax.plot(t, raw[:, i].mean(axis=0), color="0.55", lw=1.0, ls=":",
                        label="raw measurements (mean over runs)", zorder=5)
            if ok.any():
                plots.band(ax, t, plots.moving_rms(res.states[ok, :, i] - truth[ok, :, i], window),
                           cyc[k % len(cyc)])
            ax.set_ylim(bottom=0)
            ax.set_ylabel(plots.label(f"RMS error {n}", u) if k == 0 else "")
        for ax in axes[i]:
            ax.grid(alpha=0.3)
    axes[0, 0].set_title("run 0: truth and estimates", fontsize=10)
    for k, name in enumerate(filters):
        axes[0, 1 + k].set_title(f"{name}: RMS error over {window_s:g} s", fontsize=10)
    for ax in axes[-1]:
        ax.set_xlabel("t [s]")
    plots.figure_legend(fig, axes, f"{title}, {_runs_text(stage.results)}",
                        extra=plots.band_handles("over runs of the RMS error"))
    return plots.save(fig, path)




def plot_frequency(freq_results: dict, t, truth, path, units=("m", "m"), title: str = ""):
    """Small multiples: rows lf, lr; one column per steering frequency; the Dual UKF's mean and
    5-95 % band over runs, the truth on top."""
    from ... import plots

    freqs = list(freq_results)
    series = [[res.params[_ok(res), :, j] if _ok(res).any() else None for res in freq_results.values()]
              for j in range(2)]
    rows = [plots.label(n, u) for n, u in zip(("lf", "lr"), units)]
    head = title or "Dual UKF on the kinematic model: effect of the steering frequency"
    return plots.plot_band_grid(path, t, series, rows, [f"steering sine {f:g} Hz" for f in freqs],
                                f"{head}, {_runs_text(freq_results)}", truth=list(truth))


def _figure(report: list, path: Path, caption: str) -> Path:
    """Add a markdown link to ``path`` (written next to report.md) under ``caption``."""
    report.append(reporting.figure_link(path, caption))
    return path


# ----------------------------------------------------------------------------------------------
# The report and the command line


def parser():
    """The study's options (``vehjax reproduce dutta2019 --help``); each help states its default."""
    from ... import cli as _cli  # one-line user errors, finite numbers in range

    p = _cli.ArgumentParser(
        prog="vehjax reproduce dutta2019",
        description="Dual EKF, Dual UKF and Liu-West Particle+UKF on the kinematic and the 3-DOF "
                    "dynamic model (Dutta et al. 2019, Tables I-III, Fig. 4-12). Writes report.md, "
                    "which links the figures. A quick run: --runs 10.",
    )
    p.add_argument("--runs", type=_cli.count, default=100, help="Monte-Carlo runs per filter (default %(default)s)")
    p.add_argument("--particles", type=_cli.count, default=1000,
                   help="Particle+UKF particles M (default %(default)s)")
    p.add_argument("--kinematic-duration", type=_cli.positive, default=60.0,
                   help="kinematic stage length, s (default %(default)g)")
    p.add_argument("--dynamic-duration", type=_cli.positive, default=60.0,
                   help="dynamic stage length, s (default %(default)g)")
    p.add_argument("--dt", type=_cli.positive, default=0.02, help="sampling period, s (default %(default)g)")
    p.add_argument("--filters", default=",".join(_FILTERS),
                   help="comma-separated subset of the filters (default all: %(default)s)")
    p.add_argument("--settings", default=",".join(_SETTINGS),
                   help="comma-separated filter settings: paper (section III as printed), "
                        "matched (Q, R of the simulation's noise), tuned (Q, R fitted by "
                        "vehjax.tune by maximum likelihood on separate training runs, "
                        f"{_TUNE_RUNS} per stage of at most {_TUNE_DURATION:g} s, from the "
                        "paper's values; the rest as matched) (default all: %(default)s)")
    p.add_argument("--excitation", choices=("paper", "chirp"), default="paper",
                   help="the dynamic stage's excitation: paper (two-tone steering, 20 m/s, the "
                        "nominal parameters) or chirp (a second excitation with other true "
                        "m, cx, cy; module docstring) (default %(default)s)")
    p.add_argument("--smooth", action=argparse.BooleanOptionalAction, default=True,
                   help="Table II: also the RTS-smoothed states of the filters with a smoother "
                        "(Joint EKF, Joint UKF), on the same runs, as offline rows (default on; "
                        "--no-smooth skips them)")
    p.add_argument("--no-frequency-study", action="store_true",
                   help="skip the Fig. 6 study (default: run it)")
    p.add_argument("--seed", type=_cli.integer, default=0, help="random seed (default %(default)s)")
    p.add_argument("--out", type=_cli.out_folder, default="out/dutta2019",
                   help="folder for report.md and the figures (default %(default)s)")
    return p


_parser = parser


def _say(msg):
    sys.stdout.write(msg)
    sys.stdout.flush()


def _check_args(args):
    filters = reporting.split_names(args.filters)
    unknown = [f for f in filters if f not in _FILTERS]
    if unknown or not filters:
        raise ValueError(f"--filters: unknown {unknown}; expected a subset of {list(_FILTERS)}")
    settings = reporting.split_names(args.settings)
    if not settings or any(x not in _SETTINGS for x in settings):
        raise ValueError(f"--settings: expected a subset of {list(_SETTINGS)}, got {args.settings!r}")
    if args.runs < 2:
        raise ValueError(f"--runs: expected at least 2 runs (spread over runs), got {args.runs}")
    if args.particles < 1:
        raise ValueError(f"--particles: expected at least 1, got {args.particles}")
    for name in ("kinematic_duration", "dynamic_duration", "dt"):
        if not getattr(args, name) > 0:
            raise ValueError(f"--{name.replace('_', '-')}: expected a positive number of seconds")
    for name in ("kinematic_duration", "dynamic_duration"):
        if getattr(args, name) < 2 * args.dt:
            raise ValueError(f"--{name.replace('_', '-')}: expected at least two steps of --dt "
                             f"({args.dt:g} s), got {getattr(args, name):g} s")
    return filters, settings


def _report_tuning(report: list, tuning, paper: dict, model, stage_name: str, units, scale=None,
                   digits=None, fixed_note=""):
    """Add the tuned setting's Q, R beside the paper's and the simulation's, and how."""
    if tuning is None:
        return
    truth = np.asarray(model.theta)[list(model.param_index(tuning.names))]
    report += [f"### Tuned Q and R, {stage_name}",
               tuning_summary(tuning, truth, units, scale, digits, fixed_note) + "\n",
               table_noise(tuning, paper, model), ""]


def _report_kinematic(report: list, st: Stage, freq, setting: str, out: Path, dt: float):
    """Add stage 1's sections (Table I, consistency, Fig. 4-5; Fig. 6 when ``freq``, the
    frequency study of :func:`dutta2019.kinematic_study`) to ``report``; the figures go to
    ``out``."""
    kin = st.model
    truth = np.asarray(kin.theta)
    _report_tuning(report, st.tuning, KINEMATIC_SETTINGS, kin, "kinematic model", st.param_units)
    report += [f"### Table I: lf, lr from the kinematic model ({setting} settings)",
               "Final estimate (mean of the last 10 % of steps) as mean +- std over runs, "
               "(mean absolute error over runs); the initial guesses (row \"initial guess\"; "
               "every filter starts from them but Particle+UKF, whose prior is the box they are "
               "drawn from) are spread evenly around the truth, so the std and the "
               "absolute error, not the mean, show what was learned. t_conv: median time after "
               "which the error stays within 0.05 m (runs that converged). Target: every filter "
               "within 0.05 m.\n",
               table_parameters(st, PAPER_TABLE1, dt, tol=0.05, digits=(3, 3)), "",
               learning_summary(st, 0.05, "0.05 m", digits=(3, 3)), ""]
    _report_consistency(report, st, "kinematic model", setting)
    fig = plot_parameters(st, out / f"fig4_5_kinematic_lf_lr_{setting}.png",
                          f"lf, lr on the kinematic model ({setting} settings)", tol=0.05)
    _figure(report, fig, f"Fig. 4-5: lf, lr against time, each filter's mean and 5-95 % band over "
                         f"runs ({setting} settings)")
    if freq is None:
        return
    units = tuple(kin.param_units[i] for i in kin.param_index(("lf", "lr")))
    report += [f"### Fig. 6: Dual UKF and the steering frequency ({setting} settings)\n",
               frequency_table(freq, truth, dt, 0.05, units), ""]
    fig = plot_frequency(freq, np.asarray(st.sim.t), truth,
                         out / f"fig6_input_frequency_{setting}.png", units,
                         f"Dual UKF on the kinematic model, steering frequency ({setting} settings)")
    _figure(report, fig, f"Fig. 6: lf, lr of the Dual UKF under steering sines of "
                         f"{', '.join(f'{f:g}' for f in _FREQUENCIES)} Hz, mean and 5-95 % "
                         f"band over runs ({setting} settings)")


def _report_dynamic(report: list, st: Stage, setting: str, out: Path, dt: float,
                    excitation: str):
    """Add stage 2's sections (Tables II-III, consistency, Fig. 7-12) to ``report``; the
    figures go to ``out``."""
    model = st.model
    truth = st.truth
    lf_lr_true = np.asarray(model.theta)[list(model.param_index(("lf", "lr")))]
    scale = (1.0, 1e4, 1e4)
    _report_tuning(report, st.tuning, DYNAMIC_SETTINGS, model, "dynamic model", st.param_units,
                   scale=scale, digits=(1, 3, 3),
                   fixed_note="the kinematic training fit's values; truth "
                   + ", ".join(f"{n} {v:.3f}" for n, v in zip(("lf", "lr"), lf_lr_true)))
    report += [f"### Table II: state RMSE on the dynamic model ({setting} settings)",
               "RMSE over all runs and steps, [95 % interval of the per-run RMSE mean]; "
               "\"raw measurements\": the sensors' own RMSE (every state is measured). Target: "
               "Dual UKF at or below the paper's Particle+UKF row.\n",
               table_states(st, PAPER_TABLE2), "", states_summary(st, 0.03 * truth), ""]
    if st.smoothed:
        report += [SMOOTHED_NOTE + " " + smoothed_summary(st), ""]
    fig = plot_states(st, out / f"fig7_9_dynamic_states_{setting}.png",
                      f"Dynamic model states ({setting} settings)")
    _figure(report, fig, f"Fig. 7-9: vx, vy, r of run 0 and each filter's error, mean and 5-95 % "
                         f"band over runs ({setting} settings)")
    report += [f"### Table III: m, cx, cy from the dynamic model ({setting} settings)",
               "As Table I (initial guesses uniform within +-30 % of "
               + ("truth" if excitation == "paper" else "nominal, not centred on the truth")
               + "); t_conv: error within "
               "3 % of truth. Targets: Dual UKF within 3 %, "
               "Particle+UKF within 2 %.\n",
               table_parameters(st, PAPER_TABLE3, dt, tol=0.03 * truth, digits=(1, 3, 3),
                                scale=scale), "",
               learning_summary(st, 0.03 * truth, "3 % of the truth", scale=scale, digits=(1, 3, 3)),
               ""]
    _report_consistency(report, st, "dynamic model", setting)
    fig = plot_parameters(st, out / f"fig10_12_dynamic_m_cx_cy_{setting}.png",
                          f"m, cx, cy on the dynamic model ({setting} settings)", scale=scale,
                          tol=0.03 * truth)
    _figure(report, fig, f"Fig. 10-12: m, cx, cy against time, each filter's mean and 5-95 % band "
                         f"over runs ({setting} settings)")


def _report_settings(stages: dict) -> list:
    """Report lines: Tables I-III's main numbers, every setting side by side (``stages``:
    setting -> (kinematic Stage, dynamic Stage), all on the same runs)."""
    kin = {k: v[0] for k, v in stages.items()}
    dyn = {k: v[1] for k, v in stages.items()}
    return ["## The settings side by side\n",
            "Same study runs and initial guesses in every setting; the settings differ only in "
            "the filters' covariances. Parameters: mean absolute error over runs of the final "
            "estimates (mean of the last 10 % of steps); states: RMSE over all runs and steps.\n",
            "### Table I: lf, lr (kinematic model)\n", table_settings(kin), "",
            "### Table II: state RMSE (dynamic model)\n", table_settings_states(dyn), "",
            "### Table III: m, cx, cy (dynamic model)\n",
            table_settings(dyn, scale=(1.0, 1e4, 1e4), digits=(1, 3, 3)), ""]


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    filters, settings = _check_args(args)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    report = [reporting.title("dutta2019", PAPER),
              f"{args.runs} Monte-Carlo runs per filter, M = {args.particles} particles, "
              f"dt = {args.dt} s, seed {args.seed}. The dynamic model's excitation is generated "
              "with Dynamic3DOF (MATLAB's vehicledata, which the paper used, cannot ship)"
              + ("" if args.excitation == "paper" else
                 ": here the second excitation (--excitation chirp: steering chirp 0.1-1.5 Hz "
                 "at 15 m/s, true m, cx, cy at "
                 + "/".join(f"{v:g}" for v in CHIRP_TRUTH)
                 + " x nominal, initial guesses and box +-30 % around nominal)") + ". "
              "Every choice the paper leaves open is listed in the docstring of "
              "`vehjax/reproduce/dutta2019.py`.\n"]
    size = dict(runs=args.runs, particles=args.particles, dt=args.dt, progress=_say)
    times, stages = {}, {}
    for setting in settings:
        key = jax.random.key(args.seed)  # the same data and guesses for every setting
        k_kin, k_dyn = jax.random.split(key)
        report.append(f"## {setting} settings\n")
        st1, freq = _study.kinematic_study(filters, setting, k_kin,
                                           duration=args.kinematic_duration,
                                           frequency_study=not args.no_frequency_study, **size)
        _report_kinematic(report, st1, freq, setting, out, args.dt)
        st2 = _study.dynamic_study(filters, setting, k_dyn, st1, duration=args.dynamic_duration,
                                   excitation=args.excitation,
                                   smooth=getattr(args, "smooth", True), **size)
        _report_dynamic(report, st2, setting, out, args.dt, args.excitation)
        stages[setting] = (st1, st2)
        for stage_name, st in (("kinematic", st1), ("dynamic", st2)):
            if st.tuning is not None:
                times[f"{setting}, {stage_name}, tuning Q and R"] = st.tuning.fit.seconds
            times.update({f"{setting}, {stage_name}, {k}": v for k, v in st.seconds.items()})
    if len(stages) > 1:
        report += _report_settings(stages)
    report += ["## Wall time per call (compile included)\n"]
    report += [f"- {k}: {v:.1f} s" for k, v in times.items()]
    report += [f"\nTotal: {time.perf_counter() - t_start:.0f} s"]
    text = "\n".join(report) + "\n"
    reporting.write_report(out, text)
    print()
    print(text)
    print(f"wrote {out / 'report.md'} and figures in {out}")
    return 0
