"""Wang et al. 2016 (paper 001): EKF, UKF, CKF and ACKF on the 7-DOF model in a double lane change.

    vehjax reproduce wang2016 [--runs 100] [--seed 0] [--out out/wang2016]
                              [--cases a,b,c] [--filters ekf,ukf,ckf,ackf,ackf-paper]

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
* Measurements: eq. 20's (r, ay, u). The Table 1 quantities (u, v, ax, ay, r, beta) come from
  :meth:`SevenDOF.derived`: on the true states with the true parameters, and on the estimates
  with the filter's parameters (ax, ay are the tyre-force sums over m, beta = arctan(v/u)).
* Truth: RK4 with 1 ms sub-steps (the model's reference integrator). Filters: the same model
  integrated by ROS2 with one 10 ms step (``integrator="ros2"``), far cheaper (``vehjax bench
  sevendof`` measures each integrator's cost per step), whose own error over this drive is at
  most 0.008 m/s^2 in ay and 0.003 m/s in u (see tests/models/test_sevendof.py), far below the
  measurement noise.
* The truth's ax carries white noise: eq. 31's process noise on the wheel speeds moves the
  slips, hence the tyre forces, from step to step. No filter can follow it, and it sets most
  of the ax error.

Cases (``--cases``). The paper's claim is that the adaptive filter wins when the noise
statistics are time-varying and the filters' noise guess is wrong; eq. 31-32 scale Q(t) and R(t)
alike, so given the peak Q and R a fixed filter already runs at the optimal gain. That literal
study is kept as the control; two cases give the adaptive filter what the paper says it is for:

* ``a`` (R varies): process noise constant at eq. 31's peak, measurement noise R(t) per eq. 32.
  Every filter is given the true Q and the peak R (the honest constant guess), so the fixed
  filters over-weight the model while R(t) is small (start and end of the drive).
* ``b`` (wrong Q/R): the eq. 31-32 truth of the control, but every filter, ACKF's initial Q, R
  included, starts from the peak Q and R0 = ``--r-factor`` (30) times the peak R: a constant
  guess whose Q/R ratio is 30 times too small.
* ``c`` (control): the literal study as before: eq. 31-32 truth, filters given the peak Q, R,
  started at the true state, m and iz 10 % off.

Cases a and b also carry the paper's other two handicaps, large enough to matter: the
"inaccurate initial parameters" are m and iz ``--param-error`` (30 %) too large, and each
run's filter starts from a random initial state drawn from a broad prior (std 1 m/s in u,
0.3 m/s in v, 0.05 rad/s in r, 3 rad/s in each wheel speed), the paper's stated reason for the
EKF's lag. The control keeps the true initial state and 10 %.

Filters (``--filters``):

* EKF, CKF: as in the paper.
* UKF: alpha = 1, beta = 2, kappa = 2 (``UKF_KAPPA``): points at +-3 standard deviations and a
  centre point of weight 2/9, all weights positive. The library default kappa = 0 puts the
  sigma points exactly on the cubature points with zero centre weight, making UKF = CKF by
  construction.
* ACKF (the settings a user would pick, ``ACKF_USER``): Sage-Husa on R only
  (``adapt=("R",)``; estimating a full 7x7 Q from a 3-dimensional innovation is weakly
  identifiable and noisy), forgetting b = 0.98 (memory ~50 steps = 0.5 s, short against the
  10 s noise profile), ``prior_steps`` = 50 (the prior counts as one memory length, which damps
  the start-up transient of the paper's d_1 = 1), ``floor`` = 1e-3 (R stays >= 1e-3 R0).
* ACKF-paper: eq. 29-30 literally: Q and R both adapted, b = 0.98, prior_steps = 0, floor 1e-6.

The filters are built inside one jitted function per filter with Q, R, the prior and theta
as run-time arguments (:func:`run_case`), so each compiles once and serves every case.

Table: per case, quantity and filter, MAE and RMSE over time of each run, mean over runs with
its 95 % Student-t interval, beside the paper's Table 1. "meas." is the raw sensor's error for
the three measured quantities. Consistency: per filter the share of steps whose run-averaged
NEES (7 states, against the true states) and NIS (3 measurements) lie in the two-sided 95 %
chi-square band (:func:`vehjax.metrics.consistency`), and the shares above (over-confident:
covariance too small) and below (under-confident).

Limits: the paper's ordering ACKF < UKF < EKF does not appear with a margin on this model; the
ACKF wins only in cases a and b. See docs/wang2016.md for why the literal study cannot favour
adaptation, and the results case by case (margins per quantity, consistency shares).
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

from ..engine import one_run
from . import reporting

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
FILTERS = ("ekf", "ukf", "ckf", "ackf", "ackf-paper")
CASES = ("a", "b", "c")
CASE_TITLES = {
    "a": "(a) R time-varying (eq. 32), Q constant; filters given the true Q and the peak R",
    "b": "(b) eq. 31-32 truth; every filter starts from a constant guess with R0 = r-factor x peak R",
    "c": "(c) control: eq. 31-32 truth, filters given the peak Q and R (the literal study)",
}

#: Why each case, for the report.
CASE_NOTES = {
    "a": "Eq. 32's R(t) with a constant Q: the fixed filters' peak R overstates the noise "
         "most of the time, the true Q/R ratio changes along the drive; R adaptation can track it.",
    "b": "A constant noise guess with the wrong Q/R ratio (R0 = r-factor x peak R, for every "
         "filter, ACKF's R0 included), m and iz --param-error off, a broad initial state: the "
         "paper's conditions for the adaptive filter to win.",
    "c": "Q(t) and R(t) share the profile sin(pi t / 10) and the fixed filters get the peak Q, "
         "R: the Q/R ratio is right at every instant and the Kalman gain invariant to a common "
         "scale, so the fixed filters are already at the optimal gain and adaptation can only "
         "add estimation variance.",
}

#: UKF sigma-point scaling: kappa = 2 so that the UKF is not the CKF (module docstring).
UKF_ALPHA, UKF_BETA, UKF_KAPPA = 1.0, 2.0, 2.0
#: ACKF as a user would set it (module docstring) and as eq. 29-30 write it.
ACKF_USER = dict(forgetting=0.98, adapt=("R",), prior_steps=50.0, floor=1e-3)
ACKF_PAPER = dict(forgetting=0.98, adapt=("Q", "R"), prior_steps=0.0, floor=1e-6)

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
_CONTROL_PARAM_ERROR = 0.1
# Prior std of the filters' initial state (u, v, r, four wheel speeds); control: x0 is the true start.
_P0_STD = (0.1, 0.05, 0.01, 0.1, 0.1, 0.1, 0.1)
# Cases a, b: broad prior, each run's filter x0 drawn from it around the true start. The wheel
# speeds carry the u error over the rolling radius (the vehicle is faster or slower than
# thought, its wheels rolling with it) plus their own 0.1 rad/s: an independent error of a few
# rad/s in a wheel speed is a slip of several per cent, and the filters' wheels then run away.
_P0_STD_LARGE = (1.0, 0.3, 0.05, 0.1, 0.1, 0.1, 0.1)


def _large_prior(re):
    """(J, P0): x0 error = J z, z ~ N(0, diag(_P0_STD_LARGE)^2), P0 = J diag J^T."""
    J = np.eye(len(_P0_STD_LARGE))
    J[3:, 0] = 1.0 / re
    D = np.diag(np.square(_P0_STD_LARGE))
    return J, J @ D @ J.T


def parser():
    """The study's options (``vehjax reproduce wang2016 --help``); each help states its default."""
    from .. import cli as _cli  # one-line user errors, finite numbers in range

    p = _cli.ArgumentParser(
        prog="vehjax reproduce wang2016",
        description=f"EKF, UKF, CKF and ACKF on the 7-DOF model in a double lane change: {PAPER}. "
                    "Writes report.md (tables and figures), table1.md, table1.csv, "
                    "consistency.csv, results.npz.")
    p.add_argument("--runs", type=_cli.count, default=100, help="Monte-Carlo runs (default %(default)s)")
    p.add_argument("--seed", type=_cli.integer, default=0, help="random seed (default %(default)s)")
    p.add_argument("--out", type=_cli.out_folder, default="out/wang2016", help="output folder (default %(default)s)")
    p.add_argument("--cases", default=",".join(CASES),
                   help="comma-separated subset of the cases a (R varies), b (wrong Q/R guess), "
                        "c (control) (default all: %(default)s)")
    p.add_argument("--filters", default=",".join(FILTERS),
                   help="comma-separated subset of the filters (default all: %(default)s)")
    p.add_argument("--duration", type=_cli.positive, default=10.0,
                   help="manoeuvre length, s (default %(default)g, the paper's)")
    p.add_argument("--speed", type=_cli.positive, default=80.0 / 3.6,
                   help="m/s (default 22.2 = 80 km/h, the ISO 3888-1 test speed)")
    p.add_argument("--param-error", type=_cli.finite, default=0.3,
                   help="relative error of the filters' m and iz in cases a, b (default "
                        "%(default)g; the control keeps 0.1)")
    p.add_argument("--r-factor", type=_cli.positive, default=30.0,
                   help="case b: the filters' R0 over the peak R (default %(default)g)")
    p.add_argument("--smooth", action=argparse.BooleanOptionalAction, default=False,
                   help="Table 1: also the RTS-smoothed estimates of the EKF, UKF and CKF on the "
                        "same runs, as offline columns (default off: each is one more compile "
                        "of the 7-DOF model per case, the filters share one per filter across "
                        "the cases, so it more than doubles the study's time)")
    p.add_argument("--no-plots", action="store_true", help="skip the figures (default: draw them)")
    return p


_parser = parser


def _names(option, text, allowed):
    names = tuple(dict.fromkeys(reporting.split_names(text, lower=True)))
    bad = [f for f in names if f not in allowed]
    if bad or not names:
        raise ValueError(f"{option}: expected a comma-separated subset of {allowed}, got {text!r}")
    return names


def _check(args):
    if args.runs < 2:
        raise ValueError(f"--runs: expected at least 2 (intervals over runs), got {args.runs}")
    filters = _names("--filters", args.filters, FILTERS)
    cases = tuple(c for c in CASES if c in _names("--cases", args.cases, CASES))
    if not (math.isfinite(args.duration) and args.duration > 0):
        raise ValueError(f"--duration: expected a positive number of seconds, got {args.duration}")
    if not (math.isfinite(args.speed) and args.speed >= 10.0):
        raise ValueError(f"--speed: expected at least 10 m/s (the model's range), got {args.speed}")
    if not (math.isfinite(args.param_error) and -0.5 < args.param_error < 1.0):
        raise ValueError(f"--param-error: expected a relative error in (-0.5, 1), got {args.param_error}")
    if not (math.isfinite(args.r_factor) and args.r_factor > 0):
        raise ValueError(f"--r-factor: expected a positive factor, got {args.r_factor}")
    return filters, cases


def setup(runs, seed=0, duration=10.0, speed=80.0 / 3.6, param_error=0.3, r_factor=30.0,
          cases=CASES):
    """Truths, measurements and filter settings of the study (see the module docstring).

    Returns a dict with ``truth_model``, ``filter_model`` (ROS2; its theta is replaced per case),
    ``process_std`` (7,), ``meas_std`` (3,) peak stds, and ``cases``: case name -> dict with
    ``sim`` (:class:`vehjax.Simulation`, truth by RK4 1 ms), ``truth_derived`` (R, T, 6) true
    (u, v, ax, ay, r, beta), the filters' ``Q`` (7,), ``R`` (3,) variances, ``x0`` (R, 7),
    ``P0`` (7, 7), ``theta`` (9,) and ``param_error``.
    """
    import vehjax as vj
    from vehjax.models.sevendof import SevenDOF

    truth_model = SevenDOF(dt=0.01)
    scn = vj.scenarios.double_lane_change(truth_model, speed=speed, duration=duration)
    # The noise-free drive, by the same compiled simulation as the noisy runs (zero stds).
    T, nx, ny = len(scn.inputs), len(truth_model.state_names), len(truth_model.output_names)
    nom = vj.simulate(truth_model, scn, runs=runs, process_std=np.zeros(nx),
                      meas_std=np.zeros(ny),
                      noise_scale=vj.NoiseScale(process=np.ones(T), meas=np.ones(T)))
    process_std = _PROCESS_FRACTION * np.ptp(np.asarray(nom.states[0]), axis=0)
    meas_std = _MEAS_FRACTION * np.ptp(np.asarray(nom.measurements[0]), axis=0)
    sims = {}

    def sim(kind):  # "both": eq. 31-32; "r": Q constant, R(t) per eq. 32. Same key: same draws.
        if kind not in sims:
            T = np.asarray(scn.inputs).shape[0]
            one = np.ones(T)
            sine = _sine(np.arange(T) * truth_model.dt)
            s = vj.simulate(truth_model, scn, runs=runs, key=jax.random.key(seed),
                            process_std=process_std, meas_std=meas_std,
                            noise_scale=vj.NoiseScale(process=sine if kind == "both" else one,
                                                      meas=sine))
            sims[kind] = (s, _derived(truth_model, s.states, s.inputs, truth_model.theta))
        return sims[kind]

    base = np.asarray(truth_model.theta, dtype=float)
    rng = np.random.default_rng([seed, 2016])
    J, P0_large = _large_prior(base[7])
    x0_draw = (rng.standard_normal((runs, len(_P0_STD_LARGE))) * np.asarray(_P0_STD_LARGE)) @ J.T
    out = {}
    for case in cases:
        err = _CONTROL_PARAM_ERROR if case == "c" else param_error
        th = base.copy()
        th[[0, 1]] *= 1.0 + err
        s, td = sim("r" if case == "a" else "both")
        if case == "c":
            x0 = np.broadcast_to(np.asarray(scn.x0, float), (runs, len(_P0_STD))).copy()
            P0 = np.diag(np.square(_P0_STD))
        else:
            x0 = np.asarray(scn.x0, float)[None] + x0_draw
            P0 = P0_large
        R = meas_std**2 * (r_factor if case == "b" else 1.0)
        out[case] = dict(sim=s, truth_derived=td, Q=process_std**2, R=R, x0=x0, P0=P0,
                         theta=th, param_error=err)
    return dict(truth_model=truth_model, filter_model=SevenDOF(dt=0.01, integrator="ros2"),
                process_std=process_std, meas_std=meas_std, cases=out)


def _sine(t):
    return np.sin(np.pi * np.asarray(t) / 10.0)


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
    """The estimator ``name`` (one of FILTERS) on ``model`` with noise variances Q (7,), R (3,)
    (or covariances; numpy or traced)."""
    import vehjax as vj

    Q = jnp.diag(Q) if jnp.ndim(Q) == 1 else Q
    R = jnp.diag(R) if jnp.ndim(R) == 1 else R
    if name == "ekf":
        return vj.filters.ekf(model, Q, R)
    if name == "ukf":
        points = vj.filters.SigmaPoints(alpha=UKF_ALPHA, beta=UKF_BETA, kappa=UKF_KAPPA)
        return vj.filters.ukf(model, Q, R, points=points)
    if name == "ckf":
        return vj.filters.ckf(model, Q, R)
    settings = ACKF_PAPER if name == "ackf-paper" else ACKF_USER
    return vj.filters.ackf(model, Q, R, **settings)


@eqx.filter_jit
def _run_all(name, model, Q, R, ys, us, x0s, P0, theta):
    """Every run of filter ``name`` (static) in one call: Q, R, prior and theta are traced, so
    one compilation serves every case."""

    model = eqx.tree_at(lambda m: m.theta, model, theta)
    est = build_filter(name, model, Q, R)
    res = jax.vmap(lambda y, x0: one_run(est, True, y, us, x0, P0, None, None, None))(ys, x0s)
    return res.states, res.covariances, res.nis, res.n_obs, res.diverged


def run_case(name, study, case, log=print):
    """Run filter ``name`` over every run of ``case``; returns a result dict with the states,
    NEES (R, T), NIS (R, T), n_obs, the derived quantities and the non-diverged mask."""
    from vehjax import metrics

    c = study["cases"][case]
    sim, model = c["sim"], study["filter_model"]
    f = lambda x: jnp.asarray(x, dtype=jnp.result_type(float))
    (states, covs, nis, n_obs, diverged), dt = reporting.timed(lambda: jax.block_until_ready(
        _run_all(name, model, f(c["Q"]), f(c["R"]), f(sim.measurements), f(sim.inputs),
                 f(c["x0"]), f(c["P0"]), f(c["theta"]))))
    states, covs = np.asarray(states), np.asarray(covs)
    ok = ~np.asarray(diverged)
    nees = metrics.nees(states, covs, np.asarray(sim.states))
    derived = _derived(model, states, sim.inputs, c["theta"])
    log(f"  ({case}) {name.upper():10s} {dt:6.1f} s (compile + run, {len(ok)} runs x "
        f"{states.shape[1]} steps), {int((~ok).sum())} diverged")
    return dict(name=name, states=states, derived=derived, mask=ok, nees=nees,
                nis=np.asarray(nis), n_obs=np.asarray(n_obs), seconds=dt)


#: filters with a Gaussian smoother (their own RTS: extended for the EKF, unscented for the UKF,
#: cubature for the CKF); the ACKF has none
SMOOTHABLE = ("ekf", "ukf", "ckf")
#: suffix of a smoothed column's name
SMOOTHED = "-rts"
SMOOTHED_NOTE = ("Columns \"EKF-RTS\", \"UKF-RTS\", \"CKF-RTS\": the same filter's own RTS "
                 "smoother (`vehjax.run(..., smooth=True)`) on the same runs, each estimate "
                 "from all of the run's data, past and future: offline estimates, not comparable "
                 "with the paper's filters, which use the data up to each step only.")


def run_case_smoothed(name, study, case, log=print):
    """Filter ``name`` (one of :data:`SMOOTHABLE`) smoothed by its own RTS smoother over every
    run of ``case`` (``vehjax.run(..., smooth=True)``, the filter of :func:`run_case` with the
    case's Q, R, prior and theta); a result dict as :func:`run_case`'s, named ``name + "-rts"``,
    NEES from the smoothed covariances."""
    import vehjax as vj
    from vehjax import metrics

    if name not in SMOOTHABLE:
        raise ValueError(f"name: expected one of {SMOOTHABLE} (a filter with a smoother), "
                         f"got {name!r}")
    c = study["cases"][case]
    sim = c["sim"]
    model = eqx.tree_at(lambda m: m.theta, study["filter_model"],
                        jnp.asarray(c["theta"], jnp.result_type(float)))
    est = build_filter(name, model, np.asarray(c["Q"], float), np.asarray(c["R"], float))
    out, dt = reporting.timed(vj.run, est, np.asarray(sim.measurements), np.asarray(sim.inputs),
                            x0=c["x0"], P0=c["P0"], return_covariances=True, smooth=True,
                            progress=False)
    states, covs = np.asarray(out.states), np.asarray(out.covariances)
    ok = ~np.asarray(out.diverged)
    nees = metrics.nees(states, covs, np.asarray(sim.states))
    derived = _derived(model, states, sim.inputs, c["theta"])
    log(f"  ({case}) {(name + SMOOTHED).upper():10s} {dt:6.1f} s (compile + run, {len(ok)} runs "
        f"x {states.shape[1]} steps), {int((~ok).sum())} diverged")
    return dict(name=name + SMOOTHED, states=states, derived=derived, mask=ok, nees=nees,
                nis=np.asarray(out.nis), n_obs=np.asarray(out.n_obs), seconds=dt)


def run_filter(name, study, case="c", log=print):
    """Backwards-compatible name of :func:`run_case`."""
    return run_case(name, study, case, log)


def error_table(results, case_study):
    """{metric: {quantity: {column: Interval}}} with columns the filters and "meas."."""
    from vehjax import metrics

    truth = case_study["truth_derived"]
    table = {"MAE": {}, "RMSE": {}}
    meas = np.asarray(case_study["sim"].measurements)
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


def consistency_table(results, n_states=7):
    """Per filter: NEES and NIS consistency over the runs (shares of steps in, above, below the
    95 % band, and the time-mean of the run-averaged statistic over its dof)."""
    from vehjax import metrics

    rows = {}
    for res in results:
        row = {}
        for stat, vals, dof in (("NEES", res["nees"], n_states), ("NIS", res["nis"], res["n_obs"])):
            c = metrics.consistency(vals, dof, mask=res["mask"])
            has = np.isfinite(c.mean)
            above = float(np.mean(c.mean[has] > c.high[has])) if has.any() else float("nan")
            below = float(np.mean(c.mean[has] < c.low[has])) if has.any() else float("nan")
            d = np.broadcast_to(np.asarray(dof, float), vals.shape)[res["mask"]]
            ratio = float(np.nanmean(vals[res["mask"]]) / np.mean(d)) if res["mask"].any() else float("nan")
            row[stat] = dict(inside=c.inside, above=above, below=below, ratio=ratio)
        rows[res["name"]] = row
    return rows


def _verdict_word(s):
    if not math.isfinite(s["inside"]):
        return "-"
    if s["inside"] >= 0.9:
        return "consistent"
    return "over-confident" if s["above"] >= s["below"] else "under-confident"


def format_consistency(rows):
    head = ["filter", "NEES in band", "above / below", "mean NEES / 7", "reading",
            "NIS in band", "above / below", "mean NIS / 3", "reading"]
    lines = [reporting.md_row(head), reporting.md_rule(len(head))]
    for name, row in rows.items():
        cells = [name.upper()]
        for stat in ("NEES", "NIS"):
            s = row[stat]
            cells += [f"{100 * s['inside']:.0f} %", f"{100 * s['above']:.0f} / {100 * s['below']:.0f} %",
                      f"{s['ratio']:.3g}", _verdict_word(s)]
        lines.append(reporting.md_row(cells))
    return "\n".join(lines)


def _fmt(iv):
    m, h = float(iv.mean), float(iv.half_width)
    if not math.isfinite(m):
        return "-"
    return f"{m:.3g} ± {h:.2g}" if math.isfinite(h) else f"{m:.3g}"


def format_table(table, filters, metrics_=("MAE", "RMSE")):
    """Markdown table: rows metric x quantity, our columns then the paper's."""
    cols = [f.upper() for f in filters] + ["meas."]
    paper_cols = [f"paper {c.upper()}" for c in _PAPER_COLUMNS]
    head = ["metric", "quantity"] + cols + paper_cols
    lines = [reporting.md_row(head), reporting.md_rule(len(head))]
    for metric in metrics_:
        for q, unit in zip(QUANTITIES, UNITS):
            row = table[metric][q]
            ours = [_fmt(row[f]) for f in filters] + [_fmt(row["meas."]) if "meas." in row else "-"]
            paper = [f"{v:.3g}" for v in PAPER_TABLE[metric][q]]
            lines.append(reporting.md_row([metric, f"{q} [{unit}]"] + ours + paper))
    return "\n".join(lines)


def verdict(table, filters):
    """Lines on the paper's RMSE ordering ACKF < UKF < EKF and on ACKF against CKF, per quantity."""
    rm = {q: {f: float(table["RMSE"][q][f].mean) for f in filters} for q in QUANTITIES}
    lines = []
    if all(f in filters for f in ("ekf", "ukf", "ackf")):
        full = [q for q in QUANTITIES if rm[q]["ackf"] < rm[q]["ukf"] < rm[q]["ekf"]]
        au = [q for q in QUANTITIES if rm[q]["ackf"] < rm[q]["ukf"]]
        ue = [q for q in QUANTITIES if rm[q]["ukf"] < rm[q]["ekf"]]
        lines.append(f"paper's ordering ACKF < UKF < EKF (RMSE) on {len(full)} of 6 quantities"
                     f"{': ' + ', '.join(full) if full else ''}; ACKF < UKF on {len(au)} "
                     f"({', '.join(au) or 'none'}); UKF < EKF on {len(ue)} ({', '.join(ue) or 'none'})")
    if "ackf" in filters and "ckf" in filters:
        ratio = ", ".join(f"{q} {100 * (rm[q]['ackf'] / rm[q]['ckf'] - 1):+.0f} %" for q in QUANTITIES)
        lines.append(f"ACKF RMSE against CKF: {ratio}")
    if "ekf" in filters and "ckf" in filters:
        ratio = ", ".join(f"{q} {100 * (rm[q]['ekf'] / rm[q]['ckf'] - 1):+.1f} %" for q in QUANTITIES)
        lines.append(f"EKF RMSE against CKF: {ratio}")
    if "ukf" in filters and "ckf" in filters:
        ratio = ", ".join(f"{q} {100 * (rm[q]['ukf'] / rm[q]['ckf'] - 1):+.1f} %" for q in QUANTITIES)
        lines.append(f"UKF RMSE against CKF: {ratio}")
    return lines


def smoothed_summary(results, smoothed, case_study) -> str:
    """One sentence from the numbers: per smoothed filter, its RMSE over the filter's, per
    quantity (means over runs of each run's RMSE, the runs where both converged)."""
    from vehjax import metrics

    truth = case_study["truth_derived"]
    by_name = {r["name"]: r for r in results}
    parts = []
    for sm in smoothed:
        filt = by_name[sm["name"][:-len(SMOOTHED)]]
        ok = filt["mask"] & sm["mask"]
        if not ok.any():
            parts.append(f"{sm['name'].upper()}: every run diverged")
            continue
        ratio = [float(np.mean(metrics.rmse(sm["derived"][..., i:i + 1], truth[..., i:i + 1],
                                            axis="run", mask=ok)[ok])
                       / np.mean(metrics.rmse(filt["derived"][..., i:i + 1],
                                              truth[..., i:i + 1], axis="run", mask=ok)[ok]))
                 for i in range(len(QUANTITIES))]
        parts.append(f"{sm['name'].upper()} " + ", ".join(
            f"{q} {r:.2f}" for q, r in zip(QUANTITIES, ratio)))
    return "Smoothed over filtered RMSE: " + "; ".join(parts) + "."


def _write_csv(path, tables, filters):
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["case", "metric", "quantity", "unit", "column", "mean", "ci95_low",
                    "ci95_high", "paper"])
        for case, table in tables.items():
            for metric in ("MAE", "RMSE"):
                for q, unit in zip(QUANTITIES, UNITS):
                    for col, iv in table[metric][q].items():
                        paper = ""
                        if col in _PAPER_COLUMNS:
                            paper = PAPER_TABLE[metric][q][_PAPER_COLUMNS.index(col)]
                        w.writerow([case, metric, q, unit, col.upper() if col != "meas." else col,
                                    float(iv.mean), float(iv.low), float(iv.high), paper])


def _write_consistency_csv(path, cons):
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["case", "filter", "statistic", "inside", "above", "below", "mean_over_dof",
                    "reading"])
        for case, rows in cons.items():
            for name, row in rows.items():
                for stat, s in row.items():
                    w.writerow([case, name.upper(), stat, s["inside"], s["above"], s["below"],
                                s["ratio"], _verdict_word(s)])


def _runs(study, results) -> str:
    n = study["sim"].measurements.shape[0]
    return reporting.runs_text(n, sum(int((~r["mask"]).sum()) for r in results))


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
    return reporting.line_width(k, n, 0.8, 1.4)


def plot_errors(path, study, results, window_s: float = 0.2):
    """RMSE over runs and a moving ``window_s`` window against time of each quantity, one line
    per filter; the raw sensor's (grey) on the measured quantities."""
    from vehjax import metrics, plots
    from vehjax.plots import plt

    t = np.asarray(study["sim"].t)
    truth = study["truth_derived"]
    meas = np.asarray(study["sim"].measurements)
    w = reporting.window_steps(t, window_s)
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


def _noise_text(study):
    tm = study["truth_model"]
    return tuple(
        ", ".join(f"{n} {s:.3g} {u}" for n, s, u in zip(names, std, units))
        for names, std, units in ((tm.state_names, study["process_std"], tm.state_units),
                                  (tm.output_names, study["meas_std"], tm.output_units)))


def _settings_text(args):
    user = ", ".join(f"{k}={v}" for k, v in ACKF_USER.items())
    paper = ", ".join(f"{k}={v}" for k, v in ACKF_PAPER.items())
    return (f"UKF alpha={UKF_ALPHA:g}, beta={UKF_BETA:g}, kappa={UKF_KAPPA:g} (differs from the "
            f"CKF); ACKF: {user}; ACKF-paper: {paper}. Cases a, b: m and iz x "
            f"{1 + args.param_error:g}, each run's x0 drawn from a prior of std "
            f"{_P0_STD_LARGE} in (u, v, r, wheel speeds), the wheel speeds following the u "
            "error; "
            f"case b: R0 = {args.r_factor:g} x peak R; control c: m and iz x "
            f"{1 + _CONTROL_PARAM_ERROR:g}, x0 true, P0 = diag{_P0_STD}^2.")


def _write_files(out_dir, args, settings, md_all, tables, cons, study, cases, all_results,
                 filters):
    """table1.md, table1.csv, consistency.csv and results.npz; returns their paths."""
    (out_dir / "table1.md").write_text(
        f"{PAPER}\n\n{args.runs} runs, seed {args.seed}, speed {args.speed:.2f} m/s. {settings}\n\n"
        + "\n".join(md_all))
    _write_csv(out_dir / "table1.csv", tables, filters)
    _write_consistency_csv(out_dir / "consistency.csv", cons)
    first = study["cases"][cases[0]]
    np.savez(out_dir / "results.npz", t=np.asarray(first["sim"].t),
             quantities=np.array(QUANTITIES), cases=np.array(cases),
             **{f"{c}_truth": study["cases"][c]["truth_derived"] for c in cases},
             **{f"{c}_measurements": np.asarray(study["cases"][c]["sim"].measurements) for c in cases},
             **{f"{c}_{r['name']}": r["derived"] for c in cases for r in all_results[c]},
             **{f"{c}_{r['name']}_diverged": ~r["mask"] for c in cases for r in all_results[c]})
    written = [out_dir / "table1.md", out_dir / "table1.csv", out_dir / "consistency.csv",
               out_dir / "results.npz"]
    return written


def _figures(out_dir, report: list, study, cases, all_results) -> list:
    """The figures of every case, linked into ``report`` (appended in place); their paths."""
    written = []
    report += ["## Figures\n",
               "The true ax carries white noise: eq. 31's process noise on the wheel speeds "
               "moves the tyre forces from step to step (see the module docstring); no filter "
               "follows it.\n"]
    for case in cases:
        cs, results = study["cases"][case], all_results[case]
        figures = [
            (plot_fig3(out_dir / f"fig3_{case}.png", cs, results),
             f"Case ({case}), Fig. 3: truth, measurement and each filter's estimate, run 0"),
            (plot_errors(out_dir / f"rmse_time_{case}.png", cs, results),
             f"Case ({case}): RMSE over runs (and a 0.2 s window) against time"),
            (plot_error_bands(out_dir / f"error_bands_{case}.png", cs, results),
             f"Case ({case}): estimation error, each filter's mean and 5-95 % band over runs"),
        ]
        report += [reporting.figure_link(p, cap) for p, cap in figures]
        written += [p for p, _ in figures]
    return written


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    filters, cases = _check(args)
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    print(PAPER)
    t0 = time.perf_counter()
    study = setup(args.runs, args.seed, args.duration, args.speed, args.param_error,
                  args.r_factor, cases)
    T = next(iter(study["cases"].values()))["sim"].measurements.shape[1]
    print(f"truth: {args.runs} runs x {T} steps of SevenDOF (RK4, 1 ms), DLC at {args.speed:.1f} m/s, "
          f"{time.perf_counter() - t0:.1f} s")
    noise_text = _noise_text(study)
    settings = _settings_text(args)
    print(f"process noise std per step (peak) {noise_text[0]}")
    print(f"measurement noise std (peak) {noise_text[1]}")
    print(f"filters: SevenDOF (ROS2, 10 ms). {settings}")
    all_results, tables, cons = {}, {}, {}
    smoothed = {case: [] for case in cases}
    for case in cases:
        all_results[case] = [run_case(name, study, case) for name in filters]
        if args.smooth:
            smoothed[case] = [run_case_smoothed(name, study, case) for name in filters
                              if name in SMOOTHABLE]
    report = [reporting.title("wang2016", PAPER),
              f"{args.runs} Monte-Carlo runs, seed {args.seed}, double lane change at "
              f"{args.speed:.1f} m/s for {args.duration:g} s; truth SevenDOF (RK4, 1 ms), filters "
              "SevenDOF (ROS2, 10 ms). Every choice the paper leaves open, and why there are "
              "three cases, is in the docstring of `vehjax/reproduce/wang2016.py`.\n",
              f"Process noise std per step (peak): {noise_text[0]}.",
              f"Measurement noise std (peak): {noise_text[1]}.\n",
              f"Settings: {settings}\n",
              "Tables: per quantity and filter, each run's MAE and RMSE over time, mean over runs "
              "± 95 % interval; the paper's Table 1 right; \"meas.\": the raw sensor's error on "
              "the measured quantities. Also in `table1.csv`. Consistency: share of steps whose "
              "run-averaged NEES (7 states) / NIS (3 measurements) lies in the 95 % chi-square "
              "band, shares above (over-confident) / below (under-confident), and the mean "
              "statistic over its degrees of freedom (1 when consistent); also in "
              "`consistency.csv`.\n"]
    md_all = []
    for case in cases:
        results, cs = all_results[case], study["cases"][case]
        tables[case] = error_table(results, cs)
        cons[case] = consistency_table(results)
        sm_names = [r["name"] for r in smoothed[case]]
        md = format_table(error_table(results + smoothed[case], cs) if sm_names else tables[case],
                          list(filters) + sm_names)
        cmd = format_consistency(cons[case])
        ver = verdict(tables[case], filters)
        print()
        print(f"Case {CASE_TITLES[case]}: Table 1, mean over runs ± 95 % interval; paper right")
        print(md)
        print()
        print(f"Case ({case}): NEES / NIS consistency over the runs (95 % band)")
        print(cmd)
        for line in ver:
            print(f"  {line}")
        md_all.append(f"## Case {CASE_TITLES[case]}\n\n{md}\n")
        report += [f"## Case {CASE_TITLES[case]}\n", CASE_NOTES[case] + "\n", md, ""]
        if sm_names:
            report += [SMOOTHED_NOTE + " " + smoothed_summary(results, smoothed[case], cs), ""]
        report += ["Consistency:\n", cmd, ""]
        report += [f"* {line}" for line in ver] + [""]
    written = _write_files(out_dir, args, settings, md_all, tables, cons, study, cases,
                           all_results, filters)
    if not args.no_plots:
        written += _figures(out_dir, report, study, cases, all_results)
    reporting.write_report(out_dir, "\n".join(report) + "\n")
    written.insert(0, out_dir / "report.md")
    print("wrote " + ", ".join(str(p) for p in written))
    print(f"total {time.perf_counter() - t0:.1f} s")
    return 0
