"""Where a fit's time goes: one ``vehjax.tune.fit`` of :mod:`benchmarks.bench_fit_limit`'s
problem (drive A of :mod:`vehjax.studies.limit_drive`, the tyre model's parameters, the two
measurement variances and the steering noise, the staged default), with its time split into
XLA's compiles, JAX's tracing and lowering (summed from :mod:`jax.monitoring`'s events), and the
rest (the programs' evaluations and the host's work).

``--side-by-side 1`` (default) runs the fit on one host thread (``side_by_side`` of
:mod:`vehjax.execution`), so that the parts add up to the wall time; with 2 the next stage's
compile runs beside the current stage's evaluations, as ``vehjax.tune.fit`` does on a 2-core
machine. Each compile of more than ``--list`` seconds is listed with the time it ended. Run
with ``VEHJAX_COMPILATION_CACHE=off`` to time every compile (else a second run reads them from
the persistent cache).

    VEHJAX_COMPILATION_CACHE=off python benchmarks/fit_profile.py
    VEHJAX_COMPILATION_CACHE=off python benchmarks/fit_profile.py --tyres linear --duration 60
"""

from __future__ import annotations

import argparse
import collections
import sys
import time
from pathlib import Path

import jax.monitoring

import vehjax

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_fit_limit  # noqa: E402  (the problem and the fit call, as that benchmark runs them)

EVENTS = {"/jax/core/compile/backend_compile_duration": "compile",
          "/jax/core/compile/jaxpr_trace_duration": "trace",
          "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower"}
_events = []


def _listen(event, duration, **kw):
    if event in EVENTS:
        _events.append((time.perf_counter(), EVENTS[event], duration, kw.get("fun_name", "?")))


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python benchmarks/fit_profile.py",
                                description=__doc__.splitlines()[0])
    p.add_argument("--tyres", default="brush", choices=tuple(bench_fit_limit.PARAMS),
                   help="the fitted model's tyres (default %(default)s)")
    p.add_argument("--duration", type=float, default=200.0,
                   help="s of the drive at 100 Hz (default %(default)s)")
    p.add_argument("--side-by-side", type=int, default=1,
                   help="host threads the fit may use (default %(default)s)")
    p.add_argument("--list", type=float, default=0.2,
                   help="list each compile longer than this, s (default %(default)s)")
    return p


def main(argv=None) -> int:
    a = parser().parse_args(argv)
    if a.duration <= 0 or a.side_by_side < 1:
        raise SystemExit("fit_profile: --duration must be > 0 and --side-by-side >= 1")
    jax.monitoring.register_event_duration_secs_listener(_listen)
    drive = vehjax.studies.limit_drive.limit_drive("A", duration=a.duration, seed=0)
    strategy = vehjax.execution.current()._replace(side_by_side=a.side_by_side)
    with vehjax.execution.using(strategy):
        t0 = time.perf_counter()
        res, wall, cpu, _ = bench_fit_limit.fit(drive, a.tyres)
    parts = collections.defaultdict(float)
    print(f"# {a.tyres} fit, {len(drive.measurements)} steps, side_by_side {a.side_by_side}: "
          f"wall {wall:.1f} s, CPU {cpu:.1f} s, {res.evaluations} evaluations")
    print(f"{'ended at s':>10} {'compile s':>10}  program")
    for t, kind, d, name in _events:
        if t < t0:
            continue
        parts[kind] += d
        if kind == "compile" and d > a.list:
            print(f"{t - t0:10.1f} {d:10.2f}  {name}")
    rest = wall - sum(parts.values())
    print("summed: " + ", ".join(f"{k} {parts[k]:.1f} s" for k in ("compile", "trace", "lower"))
          + f"; the rest (evaluations, host work) {rest:.1f} s"
          + (" (overlapping threads: the parts need not add up)" if a.side_by_side > 1 else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
