"""What each fitted number costs the fit's derivative: the value of ``vehjax.tune.objective``
and its value and gradient by forward-mode tangents (:func:`vehjax.tune.program.forward_scores`,
the program ``vehjax.tune.fit`` compiles), per step, for fits of more and more numbers on
:mod:`benchmarks.bench_floor`'s single-track problem (the limit drive's variant A, linear tyres).

Rows: the fitted numbers (parameters and the noise's variances, as ``tune.Fitted`` names them),
their count n, the value's and the value-and-gradient's time per step [us] (best of
``--repeat`` interleaved calls, compile apart) and their ratio. The slope of the gradient's
time in n is each tangent direction's cost.

    python benchmarks/forward_directions.py
    python benchmarks/forward_directions.py --duration 20 --repeat 3
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import jax
import jax.flatten_util
import jax.numpy as jnp

import vehjax
from vehjax.tune import program

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_floor  # noqa: E402  (the problem, as that benchmark builds it)

FITS = ((("cf", "cr"), ()), (("cf", "cr"), ("R",)), (("cf",), ("Q", "R")),
        (("cf", "cr", "iz"), ("R",)), (("cf", "cr", "iz", "m"), ("R",)))


def programs(model, ys, us, names, noise):
    """(n, value program and its argument, value-and-gradient program and its argument)."""
    obj, setup = vehjax.tune.prepare(vehjax.filters.ekf, model, bench_floor.Q, bench_floor.R,
                                     ys, us, x0=bench_floor.X0, P0=bench_floor.P0,
                                     params=vehjax.tune.Fitted(names, noise=noise))
    flat, unravel = jax.flatten_util.ravel_pytree(obj.z0)

    def fwd(f, d):
        ll, dll, _ = program.forward_scores(lambda g, dd: setup.per_step(unravel(g), dd), f, d)
        return -jnp.sum(ll), -jnp.sum(dll.reshape(f.shape[0], -1), 1)

    value = jax.jit(lambda z, d: obj.loss(z, d)[0])
    return flat.shape[0], (value, (obj.z0, obj.data)), (jax.jit(fwd), (flat, obj.data))


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python benchmarks/forward_directions.py",
                                description=__doc__.splitlines()[0])
    p.add_argument("--duration", type=float, default=200.0,
                   help="s of the drive at 100 Hz (default %(default)s: 20,000 steps)")
    p.add_argument("--repeat", type=int, default=5, help="interleaved rounds (default %(default)s)")
    return p


def main(argv=None) -> int:
    a = parser().parse_args(argv)
    if a.duration <= 0 or a.repeat < 1:
        raise SystemExit("forward_directions: --duration must be > 0 and --repeat >= 1")
    _, model, ys, us, *_ = bench_floor.single_track_problem(a.duration)
    rows = []
    for names, noise in FITS:
        n, value, grad = programs(model, ys, us, names, noise)
        for fn, args in (value, grad):  # compile apart
            bench_floor.timed(fn, args)
        rows.append([names, noise, n, value, grad, float("inf"), float("inf")])
    for _ in range(a.repeat):
        for r in rows:
            r[5] = min(r[5], bench_floor.timed(*r[3]))
            r[6] = min(r[6], bench_floor.timed(*r[4]))
    T = len(ys)
    print(f"# {T} steps, SingleTrack linear, EKF, float64, {jax.devices()[0]}; best of "
          f"{a.repeat} interleaved rounds, us per step")
    print(f"{'fitted':<34} {'n':>3} {'value':>8} {'value+grad':>11} {'ratio':>6}")
    for names, noise, n, _, _, tv, tg in rows:
        label = ", ".join(names + tuple(f"noise {k}" for k in noise))
        print(f"{label:<34} {n:3d} {tv / T * 1e6:8.3f} {tg / T * 1e6:11.3f} {tg / tv:6.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
