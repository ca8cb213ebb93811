"""One evaluation of a fit's forward-mode program, its directions in one call or in blocks at
once on the host's threads (``split_directions`` of :mod:`vehjax.execution`).

The problem is :mod:`benchmarks.bench_fit_limit`'s (drive A of
:mod:`vehjax.studies.limit_drive`, the EKF with the steering's input noise, the tyre
parameters, the two measurement variances and the steering noise fitted): for each tyre model
the fit's program (:func:`vehjax.tune.program.compiled_loss`) compiled under the CPU strategy
with ``split_directions`` off and on (``side_by_side`` threads), each evaluated ``--repeat``
times at the start, interleaved, compile apart. Printed: the coordinates n, the block, the
compile and the best evaluation [ms] of each, their ratio, and how far the split's loss,
gradient and BHHH matrix are from the one call's (the loss to the bit: the filter's own
arithmetic is the same in every block).

    python benchmarks/split_directions.py
    python benchmarks/split_directions.py --duration 60 --models brush
"""

from __future__ import annotations

import argparse
import functools
import sys
import time
from pathlib import Path

import numpy as np

import vehjax
from vehjax import execution
from vehjax.tune import program
from vehjax.tune.likelihood import prepare

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_fit_limit as limit  # noqa: E402  (the problem, as that benchmark builds it)


def loss(drive, tyres: str, strategy):
    """(CompiledLoss, its Program) of the fit's objective compiled under ``strategy``."""
    obj, setup = prepare(functools.partial(vehjax.filters.ekf, input_noise=limit.INPUT0),
                         limit.start_model(tyres, drive.body), np.zeros((2, 2)), limit.R0,
                         drive.measurements, drive.inputs, x0=limit.X0, P0=limit.P0,
                         params=vehjax.tune.Fitted(limit.PARAMS[tyres], noise=("R", "input")))
    with execution.using(strategy):
        prog = program.compile_program(obj, setup)
        return program.compiled_loss(obj, setup, compiled=prog), prog


def timed(compiled, x, strategy) -> float:
    with execution.using(strategy):
        t0 = time.perf_counter()
        compiled.vgo(x + 1e-9 * np.random.default_rng().standard_normal(x.shape))  # no reuse
        return time.perf_counter() - t0


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python benchmarks/split_directions.py",
                                description=__doc__.splitlines()[0])
    p.add_argument("--duration", type=float, default=200.0,
                   help="s of drive A at 100 Hz (default %(default)s: 20,000 steps)")
    p.add_argument("--models", nargs="+", default=["linear", "brush", "pacejka"],
                   choices=sorted(limit.PARAMS))
    p.add_argument("--repeat", type=int, default=5, help="interleaved rounds (default %(default)s)")
    return p


def main(argv=None) -> int:
    a = parser().parse_args(argv)
    if a.duration <= 0 or a.repeat < 1:
        raise SystemExit("split_directions: --duration must be > 0 and --repeat >= 1")
    drive = vehjax.studies.limit_drive.limit_drive("A", duration=a.duration, seed=0)
    cpu = execution.for_platform("cpu")
    strategies = (cpu._replace(split_directions=False), cpu._replace(split_directions=True))
    print(f"# drive A, {len(drive.measurements)} steps, EKF, float64, side_by_side "
          f"{cpu.side_by_side}; best of {a.repeat} interleaved evaluations, ms")
    print(f"{'tyres':<8} {'n':>2} {'block':>5} {'compile s':>14} {'one call':>9} "
          f"{'blocks':>7} {'ratio':>6} {'loss equal':>10} {'grad rel':>9} {'BHHH rel':>9}")
    for tyres in a.models:
        (one, p1), (split, p2) = (loss(drive, tyres, s) for s in strategies)
        x = one.x0
        best = [float("inf"), float("inf")]
        for _ in range(a.repeat):
            for i, (c, s) in enumerate(zip((one, split), strategies)):
                best[i] = min(best[i], timed(c, x, s))
        with execution.using(strategies[0]):
            r1 = one.vgo(x + 1e-3)
        with execution.using(strategies[1]):
            r2 = split.vgo(x + 1e-3)
        grad = np.max(np.abs(r2[2] - r1[2]) / np.maximum(np.abs(r1[2]), 1e-300))
        bh = np.max(np.abs(r2[3] - r1[3])) / np.max(np.abs(r1[3]))
        print(f"{tyres:<8} {x.shape[0]:2d} {p2.block:5d} "
              f"{p1.stats['compile_seconds']:6.2f} {p2.stats['compile_seconds']:6.2f} "
              f"{best[0] * 1e3:9.1f} {best[1] * 1e3:7.1f} {best[1] / best[0]:6.2f} "
              f"{str(r1[0] == r2[0]):>10} {grad:9.1e} {bh:9.1e}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
