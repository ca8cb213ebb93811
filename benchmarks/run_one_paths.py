"""One run, three ways: ``jax.jit(vehjax.filter)`` (its loglik sum, its whole result) and
``vehjax.compile_run`` with one run under the CPU strategy with the runs-last step on and off.

Interleaved, best of 7 rounds, compile apart; data: a sine steer of each model from
``vehjax.simulate``; noise covariances 1e-4 I (process) and 1e-2 I (measurement). Prints us per
step. Findings: benchmarks/results/notes_run_one.md.

    python benchmarks/run_one_paths.py 2000 st:ekf,brush:ekf,3dof:ekf,3dof:ukf
"""

import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

import vehjax
from vehjax import execution, models

MODELS = {"st": lambda: models.SingleTrack(tyres="linear"),
          "brush": lambda: models.SingleTrack(tyres="brush"),
          "3dof": models.Dynamic3DOF, "7dof": models.SevenDOF}


def rows_of(case: str, T: int) -> dict:
    """{(case, row): (callable, args)} of one model:filter case, each compiled."""
    mname, fname = case.split(":")
    model = MODELS[mname]()
    sim = vehjax.simulate(model, vehjax.scenarios.sine_steer(model, speed=20.0,
                                                             duration=T * model.dt),
                          runs=1, key=jax.random.key(0))
    nx, ny = len(model.state_names), len(model.output_names)
    est = getattr(vehjax.filters, fname)(model, np.eye(nx) * 1e-4, np.eye(ny) * 1e-2)
    ys, us = np.asarray(sim.measurements), np.asarray(sim.inputs)
    us1 = us[0] if us.ndim == 3 else us
    x0, P0 = np.asarray(sim.states)[0, 0], np.eye(nx) * 1e-2
    yj, uj = jnp.asarray(ys[0]), jnp.asarray(us1)
    rows = {(case, "filter loglik"): (jax.jit(
                lambda y, u: jnp.sum(vehjax.filter(est, y, u, x0=x0, P0=P0).loglik)), (yj, uj)),
            (case, "filter full"): (jax.jit(
                lambda y, u: vehjax.filter(est, y, u, x0=x0, P0=P0)), (yj, uj))}
    cpu = execution.for_platform("cpu")
    for rl in (True, False):
        c = vehjax.compile_run(est, ys, us1, x0=x0, P0=P0, progress=False,
                               execution=vehjax.Execution(strategy=cpu._replace(runs_last=rl)))
        rows[(case, f"run runs_last={rl}")] = (c, ())
    return rows


def main(argv) -> int:
    T, cases = int(argv[0]), argv[1].split(",")
    rows = {}
    for case in cases:
        rows.update(rows_of(case, T))
    for f, a in rows.values():
        jax.block_until_ready(f(*a))
    best = {k: np.inf for k in rows}
    for _ in range(7):
        for k, (f, a) in rows.items():
            t0 = time.perf_counter()
            jax.block_until_ready(f(*a))
            best[k] = min(best[k], time.perf_counter() - t0)
    for k in rows:
        print(f"{k[0]:10s} {k[1]:22s} {best[k] / T * 1e6:8.3f} us/step")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
