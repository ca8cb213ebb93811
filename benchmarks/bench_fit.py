"""Maximum-likelihood fits: the time of one long fit, and the coverage of its 95 % intervals.

Issue #30 item 2's targets: "a fit of one run of 20,000 steps with five fitted numbers in under
a minute on the 2-core CPU" and "on the 3-DOF and single-track models, the 95 % intervals from
the standard errors hold the truth in about 95 % of 100 simulated runs".

Data come from a fine integrator, not the filter's own step: the model's continuous equations
integrated by classical RK4 at dt / ``FINE_SUBSTEPS`` (0.5 ms at dt = 10 ms; the filters' models
take 2 substeps, SingleTrack's default, or 1, Dynamic3DOF's), inputs held over each sample.

Speed part (default): ``vehjax.tune.fit`` with its defaults on one run of ``--steps`` steps of
the single-track model (linear tyres, ``vehjax.models.SingleTrack``), EKF, five fitted numbers:
the axle cornering stiffnesses cf, cr [N/rad], the std of the noise entering through the
road-wheel angle, input[delta] [rad] (the process noise, Q = 0), and the two measurement
variances R[ay,ay] [(m/s^2)^2], R[r,r] [(rad/s)^2]. The truth: the nominal car, steering noise
0.004 rad, measurement stds 0.2 m/s^2 and 0.005 rad/s; the fit starts at 0.8 x the true
stiffnesses, twice the steering noise and R = (1, 1e-3). Reported: compile time apart (wall
and CPU), the optimiser, its iterations, the evaluations of the compiled program, seconds per
evaluation per step (wall and CPU), wall and CPU time (``time.process_time``, every thread of this process), and each fitted
number against the truth in standard errors. ``--baseline`` also runs the fit as it was before
(L-BFGS, reverse-mode gradient).

Coverage part (``--coverage``): ``--runs`` simulated runs of ``--coverage-steps`` steps of each
model, each fitted by maximum likelihood, and the fraction of runs whose interval
``value +- 1.96 SE`` holds the truth, per fitted quantity, with its binomial standard error
sqrt(p (1 - p) / runs). The runs are fitted side by side (one compiled program, vmapped over
the runs; forward-mode gradients, Newton steps on the Hessian by central differences of the
gradient, the curvature and standard errors exactly as ``vehjax.tune.fit`` computes them:
:func:`vehjax.tune.hessian_from_gradients`, :func:`vehjax.tune.uncertainty`), starting at the
truth and iterated until every run's gradient is below ``GTOL`` (the maximum likelihood
estimate does not depend on the start). Models:

* single-track, linear tyres, EKF: cf, cr, input[delta], R[ay,ay], R[r,r] (as above);
* 3-DOF dual-track (``vehjax.models.Dynamic3DOF``, outputs the states), EKF: the tyre
  stiffnesses cx [N], cy [N/rad] and the three measurement variances, Q known.

    vehjax bench fit                  # the 20,000-step fit      (python benchmarks/bench_fit.py)
    vehjax bench fit --coverage       # and the coverage study
    vehjax bench fit --quick          # tiny sizes
"""

from __future__ import annotations

import argparse
import functools
import time

import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

import vehjax as vj  # noqa: E402
import vehjax.tune as vt  # noqa: E402
from vehjax import cli  # noqa: E402
from vehjax.models.base import integrate  # noqa: E402

DT = 0.01
FINE_SUBSTEPS = 20
GTOL = 1e-7  # coverage fits: max |d loss / dz| per run (loss per step, z unconstrained)

# single-track truth: steering noise [rad], measurement stds (ay [m/s^2], r [rad/s])
ST_DELTA_STD = 0.004
ST_MEAS_STD = np.array([0.2, 0.005])
# 3-DOF truth: process stds per step (vx, vy [m/s], r [rad/s]), measurement stds, same units
D3_PROC_STD = np.array([0.01, 0.005, 0.002])
D3_MEAS_STD = np.array([0.05, 0.05, 0.01])


# ----------------------------------------------------------------------------------------------
# data from a fine integrator


def fine_rollout(model, x0, inputs, theta=None, substeps: int = FINE_SUBSTEPS, process=None,
                 observed_inputs=None):
    """States (T, nx) and noise-free outputs (T, ny) of ``model``'s continuous equations
    (``model.derivative``) integrated by RK4 at ``model.dt / substeps``, input (T, nu) held
    over each sample; ``process`` (T, nx) is added to the state after each sample (discrete
    process noise). State t is the one after input t (the filters' convention: y_t is observed
    after the step with u_t). The outputs are computed with ``observed_inputs`` (T, nu) when
    given (default: ``inputs``)."""
    theta = jnp.asarray(model.theta if theta is None else theta, float)
    w = jnp.zeros((len(inputs), len(model.state_names))) if process is None else process
    uo = inputs if observed_inputs is None else observed_inputs
    xs, ys = _rollout(model, substeps, theta, jnp.asarray(x0, float), jnp.asarray(inputs, float),
                      jnp.asarray(w, float), jnp.asarray(uo, float))
    return np.asarray(xs), np.asarray(ys)


@eqx.filter_jit
def _rollout(model, substeps, theta, x0, inputs, w, uo):
    """fine_rollout's scan, compiled once per model structure and data shape (equinox keys the
    cache on the model's static fields; its arrays and theta are traced): the coverage study
    simulates 100 runs with one program, not one compile per run."""
    h = model.dt / substeps

    def step(x, uw):
        u, wt, uy = uw
        for _ in range(substeps):
            x = integrate(model.derivative, x, u, theta, h, "rk4")
        x = x + wt
        return x, (x, model.observe(x, uy, theta))

    return jax.lax.scan(step, x0, (inputs, w, uo))[1]


def steering(T: int, rng, amplitude: float = 0.03):
    """A road-wheel angle [rad] (T,): four sines of 0.2-2 Hz with random phases."""
    t = np.arange(T) * DT
    freqs, amps = np.array([0.23, 0.51, 0.97, 1.9]), amplitude * np.array([1.0, 0.7, 0.4, 0.2])
    return sum(a * np.sin(2 * np.pi * f * t + rng.uniform(0, 2 * np.pi))
               for f, a in zip(freqs, amps))


def single_track_data(T: int, seed: int, feedthrough: bool = False):
    """One run of the single-track model: (measurements (T, 2), measured inputs (T, 2)).
    The car is steered by the measured angle plus white noise of std ``ST_DELTA_STD`` held over
    each sample; the speed (18-22 m/s, a 60 s period) is known exactly. The lateral
    acceleration is computed with the measured angle (the filters' model: input noise enters
    the dynamics only); ``feedthrough``: with the true one (the steering noise also reaches
    ay directly, through the front tyre force, which the EKF's Q + G Sigma_u G^T does not
    model)."""
    rng = np.random.default_rng(seed)
    model = vj.models.SingleTrack(dt=DT)
    t = np.arange(T) * DT
    us = np.stack([steering(T, rng), 20.0 + 2.0 * np.sin(2 * np.pi * t / 60.0)], axis=1)
    true_u = us.copy()
    true_u[:, 0] += ST_DELTA_STD * rng.normal(size=T)
    _, y = fine_rollout(model, np.zeros(2), true_u, observed_inputs=None if feedthrough else us)
    return y + ST_MEAS_STD * rng.normal(size=y.shape), us


def dynamic_data(T: int, seed: int):
    """One run of the 3-DOF model (outputs the states): (measurements (T, 3), inputs (T, 5)).
    Front slips 0.004 +- 0.003 (a 7 s period), rear slips zero, steering as above at 15 m/s;
    process noise of std ``D3_PROC_STD`` added per step."""
    rng = np.random.default_rng(seed)
    model = vj.models.Dynamic3DOF(dt=DT)
    t = np.arange(T) * DT
    s = 0.004 + 0.003 * np.sin(2 * np.pi * t / 7.0 + rng.uniform(0, 2 * np.pi))
    us = np.stack([s, s, 0 * s, 0 * s, steering(T, rng, 0.02)], axis=1)
    w = D3_PROC_STD * rng.normal(size=(T, 3))
    _, y = fine_rollout(model, np.array([15.0, 0.0, 0.0]), us, process=w)
    return y + D3_MEAS_STD * rng.normal(size=y.shape), us


# ----------------------------------------------------------------------------------------------
# the two fitting problems


def single_track_problem():
    """(keyword arguments of vehjax.tune.fit except the data, the builder with its options,
    the truth by fitted name)."""
    true = vj.models.SingleTrack(dt=DT)
    cf, cr = (float(true.theta[true.param_names.index(p)]) for p in ("cf", "cr"))
    start = true.with_theta(cf=0.8 * cf, cr=0.8 * cr)
    ekf = functools.partial(vj.filters.ekf, input_noise={"delta": 2 * ST_DELTA_STD})
    kw = dict(builder=ekf, model=start, Q0=np.zeros(2), R0=np.array([1.0, 1e-3]),
              x0=np.zeros(2), P0=np.diag([0.1, 0.01]), params=("cf", "cr"),
              noise=("R", "input"))
    truth = {"cf": cf, "cr": cr, "input[delta]": ST_DELTA_STD,
             "R[ay,ay]": ST_MEAS_STD[0] ** 2, "R[r,r]": ST_MEAS_STD[1] ** 2}
    return kw, truth


def dynamic_problem():
    true = vj.models.Dynamic3DOF(dt=DT)
    cx, cy = (float(true.theta[true.param_names.index(p)]) for p in ("cx", "cy"))
    start = true.with_theta(cx=0.8 * cx, cy=0.8 * cy)
    kw = dict(builder=vj.filters.ekf, model=start, Q0=D3_PROC_STD**2, R0=np.array([0.01] * 3),
              x0=np.array([15.0, 0.0, 0.0]), P0=np.diag([0.1, 0.01, 0.01]),
              params=("cx", "cy"), noise=("R",))
    truth = {"cx": cx, "cy": cy, "R[vx,vx]": D3_MEAS_STD[0] ** 2,
             "R[vy,vy]": D3_MEAS_STD[1] ** 2, "R[r,r]": D3_MEAS_STD[2] ** 2}
    return kw, truth


PROBLEMS = {"single-track": (single_track_problem, single_track_data),
            "3-DOF": (dynamic_problem, dynamic_data)}


# ----------------------------------------------------------------------------------------------
# speed


def time_fit(steps: int, seed: int = 0, baseline: bool = False):
    """Fit the single-track problem on one run of ``steps`` steps with vehjax.tune.fit's
    defaults (``baseline``: L-BFGS and reverse-mode gradients, the defaults before forward-mode
    scoring). Prints and returns the TuneResult."""
    kw, truth = single_track_problem()
    ys, us = single_track_data(steps, seed)
    builder, model, Q0, R0 = (kw.pop(k) for k in ("builder", "model", "Q0", "R0"))
    saved = vt.program.FORWARD_MAX
    optimizer = None
    if baseline:
        vt.program.FORWARD_MAX, optimizer = 0, "lbfgs"
    try:
        c0, w0 = time.process_time(), time.perf_counter()
        res = vt.fit(builder, model, Q0, R0, ys, us, x0=kw["x0"], P0=kw["P0"],
                     params=vt.Fitted(kw["params"], noise=kw["noise"]),
                     options=vt.Options(optimizer=optimizer, progress=False))
        wall, cpu = time.perf_counter() - w0, time.process_time() - c0
    finally:
        vt.program.FORWARD_MAX = saved
    run_s = res.seconds - res.compile_seconds
    label = "baseline (lbfgs, reverse)" if baseline else "default"
    print(f"{label}: {steps} steps, 5 fitted numbers, optimizer {res.optimizer}, derivatives "
          f"{res.derivatives}")
    print(f"  wall {wall:.1f} s, CPU {cpu:.1f} s (all threads); compile {res.compile_seconds:.1f} s"
          f" wall, {res.compile_cpu_seconds:.1f} s CPU; {res.iterations} iterations, "
          f"{res.evaluations} evaluations, "
          f"{(run_s - res.hessian_compile_seconds) / max(res.evaluations, 1) / steps * 1e6:.1f}"
          f" us per evaluation per step (wall, after compile; "
          f"{(cpu - res.compile_cpu_seconds) / max(res.evaluations, 1) / steps * 1e6:.1f} CPU)")
    if res.hessian_batches:
        print(f"  Hessian: {res.hessian_batches} batched evaluation(s) of its 10 difference points"
              f" (their program compiled in {res.hessian_compile_seconds:.1f} s wall)")
    print(f"  converged {res.converged}, max |gradient| {res.gradient:.1e}, log-likelihood "
          f"{res.loglik0:.6g} -> {res.loglik:.6g}")
    for k, v in truth.items():
        se = res.std_errors.get(k, np.nan)
        print(f"  {k:<13} {res.values[k]:12.6g} +- {se:9.3g} [{res.units[k]}]  truth "
              f"{v:10.6g}  ({(res.values[k] - v) / se:+.2f} SE)")
    return res, wall, cpu


# ----------------------------------------------------------------------------------------------
# coverage


def batched_fits(problem: str, runs: int, steps: int, seed0: int = 1000, iters: int = 12):
    """Maximum-likelihood fits of ``runs`` simulated runs, side by side (module docstring).

    Returns (names (m,), values (runs, m), standard errors (runs, m), truth (m,),
    max |gradient| per run (runs,), seconds)."""
    make, data_fn = PROBLEMS[problem]
    kw, truth = make()
    sims = [data_fn(steps, seed0 + r) for r in range(runs)]
    ys = np.stack([s[0] for s in sims])
    us = np.stack([s[1] for s in sims])
    # the objective's structure and the true point from one run; data of every run beside it
    model = kw["model"].with_theta(**{p: truth[p] for p in kw["params"]})
    builder, bk = vj.validation.builder_options(kw["builder"])
    if "input_noise" in bk:
        bk["input_noise"] = {"delta": truth["input[delta]"]}
    R_true = np.array([truth[k] for k in truth if k.startswith("R[")])
    obj = vt.objective(functools.partial(builder, **bk), model, kw["Q0"], R_true, ys[0], us[0],
                       x0=kw["x0"], P0=kw["P0"],
                       params=vt.Fitted(kw["params"], noise=kw["noise"]))
    flat0, unravel = jax.flatten_util.ravel_pytree(obj.z0)
    n = flat0.shape[0]
    names = list(truth)
    t0 = time.perf_counter()

    def loss(f, y, u):
        return obj.loss(unravel(f), (y[None], u, obj.data[2], obj.data[3], None))[0]

    def value_grad(f, y, u):
        val, der = jax.vmap(lambda v: jax.jvp(lambda g: loss(g, y, u), (f,), (v,)),
                            out_axes=(None, 0))(jnp.eye(n))
        return val, der

    vg = jax.jit(jax.vmap(value_grad))

    def quantities(f):
        v = obj.unpack(unravel(f))
        th = dict(zip(model.param_names, v["theta"]))
        out = []
        for k in names:
            if k.startswith("R["):
                i = [q for q in names if q.startswith("R[")].index(k)
                out.append(v["R"][i, i])
            elif k.startswith("input["):
                out.append(v["input"]["delta"])
            else:
                out.append(th[k])
        return jnp.stack(out)

    jac = jax.jit(jax.vmap(jax.jacfwd(quantities)))
    X = np.tile(np.asarray(flat0), (runs, 1))
    ones = np.ones(n)

    def hessians(X):
        H = np.zeros((runs, n, n))
        for i in range(n):
            e = np.zeros(n)
            e[i] = 1e-4
            H[:, :, i] = (np.asarray(vg(X + e, ys, us)[1]) - np.asarray(vg(X - e, ys, us)[1])) \
                / 2e-4
        return 0.5 * (H + np.swapaxes(H, 1, 2))

    f, g = (np.asarray(a) for a in vg(X, ys, us))
    for _ in range(iters):
        if np.max(np.abs(g)) <= GTOL:
            break
        H = hessians(X)
        lam, V = np.linalg.eigh(H)
        lam = np.maximum(lam, 1e-8 * lam.max(axis=1, keepdims=True))
        D = -np.einsum("rij,rj->ri", V, np.einsum("rji,rj->ri", V, g) / lam)
        t = np.ones(runs)
        todo = np.max(np.abs(g), axis=1) > GTOL
        D[~todo] = 0.0
        for _ in range(20):  # per-run backtracking (Armijo), all runs evaluated together
            f_new, g_new = (np.asarray(a) for a in vg(X + t[:, None] * D, ys, us))
            ok = np.isfinite(f_new) & (f_new <= f + 1e-4 * t * np.sum(g * D, axis=1) + 1e-15)
            if np.all(ok | ~todo):
                break
            t = np.where(ok | ~todo, t, 0.5 * t)
        X = X + t[:, None] * D
        f, g = f_new, g_new
    H = hessians(X)
    J = np.asarray(jac(X))
    N = steps
    values = np.asarray(jax.vmap(quantities)(X))
    se = np.stack([vt.uncertainty(N * H[r], J[r], ones, tuple(names)).std_errors
                   for r in range(runs)])
    return (names, values, se, np.array([truth[k] for k in names]),
            np.max(np.abs(g), axis=1), time.perf_counter() - t0)


def coverage(problem: str, runs: int, steps: int):
    """Print the coverage of the 95 % intervals of each fitted quantity; returns the fraction
    per quantity (m,)."""
    names, values, se, truth, gmax, secs = batched_fits(problem, runs, steps)
    ok = np.isfinite(se) & (gmax[:, None] <= 1e3 * GTOL)  # determined, converged
    hit = (np.abs(values - truth) <= 1.96 * se) & ok
    n_ok = ok.sum(axis=0)
    p = hit.sum(axis=0) / np.maximum(n_ok, 1)
    z = np.where(ok, (values - truth) / np.where(ok, se, 1.0), np.nan)
    print(f"{problem}: {runs} runs x {steps} steps, EKF, fitted side by side in {secs:.1f} s; "
          f"max |gradient| over runs {gmax.max():.1e}")
    print(f"  {'quantity':<13}{'coverage':>9}{'+- (binom.)':>12}{'runs':>6}{'mean z':>8}"
          f"{'std z':>7}{'mean SE':>11}{'std of values':>15}")
    for j, k in enumerate(names):
        print(f"  {k:<13}{p[j]:>9.3f}{np.sqrt(p[j] * (1 - p[j]) / max(n_ok[j], 1)):>12.3f}"
              f"{n_ok[j]:>6d}{np.nanmean(z[:, j]):>8.2f}{np.nanstd(z[:, j]):>7.2f}"
              f"{np.nanmean(np.where(ok[:, j], se[:, j], np.nan)):>11.3g}"
              f"{values[:, j].std():>15.3g}")
    print("  coverage over the runs whose fit converged with a finite standard error ('runs'); "
          "z = (value - truth) / SE, mean 0 and std 1 when the SEs are right")
    return p


def _models(text: str) -> list[str]:
    """argparse type of ``--models``: a comma list of names of PROBLEMS."""
    names = [m.strip() for m in str(text).split(",") if m.strip()]
    bad = [m for m in names if m not in PROBLEMS]
    if not names or bad:
        raise argparse.ArgumentTypeError(f"expected a comma list out of {', '.join(PROBLEMS)}, "
                                         f"got {text!r}" + (f" (unknown: {', '.join(bad)})"
                                                            if bad else ""))
    return names


def parser() -> argparse.ArgumentParser:
    """The benchmark's options (``vehjax bench fit --help``); a refused one raises ValueError
    naming it and what it takes (``vehjax`` prints it as one line on stderr, exit code 2)."""
    p = cli.ArgumentParser(prog="vehjax bench fit", description=__doc__.splitlines()[0])
    p.add_argument("--steps", type=cli.at_least(int, 10), default=20000,
                   help="steps of the timed single-track fit (default %(default)s)")
    p.add_argument("--baseline", action="store_true",
                   help="also time the fit with L-BFGS and reverse-mode gradients (default off)")
    p.add_argument("--no-speed", action="store_true", help="skip the timed fit (default off)")
    p.add_argument("--coverage", action="store_true",
                   help="run the coverage study too (default off)")
    p.add_argument("--runs", type=cli.at_least(int, 2), default=100,
                   help="simulated runs per model, coverage (default %(default)s)")
    p.add_argument("--coverage-steps", type=cli.at_least(int, 10), default=1000,
                   help="steps per run, coverage (default %(default)s)")
    p.add_argument("--models", type=_models, default="single-track,3-DOF",
                   help="comma list of coverage models (default %(default)s)")
    p.add_argument("--quick", action="store_true",
                   help="tiny sizes: a 300-step fit, coverage of 4 runs x 150 steps of the "
                        "single-track model (default off)")
    return p


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    if args.quick:
        args.steps, args.runs, args.coverage_steps = 300, 4, 150
        args.coverage, args.models = True, ["single-track"]
    models = args.models
    print(f"vehjax bench fit, float64, {jax.devices()[0].platform.upper()}, "
          f"{len(jax.devices())} device(s)")
    if not args.no_speed:
        time_fit(args.steps)
        if args.baseline:
            time_fit(args.steps, baseline=True)
    if args.coverage:
        for m in models:
            coverage(m, args.runs, args.coverage_steps)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
