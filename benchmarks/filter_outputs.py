"""The Gaussian filters' outputs on fixed problems, saved to compare two versions of vehjax
(an A/B of a change that should keep the numbers, or change them by rounding only).

``save FILE``: ``vehjax.filter`` (one run) and ``vehjax.run`` (six runs, filtered and
RTS-smoothed) of the EKF, UKF and CKF on SingleTrack (linear and brush tyres) and Dynamic3DOF:
a sine steer simulated with process noise, measurement noise and missing samples; states,
covariances, log-likelihoods and NIS, into one ``.npz``. ``compare A B``: for each array, equal
bits or the largest relative difference (entries above 1e-300 in magnitude in A).

    python benchmarks/filter_outputs.py save /tmp/before.npz      # at one commit
    python benchmarks/filter_outputs.py save /tmp/after.npz       # at the other
    python benchmarks/filter_outputs.py compare /tmp/before.npz /tmp/after.npz
"""

from __future__ import annotations

import argparse

import jax
import numpy as np

import vehjax as vj

FAMILIES = ("ekf", "ukf", "ckf")


def problems():
    """{name: (model, ys (6, T, ny) with missing samples, us, Q, R, x0 (6, nx), P0)}."""
    out = {}
    for name, model in (("single_track", vj.models.SingleTrack()),
                        ("brush", vj.models.SingleTrack(tyres="brush")),
                        ("3dof", vj.models.Dynamic3DOF(dt=0.01))):
        scn = vj.scenarios.sine_steer(model, speed=20.0, amplitude=0.03, frequency=0.4,
                                      duration=10.0)
        nx, ny = len(model.state_names), len(model.output_names)
        sim = vj.simulate(model, scn, runs=6, key=jax.random.key(1),
                          process_std=np.full(nx, 1e-3), meas_std=np.full(ny, 0.05))
        ys = np.array(sim.measurements)
        ys[:, 5:9, 0] = np.nan
        ys[:, 20, :] = np.nan
        out[name] = (model, ys, np.asarray(sim.inputs), np.eye(nx) * 1e-5,
                     np.eye(ny) * 0.0025, np.asarray(sim.states)[:, 0], np.eye(nx) * 0.01)
    return out


def outputs() -> dict:
    arrays = {}
    for name, (model, ys, us, Q, R, x0, P0) in problems().items():
        for family in FAMILIES:
            est = getattr(vj.filters, family)(model, Q, R)
            one = vj.filter(est, ys[0], us, x0=x0[0], P0=P0)
            results = {"filter": one}
            for smooth in (False, True):
                results["run_smooth" if smooth else "run"] = vj.run(
                    est, ys, us, x0=x0, P0=P0, smooth=smooth, return_covariances=True,
                    progress=False)
            for how, r in results.items():
                for field in ("states", "covariances", "loglik", "nis"):
                    value = getattr(r, field, None)
                    if value is not None:
                        arrays[f"{name}/{family}/{how}/{field}"] = np.asarray(value, float)
    return arrays


def compare(a_path, b_path) -> int:
    a, b = np.load(a_path), np.load(b_path)
    for k in sorted(set(a.files) | set(b.files)):
        if k not in a.files or k not in b.files:
            print(f"{k:<44} only in {'A' if k in a.files else 'B'}")
            continue
        x, y = a[k], b[k]
        if np.array_equal(x, y, equal_nan=True):
            print(f"{k:<44} equal bits")
            continue
        big = np.abs(x) > 1e-300
        rel = np.nanmax(np.abs(x - y)[big] / np.abs(x)[big]) if big.any() else np.nan
        print(f"{k:<44} max relative difference {rel:.1e}")
    return 0


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python benchmarks/filter_outputs.py",
                                description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="what", required=True)
    sub.add_parser("save", help="write the outputs to FILE (.npz)").add_argument("file")
    c = sub.add_parser("compare", help="compare two saved files")
    c.add_argument("a")
    c.add_argument("b")
    return p


def main(argv=None) -> int:
    a = parser().parse_args(argv)
    if a.what == "save":
        np.savez(a.file, **outputs())
        return 0
    return compare(a.a, a.b)


if __name__ == "__main__":
    raise SystemExit(main())
