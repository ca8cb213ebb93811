"""SevenDOF's integrators: accuracy against a fine-step reference, and cost per step and Jacobian.

The manoeuvre is the 10 s ISO double lane change at 80 km/h (``vehjax.scenarios.
double_lane_change`` on SevenDOF, |ay| up to 5.9 m/s^2), its inputs replayed open loop by each
integrator (10 ms zero-order hold). Errors are the largest absolute deviations over the 1000
steps from RK4 with ``--ref-substeps`` sub-steps per 10 ms: of u, v, r, the four wheel speeds
(the largest of the four) and ay from ``SevenDOF.derived``. "One step" repeats that from the
reference's own states, one step at a time (what a filter's prediction sees), and gives the
largest error of one step.

Cost: ``transition`` and ``jax.jacfwd(transition)``, each jitted and vmapped over ``--states``
states drawn from the reference trajectory; compile apart; timed interleaved (one call of each
contender per round, ``--repeat`` rounds, best kept), so that a change in machine load hits all
alike. "x rk4" is RK4-10's time divided by the row's (above 1: cheaper than RK4-10).

    python benchmarks/bench_sevendof.py                 # a few minutes on 2 CPU cores
    python benchmarks/bench_sevendof.py --integrators rk4:10,etdrk4:3 --states 200 --repeat 3
"""

from __future__ import annotations

import argparse
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import vehjax as vj
from vehjax.models.sevendof import SevenDOF

SPEED = 80.0 / 3.6  # m/s
COLUMNS = ("u", "v", "r", "wheels", "ay")


@eqx.filter_jit
def _replay(model, x0, inputs):
    def step(x, u):
        xn = model.transition(x, u, model.theta)
        return xn, (xn, model.derived(xn, u, model.theta))

    return jax.lax.scan(step, x0, inputs)[1]


@eqx.filter_jit
def _one_steps(model, states, inputs):
    def one(x, u):
        xn = model.transition(x, u, model.theta)
        return xn, model.derived(xn, u, model.theta)

    return jax.vmap(one)(states, inputs)


def _errors(x, d, x_ref, d_ref):
    ex = np.max(np.abs(np.asarray(x) - np.asarray(x_ref)), axis=0)
    ed = np.max(np.abs(np.asarray(d) - np.asarray(d_ref)), axis=0)
    return np.array([ex[0], ex[1], ex[2], np.max(ex[3:]), ed[3]])


def _model(spec: str) -> SevenDOF:
    name, _, sub = spec.partition(":")
    return SevenDOF(integrator=name, substeps=int(sub) if sub else None)


def parser() -> argparse.ArgumentParser:
    """The benchmark's options (``vehjax bench sevendof --help``)."""
    ap = argparse.ArgumentParser(prog="vehjax bench sevendof",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("--integrators", default="rk4:10,ros2:1,ros2:2,etdrk4:2,etdrk4:3,etdrk4:4",
                    help="integrator:substeps, comma separated (default %(default)s)")
    ap.add_argument("--ref-substeps", type=int, default=160,
                    help="RK4 sub-steps per 10 ms of the reference (default %(default)s)")
    ap.add_argument("--states", type=int, default=1000,
                    help="states per timed call (default %(default)s)")
    ap.add_argument("--repeat", type=int, default=7,
                    help="timing rounds, the best kept (default %(default)s)")
    ap.add_argument("--no-timing", action="store_true",
                    help="accuracy only (default: time them too)")
    return ap


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    specs = [s.strip() for s in args.integrators.split(",") if s.strip()]
    models = {spec: _model(spec) for spec in specs}

    scn = vj.scenarios.double_lane_change(SevenDOF(), speed=SPEED, duration=10.0)
    x_ref, d_ref = _replay(SevenDOF(substeps=args.ref_substeps), scn.x0, scn.inputs)
    starts = jnp.concatenate([jnp.asarray(scn.x0)[None], x_ref[:-1]])
    print(f"SevenDOF, double lane change at {SPEED * 3.6:.0f} km/h, 10 s, dt = 10 ms, float64, "
          f"{jax.default_backend()}; reference: RK4 with {args.ref_substeps} sub-steps per step; "
          f"peak |ay| {float(jnp.max(jnp.abs(d_ref[:, 3]))):.2f} m/s^2")
    print(f"{'max abs error':<14}" + "".join(f"{c:>10}" for c in COLUMNS)
          + "   | one step:" + "".join(f"{c:>9}" for c in COLUMNS))
    for spec, model in models.items():
        x, d = _replay(model, scn.x0, scn.inputs)
        x1, d1 = _one_steps(model, starts, scn.inputs)
        e, e1 = _errors(x, d, x_ref, d_ref), _errors(x1, d1, x_ref, d_ref)
        print(f"{spec:<14}" + "".join(f"{v:>10.1e}" for v in e) + "   |          "
              + "".join(f"{v:>9.1e}" for v in e1))
    print("units: u, v [m/s], r [rad/s], wheels [rad/s] (about 62), ay [m/s^2]")
    if args.no_timing:
        return 0

    rng = np.random.default_rng(0)
    idx = rng.integers(0, x_ref.shape[0], args.states)
    X = jnp.asarray(np.asarray(x_ref)[idx] * (1.0 + 1e-3 * rng.normal(size=(args.states, 7))))
    U = jnp.asarray(np.asarray(scn.inputs)[idx])
    fns, compile_s = {}, {}
    for spec, model in models.items():
        th = model.theta
        step = jax.jit(jax.vmap(lambda x, u, m=model: m.transition(x, u, th)))
        jac = jax.jit(jax.vmap(jax.jacfwd(lambda x, u, m=model: m.transition(x, u, th))))
        times = []
        for fn in (step, jac):
            t0 = time.perf_counter()
            jax.block_until_ready(fn(X, U))
            times.append(time.perf_counter() - t0)
        fns[spec], compile_s[spec] = (step, jac), times
    best = {spec: [np.inf, np.inf] for spec in fns}
    for _ in range(args.repeat):
        for spec, pair in fns.items():
            for i, fn in enumerate(pair):
                t0 = time.perf_counter()
                jax.block_until_ready(fn(X, U))
                best[spec][i] = min(best[spec][i], time.perf_counter() - t0)
    ref = best.get("rk4:10")
    print(f"\ncost over {args.states} states, best of {args.repeat} (interleaved), compile apart")
    print(f"{'':<14}{'step [ms]':>10}{'x rk4':>8}{'jacfwd [ms]':>13}{'x rk4':>8}"
          f"{'compile [s]':>14}")
    for spec, (t_step, t_jac) in best.items():
        r1 = f"{ref[0] / t_step:>8.2f}" if ref else f"{'':>8}"
        r2 = f"{ref[1] / t_jac:>8.2f}" if ref else f"{'':>8}"
        c = compile_s[spec]
        print(f"{spec:<14}{t_step * 1e3:>10.1f}{r1}{t_jac * 1e3:>13.1f}{r2}"
              f"{c[0]:>7.1f} /{c[1]:>5.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
