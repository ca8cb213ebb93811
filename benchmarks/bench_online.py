"""Online filtering latency: ``vehjax.Online.update`` per sample, beside the per-step time of
``vehjax.filter`` / ``vehjax.run`` over the same data and filterpy's step in a Python loop.

Rows (float64, this machine's CPU):

    ekf   the EKF on ``SingleTrack`` (linear tyres, RK4, 2 substeps, dt = 0.01 s; outputs ay,
          r), a sine steer at 20 m/s simulated with ``vehjax.simulate``
    ukf   the UKF (alpha 1, beta 2, kappa 0) on the same model and data
    mpf   the noise-adaptive marginalized PF (paper 004, ``banked_road.build_sim_filter``) at
          ``--particles`` N on ``SingleTrackBank``, ``vehjax reproduce berntorp2018``'s
          simulated drive (``bench marginalized``'s problem)

Contenders per row:

    Online.update   one call per sample after ``--warmup`` samples: the latency of a live
                    filter, from the measurement as a numpy array to the estimate as numpy
                    arrays (median, 99th percentile and worst over every timed sample)
    vehjax.filter   one run of ``--steps`` samples under ``jax.jit`` (compile apart), its time
                    over the steps: the per-step cost without the per-call overhead
    vehjax.run      the same through ``vehjax.compile_run`` (one run, results on the host; a
                    compiled study runs on the data it was compiled with: the first round's)
    filterpy        ``ExtendedKalmanFilter`` / ``UnscentedKalmanFilter`` over a NumPy
                    transcription of the linear single-track model, ``predict`` + ``update``
                    per sample in a plain Python loop (median, 99th percentile, worst); not
                    in the mpf row (filterpy has no such filter); the row is left out with a
                    note when filterpy is not installed

Before timing, the estimates are checked: Online equal to vehjax.filter (``--tol``, max abs
difference of the means over the first round), filterpy equal to them. Rounds are interleaved
(``--rounds``: each contender once per round on its own slice of the data), so that a change in
machine load hits all alike; the per-sample statistics pool every round, and "best round" is
the lowest of the rounds' medians (steadier on a shared machine). Targets: a median
under 30 us for the EKF and UKF, under 2 ms for the marginalized PF at N = 500, whose paper
reports 1.4 ms a step (C, a 2014 laptop): the ratio is printed.

JAX's CPU dispatch. ``--dispatch sync`` runs JAX's CPU computations in the calling thread
(``jax_cpu_enable_async_dispatch`` False, set before JAX starts its backend), ``async`` hands
them to a worker thread (JAX's default). XLA:CPU runs a computation of under 1000 flops (its
cost analysis, printed in the Online.update row's note) in the calling thread either way; the
EKF step is under that, the UKF's and the marginalized PF's are over it. ``vehjax.Online``
runs its step on a synchronous CPU client of its own under either setting
(:func:`vehjax.execution.live_device`), so both should measure alike; before it did, the UKF
took 80-89 us a sample under ``async`` against 14 us under ``sync`` (``benchmarks/results``).
The default ``both`` runs each in a fresh Python process (the setting acts only before JAX's
backend starts), sync first, and ends with one line per row comparing them with the target.

    vehjax bench online                      # or: python benchmarks/bench_online.py
    vehjax bench online --quick              # tiny sizes
    vehjax bench online --dispatch sync      # this process only, in the calling thread
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np

import vehjax as vj
from vehjax.cli import load_benchmark

ROWS = ("ekf", "ukf", "mpf")
ALPHA, BETA, KAPPA = 1.0, 2.0, 0.0
PAPER_MS = 1.4  # paper 004, Fig. 13: the marginalized PF at N = 500, ms per step
TARGET_US = {"ekf": 30.0, "ukf": 30.0, "mpf": 2000.0}
DISPATCH = ("both", "sync", "async")
#: Online.update's median [us] per row of this process's run (``--medians`` writes it)
MEDIANS: dict = {}


class Timing:
    """Per-sample latencies [s] of one contender, by round."""

    def __init__(self, name, note=""):
        self.name, self.note, self.rounds = name, note, []

    def stats(self):
        """(median, p99, worst, best round's median) in us; per-step rows have one number a
        round (p99 and worst NaN)."""
        per = [np.asarray(r) for r in self.rounds]
        pooled = np.concatenate(per) * 1e6
        best = min(float(np.median(r)) for r in per) * 1e6
        if all(r.size == 1 for r in per):
            return float(np.median(pooled)), math.nan, math.nan, best
        return (float(np.median(pooled)), float(np.percentile(pooled, 99)), float(pooled.max()),
                best)


# -- the Gaussian rows' problem and filterpy's transcription ----------------------------------

def single_track_problem(samples: int):
    """(model, ys (samples, 2), us (samples, 2), Q, R, x0, P0): a sine steer on SingleTrack."""
    model = vj.models.SingleTrack(dt=0.01)
    scn = vj.scenarios.sine_steer(model, speed=20.0, amplitude=0.03, frequency=0.4,
                                  duration=samples * model.dt)
    std_x, std_y = np.array([0.02, 0.005]), np.array([0.3, 0.005])
    sim = vj.simulate(model, scn, runs=1, key=jax.random.key(0), process_std=std_x,
                      meas_std=std_y)
    ys, us = np.asarray(sim.measurements[0]), np.asarray(sim.inputs)
    return (model, ys[:samples], us[:samples], np.diag(std_x ** 2), np.diag(std_y ** 2),
            np.array([0.1, 0.0]), np.diag([0.1, 0.01]))


def single_track_numpy(model):
    """The linear single-track model in NumPy for filterpy: (fx(x, dt, u), F(u), hx(x, u),
    H(u)): transition, its Jacobian (the model is affine in x: RK4's matrix polynomial per
    substep), observation and its Jacobian."""
    m, iz, lf, lr, cf, cr = (float(v) for v in np.asarray(model.theta))
    h, n_sub = model.dt / model.substeps, model.substeps

    def rows(vx):
        fy = np.array([-(cf + cr) / vx, (cr * lr - cf * lf) / vx])
        mz = np.array([(cr * lr - cf * lf) / vx, -(cf * lf ** 2 + cr * lr ** 2) / vx])
        return fy, mz

    def deriv(x, u):
        delta, vx = u
        ff = cf * (delta - (x[0] + lf * x[1]) / vx)
        fr = cr * (lr * x[1] - x[0]) / vx
        return np.array([(ff + fr) / m - vx * x[1], (lf * ff - lr * fr) / iz])

    def fx(x, dt, u):
        for _ in range(n_sub):
            k1 = deriv(x, u)
            k2 = deriv(x + 0.5 * h * k1, u)
            k3 = deriv(x + 0.5 * h * k2, u)
            k4 = deriv(x + h * k3, u)
            x = x + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
        return x

    def F(u):
        fy, mz = rows(u[1])
        hA = h * np.array([fy / m - np.array([0.0, u[1]]), mz / iz])
        step = np.eye(2) + hA @ (np.eye(2) + hA @ (np.eye(2) / 2 + hA @ (
            np.eye(2) / 6 + hA / 24)))
        return np.linalg.matrix_power(step, n_sub)

    def hx(x, u):
        delta, vx = u
        ff = cf * (delta - (x[0] + lf * x[1]) / vx)
        fr = cr * (lr * x[1] - x[0]) / vx
        return np.array([(ff + fr) / m, x[1]])

    def H(x, u):
        return np.array([rows(u[1])[0] / m, [0.0, 1.0]])

    return fx, F, hx, H


def filterpy_loop(row, model, ys, us, Q, R, x0, P0):
    """A function (ys, us) -> (means (T, nx), per-step seconds (T,)) running filterpy's
    ``row`` filter on, its state continuing between calls."""
    from filterpy.kalman import ExtendedKalmanFilter, MerweScaledSigmaPoints, UnscentedKalmanFilter

    fx, F, hx, H = single_track_numpy(model)
    if row == "ekf":
        class EKF(ExtendedKalmanFilter):
            def predict_x(self, u=0):
                self.F = F(u)
                self.x = fx(self.x, model.dt, u)

        kf = EKF(dim_x=2, dim_z=2)
    else:
        pts = MerweScaledSigmaPoints(2, alpha=ALPHA, beta=BETA, kappa=KAPPA)
        kf = UnscentedKalmanFilter(dim_x=2, dim_z=2, dt=model.dt, fx=fx, hx=hx, points=pts)
    kf.x, kf.P, kf.Q, kf.R = x0.copy(), P0.copy(), Q.copy(), R.copy()

    def run(ys, us):
        means, ts = np.empty((len(ys), 2)), np.empty(len(ys))
        for t in range(len(ys)):
            t0 = time.perf_counter()
            if row == "ekf":
                kf.predict(u=us[t])
                kf.update(ys[t], H, hx, args=(us[t],), hx_args=(us[t],))
            else:
                kf.predict(u=us[t])
                kf.update(ys[t], u=us[t])
            ts[t] = time.perf_counter() - t0
            means[t] = kf.x
        return means, ts

    return run


# -- contenders -------------------------------------------------------------------------------

def online_loop(est, x0, P0, key, dt):
    """(Online, a function (ys, us) -> (means, per-sample seconds)) over one Online filter."""
    live = vj.Online(est, x0, P0, key=key, dt=dt)

    def run(ys, us):
        means, ts = np.empty((len(ys), est.nx)), np.empty(len(ys))
        for t in range(len(ys)):
            t0 = time.perf_counter()
            out = live.update(ys[t], us[t])
            ts[t] = time.perf_counter() - t0
            means[t] = out.mean
        return means, ts

    return live, run


def batch_calls(est, ys, us, x0, P0, key):
    """(compiled vehjax.filter over ys, us: (compile s, call), the same with compile_run)."""
    x0j, P0j = jnp.asarray(x0), jnp.asarray(P0)

    def one(ys, us):
        return vj.filter(est, ys, us, x0=x0j, P0=P0j, key=key, return_covariances=False).states

    t0 = time.perf_counter()
    compiled = jax.jit(one).lower(jnp.asarray(ys), jnp.asarray(us)).compile()
    filt = (time.perf_counter() - t0, lambda y, u: jax.block_until_ready(compiled(y, u)))
    t0 = time.perf_counter()
    prepared = vj.compile_run(est, ys[None], us, x0=x0, P0=P0, key=key, progress=False)
    # a compiled study runs with the data it was compiled with: the first round's, every round
    run = (time.perf_counter() - t0, lambda y, u: prepared(progress=False).states)
    return filt, run


def step_flops(est, live) -> float:
    """The flops XLA's cost analysis counts in the sample step :class:`vehjax.Online` compiles
    (:func:`vehjax.online.packed_step` on its state's layout): under 1000, XLA:CPU runs it in
    the calling thread whatever the dispatch (module docstring)."""
    buffers = vj.online.pack(live.state, live.layout)
    yu = jnp.zeros((est.ny + est.nu,), buffers[0].dtype)
    fn = jax.jit(lambda b, v: vj.online.packed_step(est, live.layout, b, v))
    cost = fn.lower(buffers, yu).compile().cost_analysis()
    cost = cost[0] if isinstance(cost, (list, tuple)) else cost
    return float(cost.get("flops", math.nan))


def check(name, got, want, tol):
    diff = float(np.max(np.abs(np.asarray(got) - np.asarray(want))))
    print(f"  check {name}: max |difference| of the means {diff:.1e}"
          + ("" if diff <= tol else f"  > {tol}: FAILED"))
    return diff <= tol


def row_problem(row, samples, particles):
    """(est, ys, us, x0, P0, key, dt, model) of a row."""
    if row in ("ekf", "ukf"):
        model, ys, us, Q, R, x0, P0 = single_track_problem(samples)
        est = (vj.filters.ekf(model, Q, R) if row == "ekf" else
               vj.filters.ukf(model, Q, R, points=vj.filters.SigmaPoints(alpha=ALPHA, beta=BETA,
                                                                         kappa=KAPPA)))
        return est, ys, us, x0, P0, None, model.dt, model, (Q, R)
    mb = load_benchmark("marginalized")
    road, model, U, _, Y, = mb._problem(1, samples)[:5]
    x0 = np.zeros(5)
    P0 = np.diag([0.1, 0.5 * road.DEG, 0.5 * road.DEG, 0.2 * road.DEG, 0.2 * road.DEG]) ** 2
    est = road.build_sim_filter(model, particles)
    return est, np.asarray(Y[0]), np.asarray(U), x0, P0, jax.random.key(1), model.dt, model, None


def time_row(row, args):
    """Print one row's contenders; False when a check failed."""
    samples = args.warmup + args.rounds * args.steps
    est, ys, us, x0, P0, key, dt, model, noise = row_problem(row, samples, args.particles)
    t0 = time.perf_counter()
    live, online = online_loop(est, x0, P0, key, dt)
    build_s = time.perf_counter() - t0
    flops = step_flops(est, live)
    (c_filter, filt), (c_run, run) = batch_calls(est, ys[:args.steps], us[:args.steps], x0, P0,
                                                 key)
    fp = None
    if noise is not None and _has_filterpy():
        fp = filterpy_loop(row, model, ys, us, *noise, x0, P0)
    w = args.warmup
    ok = True
    # checks: the warm-up plus the first round from the prior, against vehjax.filter
    means, _ = online(ys[:w], us[:w])
    first = slice(w, w + args.steps)
    ref = np.asarray(vj.filter(est, ys[:w + args.steps], us[:w + args.steps], x0=x0, P0=P0, key=key,
                               return_covariances=False).states)
    timings = [Timing("Online.update", f"built and compiled in {build_s:.1f} s; its step "
                                       f"{flops:.0f} flops (XLA's cost analysis)"),
               Timing("vehjax.filter", f"per step of a {args.steps}-step jit; compile "
                                       f"{c_filter:.1f} s"),
               Timing("vehjax.run", f"per step of compile_run, one run; compile {c_run:.1f} s")]
    if fp is not None:
        fp(ys[:w], us[:w])  # the warm-up
        from importlib.metadata import version
        timings.append(Timing(f"filterpy {version('filterpy')}",
                              "predict + update in a Python loop, NumPy model"))
    for r in range(args.rounds):
        sl = slice(w + r * args.steps, w + (r + 1) * args.steps)
        means, ts = online(ys[sl], us[sl])
        timings[0].rounds.append(ts)
        if r == 0:
            ok &= check("Online vs vehjax.filter", means, ref[first], args.tol)
        for t, call in ((timings[1], filt), (timings[2], run)):
            t0 = time.perf_counter()
            call(ys[sl], us[sl])
            t.rounds.append([(time.perf_counter() - t0) / args.steps])
        if fp is not None:
            fmeans, ts = fp(ys[sl], us[sl])
            timings[3].rounds.append(ts)
            if r == 0:
                ok &= check("filterpy vs vehjax.filter", fmeans, ref[first], args.fp_tol)
    report(row, est, timings, args)
    if noise is not None and fp is None:
        print(f"{row:<5}filterpy      not installed: row left out (pip install filterpy)")
    return ok


def report(row, est, timings, args):
    for t in timings:
        med, p99, worst, best = t.stats()
        print(f"{row:<5}{t.name:<16}{med:>12.1f}{p99:>11.1f}{worst:>11.1f}{best:>12.1f}  {t.note}")
    med = timings[0].stats()[0]
    MEDIANS[row] = med
    target = TARGET_US[row]
    line = (f"{row:<5}target: Online.update median {med:.1f} us "
            f"{'<' if med < target else '>='} {target:g} us (dispatch {args.dispatch})")
    if row == "mpf":
        line += (f" (N = {args.particles}); paper 004's {PAPER_MS} ms a step: ratio "
                 f"{med / 1e3 / PAPER_MS:.2f}")
    print(line)


def _has_filterpy() -> bool:
    try:
        import filterpy  # noqa: F401
    except ImportError:
        return False
    return True


def parser() -> argparse.ArgumentParser:
    """The benchmark's options (``vehjax bench online --help``)."""
    p = argparse.ArgumentParser(prog="vehjax bench online", description=__doc__.splitlines()[0])
    p.add_argument("--rows", default=",".join(ROWS),
                   help="comma list of rows out of %s (default %%(default)s)" % ", ".join(ROWS))
    p.add_argument("--steps", type=int, default=2000,
                   help="samples per round (default %(default)s)")
    p.add_argument("--rounds", type=int, default=5,
                   help="interleaved timing rounds (default %(default)s)")
    p.add_argument("--warmup", type=int, default=200,
                   help="samples before the timed ones (default %(default)s)")
    p.add_argument("--particles", type=int, default=500,
                   help="particles N of the mpf row (default %(default)s)")
    p.add_argument("--mpf-steps", type=int, default=500,
                   help="samples per round of the mpf row (default %(default)s)")
    p.add_argument("--dispatch", choices=DISPATCH, default="both",
                   help="JAX's CPU dispatch: sync (the calling thread), async (JAX's default: "
                        "a worker thread) or both, each in a fresh process (module docstring; "
                        "default %(default)s)")
    p.add_argument("--medians", default=None, metavar="FILE",
                   help="also write each row's Online.update median [us] to this JSON file "
                        "(how --dispatch both reads its children's; default none)")
    p.add_argument("--tol", type=float, default=1e-9,
                   help="max abs difference, Online vs vehjax.filter (default %(default)s)")
    p.add_argument("--fp-tol", type=float, default=1e-8,
                   help="max abs difference, filterpy vs vehjax.filter (default %(default)s)")
    p.add_argument("--quick", action="store_true",
                   help="tiny sizes: 50 samples a round, 2 rounds, warm-up 20, N = 50 "
                        "(default off)")
    return p


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    if args.quick:
        args.steps, args.rounds, args.warmup, args.particles, args.mpf_steps = 50, 2, 20, 50, 50
    rows = [r.strip() for r in args.rows.split(",") if r.strip()]
    if [r for r in rows if r not in ROWS] or min(args.steps, args.rounds, args.mpf_steps) < 1 \
            or args.warmup < 0 or args.particles < 2:
        print(f"bench online: rows out of {', '.join(ROWS)}; --steps, --rounds, --mpf-steps "
              f">= 1, --warmup >= 0, --particles >= 2")
        return 2
    if args.dispatch == "both":
        return both(argv if argv is not None else sys.argv[1:], rows)
    if args.dispatch == "sync":  # before JAX's backend starts (it starts on first use)
        jax.config.update("jax_cpu_enable_async_dispatch", False)
    plat = jax.devices()[0].platform.upper()
    print(f"Online latency, float64, {plat}, dispatch {args.dispatch}: {args.rounds} interleaved "
          f"rounds of {args.steps} samples (mpf: {args.mpf_steps}) after {args.warmup} warm-up "
          f"samples; times in us")
    print(f"{'row':<5}{'contender':<16}{'median':>12}{'p99':>11}{'worst':>11}{'best round':>12}"
          f"  note")
    ok = True
    for row in rows:
        steps = args.steps
        if row == "mpf":
            args.steps = args.mpf_steps
        ok &= time_row(row, args)
        args.steps = steps
    print("median, p99, worst: over every timed sample of every round (Online.update, "
          "filterpy); vehjax.filter / vehjax.run: the step time of a whole run (no p99); best "
          "round: the lowest round median")
    if args.medians:
        with open(args.medians, "w") as f:
            json.dump(MEDIANS, f)
    return 0 if ok else 1


def both(argv, rows) -> int:
    """Run this benchmark with ``--dispatch sync`` and then ``async``, each in a fresh Python
    process (its output passed through), then print each row's medians beside the target."""
    rest, skip = [], False
    for a in argv:  # argv without its --dispatch option
        if not skip and a != "--dispatch" and not a.startswith("--dispatch="):
            rest.append(a)
        skip = a == "--dispatch"
    medians, code = {}, 0
    with tempfile.TemporaryDirectory() as tmp:
        for mode in DISPATCH[1:]:
            out = os.path.join(tmp, f"{mode}.json")
            sys.stdout.flush()
            code |= subprocess.call([sys.executable, os.path.abspath(__file__), *rest,
                                     "--dispatch", mode, "--medians", out])
            if os.path.exists(out):
                with open(out) as f:
                    medians[mode] = json.load(f)
    print("Online.update median against the target, us (sync: the calling thread, a live "
          "filter's configuration; async: JAX's default)")
    for row in rows:
        got = {m: medians.get(m, {}).get(row, math.nan) for m in DISPATCH[1:]}
        judged = "; ".join(f"{m} {v:.1f} {'met' if v < TARGET_US[row] else 'not met'}"
                           for m, v in got.items())
        print(f"{row:<5}target {TARGET_US[row]:g} us: {judged}")
    return code


if __name__ == "__main__":
    raise SystemExit(main())
