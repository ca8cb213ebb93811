"""UKF study side by side: vehjax vs dynamax 1.0.3 vs filterpy, same model, data and tuning.

A 100-run x 1000-step UKF study on Dynamic3DOF (float64, CPU). vehjax runs it as one jitted
``vehjax.run`` call; dynamax's ``unscented_kalman_filter`` is vmapped over runs; filterpy's
``UnscentedKalmanFilter`` loops in Python over a NumPy transcription of the same model, timed on
a few runs and extrapolated. Compile time is reported apart from run time; the vehjax and dynamax
runs are timed interleaved, best of ``--repeat``, so that a change in machine load hits both
alike. The three filters are checked to give the same estimates before any time is printed.

    python benchmarks/bench_gaussian.py            # or: vehjax bench gaussian
    python benchmarks/bench_gaussian.py --runs 10 --steps 200 --filterpy-runs 1
"""

from __future__ import annotations

import argparse
import math
import time

import jax
import jax.numpy as jnp
import numpy as np

import vehjax as vj

ALPHA, BETA, KAPPA = 1.0, 2.0, 0.0


def _dynamic3dof_numpy(model):
    """The 3-DOF model's RK4 step in plain NumPy/math, for filterpy's per-step Python loop."""
    m, cx, cy, lf, lr, iz, ca = (float(v) for v in np.asarray(model.theta))
    dt = model.dt

    def rhs(x, u):
        vx, vy, r = x
        s_fl, s_fr, s_rl, s_rr, d = u
        af = d - math.atan((vy + lf * r) / vx)
        ar = -math.atan((vy - lr * r) / vx)
        fxf, fxr = cx * (s_fl + s_fr), cx * (s_rl + s_rr)
        fyf, fyr = 2 * cy * af, 2 * cy * ar
        c, s = math.cos(d), math.sin(d)
        return np.array([
            vy * r + (fxf * c - fyf * s + fxr - ca * vx * vx) / m,
            -vx * r + (fxf * s + fyf * c + fyr) / m,
            (lf * (fxf * s + fyf * c) - lr * fyr) / iz,
        ])

    def fx(x, dt_, u):
        k1 = rhs(x, u)
        k2 = rhs(x + 0.5 * dt * k1, u)
        k3 = rhs(x + 0.5 * dt * k2, u)
        k4 = rhs(x + dt * k3, u)
        return x + dt / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)

    return fx


def _problem(runs: int, steps: int):
    model = vj.models.Dynamic3DOF(dt=0.01)
    scn = vj.scenarios.sine_steer(model, speed=20.0, amplitude=0.05, frequency=0.5,
                                  duration=steps * model.dt)
    Q = np.diag([0.05, 0.05, 0.01]) ** 2
    R = np.diag([0.2, 0.2, 0.05]) ** 2
    sim = vj.simulate(model, scn, runs=runs, key=jax.random.key(0), process_std=np.sqrt(np.diag(Q)),
                      meas_std=np.sqrt(np.diag(R)))
    x0 = np.asarray(scn.x0) + np.array([0.5, 0.1, 0.02])
    P0 = np.diag([1.0, 0.2, 0.05]) ** 2
    return model, sim, Q, R, x0, P0


def _best_of(fn, repeat: int) -> float:
    best = math.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        best = min(best, time.perf_counter() - t0)
    return best


def bench_vehjax(model, sim, Q, R, x0, P0):
    """(compile time in s, a call that runs the compiled study and returns the states)."""
    est = vj.filters.ukf(model, Q=Q, R=R, points=vj.filters.SigmaPoints(alpha=ALPHA, beta=BETA,
                                                                        kappa=KAPPA))
    t0 = time.perf_counter()
    compiled = vj.compile_run(est, sim.measurements, sim.inputs, x0=x0, P0=P0)
    compile_s = time.perf_counter() - t0
    return compile_s, lambda: compiled(progress=False).states


def bench_dynamax(model, sim, Q, R, x0, P0):
    """(compile time in s, a call that runs the compiled study and returns the means)."""
    from dynamax.nonlinear_gaussian_ssm import ParamsNLGSSM, UKFHyperParams, unscented_kalman_filter

    theta = model.theta
    f = lambda z, u: model.transition(z, u, theta)  # noqa: E731
    h = lambda z, u: model.observe(z, u, theta)  # noqa: E731
    hyper = UKFHyperParams(alpha=ALPHA, beta=BETA, kappa=KAPPA)
    # dynamax conditions on y_t first and then predicts with u_{t+1}; vehjax predicts with u_t
    # and then conditions. Giving dynamax vehjax's first prediction as its prior makes the two
    # recursions identical.
    prior = vj.filters.ukf(model, Q=Q, R=R, points=vj.filters.SigmaPoints(alpha=ALPHA, beta=BETA,
                                                                          kappa=KAPPA))
    nan_y = jnp.full((sim.measurements.shape[-1],), jnp.nan)
    _, first = prior.step(prior.init(jnp.asarray(x0), jnp.asarray(P0)), nan_y, sim.inputs[0])
    params = ParamsNLGSSM(initial_mean=first.mean, initial_covariance=first.cov, dynamics_function=f,
                          dynamics_covariance=jnp.asarray(Q), emission_function=h,
                          emission_covariance=jnp.asarray(R))

    def one(y):
        post = unscented_kalman_filter(params, y, hyper, inputs=sim.inputs,
                                       output_fields=["filtered_means"])
        return post.filtered_means

    fn = jax.jit(jax.vmap(one))
    t0 = time.perf_counter()
    compiled = fn.lower(sim.measurements).compile()
    compile_s = time.perf_counter() - t0
    return compile_s, lambda: compiled(sim.measurements)


def bench_filterpy(model, sim, Q, R, x0, P0, n_runs):
    from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

    fx = _dynamic3dof_numpy(model)
    ys = np.asarray(sim.measurements)
    us = np.asarray(sim.inputs)
    out = np.empty((n_runs,) + ys.shape[1:])
    t0 = time.perf_counter()
    for k in range(n_runs):
        pts = MerweScaledSigmaPoints(3, alpha=ALPHA, beta=BETA, kappa=KAPPA)
        ukf = UnscentedKalmanFilter(dim_x=3, dim_z=3, dt=model.dt, fx=fx, hx=lambda x: x, points=pts)
        ukf.x, ukf.P, ukf.Q, ukf.R = x0.copy(), P0.copy(), Q.copy(), R.copy()
        for t in range(ys.shape[1]):
            ukf.predict(u=us[t])
            ukf.update(ys[k, t])
            out[k, t] = ukf.x
    return (time.perf_counter() - t0) / n_runs, out


def parser() -> argparse.ArgumentParser:
    """The benchmark's options (``vehjax bench gaussian --help``)."""
    p = argparse.ArgumentParser(prog="vehjax bench gaussian", description=__doc__.splitlines()[0])
    p.add_argument("--runs", type=int, default=100, help="Monte-Carlo runs (default %(default)s)")
    p.add_argument("--steps", type=int, default=1000, help="steps per run (default %(default)s)")
    p.add_argument("--filterpy-runs", type=int, default=3,
                   help="filterpy runs timed, then extrapolated to --runs (default %(default)s)")
    p.add_argument("--repeat", type=int, default=7,
                   help="timed repeats; the best is reported (default %(default)s)")
    return p


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    model, sim, Q, R, x0, P0 = _problem(args.runs, args.steps)
    work = f"{args.runs} runs x {args.steps} steps, UKF on Dynamic3DOF (nx = 3, 7 sigma points), float64"
    print(f"Gaussian-filter benchmark: {work}, {jax.devices()[0].platform.upper()}")

    vj_c, vj_fn = bench_vehjax(model, sim, Q, R, x0, P0)
    dx_c, dx_fn = bench_dynamax(model, sim, Q, R, x0, P0)
    vj_x, dx_x = np.asarray(vj_fn()), np.asarray(jax.block_until_ready(dx_fn()))
    # interleaved, so that a change in machine load hits both alike; best of --repeat
    vj_r = dx_r = math.inf
    for _ in range(args.repeat):
        vj_r = min(vj_r, _best_of(vj_fn, 1))
        dx_r = min(dx_r, _best_of(dx_fn, 1))
    n_fp = max(1, min(args.filterpy_runs, args.runs))
    fp_per_run, fp_x = bench_filterpy(model, sim, Q, R, x0, P0, n_fp)
    fp_r = fp_per_run * args.runs

    diff_dx = float(np.max(np.abs(vj_x - dx_x)))
    diff_fp = float(np.max(np.abs(vj_x[:n_fp] - fp_x)))
    print(f"same estimates: max |vehjax - dynamax| = {diff_dx:.1e}, max |vehjax - filterpy| = {diff_fp:.1e}")
    if not (diff_dx < 1e-6 and diff_fp < 1e-6):
        print("the libraries disagree: timings are not of the same work")
        return 1
    rows = [
        ("vehjax", vj_c, vj_r, "measured"),
        ("dynamax 1.0.3", dx_c, dx_r, "measured"),
        ("filterpy", 0.0, fp_r, f"extrapolated from {n_fp} run(s)"),
    ]
    print(f"{'library':<16}{'compile [s]':>12}{'run [s]':>12}{'us/run-step':>13}{'vehjax/x':>10}  note")
    for name, c, r, note in rows:
        per = r / (args.runs * args.steps) * 1e6
        print(f"{name:<16}{c:>12.3f}{r:>12.4f}{per:>13.3f}{vj_r / r:>10.3f}  {note}")
    print("run: compiled run time of the whole study, best of --repeat (compile apart); "
          "us/run-step: run time per run and step in microseconds; vehjax/x: vehjax's run time "
          "divided by this library's (below 1: vehjax is faster, 0.25 = 4 times faster)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
