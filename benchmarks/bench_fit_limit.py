"""Identification at the limit: saturating tyre models fitted to simulated limit drives.

The truth is :mod:`vehjax.studies.limit_drive`'s two-track car (magic-formula tyres with a curvature
factor, load-sensitive stiffness, lateral load transfer): none of the fitted models. Each
drive is 200 s at 100 Hz (20,000 steps), peaking at about 1.39 g (variant A, truth mu 1.445)
and 1.27 g (variant B, mu 1.30; held back from every choice made in :mod:`vehjax.tune.staged`).

For each variant and tyre model (``SingleTrack(tyres="linear" | "brush" | "pacejka")``, the
body (m, iz, lf, lr) known from the data sheet, the tyre parameters at the model's nominal
values), ``vehjax.tune.fit`` with its defaults (``start="data"``) fits, by the EKF, the tyre
parameters (cf, cr; mu; the shape factors), the two measurement variances and the steering's
input-noise std on the drive with seed 0. Reported: wall and CPU time (compile included; CPU =
``time.process_time``, every thread), evaluations of the compiled program, the fitted mu
against the truth's peak, whether every parameter is inside its domain, the log-likelihood and
the nested linear model's, and the sideslip RMS [deg] of ``vehjax.filter`` and ``vehjax.smooth``
with the fitted model on another realisation of the drive (seed 1: other sensor noise, other
steering corrections). ``--trap`` also fits the brush model from its nominal values as they are
(``start="theta"``), the start that traps a fit on real data, to show what the report says.

    python benchmarks/bench_fit_limit.py                      # A and B, three tyre models
    python benchmarks/bench_fit_limit.py --variants A --models brush --trap
    python benchmarks/bench_fit_limit.py --duration 60        # shorter drives
"""

from __future__ import annotations

import argparse
import functools
import time
import warnings

import numpy as np

import vehjax
from vehjax.models import SingleTrack

PARAMS = {"linear": ("cf", "cr"), "brush": ("cf", "cr", "mu"),
          "pacejka": ("cf", "cr", "mu", "shape_f", "shape_r")}
X0, P0 = np.zeros(2), np.array([0.1, 0.01])
R0 = np.array([0.1, 1e-4])
INPUT0 = {"delta": 0.002}


def start_model(tyres: str, body: dict) -> SingleTrack:
    """The model a user starts from: the known body, the tyres' nominal values."""
    nominal = np.asarray(SingleTrack(tyres=tyres).theta)
    return SingleTrack(tyres=tyres, theta=tuple(body.values()) + tuple(nominal[4:]))


def fit(drive, tyres: str, start: str = "data"):
    """(TuneResult, wall s, CPU s, warnings' texts)."""
    t0, c0 = time.perf_counter(), time.process_time()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = vehjax.tune.fit(functools.partial(vehjax.filters.ekf, input_noise=INPUT0),
                              start_model(tyres, drive.body), np.zeros((2, 2)),
                              R0, drive.measurements, drive.inputs, x0=X0, P0=P0,
                              params=vehjax.tune.Fitted(PARAMS[tyres], noise=("R", "input")),
                              options=vehjax.tune.Options(progress=False), start=start)
    return res, time.perf_counter() - t0, time.process_time() - c0, [str(w.message) for w in
                                                                     caught]


def sideslip_rms(res, drive) -> tuple[float, float]:
    """Sideslip RMS [deg] of the fitted filter and its RTS smoother on ``drive``."""
    out = []
    for run in (vehjax.filter, vehjax.smooth):
        r = run(res.estimator, drive.measurements, drive.inputs, x0=X0, P0=P0)
        beta = np.arctan(np.asarray(r.states)[:, 0] / drive.inputs[:, 1])
        out.append(float(np.degrees(np.sqrt(np.mean((beta - drive.sideslip) ** 2)))))
    return out[0], out[1]


def in_domain(res) -> bool:
    lo, hi = res.model.param_domains().bounds()
    th = np.asarray(res.model.theta)
    return bool(np.all((th > lo) & (th < hi)))


def report(variant: str, tyres: str, start: str, res, wall, cpu, drive, held):
    mu = res.params.get("mu")
    f, s = sideslip_rms(res, held)
    nested = "-" if res.nested is None else f"{res.nested.loglik:.1f}"
    mu_txt = "-" if mu is None else f"{mu:.4f} ({100 * (mu / drive.mu - 1):+.1f} %)"
    print(f"{variant:>2} {tyres:>8} {start:>5} {wall:7.1f} {cpu:7.1f} {res.evaluations:5d} "
          f"{mu_txt:>18} {str(in_domain(res)):>6} {res.loglik:11.1f} {nested:>11} "
          f"{f:7.3f} {s:7.3f}  {'below nested' if res.below_nested else ''}"
          f"{' below floor' if res.below_floor else ''}")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--variants", default="A,B")
    p.add_argument("--models", default="linear,brush,pacejka")
    p.add_argument("--duration", type=float, default=200.0, help="s per drive (default 200)")
    p.add_argument("--trap", action="store_true", help="also the brush fit from its nominal "
                   "values as they are (start='theta')")
    p.add_argument("--summaries", action="store_true", help="print each fit's summary")
    a = p.parse_args(argv)
    print("variant, tyres, start, wall s, CPU s, evaluations, mu (against the truth's peak), "
          "in domain, log-likelihood, nested linear's, sideslip RMS deg filter / smoother "
          "(held-out realisation)")
    for v in a.variants.split(","):
        drive = vehjax.studies.limit_drive.limit_drive(v, duration=a.duration, seed=0)
        held = vehjax.studies.limit_drive.limit_drive(v, duration=a.duration, seed=1)
        print(f"# {v}: {drive.t.size} steps, truth mu {drive.mu:.4f}, peak |ay| "
              f"{np.max(np.abs(drive.ay)) / 9.81:.3f} g")
        runs = [(t, "data") for t in a.models.split(",")]
        if a.trap:
            runs.append(("brush", "theta"))
        for tyres, start in runs:
            res, wall, cpu, msgs = fit(drive, tyres, start)
            report(v, tyres, start, res, wall, cpu, drive, held)
            if a.summaries:
                print(res.summary())
                for m in msgs:
                    print("   warning:", m)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
