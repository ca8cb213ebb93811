"""Liu-West PF + UKF: bias of the parameter estimate and calibration of its covariance (issue #17).

``vehjax bench liu_west_bias`` compares the two kernel timings of
:func:`vehjax.filters.liu_west_ukf` (``move="resampled"``, the default, and ``move="every"``,
Liu and West's) on three pieces of work, each chosen with ``--parts``:

``3dof``
    Dynamic3DOF, m, cx, cy estimated, matched noise
    (``vehjax.studies.dual_settings.matched_settings``), true lf, lr. Two excitations: "dutta2019" (``vehjax.scenarios.slip_and_steer``, truth at nominal, prior
    box +-30 % around it) and "second" (chirp steering 0.1-1.5 Hz, 15 m/s with a +-0.8 m/s^2
    speed swing of 12 s period, truth 1.10, 0.92, 1.06 x nominal, the box still +-30 % of
    nominal, so not centred on the truth). Per filter: the mean over runs of the final estimate
    (mean of the last 10 % of the steps) relative to the truth in % with its standard error,
    the share of runs whose truth lies in the final 95 % interval, and the root-mean-square of
    (final estimate - truth) / reported std (1 = calibrated). With ``--reference``, also the
    exact reference: per run the posterior mean under the same per-parameter UKF likelihood and
    the uniform prior, on a grid (11^3 points over +-5 posterior std, refined twice, one UKF per
    point over the whole run; about 15 s per run on 2 cores), and each filter minus it. The
    grid ignores the prior box: valid when the posterior lies well inside it (60 s runs: posterior
    std 3-4 % against the box's +-30 %), not for short runs.
``skewed``
    x' = 0.9 x + u / g + w, y = x + v (the posterior of g is skewed), 200 runs x 300 steps, M =
    500 and 2000: each filter's final estimate minus the exact grid posterior mean (numpy Kalman
    filter per grid point), in posterior standard deviations: mean, its se, per-run scatter.
``few``
    KinematicBicycle, sine steering 0.5 Hz, lf and lr, 40 runs x 100 steps, M = 100, 300,
    1000: root-mean-square of (final estimate - truth) / reported std per parameter.

Every run of a piece sees the same data for both filters. Compile time is included in the
printed seconds (this is an accuracy check, not a timing).
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

PARTS = ("3dof", "skewed", "few")
MOVES = ("resampled", "every")


def parser() -> argparse.ArgumentParser:
    """Options of ``vehjax bench liu_west_bias``; each help states its default."""
    p = argparse.ArgumentParser(prog="vehjax bench liu_west_bias",
                                description="Liu-West bias against exact posteriors and "
                                            "calibration, both kernel timings (issue #17).")
    p.add_argument("--parts", default=",".join(PARTS),
                   help="comma-separated pieces of work (default %(default)s)")
    p.add_argument("--runs", type=int, default=100, help="3dof runs (default %(default)s)")
    p.add_argument("--duration", type=float, default=60.0,
                   help="3dof run length, s at 50 Hz (default %(default)g)")
    p.add_argument("--particles", type=int, default=1000,
                   help="3dof parameter particles M (default %(default)s)")
    p.add_argument("--reference", default="",
                   help="3dof: comma-separated excitations (dutta2019, second) for which to also "
                        "compute the exact grid posterior per run (slow; default none)")
    p.add_argument("--small-runs", type=int, default=200,
                   help="skewed runs (few: a fifth of them) (default %(default)s)")
    p.add_argument("--seed", type=int, default=7, help="random seed (default %(default)s)")
    return p


# -- 3dof ----------------------------------------------------------------------------------------


def _second_excitation(dyn, duration):
    from vehjax import scenarios

    nom = dict(zip(dyn.param_names, np.asarray(dyn.theta)))
    t = np.arange(int(round(duration / dyn.dt))) * dyn.dt
    speed = 15.0
    hold = nom["ca"] * speed**2 / (2 * nom["cx"])  # slip per front wheel that balances drag
    swing = 0.8 * nom["m"] / (2 * nom["cx"])  # +-0.8 m/s^2
    s = np.sin(2 * np.pi * t / 12.0)
    slip = hold + swing * np.sign(s) * np.sqrt(np.abs(s))
    rate = (1.5 - 0.1) / duration
    delta = 0.03 * np.sin(2 * np.pi * (0.1 * t + 0.5 * rate * t**2))
    z = np.zeros_like(t)
    return scenarios.from_inputs(dyn, np.stack([slip, slip, z, z, delta], 1), [speed, 0.0, 0.0],
                                 name="second excitation")


def _case(name, duration):
    """(model with the true parameters, scenario, truth (3,), box (3, 2))."""
    from vehjax import scenarios
    from vehjax.models import Dynamic3DOF

    dyn = Dynamic3DOF(dt=0.02)
    nominal = np.asarray(dyn.theta)[list(dyn.param_index(("m", "cx", "cy")))]
    box = np.stack([0.7 * nominal, 1.3 * nominal], 1)
    if name == "dutta2019":
        return dyn, scenarios.slip_and_steer(dyn, duration=duration), nominal, box
    scn = _second_excitation(dyn, duration)
    truth = nominal * np.array([1.10, 0.92, 1.06])
    return dyn.with_theta(m=truth[0], cx=truth[1], cy=truth[2]), scn, truth, box


def _grid_reference(est, dyn, sim, x0, P0, start):
    """Per run, the exact posterior mean of (m, cx, cy) on a grid, (R, 3)."""
    idx = np.asarray(dyn.param_index(("m", "cx", "cy")))
    base = jnp.asarray(dyn.theta)

    def loglik(th, Y, U):
        def body(c, yu):
            c, o = est.step(c, *yu)
            return c, o.loglik

        return jax.lax.scan(body, est.init(x0, P0, base.at[idx].set(th)), (Y, U))[1].sum()

    ll_grid = jax.jit(jax.vmap(loglik, in_axes=(0, None, None)))
    g = np.linspace(-1.0, 1.0, 11)
    G = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    U = np.asarray(sim.inputs)
    out = []
    for r in range(sim.measurements.shape[0]):
        centre, half = start[r], 0.15 * start[r]  # first pass +-15 %, then +-5 posterior std
        for _ in range(3):
            th = centre + half * G
            ll = np.asarray(ll_grid(jnp.asarray(th), jnp.asarray(sim.measurements[r]),
                                    jnp.asarray(U[r] if U.ndim == 3 else U)))
            w = np.exp(ll - ll.max())
            w /= w.sum()
            centre = w @ th
            half = 5.0 * np.sqrt(w @ (th - centre) ** 2)
        out.append(centre)
    return np.array(out)


def _three_dof(args):
    import vehjax as vj
    from vehjax.studies.dual_settings import DYNAMIC_SETTINGS, matched_settings, simulate_runs
    from vehjax.filters.gaussian import ukf

    for name in ("dutta2019", "second"):
        dyn, scn, truth, box = _case(name, args.duration)
        s = matched_settings(DYNAMIC_SETTINGS, dyn, truth, box)
        sim = simulate_runs(dyn, scn, args.runs, jax.random.key(args.seed))
        R, T = sim.measurements.shape[:2]
        print(f"\n3dof, {name} excitation: {R} runs x {T} steps, M = {args.particles}, truth "
              f"m, cx, cy = {truth[0]:.0f} kg, {truth[1]:.0f} N, {truth[2]:.0f} N/rad")
        finals = {}
        for move in MOVES:
            est = vj.filters.liu_west_ukf(dyn, s["Q"], s["R"], n_particles=args.particles,
                                          estimate=("m", "cx", "cy"), theta_low=box[:, 0],
                                          theta_high=box[:,
                                                         1], kernel=vj.filters.LiuWestKernel(move=move))
            t0 = time.perf_counter()
            res = vj.run(est, sim.measurements, sim.inputs, x0=np.asarray(scn.x0),
                         P0=np.diag(s["P0"]), key=jax.random.key(args.seed + 1),
                         return_covariances=True, progress=False)
            sec = time.perf_counter() - t0
            P = np.asarray(res.params)
            final = P[:, -max(1, T // 10):].mean(1)
            finals[move] = final
            rel = (final / truth - 1) * 100
            sd = np.sqrt(np.diagonal(np.asarray(res.params_cov)[:, -1], axis1=1, axis2=2))
            z = (P[:, -1] - truth) / sd
            print(f"  move={move:9s} final - truth %: {_pm(rel)}; truth in 95 %: "
                  f"{np.round((np.abs(z) < 1.96).mean(0), 2)}; rms z {np.round(np.sqrt((z**2).mean(0)), 2)}"
                  f"; after {T // 10 * 0.02:g} s: {np.round((P[:, T // 10 - 1] / truth - 1).mean(0) * 100, 2)}"
                  f" ({sec:.0f} s, {int(np.sum(res.diverged))} diverged)")
        if name in args.reference.split(","):
            t0 = time.perf_counter()
            ref = _grid_reference(ukf(dyn, s["Q"], s["R"]), dyn, sim, jnp.asarray(scn.x0),
                                  jnp.diag(jnp.asarray(s["P0"])), finals["resampled"])
            print(f"  exact posterior mean - truth %: {_pm((ref / truth - 1) * 100)} "
                  f"({time.perf_counter() - t0:.0f} s)")
            for move in MOVES:
                d_ = (finals[move] - ref) / truth * 100
                print(f"  move={move:9s} minus exact %: {_pm(d_)}; per-run scatter "
                      f"{np.round(d_.std(0), 2)}")


def _pm(x):
    """'mean (se)' per column of x (runs, p)."""
    m, se = x.mean(0), x.std(0) / np.sqrt(x.shape[0])
    return ", ".join(f"{a:+.2f} ({b:.2f})" for a, b in zip(m, se))


# -- skewed: scalar model, exact grid posterior -------------------------------------------------

_A, _QV, _RV = 0.9, 0.05, 0.1


def _skewed(args):
    import vehjax as vj

    T, runs, g_true, low, high = 300, args.small_runs, 1.0, 0.3, 3.0
    rng = np.random.default_rng(args.seed)
    us = 0.3 * rng.normal(size=(runs, T))
    ys, x = np.zeros((runs, T)), np.zeros(runs)
    for t in range(T):
        x = _A * x + us[:, t] / g_true + rng.normal(size=runs) * np.sqrt(_QV)
        ys[:, t] = x + rng.normal(size=runs) * np.sqrt(_RV)
    grid = np.linspace(low, high, 4001)
    xs, Ps, ll = np.zeros((runs, grid.size)), np.ones((runs, grid.size)), np.zeros((runs, grid.size))
    for t in range(T):  # a Kalman filter per run and grid point
        xs, Ps = _A * xs + us[:, t, None] / grid, _A * _A * Ps + _QV
        S = Ps + _RV
        e = ys[:, t, None] - xs
        ll += -0.5 * (e * e / S + np.log(S))
        K = Ps / S
        xs, Ps = xs + K * e, Ps * (1 - K)
    w = np.exp(ll - ll.max(1, keepdims=True))
    w /= w.sum(1, keepdims=True)
    mean = w @ grid
    std = np.sqrt(np.sum(w * (grid - mean[:, None]) ** 2, 1))
    mode = grid[np.argmax(w, 1)]
    print(f"\nskewed: x' = {_A} x + u / g, {runs} runs x {T} steps; exact posterior (mean - mode)"
          f" / std {np.mean((mean - mode) / std):.2f}")
    model = vj.models.Model(transition=lambda x, u, th: _A * x + u / th[0],
                            observe=lambda x, u, th: x, dt=0.1, state_names=("x",),
                            param_names=("g",), input_names=("u",), theta=[g_true])
    for M in (500, 2000):
        for move in MOVES:
            est = vj.filters.liu_west_ukf(model, Q=[_QV], R=[_RV], n_particles=M, estimate=("g",),
                                          theta_low=[low], theta_high=[high], kernel=vj.filters.LiuWestKernel(move=move))
            out = vj.run(est, ys[:, :, None], us[:, :, None], x0=[0.0], P0=[[1.0]],
                         key=jax.random.key(args.seed), progress=False)
            z = (np.asarray(out.params[:, -1, 0]) - mean) / std
            print(f"  M = {M:5d} move={move:9s} (estimate - exact mean) / std: mean {z.mean():+.3f}"
                  f" (se {z.std() / np.sqrt(runs):.3f}), scatter {z.std():.3f}")


# -- few particles: calibration on the kinematic bicycle -----------------------------------------


def _few(args):
    import vehjax as vj

    model = vj.models.KinematicBicycle(dt=0.1)
    scn = vj.scenarios.sine_steer(model, speed=10.0, amplitude=0.3, frequency=0.5, duration=10.0)
    meas_std = np.array([0.1, 0.1, 0.02, 0.1])
    runs = max(2, args.small_runs // 5)
    sim = vj.simulate(model, scn, runs=runs, key=jax.random.key(args.seed), process_std=0.01,
                      meas_std=meas_std)
    low, high = np.array([0.5, 0.5]), np.array([3.0, 3.0])
    truth = np.asarray(model.theta)[list(model.param_index(("lf", "lr")))]
    print(f"\nfew: KinematicBicycle sine steering, lf and lr, {runs} runs x "
          f"{sim.measurements.shape[1]} steps; rms of (estimate - truth) / reported std")
    for M in (100, 300, 1000):
        for move in MOVES:
            est = vj.filters.liu_west_ukf(model, Q=np.full(4, 1e-4), R=meas_std**2,
                                          n_particles=M, estimate=("lf", "lr"), theta_low=low,
                                          theta_high=high, kernel=vj.filters.LiuWestKernel(move=move))
            out = vj.run(est, sim.measurements, sim.inputs, x0=scn.x0,
                         P0=np.diag([1, 1, 0.2, 2.0]), key=jax.random.key(args.seed + 1),
                         return_covariances=True, progress=False)
            sd = np.sqrt(np.diagonal(np.asarray(out.params_cov)[:, -1], axis1=1, axis2=2))
            z = (np.asarray(out.params)[:, -1] - truth) / sd
            print(f"  M = {M:5d} move={move:9s} rms z {np.round(np.sqrt((z**2).mean(0)), 2)}, "
                  f"|z| > 3 in {int((np.abs(z) > 3).sum())} of {z.size}")


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    parts = [p.strip() for p in args.parts.split(",") if p.strip()]
    bad = [p for p in parts if p not in PARTS]
    if bad or not parts:
        raise SystemExit(f"--parts: expected a comma-separated subset of {PARTS}, got {args.parts!r}")
    for name, value in (("--runs", args.runs), ("--particles", args.particles),
                        ("--small-runs", args.small_runs)):
        if value < 2:
            raise SystemExit(f"{name}: expected at least 2, got {value}")
    jax.config.update("jax_enable_x64", True)
    print(f"Liu-West bias and calibration on {jax.devices()[0].device_kind}")
    for part in parts:
        {"3dof": _three_dof, "skewed": _skewed, "few": _few}[part](args)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
