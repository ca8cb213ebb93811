"""Smoothers: vehjax's extended / unscented RTS against dynamax's, and the parallel-in-time
Kalman filter + RTS smoother against the sequential one.

The model and data are those of ``vehjax bench all``: the user-written 3-DOF dual-track model
(nx = 3, RK4, H = I), ``--runs`` simulated sine-steer runs of ``--steps`` steps, float64.

Rows:

    eks   vehjax's extended RTS through its public path, ``vehjax.compile_run(..., smooth=True)``
          (compile apart, timed calling the compiled study, results copied to the host; on the
          CPU the runs-last forward filter, which keeps its predictions, and the runs-last
          backward pass from them, :func:`vehjax.smoothing.smooth_runs_last`), and
          ``vehjax.smoothing.smooth_one_run``
          ``jax.vmap``-ed over runs ("vehjax vmap") vs dynamax ``extended_kalman_smoother``,
          ``jax.vmap``-ed and ``jax.jit``-ed; vehjax/x is the first row's time over each row's
    uks   the same with the UKF (alpha 1, beta 2, kappa 0) vs ``unscented_kalman_smoother``
    par   one run of T = each of ``--sizes`` steps: the Kalman filter + RTS smoother passes on
          the EKF's linearisation of the 3-DOF model (:func:`vehjax.smoothers.gaussian.
          linearize_filtered`, built once, outside the timing), sequential
          (:mod:`vehjax.smoothers.linear`) against parallel in time
          (:mod:`vehjax.smoothers.parallel`: recursive doubling, and ``associative_scan`` up
          to ``--assoc-max``), the passes every parallel smoother and every IEKS / IPLS
          iteration runs

dynamax conditions on y_t then predicts with the input of step t + 1, exactly vehjax's
convention; its prior is vehjax's first prediction (as in ``bench all``). cuthbert's Gaussian
smoother is not included (its smoother API is not wired here). The smoothed means are checked
before any timing (max abs difference <= ``--tol``); timing is interleaved (one call of each
contender per round, ``--repeat`` rounds, best kept), compile apart.

    vehjax bench smooth                 # or: python benchmarks/bench_smooth.py
    vehjax bench smooth --quick         # tiny sizes, one round
"""

from __future__ import annotations

import argparse
import time
from importlib.metadata import version

import jax
import jax.numpy as jnp
import numpy as np

import vehjax as vj
from vehjax.cli import load_benchmark
from vehjax.smoothers import gaussian as sgauss
from vehjax.smoothers import linear, parallel
from vehjax.smoothing import forward, smooth_one_run

ROWS = ("eks", "uks", "par")


class Contender:
    def __init__(self, name, compile_s, fn, note=""):
        self.name, self.compile_s, self.fn, self.note = name, compile_s, fn, note
        self.best = float("inf")
        self.best_cpu = float("inf")  # process CPU time of the call (all threads), s


def _compile(jitted, *args):
    t0 = time.perf_counter()
    compiled = jitted.lower(*args).compile()
    return time.perf_counter() - t0, (lambda: jax.block_until_ready(compiled(*args)))


def _dynamax_params(est, p, f, h):
    from dynamax.nonlinear_gaussian_ssm import ParamsNLGSSM

    nan_y = jnp.full((p["ys"].shape[-1],), jnp.nan)
    _, first = est.step(est.init(jnp.asarray(p["x0"]), jnp.asarray(p["P0"])), nan_y, p["us"][0])
    return ParamsNLGSSM(initial_mean=first.mean, initial_covariance=first.cov,
                        dynamics_function=f, dynamics_covariance=jnp.asarray(p["Q"]),
                        emission_function=h, emission_covariance=jnp.asarray(p["R"]))


def gaussian_row(row, p, ball):
    """Contenders of the eks / uks row: [vehjax, dynamax (when installed)]."""
    th = jnp.asarray(ball.THETA)
    f = lambda x, u: ball.transition(x, u, th)  # noqa: E731
    h = lambda x, u: ball.observe(x, u, th)  # noqa: E731
    model = ball.user_model()
    if row == "eks":
        est = vj.filters.ekf(model, Q=p["Q"], R=p["R"])
    else:
        est = vj.filters.ukf(model, Q=p["Q"], R=p["R"], points=vj.filters.SigmaPoints(alpha=1.0,
                                                                                      beta=2.0, kappa=0.0))
    us, x0, P0 = p["us"], jnp.asarray(p["x0"]), jnp.asarray(p["P0"])

    t0 = time.perf_counter()
    prepared = vj.compile_run(est, p["sim"].measurements, p["sim"].inputs, x0=p["x0"],
                              P0=p["P0"], progress=False, smooth=True)
    c = time.perf_counter() - t0
    out = [Contender("vehjax", c, lambda: prepared(progress=False).states,
                     "vehjax.run(smooth=True): runs-last forward and backward, results on host")]

    def vj_one(y):
        return smooth_one_run(est, y, us, x0, P0).states

    c, fn = _compile(jax.jit(jax.vmap(vj_one)), p["ys"])
    out.append(Contender("vehjax vmap", c, fn, "smooth_one_run vmapped"))
    if ball._installed("dynamax", "dynamax"):
        from dynamax.nonlinear_gaussian_ssm import (UKFHyperParams, extended_kalman_smoother,
                                                    unscented_kalman_smoother)

        params = _dynamax_params(est, p, f, h)
        if row == "eks":
            def dx_one(y):
                return extended_kalman_smoother(params, y, inputs=us).smoothed_means
            note = "extended_kalman_smoother"
        else:
            hyper = UKFHyperParams(alpha=1.0, beta=2.0, kappa=0.0)

            def dx_one(y):
                return unscented_kalman_smoother(params, y, hyper, inputs=us).smoothed_means
            note = "unscented_kalman_smoother"
        c, fn = _compile(jax.jit(jax.vmap(dx_one)), p["ys"])
        out.append(Contender(f"dynamax {version('dynamax')}", c, fn,
                             note + ", prior = vehjax's first prediction"))
    return out


def check_and_time(contenders, repeat: int, tol: float):
    """(max abs difference of the results against the first contender, checked ok)."""
    ref = np.asarray(contenders[0].fn())
    diff = max((float(np.max(np.abs(np.asarray(c.fn()) - ref))) for c in contenders[1:]),
               default=0.0)
    if diff > tol:
        return diff, False
    for _ in range(repeat):
        for c in contenders:
            t0, c0 = time.perf_counter(), time.process_time()
            c.fn()
            c.best = min(c.best, time.perf_counter() - t0)
            c.best_cpu = min(c.best_cpu, time.process_time() - c0)
    return diff, True


def parallel_row(T: int, ball, assoc_max: int):
    """Contenders (sequential, parallel by recursive doubling, parallel by
    ``associative_scan`` when T <= assoc_max) of the passes on one run of T steps."""
    p = ball._problem(1, T)
    est = vj.filters.ekf(ball.user_model(), Q=p["Q"], R=p["R"])
    y, u = p["ys"][0], p["us"]
    states, _ = jax.jit(lambda y: forward(est, y, u, jnp.asarray(p["x0"]), jnp.asarray(p["P0"]),
                                          None, None, None))(y)
    mod = jax.jit(lambda s: sgauss.linearize_filtered(est.smoother, s, u, y.shape[1]))(states)
    ys = jnp.concatenate([jnp.full((1, y.shape[1]), jnp.nan), y])
    out = []
    kinds = [("sequential", linear, {}), ("doubling", parallel, {"scan": "doubling"})]
    if T <= assoc_max:
        kinds.append(("associative", parallel, {"scan": "associative"}))
    for name, lib, kw in kinds:
        def passes(mod, ys, lib=lib, kw=kw):
            ms, Ps, ll = lib.kalman_filter(mod, ys, **kw)
            return lib.rts_smoother(mod, ms, Ps, **kw)[0]
        c, fn = _compile(jax.jit(passes), mod, ys)
        out.append(Contender(name, c, fn))
    return out


def parser() -> argparse.ArgumentParser:
    """The benchmark's options (``vehjax bench smooth --help``)."""
    p = argparse.ArgumentParser(prog="vehjax bench smooth", description=__doc__.splitlines()[0])
    p.add_argument("--runs", type=int, default=20, help="runs, eks/uks rows (default %(default)s)")
    p.add_argument("--steps", type=int, default=500,
                   help="steps per run, eks/uks rows (default %(default)s)")
    p.add_argument("--sizes", default="1000,10000,100000",
                   help="comma list of T for the par row (default %(default)s)")
    p.add_argument("--repeat", type=int, default=3,
                   help="interleaved timing rounds; the best is reported (default %(default)s)")
    p.add_argument("--rows", default=",".join(ROWS),
                   help="comma list of rows out of %s (default %%(default)s)" % ", ".join(ROWS))
    p.add_argument("--tol", type=float, default=1e-6,
                   help="max abs difference of the smoothed means (default %(default)s)")
    p.add_argument("--assoc-max", type=int, default=1000,
                   help="largest T for which the associative_scan form is compiled and timed "
                        "(its compile takes minutes on XLA:CPU beyond; default %(default)s)")
    p.add_argument("--quick", action="store_true",
                   help="tiny sizes: 2 runs x 50 steps, par T = 100, 1000; one round (default off)")
    return p


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    if args.quick:
        args.runs, args.steps, args.sizes, args.repeat = 2, 50, "100,1000", 1
    rows = [r.strip() for r in args.rows.split(",") if r.strip()]
    bad = [r for r in rows if r not in ROWS]
    if bad or min(args.runs, args.steps, args.repeat) < 1:
        print(f"bench smooth: rows out of {', '.join(ROWS)}; --runs, --steps, --repeat >= 1")
        return 2
    sizes = [int(s) for s in args.sizes.split(",") if s.strip()]
    ball = load_benchmark("all")
    plat = jax.devices()[0].platform.upper()
    print(f"Smoothers, 3-DOF dual-track user model (nx = 3), float64, {plat}, best of "
          f"{args.repeat} interleaved, compile apart")
    failed = False
    head = (f"{'row':<6}{'library':<16}{'compile [s]':>12}{'run [s]':>10}{'vehjax/x':>10}"
            f"{'cpu [s]':>10}{'cpu ratio':>10}  note")
    if {"eks", "uks"} & set(rows):
        p = ball._problem(args.runs, args.steps)
        print(f"eks/uks: {args.runs} runs x {args.steps} steps")
        print(head)
        for row in [r for r in rows if r != "par"]:
            cs = gaussian_row(row, p, ball)
            diff, ok = check_and_time(cs, args.repeat, args.tol)
            if not ok:
                print(f"{row:<6}check FAILED: smoothed means differ by {diff:.2e} > {args.tol}")
                failed = True
                continue
            for c in cs:
                print(f"{row:<6}{c.name:<16}{c.compile_s:>12.2f}{c.best:>10.4f}"
                      f"{cs[0].best / c.best:>10.3f}{c.best_cpu:>10.4f}"
                      f"{cs[0].best_cpu / c.best_cpu:>10.3f}  {c.note}")
            print(f"{row:<6}check: max |vehjax - peer| of the smoothed means {diff:.1e}")
    if "par" in rows:
        print("par: one run, Kalman filter + RTS passes on the EKF's linearisation; "
              "ratio = time / sequential time")
        for T in sizes:
            cs = parallel_row(T, ball, args.assoc_max)
            diff, ok = check_and_time(cs, args.repeat, 1e-6)
            failed |= not ok
            for c in cs:
                print(f"T={T:<8}{c.name:<13}compile {c.compile_s:8.2f} s  run {c.best:9.4f} s  "
                      f"ratio {c.best / cs[0].best:6.2f}" + ("" if ok else "  check FAILED"))
            print(f"T={T:<8}check: max |parallel - sequential| of the smoothed means {diff:.1e}")
    print("vehjax/x: vehjax's time / this library's (0.5 = vehjax twice as fast); cpu: the "
          "best call's process CPU time (all threads), its ratio the same way (steadier than "
          "wall time on a loaded machine); par/seq < 1: the parallel passes are faster")
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
