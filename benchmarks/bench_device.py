"""Every family on the device at hand (GPU, TPU or CPU) against its peers, in one command.

What issue #28 asks of a GPU, measured on whatever ``jax.devices()[0]`` is, through the public
API (``vehjax.compile_run``, compile time apart, the study's results brought to the host):

1. ``bench all``'s rows (EKF, UKF, bootstrap PF, Liu-West on the user-written 3-DOF model, each
   against the installed peers, estimates checked first, timing interleaved) at two sizes:
   20 runs x 500 steps with 500 particles, and 1000 runs x 1000 steps with 1000 particles.
2. The marginalized PF (paper 004's filter, N = 500): time per run-step at 1000 runs through
   ``vehjax.run`` and per step for one run.
3. A UKF study of 100,000 runs x 1000 steps (results on the host), and the bootstrap PF's
   particle-steps per second at 1000 runs x 1000 particles.
4. float32 against float64 for every family: time and the largest difference of the filtered
   means (relative to the float64 estimate's error against the truth).

Each timing is the best of ``--repeat``; the device's name is printed. The execution strategy is
the device's own (:mod:`vehjax.execution`); ``--strategy cpu|gpu`` forces another.

    vehjax bench device                  # on a GPU: about 5 minutes
    vehjax bench device --quick          # tiny sizes on any device (the test suite runs it)
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import vehjax as vj

#: (runs, steps, particles) of the peer comparison; --quick replaces them.
SIZES = ((20, 500, 500), (1000, 1000, 1000))
QUICK = ((2, 20, 32),)
MPF = dict(particles=500, runs=1000, steps=500)
MPF_QUICK = dict(particles=16, runs=2, steps=10)
SCALE = dict(ukf_runs=100_000, steps=1000, pf_runs=1000, particles=1000)
SCALE_QUICK = dict(ukf_runs=50, steps=10, pf_runs=2, particles=32)


def _bench_all():
    """benchmarks/bench_all.py beside this file, as a module (its problem, rows and table)."""
    path = Path(__file__).resolve().parent / "bench_all.py"
    spec = importlib.util.spec_from_file_location("bench_all", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def parser() -> argparse.ArgumentParser:
    """The benchmark's options (``vehjax bench device --help``)."""
    p = argparse.ArgumentParser(prog="vehjax bench device", description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true",
                   help="tiny sizes (seconds, any device; default off: the issue's sizes)")
    p.add_argument("--repeat", type=int, default=3,
                   help="timed repeats; the best is reported (default %(default)s)")
    p.add_argument("--parts", default="peers,mpf,scale,float32",
                   help="comma list of parts: peers, mpf, scale, float32 (default %(default)s)")
    p.add_argument("--families", default="EKF,UKF,bootstrap PF,Liu-West",
                   help="comma list of the float32 part's families (default %(default)s)")
    p.add_argument("--strategy", default=None, choices=("cpu", "gpu", "tpu"),
                   help="force a platform's execution strategy (default: the device's)")
    return p


def _best(fn, repeat: int) -> float:
    fn()  # warm
    best = math.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def _prepared(est, ys, us, x0, P0, strategy, key=None, dtype=np.float64):
    """(compile s, the prepared study) in ``dtype``."""
    cast = lambda a: np.asarray(a, dtype)  # noqa: E731
    t0 = time.perf_counter()
    prep = vj.compile_run(est, cast(ys), cast(us), x0=cast(x0), P0=cast(P0), key=key,
                          progress=False,
                          execution=vj.Execution(strategy=strategy))
    return time.perf_counter() - t0, prep


def peers(ba, args, sizes) -> list:
    """bench all's table at each size; [(size, title, ratio, peer)]."""
    out = []
    for runs, steps, particles in sizes:
        ns = argparse.Namespace(runs=runs, steps=steps, particles=particles, repeat=args.repeat,
                                filterpy_runs=1, tol=1e-6)
        print(f"\n== peers: {runs} runs x {steps} steps, {particles} particles ==")
        p = ba._problem(runs, steps)
        rows = [r for r in ba.ROWS]
        results, _ = ba.measure(rows, p, ns)
        for title, ratio, name in ba.table(results, runs * steps):
            out.append((f"{runs}x{steps}", title, ratio, name))
    return out


def marginalized(args, size) -> dict:
    """The marginalized PF at N particles: ms per run-step at ``runs`` runs, ms per step for
    one run (both through ``vehjax.compile_run``)."""
    from vehjax.studies import banked_road as road

    drive = vj.data.load_comma2k19()
    model = vj.models.SingleTrackBank(dt=drive.dt)
    T, R, N = size["steps"], size["runs"], size["particles"]
    U = road.looped_inputs(drive.inputs(model), T)
    t = np.arange(1, T + 1) * model.dt
    acc, _ = road.bank_profile(t, model.dt)
    _, Y, _ = (np.asarray(a) for a in road.simulate_truth(model, U, acc, R, jax.random.key(0)))
    est = road.build_sim_filter(model, N)
    x0 = np.zeros(5)
    P0 = np.diag([0.1, 0.5 * road.DEG, 0.5 * road.DEG, 0.2 * road.DEG, 0.2 * road.DEG]) ** 2
    res = {}
    for runs in (R, 1):
        c, prep = _prepared(est, Y[:runs], U, x0, P0, args.strategy, key=jax.random.key(1))
        s = _best(prep, args.repeat)
        res[runs] = s / (runs * T) * 1e3
        print(f"marginalized PF N = {N}, {runs} run(s) x {T} steps: compile {c:.1f} s, "
              f"{res[runs]:.5f} ms per run-step")
    return res


def scale(ba, args, size) -> dict:
    """The UKF over ``ukf_runs`` runs (seconds, results on the host) and the bootstrap PF's
    particle-steps per second at ``pf_runs`` runs."""
    T = size["steps"]
    p = ba._problem(1, T)
    ys = np.broadcast_to(np.asarray(p["ys"]), (size["ukf_runs"],) + np.shape(p["ys"])[1:])
    est = vj.filters.ukf(ba.user_model(), Q=p["Q"], R=p["R"])
    c, prep = _prepared(est, ys, p["us"], p["x0"], p["P0"], args.strategy)
    s = _best(prep, max(1, args.repeat - 1))
    print(f"UKF {size['ukf_runs']} runs x {T} steps: compile {c:.1f} s, run {s:.3f} s "
          f"({prep.n_chunks} chunk(s))")
    pf = vj.filters.bootstrap_pf(ba.user_model(), p["Q"], p["R"], n_particles=size["particles"],
                                 resampling=vj.filters.Resampling(scheme="systematic",
                                                                  ess_threshold=ba.ESS_THRESHOLD))
    ys = np.broadcast_to(np.asarray(p["ys"]), (size["pf_runs"],) + np.shape(p["ys"])[1:])
    c, prep = _prepared(pf, ys, p["us"], p["x0"], p["P0"], args.strategy, key=jax.random.key(1))
    s_pf = _best(prep, max(1, args.repeat - 1))
    rate = size["pf_runs"] * T * size["particles"] / s_pf
    print(f"bootstrap PF {size['pf_runs']} runs x {T} steps x {size['particles']} particles: "
          f"compile {c:.1f} s, run {s_pf:.3f} s, {rate:.3g} particle-steps per second")
    return dict(ukf_s=s, pf_rate=rate)


def float32(ba, args, runs, steps, particles) -> list:
    """Each family in float32 and float64: [(family, t32/t64, max |mean32 - mean64| / RMSE64)]."""
    p = ba._problem(runs, steps)
    m = ba.user_model()
    idx, low, high = ba._box()
    families = {
        "EKF": (vj.filters.ekf(m, Q=p["Q"], R=p["R"]), None),
        "UKF": (vj.filters.ukf(m, Q=p["Q"], R=p["R"]), None),
        "bootstrap PF": (vj.filters.bootstrap_pf(m, p["Q"], p["R"], n_particles=particles,
                                                 resampling=vj.filters.Resampling(scheme="systematic", ess_threshold=ba.ESS_THRESHOLD)), jax.random.key(1)),
        "Liu-West": (vj.filters.liu_west_ukf(m, p["Q"], p["R"], n_particles=particles,
                                             estimate=ba.ESTIMATE, theta_low=low,
                                             theta_high=high), jax.random.key(2)),
    }
    wanted = [f.strip() for f in args.families.split(",") if f.strip()]
    unknown = [f for f in wanted if f not in families]
    if unknown:
        raise ValueError(f"--families: unknown {unknown}; expected some of {list(families)}")
    families = {k: v for k, v in families.items() if k in wanted}
    out = []
    print(f"\n== float32 vs float64: {runs} runs x {steps} steps, {particles} particles ==")
    print(f"{'family':<14}{'t64 [s]':>10}{'t32 [s]':>10}{'t32/t64':>9}{'rmse64':>10}"
          f"{'rmse32':>10}{'max|d|/rmse64':>15}")
    for name, (est, key) in families.items():
        res = {}
        for dtype in (np.float64, np.float32):
            # float32 throughout: vehjax switches float64 on globally, and a filter's constants
            # (Q, R, the model's numbers) are float64 numpy arrays that would promote the step
            # back to float64; traced with x64 off they become float32 too
            with jax.enable_x64(dtype == np.float64):
                _, prep = _prepared(est, p["sim"].measurements, p["sim"].inputs, p["x0"],
                                    p["P0"], args.strategy, key=key, dtype=dtype)
                t = _best(prep, args.repeat)
                states = prep().states
                assert states.dtype == dtype, (name, states.dtype)
                res[dtype] = (t, np.asarray(states, np.float64))
        (t64, s64), (t32, s32) = res[np.float64], res[np.float32]
        rm64 = ba._rmse(s64, p["truth"])
        rm32 = ba._rmse(s32, p["truth"])
        d = float(np.nanmax(np.abs(s32 - s64))) / rm64
        print(f"{name:<14}{t64:>10.4f}{t32:>10.4f}{t32 / t64:>9.2f}{rm64:>10.4f}{rm32:>10.4f}"
              f"{d:>15.1e}")
        out.append((name, t32 / t64, d))
    return out


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    if args.repeat < 1:
        print("bench device: --repeat must be >= 1")
        return 2
    parts = [s.strip() for s in args.parts.split(",") if s.strip()]
    bad = [s for s in parts if s not in ("peers", "mpf", "scale", "float32")]
    if bad:
        print(f"bench device: unknown part(s) {', '.join(bad)}")
        return 2
    dev = jax.devices()[0]
    print(f"Device benchmark on {dev.device_kind} ({dev.platform.upper()}, "
          f"{jax.device_count()} device(s)), float64 unless said, strategy "
          f"{args.strategy or 'the device'}'s: {vj.execution.resolve(args.strategy, dev)}")
    ba = _bench_all()
    sizes = QUICK if args.quick else SIZES
    verdicts = peers(ba, args, sizes) if "peers" in parts else []
    mpf = marginalized(args, MPF_QUICK if args.quick else MPF) if "mpf" in parts else None
    sc = scale(ba, args, SCALE_QUICK if args.quick else SCALE) if "scale" in parts else None
    f32 = float32(ba, args, *sizes[0]) if "float32" in parts else None

    print("\n== targets (issue #28; met or not, as measured here) ==")
    for size, title, ratio, name in verdicts:
        if math.isnan(ratio):
            print(f"{size} {title}: no peer installed")
        else:
            print(f"{size} {title}: vehjax / {name} = {ratio:.3f} "
                  f"({'meets' if ratio <= 0.5 else 'misses'} <= 0.5)")
    if mpf is not None:
        many = max(mpf)
        print(f"marginalized PF: {mpf[many] * 1e3:.2f} us per run-step at {many} runs "
              f"(target <= 1 us at 1000), {mpf[1]:.3f} ms per step for one run (target <= 0.3)")
    if sc is not None:
        print(f"UKF {SCALE_QUICK['ukf_runs'] if args.quick else SCALE['ukf_runs']} runs: "
              f"{sc['ukf_s']:.3f} s (target <= 1 s at 100,000 x 1000); bootstrap PF "
              f"{sc['pf_rate']:.3g} particle-steps/s (target >= 5e9)")
    if f32 is not None:
        print("float32: " + ", ".join(f"{n} {r:.2f}x the float64 time, max diff {d:.1e} "
                                      f"RMSE" for n, r, d in f32))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
