"""The ``vehjax`` command: list models, simulate manoeuvres, reproduce the papers, run benchmarks."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def _cmd_models(args) -> int:
    from . import models

    for cls in models.REGISTRY.values():
        print(cls().describe())
        print()
    return 0


def _cmd_simulate(args) -> int:
    import jax

    from . import models, plots, scenarios
    from .simulate import simulate

    model = models.REGISTRY[args.model](dt=args.dt)
    scn = scenarios.REGISTRY[args.scenario](model, speed=args.speed)
    sim = simulate(model, scn, runs=args.runs, key=jax.random.key(args.seed),
                   process_std=args.process_std, meas_std=args.meas_std)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    stem = out / f"{args.model}_{args.scenario}"
    sim.save(stem.with_suffix(".npz"))
    plots.plot_simulation(sim, stem.with_suffix(".png"),
                          title=f"{args.model}, {args.scenario} at {args.speed} m/s, {args.runs} runs")
    print(f"{args.runs} runs x {len(scn.t)} steps of {args.model} on {args.scenario}")
    print(f"wrote {stem.with_suffix('.npz')} (arrays: {', '.join(sim.to_dict())})")
    print(f"wrote {stem.with_suffix('.png')}")
    return 0


def _cmd_bench(args) -> int:
    import importlib.util

    path = Path(__file__).resolve().parents[1] / "benchmarks" / f"bench_{args.which}.py"
    if not path.exists():
        print(f"vehjax: error: {path} not found (benchmarks run from a source checkout)", file=sys.stderr)
        return 2
    spec = importlib.util.spec_from_file_location(f"bench_{args.which}", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return int(mod.main(args.rest) or 0)


def _cmd_reproduce(args) -> int:
    from . import reproduce

    return int(reproduce.load(args.paper).main(args.rest) or 0)


def build_parser() -> argparse.ArgumentParser:
    from . import models, scenarios

    parser = argparse.ArgumentParser(
        prog="vehjax", description="Batched, jitted state and parameter estimation for road vehicles."
    )
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("models", help="list every model with its states, inputs, parameters, outputs")
    p.set_defaults(func=_cmd_models)

    p = sub.add_parser("simulate", help="simulate R noisy runs of a manoeuvre; writes .npz and .png")
    p.add_argument("model", choices=sorted(models.REGISTRY))
    p.add_argument("scenario", choices=sorted(scenarios.REGISTRY))
    p.add_argument("--runs", type=int, default=10, help="Monte-Carlo runs (default 10)")
    p.add_argument("--speed", type=float, default=20.0, help="speed in m/s (default 20)")
    p.add_argument("--dt", type=float, default=0.01, help="sampling period in s (default 0.01)")
    p.add_argument("--process-std", type=float, default=0.0, help="process noise std per step")
    p.add_argument("--meas-std", type=float, default=0.1, help="measurement noise std")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="out", help="output folder (default ./out)")
    p.set_defaults(func=_cmd_simulate)

    from . import reproduce

    p = sub.add_parser("reproduce", help="reproduce a paper's study: tables and figures")
    p.add_argument("paper", choices=sorted(reproduce.REGISTRY))
    p.add_argument("rest", nargs=argparse.REMAINDER, help="study options, e.g. --runs 4 (see --help)")
    p.set_defaults(func=_cmd_reproduce)

    p = sub.add_parser("bench", help="side-by-side timings against other libraries")
    p.add_argument("which", choices=["gaussian", "particle"])
    p.add_argument("rest", nargs=argparse.REMAINDER, help="benchmark options, e.g. --runs 2")
    p.set_defaults(func=_cmd_bench)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except ValueError as err:
        print(f"vehjax: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
