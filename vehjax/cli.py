"""The ``vehjax`` command: list models, simulate manoeuvres, fit a model to a drive file and run
it over another, reproduce the papers, run benchmarks."""

from __future__ import annotations

import argparse
import importlib.metadata
import importlib.util
import math
import sys
import textwrap
from pathlib import Path

from . import reproduce  # light: its registry names the study modules, loaded when run
from .commands import drive_cli  # light: fit and estimate load their work when run

BENCHMARKS = ("gaussian", "particle", "marginalized", "sevendof", "scale", "all", "liu_west_bias",
              "device", "smooth", "fit", "floor", "online")
#: the keys of vehjax.models.REGISTRY and vehjax.scenarios.REGISTRY (tests/test_import.py checks
#: that they agree), written out so that building the parser (``vehjax --help``) imports no JAX
MODELS = ("Dynamic3DOF", "KinematicBicycle", "SevenDOF", "SingleTrack", "SingleTrackBank",
          "SingleTrackLag")
SCENARIOS = ("chirp", "double_lane_change", "sine_steer", "sine_with_dwell", "step_steer")


class UsageError(ValueError):
    """A refused command-line option: a ValueError (what a reproduction's ``main`` raises for
    its bad options), reported by :func:`main` as one line under the parser's name."""

    def __init__(self, prog: str, message: str):
        super().__init__(message)
        self.prog = prog


class ArgumentParser(argparse.ArgumentParser):
    """argparse's parser whose user errors raise :class:`UsageError` instead of printing the
    usage block and exiting, so that :func:`main` reports them as one line with exit code 2
    (``vehjax simulate: error: argument --runs: expected an integer >= 1, got '0'``) and a
    reproduction's ``main`` called from Python raises ValueError for every bad option alike.
    Subparsers and the reproductions' parsers use it too."""

    def error(self, message):
        raise UsageError(self.prog, message)


def _number(kind, low=None, high=None, low_open=False):
    """An argparse type: a finite ``kind`` (int or float) with low <= value (< when
    ``low_open``) <= high; else a one-line error naming what was expected."""
    rng = "" if low is None else (f" > {low:g}" if low_open else f" >= {low:g}")
    rng += "" if high is None else (" and" if rng else "") + f" <= {high:g}"
    what = ("an integer" if kind is int else "a finite number") + rng

    def parse(text):
        try:
            v = kind(text)
        except (TypeError, ValueError):
            v = None
        if v is None or not math.isfinite(v) or (low is not None and (
                v <= low if low_open else v < low)) or (high is not None and v > high):
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
        return v

    parse.__name__ = "integer" if kind is int else "number"
    return parse


#: argparse types of the command-line numbers (finite, in range)
count = _number(int, 1)  # runs, particles: an integer >= 1
integer = _number(int)  # random seed: any integer
positive = _number(float, 0.0, low_open=True)  # seconds, m/s, factors: finite and > 0
finite = _number(float)  # any finite number


def at_least(kind, low):
    """argparse type: a finite ``kind`` (int or float) >= ``low``."""
    return _number(kind, low)


def out_folder(text: str) -> str:
    """argparse type of ``--out``: a folder that exists or can be made (no part of the path an
    existing file), refused at parsing, before any work starts."""
    path = Path(text)
    for p in (path, *path.parents):
        if p.exists():
            if not p.is_dir():
                raise argparse.ArgumentTypeError(f"{str(p)!r} exists and is not a folder")
            break
    return text


def _cmd_models(args) -> int:
    from . import models

    for cls in models.REGISTRY.values():
        print(cls().describe())
        print()
    return 0


def _floats(text: str) -> list[float]:
    """``"0.1"`` or ``"0.1,0.1,0.02"`` -> list of floats (argparse type of the noise options)."""
    try:
        values = [float(v) for v in str(text).split(",") if v.strip()]
    except ValueError:
        values = []
    if not values or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(
            f"expected a finite number or comma-separated finite numbers, got {text!r}")
    return values


def _per_component(option: str, values: list[float], names, units) -> list[float]:
    """One value per component: a single value is used for every one."""
    if len(values) == 1:
        return values * len(names)
    if len(values) != len(names):
        raise ValueError(f"{option}: expected 1 value or {len(names)} (one per "
                         f"{', '.join(names)}), got {len(values)}")
    return values


#: a scenario of at least this many steps is announced on stderr before it is driven (it takes
#: about a second per million steps, before the simulation's own progress bar)
LONG_SCENARIO_STEPS = 1_000_000


def _cmd_simulate(args) -> int:
    import jax

    from . import models, plots, scenarios
    from .simulate import check_size, simulate

    model = models.REGISTRY[args.model](dt=args.dt)
    process = _per_component("--process-std", args.process_std, model.state_names, model.state_units)
    meas = _per_component("--meas-std", args.meas_std, model.output_names, model.output_units)
    build = scenarios.REGISTRY[args.scenario]
    steps = scenarios.default_steps(build, model, args.speed)
    try:  # before the scenario is driven
        check_size(model, args.runs, steps, names="--runs, --dt")
    except ValueError as err:
        raise UsageError("vehjax simulate", str(err)) from None
    if steps >= LONG_SCENARIO_STEPS:
        print(f"vehjax simulate: driving {args.scenario} for {steps} steps of {args.dt:g} s "
              f"first", file=sys.stderr)
    scn = build(model, speed=args.speed)
    sim = simulate(model, scn, runs=args.runs, key=jax.random.key(args.seed),
                   process_std=process, meas_std=meas)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    stem = out / f"{args.model}_{args.scenario}"
    sim.save(stem.with_suffix(".npz"))

    def listing(names, units, values):
        return ", ".join(f"{n} {v:g} {u}".rstrip() if u not in ("-", "") else f"{n} {v:g}"
                         for n, u, v in zip(names, units, values))

    note = None
    if not any(process):
        note = ("process noise 0: every run has the same true states; "
                "only the measurement noise differs between runs")
    print(f"{args.runs} runs x {len(scn.t)} steps of {args.model} on {args.scenario}")
    print("process noise std per step: " + listing(model.state_names, model.state_units, process))
    print("measurement noise std: " + listing(model.output_names, model.output_units, meas))
    if note:
        print(f"note: {note} (set --process-std to make the runs differ)")
    plots.plot_simulation(sim, stem.with_suffix(".png"), model=model, note=note,
                          title=f"{args.model}, {args.scenario} at {args.speed:g} m/s")
    print(f"wrote {stem.with_suffix('.npz')} (arrays: {', '.join(sim.to_dict())})")
    print(f"wrote {stem.with_suffix('.png')}")
    return 0


def load_benchmark(which: str):
    """The module benchmarks/bench_<which>.py of a source checkout (ValueError when absent)."""
    path = Path(__file__).resolve().parents[1] / "benchmarks" / f"bench_{which}.py"
    if not path.exists():
        raise ValueError(f"bench: {path} not found (benchmarks run from a source checkout)")
    spec = importlib.util.spec_from_file_location(f"bench_{which}", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _cmd_bench(args) -> int:
    bench = load_benchmark(args.which)
    parser = bench.parser()

    def error(message):  # a refused option: one line and exit code 2 (main), not argparse's
        raise UsageError(parser.prog, message)

    parser.error = error
    parser.parse_args(args.rest)  # the benchmark's own options checked before any work
    return int(bench.main(args.rest) or 0)


def _cmd_reproduce(args) -> int:
    from . import reproduce

    return int(reproduce.load(args.paper).main(args.rest) or 0)


def _study_options(name: str, parser: argparse.ArgumentParser) -> str:
    """The options part of a study's own --help, indented under its name."""
    text = parser.format_help()
    # drop the usage line(s): the command line is shown in the heading
    body = text.split("\n\n", 1)[1] if "\n\n" in text else text
    return f"{name}:\n" + textwrap.indent(body.rstrip(), "  ")


class _HelpWithStudies(argparse.Action):
    """-h/--help of ``reproduce`` and ``bench``: the usual help, then every study's options with
    their defaults (the study modules are imported only when asked)."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS,
                 studies=None, help=None):
        super().__init__(option_strings, dest=dest, default=default, nargs=0, help=help)
        self.studies = studies

    def __call__(self, parser, namespace, values, option_string=None):
        parser.print_help()
        print()
        for name, get_parser in self.studies():
            try:
                print(_study_options(name, get_parser()))
            except Exception as err:  # a benchmark's optional dependency may be missing
                print(f"{name}: options not available ({err})")
            print()
        parser.exit()


def _reproduce_studies():
    return [(f"vehjax reproduce {name} [options]", reproduce.load(name).parser)
            for name in sorted(reproduce.REGISTRY)]


def _bench_studies():
    return [(f"vehjax bench {which} [options]", lambda w=which: load_benchmark(w).parser())
            for which in BENCHMARKS]


def _version() -> str:
    """The installed distribution's version (the package metadata, read without importing
    vehjax's modules), or "unknown" when vehjax runs from a source tree that is not installed."""
    try:
        return importlib.metadata.version("vehjax")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(
        prog="vehjax", description="Batched, jitted state and parameter estimation for road vehicles."
    )
    parser.add_argument("--version", action="version", version=f"vehjax {_version()}")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("models", help="list every model with its states, inputs, parameters, outputs")
    p.set_defaults(func=_cmd_models)

    p = sub.add_parser(
        "simulate", help="simulate R noisy runs of a manoeuvre; writes .npz and .png",
        description="Simulate R noisy runs of a manoeuvre; writes the arrays (.npz) and a figure "
                    "of the true states, the measurements and the inputs (.png). `vehjax models` "
                    "lists each model's states and outputs with their units.")
    p.add_argument("model", choices=MODELS)
    p.add_argument("scenario", choices=SCENARIOS)
    p.add_argument("--runs", type=count, default=10, help="Monte-Carlo runs (default 10)")
    p.add_argument("--speed", type=positive, default=20.0, help="speed in m/s (default 20)")
    p.add_argument("--dt", type=positive, default=0.01, help="sampling period in s (default 0.01)")
    p.add_argument("--process-std", type=_floats, default=[0.0], metavar="STD[,STD...]",
                   help="process noise std per step, in state units: one value for every state "
                        "or one per state, comma-separated (default 0: no process noise, every "
                        "run has the same true states)")
    p.add_argument("--meas-std", type=_floats, default=[0.1], metavar="STD[,STD...]",
                   help="measurement noise std, in output units: one value for every output or "
                        "one per output, comma-separated, e.g. 0.1,0.1,0.01 for Dynamic3DOF's "
                        "vx [m/s], vy [m/s], r [rad/s] (default 0.1 on every output)")
    p.add_argument("--seed", type=integer, default=0, help="random seed (default 0)")
    p.add_argument("--out", type=out_folder, default="out", help="output folder (default ./out)")
    p.set_defaults(func=_cmd_simulate)

    drive_cli.add_commands(sub, out_folder)  # fit, estimate

    p = sub.add_parser(
        "reproduce", help="reproduce a paper's study: tables and figures", add_help=False,
        usage="vehjax reproduce [-h] {%s} [options]" % ",".join(sorted(reproduce.REGISTRY)),
        description="Reproduce a paper's study: tables, report and figures. Each study's "
                    "options and their defaults are listed below; "
                    "`vehjax reproduce NAME --help` shows one study's.")
    p.add_argument("-h", "--help", action=_HelpWithStudies, studies=_reproduce_studies,
                   help="show this help with every study's options and exit")
    p.add_argument("paper", choices=sorted(reproduce.REGISTRY))
    p.add_argument("rest", nargs=argparse.REMAINDER, help="study options, e.g. --runs 4 (below)")
    p.set_defaults(func=_cmd_reproduce)

    p = sub.add_parser(
        "bench", help="side-by-side timings against other libraries", add_help=False,
        usage="vehjax bench [-h] {%s} [options]" % ",".join(BENCHMARKS),
        description="Side-by-side timings against other libraries (from a source checkout: "
                    "benchmarks/bench_NAME.py). Each benchmark's options and their defaults "
                    "are listed below; `vehjax bench NAME --help` shows one benchmark's.")
    p.add_argument("-h", "--help", action=_HelpWithStudies, studies=_bench_studies,
                   help="show this help with every benchmark's options and exit")
    p.add_argument("which", choices=list(BENCHMARKS))
    p.add_argument("rest", nargs=argparse.REMAINDER, help="benchmark options, e.g. --runs 2 (below)")
    p.set_defaults(func=_cmd_bench)
    return parser


def main(argv=None) -> int:
    """Run the command and return its exit code; a user error (a bad option, a ValueError
    naming an argument, a study too large for the memory, a path that cannot be written) is
    one line on stderr and code 2, never a traceback. ``--help`` exits (SystemExit 0) as
    argparse does."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
        return int(args.func(args) or 0)
    except SystemExit as done:  # --help (0) goes on; a refused option (2) is returned
        if done.code == 2:
            return 2
        raise
    except (ValueError, OSError) as err:
        text = " ".join(str(err).split())  # one line
        prog = getattr(err, "prog", "vehjax")  # a UsageError (also of ``python -m``'s copy)
        print(f"{prog}: error: {text}", file=sys.stderr)
        return 2
    except RuntimeError as err:  # XLA out of memory where no estimate refused the job first
        if "RESOURCE_EXHAUSTED" not in str(err):
            raise
        print(f"vehjax: error: out of memory: {_first_line(err)}; use fewer runs, steps or "
              f"particles", file=sys.stderr)
        return 2


def _first_line(err: BaseException) -> str:
    """The first non-empty line of an error's message."""
    return next((line.strip() for line in str(err).splitlines() if line.strip()), "")


if __name__ == "__main__":
    sys.exit(main())
