"""The limit drives of :mod:`vehjax.studies.limit_drive`: their figures, and an EKF at the truth's values.

Per variant: the cost of generating the drive (first call with compilation, then again), its
peak |ay|, the fraction of time above 1 g, the truth's peak friction coefficient, the loop's
residual, the two-track truth's steady-state limit at a few speeds (as a fraction of mu g: where
the steady-state inverse stops converging on a slow ramp of ay), and the sideslip RMS of
``vehjax.filter`` with ``vehjax.filters.ekf`` on SingleTrack models given the body's data-sheet
values and the truth's axle cornering stiffnesses at static load: linear, brush at the truth's
mu, brush at its nominal mu = 1 (the trap of issue 47) and Pacejka (C = 1.45) at the truth's mu.
No fitting: a sanity check of the drive, not a benchmark of a fit.

    python benchmarks/limit_drive_check.py        # about a minute on 2 CPU cores
"""

from __future__ import annotations

import time

import jax.numpy as jnp
import numpy as np

import vehjax as vj
from vehjax.studies import limit_drive as ld


def steady_limit(truth, speed: float, points: int = 3000) -> float:
    """Largest ay / (mu g) at which the steady-state inverse converges, on a ramp to mu g."""
    ay = jnp.linspace(0.0, truth.mu * ld.G, points)
    vx = jnp.full(points, speed)
    z = ld.steady_state(truth, ay, vx, iterations=4)
    res = np.array([np.abs(np.asarray(ld.steady_residual(truth, z[k], ay[k], speed))).max()
                    for k in range(0, points, 10)])
    bad = np.flatnonzero(res > 1e-6)
    return 1.0 if bad.size == 0 else float(ay[10 * bad[0]] / (truth.mu * ld.G))


def ekf_sideslip(d, tyres: str, extra: tuple):
    b = d.body
    model = vj.models.SingleTrack(
        tyres=tyres, theta=(b["m"], b["iz"], b["lf"], b["lr"], d.truth.cf, d.truth.cr) + extra)
    R = np.array([d.noise_std["ay"] ** 2, d.noise_std["r"] ** 2])
    steer = float(np.hypot(d.noise_std["delta"], d.noise_std["steer_disturbance"]))
    est = vj.filters.ekf(model, np.array([0.02**2, 0.002**2]), R, input_noise={"delta": steer})
    res = vj.filter(est, jnp.asarray(d.measurements), jnp.asarray(d.inputs), x0=jnp.zeros(2),
                    P0=jnp.array([0.1, 0.01]))
    states = np.asarray(res.states)
    err = np.degrees(np.arctan(states[:, 0] / d.inputs[:, 1]) - d.sideslip)
    return np.isnan(states).any(), np.sqrt(np.mean(err**2)), float(res.loglik.sum())


def main():
    for variant in ("A", "B"):
        t0 = time.perf_counter()
        ld.limit_drive(variant)
        first = time.perf_counter() - t0
        t0 = time.perf_counter()
        d = ld.limit_drive(variant)
        again = time.perf_counter() - t0
        g = np.abs(d.ay) / ld.G
        res = np.abs(np.asarray(ld.lateral_acceleration(
            d.truth, jnp.asarray(d.states), jnp.asarray(d.true_inputs), jnp.asarray(d.ay),
            passes=1)) - d.ay).max()
        print(f"{variant}: {len(d.t)} samples, generated in {first:.1f} s (first call), "
              f"{again:.2f} s (again); peak |ay| {g.max():.3f} g, above 1 g {(g > 1).mean():.3f} "
              f"of the time; mu {d.mu:.4f} (wheels {d.truth.mu}, axles {d.axle_mu[0]:.4f}, "
              f"{d.axle_mu[1]:.4f}); loop residual {res:.1e} m/s^2; sideslip max "
              f"{np.degrees(np.abs(d.sideslip).max()):.2f} deg")
        limits = ", ".join(f"{v} m/s {steady_limit(d.truth, v):.3f}" for v in (15, 20, 25, 32))
        print(f"   steady-state limit / (mu g): {limits}")
        for tyres, extra in (("linear", ()), ("brush", (d.mu,)), ("brush", (1.0,)),
                             ("pacejka", (d.mu, 1.45, 1.45))):
            nan, rms, loglik = ekf_sideslip(d, tyres, extra)
            mu = f"mu {extra[0]:.3f}" if extra else ""
            print(f"   ekf {tyres:8s}{mu:10s} NaN {nan}, sideslip RMS {rms:.3f} deg, "
                  f"loglik {loglik:.0f}")


if __name__ == "__main__":
    main()
