"""Noise-adaptive marginalized PF (paper 004) timing: time per iteration against N, beside
vehjax's bootstrap PF on the same model, data and N.

The model is :class:`~vehjax.models.SingleTrackBank` with the paper's full filter (sensors ay,
yaw and roll gyros with unknown bias and std, the steering offset, the bank (phi, phi_dot,
phi_ddot) in a Kalman filter per particle, bank angle and virtual yaw rate of known std), on
``vehjax reproduce berntorp2018``'s simulated drive. The bootstrap PF filters the same five
states with fixed Gaussian process and measurement noise (no parameter learning). Per N, four
timings of compiled code only (compile time printed apart, from ``jit.lower().compile()``),
best of ``--repeat``, interleaved so that a change in machine load hits them alike:

    MPF 1 run        one run, ``lax.scan`` of ``step``: the latency of one iteration (paper
                     Fig. 13: 1.4 ms at N = 500 in C on a 2014 laptop, about linear in N).
    MPF R runs       ``--runs`` runs vmapped in one call: amortized time per run and step.
    bootstrap 1 run, bootstrap R runs: the same for ``bootstrap_pf``.

Targets printed at the end: one run at N = 500 <= 0.3 ms/step; R runs amortized <= 0.05 ms per
run-step; time linear in N; MPF <= 4x the bootstrap PF per particle. Then XLA's operation count
of one step per particle for both filters (cost analysis of the compiled step), the rate in
GFLOP/s the amortized target asks for, and the rates both filters reach now.

    python benchmarks/bench_marginalized.py          # or: vehjax bench marginalized
    python benchmarks/bench_marginalized.py --particles 20,40 --steps 50 --runs 2 --repeat 1
"""

from __future__ import annotations

import argparse
import math
import time

import jax
import jax.numpy as jnp
import numpy as np

PARTICLES = (50, 100, 200, 500, 1000, 2000)


def parser() -> argparse.ArgumentParser:
    """The benchmark's options (``vehjax bench marginalized --help``)."""
    p = argparse.ArgumentParser(prog="vehjax bench marginalized",
                                description=__doc__.splitlines()[0])
    p.add_argument("--particles", default=",".join(map(str, PARTICLES)),
                   help="comma-separated particle counts (default %(default)s)")
    p.add_argument("--steps", type=int, default=1000, help="steps per run (default %(default)s)")
    p.add_argument("--runs", type=int, default=100,
                   help="runs of the amortized timing; 1 skips it (default %(default)s)")
    p.add_argument("--repeat", type=int, default=3,
                   help="timed repeats; the best is reported (default %(default)s)")
    p.add_argument("--no-bootstrap", action="store_true",
                   help="skip the bootstrap PF (default: time it)")
    return p


def _problem(runs: int, steps: int):
    import vehjax as vj
    from vehjax.studies import banked_road as road

    drive = vj.data.load_comma2k19()
    model = vj.models.SingleTrackBank(dt=drive.dt)
    U = road.looped_inputs(drive.inputs(model), steps)
    t = np.arange(1, steps + 1) * model.dt
    acc, _ = road.bank_profile(t, model.dt)
    X, Y, _ = (np.asarray(a) for a in road.simulate_truth(model, U, acc, runs, jax.random.key(0)))
    return road, model, U, X, Y


def _options(est):
    """The XLA options ``vehjax.run`` compiles ``est``'s studies with on this platform (the
    execution seam's, from the estimator's workload); None for XLA's defaults."""
    from vehjax import execution

    return execution.compiler_options(execution.for_device(jax.devices()[0]), est.workload)


def _compile(jitted, *args, options=None):
    """Compiled ``jitted`` with XLA ``options`` (what ``vehjax.run`` compiles it with on this
    platform, :func:`_options`), a function that runs it, and the compile time."""
    t0 = time.perf_counter()
    compiled = jitted.lower(*args).compile(compiler_options=options)
    compile_s = time.perf_counter() - t0
    return (lambda: jax.block_until_ready(compiled(*args))), compile_s


def _driver(est, U, x0, P0, batched: bool):
    us = jnp.asarray(U)

    def one(key, ys):
        state = est.init(jnp.asarray(x0), jnp.asarray(P0), key=key)

        def body(state, yu):
            state, out = est.step(state, *yu)
            return state, out.mean

        state, mean = jax.lax.scan(body, state, (ys, us))
        return mean

    return jax.jit(jax.vmap(one) if batched else one)


def _bootstrap(model, road, n):
    from vehjax.filters import Resampling
    from vehjax.filters.particle import bootstrap_pf

    D = road.DEG
    # the steering noise and the bank jerk as additive process noise, the sensors' true stds
    g = np.asarray(model.steering_noise_gain(jnp.zeros(5), jnp.array([15.0, 0.0]), model.theta))
    Bq = np.asarray(model.bank_noise_gain())
    Q = np.outer(g, g) * (0.05 * D) ** 2 + np.outer(Bq, Bq) * road.BANK_JERK_STD ** 2
    Q = Q + np.diag([1e-4, 1e-4 * D, 1e-6, 1e-6, 1e-6]) ** 2
    R = np.array([0.2, 0.3 * D, 0.3 * D, road.PHI_STD, road.RVIRT_STD]) ** 2
    return bootstrap_pf(model, Q, R, n_particles=n, resampling=Resampling(scheme="systematic",
                                                                          ess_threshold=0.5))


def _step_flops(est, x0, P0, key, y, u, n):
    """XLA's operation count and bytes accessed of one ``step`` per particle (cost analysis of
    the step compiled with the options ``vehjax.run`` uses on this platform)."""
    state = est.init(jnp.asarray(x0), jnp.asarray(P0), key=key)
    lowered = jax.jit(est.step).lower(state, jnp.asarray(y), jnp.asarray(u))
    ca = lowered.compile(compiler_options=_options(est)).cost_analysis()
    ca = ca[0] if isinstance(ca, (list, tuple)) else ca
    return float(ca.get("flops", math.nan)) / n, float(ca.get("bytes accessed", math.nan)) / n


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    try:
        Ns = tuple(int(v) for v in args.particles.split(",") if v.strip())
    except ValueError:
        print(f"bench marginalized: --particles: expected integers, got {args.particles!r}")
        return 2
    if not Ns or min(Ns) < 2 or args.steps < 1 or args.runs < 1 or args.repeat < 1:
        print("bench marginalized: --particles >= 2, --steps, --runs, --repeat >= 1")
        return 2
    road, model, U, X, Y = _problem(args.runs, args.steps)
    x0 = np.zeros(5)
    P0 = np.diag([0.1, 0.5 * road.DEG, 0.5 * road.DEG, 0.2 * road.DEG, 0.2 * road.DEG]) ** 2
    keys = jax.random.split(jax.random.key(1), args.runs)
    Yj = jnp.asarray(Y)
    platform = jax.devices()[0].platform.upper()
    print(f"Marginalized PF benchmark: SingleTrackBank (5 states, bank in a KF per particle), "
          f"{args.steps} steps, {args.runs} runs in the amortized timing, float64, {platform}, "
          f"{jax.device_count()} device(s). The machine may be shared with other jobs: the "
          f"times are upper bounds.")
    rows = {}
    ref = 500 if 500 in Ns else max(Ns)
    for n in Ns:
        est = road.build_sim_filter(model, n)
        opts = _options(est)
        rows[(n, "MPF", 1)] = _compile(_driver(est, U, x0, P0, False), keys[0], Yj[0],
                                       options=opts)
        if args.runs > 1:
            rows[(n, "MPF", args.runs)] = _compile(_driver(est, U, x0, P0, True), keys, Yj,
                                                   options=opts)
        if n == ref and opts:  # the same with XLA's defaults, to show what the options buy
            ref_opts = opts
            rows[(n, "MPF default", 1)] = _compile(_driver(est, U, x0, P0, False), keys[0],
                                                   Yj[0])
            if args.runs > 1:
                rows[(n, "MPF default", args.runs)] = _compile(_driver(est, U, x0, P0, True),
                                                               keys, Yj)
        if not args.no_bootstrap:
            bs = _bootstrap(model, road, n)
            rows[(n, "bootstrap", 1)] = _compile(_driver(bs, U, x0, P0, False), keys[0], Yj[0])
            if args.runs > 1:
                rows[(n, "bootstrap", args.runs)] = _compile(_driver(bs, U, x0, P0, True),
                                                             keys, Yj)
    # sanity: the MPF at the largest N tracks r better than the raw gyro
    mean = np.asarray(rows[(max(Ns), "MPF", 1)][0]())
    rmse = float(np.sqrt(np.mean((mean[:, 1] - X[0, :, 1]) ** 2)) / road.DEG)
    print(f"MPF (N = {max(Ns)}) yaw-rate RMSE {rmse:.3f} deg/s vs the gyro's noise 0.3 deg/s")
    best = {k: math.inf for k in rows}
    for fn, _ in rows.values():
        fn()
    for _ in range(args.repeat):
        for k, (fn, _) in rows.items():
            t0 = time.perf_counter()
            fn()
            best[k] = min(best[k], time.perf_counter() - t0)
    ms = {k: best[k] / (args.steps * k[2]) * 1e3 for k in rows}
    R = args.runs
    for (n, what, r) in list(rows):  # --runs 1: the amortized timing is the 1-run one
        ms.setdefault((n, what, R), ms[(n, what, 1)])
    head = (f"{'N':>6}{'MPF 1 run':>12}{f'MPF {R} runs':>14}{'boot 1 run':>12}{f'boot {R} runs':>15}"
            f"{'MPF/boot':>10}{'compile MPF [s]':>17}")
    print("ms per step (1 run) and ms per run-step (amortized), compile apart, best of "
          f"{args.repeat}")
    print(head)
    for n in Ns:
        b1 = ms.get((n, "bootstrap", 1), math.nan)
        bR = ms.get((n, "bootstrap", R), math.nan)
        print(f"{n:>6}{ms[(n, 'MPF', 1)]:>12.4f}{ms[(n, 'MPF', R)]:>14.5f}{b1:>12.4f}{bR:>15.5f}"
              f"{ms[(n, 'MPF', 1)] / b1:>10.2f}"
              f"{sum(rows[k][1] for k in rows if k[:2] == (n, 'MPF')):>17.1f}")
    if (ref, "MPF default", 1) in ms:
        opts = ", ".join(f"{k}={v}" for k, v in ref_opts.items())
        print(f"MPF at N = {ref} compiled with XLA's defaults instead of the platform's "
              f"options ({opts}): {ms[(ref, 'MPF default', 1)]:.4f} ms (1 run), "
              f"{ms[(ref, 'MPF default', R)]:.5f} ms per run-step ({R} runs)")
    # targets
    if len(Ns) >= 2:
        n_lo, n_hi = min(Ns), max(Ns)
        slope = (ms[(n_hi, "MPF", 1)] - ms[(n_lo, "MPF", 1)]) / (n_hi - n_lo)
        fit = np.polyfit(np.array(Ns, float), np.array([ms[(n, "MPF", 1)] for n in Ns]), 1)
        resid = max(abs(np.polyval(fit, n) / ms[(n, "MPF", 1)] - 1) for n in Ns)
        print(f"linearity: 1-run time = {fit[1]:.4f} ms + {fit[0] * 1e3:.4f} us x N "
              f"(worst relative deviation from the line {resid:.2f}); slope end to end "
              f"{slope * 1e3:.4f} us per particle")
    one = ms[(ref, "MPF", 1)]
    amort = ms[(ref, "MPF", R)]
    print(f"target: 1 run at N = {ref}: {one:.4f} ms/step (target <= 0.3; paper 1.4 ms in C) "
          f"-> {'met' if one <= 0.3 else 'NOT met'}")
    print(f"target: {R} runs at N = {ref}: {amort:.5f} ms per run-step (target <= 0.05) -> "
          f"{'met' if amort <= 0.05 else 'NOT met'}")
    if not args.no_bootstrap:
        ratio = max(ms[(n, "MPF", 1)] / ms[(n, "bootstrap", 1)] for n in Ns)
        ratio_r = max(ms[(n, "MPF", R)] / ms[(n, "bootstrap", R)] for n in Ns)
        print(f"target: MPF / bootstrap PF per particle <= 4: worst {ratio:.2f} (1 run), "
              f"{ratio_r:.2f} ({R} runs) -> {'met' if max(ratio, ratio_r) <= 4 else 'NOT met'}")
    # what the amortized target asks of the machine
    f_mpf, b_mpf = _step_flops(road.build_sim_filter(model, ref), x0, P0, keys[0], Y[0, 0],
                               U[0], ref)
    line = (f"operations and bytes accessed per particle-step (XLA cost analysis of one step): "
            f"MPF {f_mpf:.0f}, {b_mpf / 1e3:.1f} kB")
    if not args.no_bootstrap:
        f_bs, b_bs = _step_flops(_bootstrap(model, road, ref), x0, P0, keys[0], Y[0, 0], U[0],
                                 ref)
        line += (f"; bootstrap PF {f_bs:.0f}, {b_bs / 1e3:.1f} kB (ratios {f_mpf / f_bs:.1f}, "
                 f"{b_mpf / b_bs:.1f})")
    print(line)
    need = f_mpf * ref / 0.05e-3 / 1e9
    line = (f"the {R}-run target at N = {ref} needs {need:.1f} GFLOP/s and "
            f"{b_mpf * ref / 0.05e-3 / 1e9:.0f} GB/s sustained (XLA's counts); amortized now: "
            f"MPF {f_mpf * ref / (amort * 1e-3) / 1e9:.1f} GFLOP/s, "
            f"{b_mpf * ref / (amort * 1e-3) / 1e9:.0f} GB/s")
    if not args.no_bootstrap:
        line += (f", bootstrap PF "
                 f"{f_bs * ref / (ms[(ref, 'bootstrap', R)] * 1e-3) / 1e9:.1f} GFLOP/s")
    print(line)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
