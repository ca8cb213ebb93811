"""The integrator's sub-steps written out or as a loop (``rolled_substeps`` of
:mod:`vehjax.execution`), on the programs a user runs: the brush single-track EKF fit's program
and a 100-run study; and one run through ``vehjax.run`` against ``vehjax.filter``.

1. The fit's program (what ``vehjax.tune.fit`` compiles for the brush fit of
   :mod:`vehjax.studies.limit_drive`'s drive A: forward-mode loss, gradient and BHHH matrix
   over cf, cr, mu, R and the steering noise): trace, compile and one evaluation [s], under
   the CPU strategy with ``rolled_substeps`` True and False (one process each,
   ``--fit-one``, alternated, so neither compile is cached), and the largest relative
   difference of the two programs' outputs.
2. A study: ``vehjax.run`` of the brush EKF and UKF over ``--runs`` noisy copies of the drive
   (the runs-last step), best of ``--repeat`` interleaved calls after the first [s].
3. One run of the linear single-track EKF (sine steer, 20,000 steps): ``vehjax.run`` and
   ``vehjax.filter``, whole results, best of 7 interleaved calls after the first [ms].

    python benchmarks/rolled_substeps.py                  # all three
    python benchmarks/rolled_substeps.py --parts study --duration 40
"""

from __future__ import annotations

import argparse
import functools
import os
import subprocess
import sys
import time

import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np

import vehjax
from vehjax import execution
from vehjax.tune import likelihood, program

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import bench_fit_limit as bl  # noqa: E402

CPU = execution.for_platform("cpu")


def fit_one(rolled: bool, duration: float, out: str) -> None:
    """Part 1 in this process: print trace, compile, evaluation s; save the outputs."""
    drive = vehjax.studies.limit_drive.limit_drive("A", duration=duration, seed=0)
    model = bl.start_model("brush", drive.body)
    with execution.using(CPU._replace(rolled_substeps=rolled)):
        obj, setup = likelihood.prepare(
            functools.partial(vehjax.filters.ekf, input_noise=bl.INPUT0), model,
            np.zeros((2, 2)), bl.R0, drive.measurements, drive.inputs, x0=bl.X0, P0=bl.P0,
            params=vehjax.tune.Fitted(bl.PARAMS["brush"], noise=("R", "input")))
        flat, unravel = jax.flatten_util.ravel_pytree(obj.z0)
        fn = program._forward(obj, setup, unravel)
        f = jnp.asarray(flat)
        args = (f, jnp.eye(f.shape[0], dtype=f.dtype), jnp.zeros((0,), f.dtype), obj.data)
        t0 = time.perf_counter()
        traced = jax.jit(fn).trace(*args)
        t1 = time.perf_counter()
        compiled = traced.lower().compile()
        t2 = time.perf_counter()
    jax.block_until_ready(compiled(*args))
    times = []
    for _ in range(3):
        t = time.perf_counter()
        res = jax.block_until_ready(compiled(*args))
        times.append(time.perf_counter() - t)
    np.save(out, np.concatenate([np.ravel(np.asarray(r)) for r in jax.tree.leaves(res)]))
    print(f"{'loop' if rolled else 'written out':>12} trace {t1 - t0:6.2f}  compile "
          f"{t2 - t1:6.2f}  evaluation {min(times):6.3f}", flush=True)


def fit_part(duration: float, rounds: int) -> None:
    print(f"# 1. the brush fit's program, drive A of {duration:g} s, one process each, "
          f"alternated [s]")
    tmp = os.path.join(os.environ.get("TMPDIR", "/tmp"), f"rolled_substeps_{os.getpid()}")
    for _ in range(rounds):
        for rolled in (True, False):
            subprocess.run([sys.executable, __file__, "--fit-one", str(int(rolled)),
                            "--duration", str(duration), "--out", f"{tmp}_{int(rolled)}.npy"],
                           check=True, env=dict(os.environ, VEHJAX_COMPILATION_CACHE="off"))
    a, b = np.load(f"{tmp}_1.npy"), np.load(f"{tmp}_0.npy")
    print(f"  largest relative difference of the outputs: "
          f"{np.max(np.abs(a - b) / np.maximum(np.abs(b), 1e-300)):.2g}")


def study_part(duration: float, runs: int, repeat: int) -> None:
    drive = vehjax.studies.limit_drive.limit_drive("A", duration=duration, seed=0)
    model = bl.start_model("brush", drive.body)
    ys = drive.measurements + 0.01 * np.random.default_rng(0).standard_normal(
        (runs,) + drive.measurements.shape)
    print(f"# 2. a study: {runs} runs x {drive.t.size} steps, brush, best of {repeat} [s]")
    for name in ("ekf", "ukf"):
        est = getattr(vehjax.filters, name)(model, 1e-4 * np.eye(2), bl.R0)
        best = {True: np.inf, False: np.inf}
        for rolled in (True, False):  # the compiles
            vehjax.run(est, ys, drive.inputs, x0=bl.X0, P0=bl.P0, progress=False,
                       execution=vehjax.Execution(
                           strategy=CPU._replace(rolled_substeps=rolled)))
        for _ in range(repeat):
            for rolled in (True, False):
                t = time.perf_counter()
                vehjax.run(est, ys, drive.inputs, x0=bl.X0, P0=bl.P0, progress=False,
                           execution=vehjax.Execution(
                           strategy=CPU._replace(rolled_substeps=rolled)))
                best[rolled] = min(best[rolled], time.perf_counter() - t)
        print(f"  {name.upper()}: loop {best[True]:.3f}, written out {best[False]:.3f}")


def one_run_part() -> None:
    model = vehjax.models.SingleTrack()
    sim = vehjax.simulate(model, vehjax.scenarios.sine_steer(model, speed=20.0, duration=200.0),
                          runs=1, key=jax.random.key(0))
    est = vehjax.filters.ekf(model, np.eye(2) * 1e-4, np.eye(2) * 1e-2)
    ys, us = np.asarray(sim.measurements), np.asarray(sim.inputs)
    us = us[0] if us.ndim == 3 else us
    x0, P0 = np.zeros(2), np.eye(2) * 1e-2
    calls = {"run": lambda: vehjax.run(est, ys, us, x0=x0, P0=P0, progress=False).states,
             "filter": lambda: vehjax.filter(est, ys[0], us, x0=x0, P0=P0).states}
    best = {}
    for f in calls.values():
        f()
    for _ in range(7):
        for name, f in calls.items():
            t = time.perf_counter()
            jax.block_until_ready(f())
            best[name] = min(best.get(name, np.inf), time.perf_counter() - t)
    print(f"# 3. one run, linear single-track EKF, {ys.shape[1]} steps, whole result [ms]: "
          f"run {1e3 * best['run']:.2f}, filter {1e3 * best['filter']:.2f} "
          f"(run / filter {best['run'] / best['filter']:.2f})")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--parts", default="fit,study,one", help="of fit, study, one")
    p.add_argument("--duration", type=float, default=200.0, help="s of drive (default 200)")
    p.add_argument("--runs", type=int, default=100)
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--rounds", type=int, default=2, help="alternated rounds of part 1")
    p.add_argument("--fit-one", type=int, choices=(0, 1), help=argparse.SUPPRESS)
    p.add_argument("--out", help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a.fit_one is not None:
        fit_one(bool(a.fit_one), a.duration, a.out)
        return 0
    parts = a.parts.split(",")
    if "fit" in parts:
        fit_part(a.duration, a.rounds)
    if "study" in parts:
        study_part(a.duration, a.runs, a.repeat)
    if "one" in parts:
        one_run_part()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
