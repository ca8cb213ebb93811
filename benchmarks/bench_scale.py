"""Scale: large studies through ``vehjax.run`` finish in bounded memory, in time linear in runs,
steps and particles.

A UKF study of up to 10,000 runs x 1,000 steps and a bootstrap-PF study of up to 1,000 runs x
1,000 steps x 1,000 particles on Dynamic3DOF (float64, the model's sine-steer manoeuvre, each run
its own noise). Every study goes through the public API a user calls: ``vehjax.compile_run``
(compile time printed apart) and then the compiled study, which splits the runs into chunks
(progress bar on stderr) and brings each chunk's results back to host memory. Printed per study:
wall time, microseconds per run-step (and per particle-step for the PF), the growth against the
smallest study of its kind next to the ideal (linear) growth, and the process's peak resident
memory. Each study runs once (no best-of: the large ones take minutes); on a shared machine the
ratios are only as steady as its load.

    python benchmarks/bench_scale.py           # or: vehjax bench scale
    python benchmarks/bench_scale.py --ukf-runs 20,40 --pf-runs 4,8 --steps 50 --particles 50,100
"""

from __future__ import annotations

import argparse
import resource
import sys
import time

import jax
import numpy as np

import vehjax as vj
from vehjax.filters.particle import bootstrap_pf


def parser() -> argparse.ArgumentParser:
    """The benchmark's options (``vehjax bench scale --help``)."""
    p = argparse.ArgumentParser(prog="vehjax bench scale", description=__doc__.splitlines()[0])
    p.add_argument("--ukf-runs", default="1000,10000",
                   help="comma-separated run counts of the UKF study (default %(default)s)")
    p.add_argument("--pf-runs", default="100,1000",
                   help="comma-separated run counts of the PF study (default %(default)s)")
    p.add_argument("--steps", type=int, default=1000,
                   help="steps per run; the PF is also timed at half of it (default %(default)s)")
    p.add_argument("--particles", default="500,1000",
                   help="comma-separated particle counts, timed at the smallest PF run count; the "
                        "largest is used for the run-count study (default %(default)s)")
    return p


def _ints(text: str, what: str) -> tuple[int, ...]:
    vals = tuple(int(v) for v in text.split(",") if v.strip())
    if not vals or min(vals) < 1:
        raise ValueError(f"{what}: expected positive integers, got {text!r}")
    return tuple(sorted(set(vals)))


def _peak_rss_gib() -> float:
    kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux
    return kib / 2**20


def _problem(runs: int, steps: int):
    """bench_particle's problem (Dynamic3DOF, sine steer, Q, R, prior), as numpy arrays."""
    from vehjax.cli import load_benchmark

    model, sim, Q, R, x0, P0 = load_benchmark("particle")._problem(runs, steps)
    return model, np.asarray(sim.measurements), np.asarray(sim.inputs), Q, R, x0, P0


def _study(est, ys, us, x0, P0, key):
    """(compile s, run s, result) of one study through the public API."""
    t0 = time.perf_counter()
    prepared = vj.compile_run(est, ys, us, x0=x0, P0=P0, key=key, progress=True)
    t1 = time.perf_counter()
    out = prepared()
    t2 = time.perf_counter()
    return t1 - t0, t2 - t1, out


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    try:
        ukf_runs = _ints(args.ukf_runs, "--ukf-runs")
        pf_runs = _ints(args.pf_runs, "--pf-runs")
        particles = _ints(args.particles, "--particles")
    except ValueError as err:
        print(f"bench scale: {err}")
        return 2
    if args.steps < 2:
        print("bench scale: --steps >= 2")
        return 2
    T, T_half = args.steps, args.steps // 2
    model, Y, U, Q, R, x0, P0 = _problem(max(ukf_runs + pf_runs), T)
    print(f"Scale benchmark: Dynamic3DOF, float64, {jax.devices()[0].platform.upper()}, "
          f"{jax.device_count()} device(s); peak memory before the studies "
          f"{_peak_rss_gib():.2f} GiB (the simulated data of {Y.shape[0]} runs included).",
          flush=True)

    rows = []  # (label, work units, unit name, compile s, run s, diverged)

    def record(label, est, runs, steps, units, unit, key=None):
        c, r, out = _study(est, Y[:runs, :steps], U[:steps], x0, P0, key)
        n_div = int(np.sum(out.diverged))
        rows.append((label, units, unit, c, r, n_div))
        print(f"  {label}: compile {c:.1f} s, run {r:.1f} s, {n_div} diverged, peak memory "
              f"{_peak_rss_gib():.2f} GiB", file=sys.stderr, flush=True)

    ukf = vj.filters.ukf(model, Q, R)
    for n in ukf_runs:
        record(f"UKF {n} runs x {T} steps", ukf, n, T, n * T, "run-step")
    key = jax.random.key(1)
    n_max, r_min = max(particles), min(pf_runs)
    for n in particles:
        record(f"PF {r_min} runs x {T} steps x {n} particles", bootstrap_pf(model, Q, R, n_particles=n),
               r_min, T, r_min * T * n, "particle-step", key)
    pf = bootstrap_pf(model, Q, R, n_particles=n_max)
    record(f"PF {r_min} runs x {T_half} steps x {n_max} particles", pf, r_min, T_half,
           r_min * T_half * n_max, "particle-step", key)
    for n in pf_runs[1:]:
        record(f"PF {n} runs x {T} steps x {n_max} particles", pf, n, T, n * T * n_max,
               "particle-step", key)

    print(f"\n{'study':<44}{'compile [s]':>12}{'run [s]':>10}{'us per unit':>13}"
          f"{'work x':>9}{'time x':>9}{'diverged':>10}")
    base = {}
    for label, units, unit, c, r, n_div in rows:
        kind = label.split()[0]
        b_units, b_time = base.setdefault(kind, (units, r))
        print(f"{label:<44}{c:>12.1f}{r:>10.1f}{r / units * 1e6:>13.4f}"
              f"{units / b_units:>9.2f}{r / b_time:>9.2f}{n_div:>10d}")
    print(f"(us per unit: per run-step for the UKF, per particle-step for the PF; 'work x' and "
          f"'time x' against the first study of each filter: linear growth means equal "
          f"numbers.) Peak memory of the process: {_peak_rss_gib():.2f} GiB.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
