"""Bootstrap particle filter side by side: vehjax vs cuthbert 0.1.1, same model, data and tuning.

A 20-run x 1000-step x 1000-particle bootstrap PF on Dynamic3DOF (float64, CPU): sine steer at
20 m/s, process noise N(0, Q) after the RK4 transition, Gaussian likelihood N(y; x, R),
systematic resampling when ESS < N / 2. Five timings, each of compiled code only (compile time
is reported apart, from ``jax.jit(...).lower(...).compile()``), best of ``--repeat``, all
interleaved so that a change in machine load hits them alike:

    vehjax scan       vehjax's ``bootstrap_pf`` Estimator: ``lax.scan`` over steps of ``step``,
                      ``vmap`` over runs; per step it keeps the weighted mean and covariance,
                      the log-likelihood increment and the NIS.
    cuthbert scan     cuthbert's ``particle_filter.build_filter`` driven the same way: a
                      ``lax.scan`` of ``filter_prepare``/``filter_combine`` (what
                      ``cuthbert.filter`` does), ``vmap`` over runs, keeping per step the
                      weighted mean and covariance; resampling ``ess_decorator(systematic, 0.5)``.
    vehjax.run        the user path: ``vehjax.run``'s compiled study (adds per-step divergence
                      checks and the copy of the results to host memory).
    cuthbert.filter   cuthbert's own driver, which returns every step's particles, weights and
                      ancestors.
    model (N, nx)     the floor: the particles through the model's transition and nothing else
    model (nx, N)     (no noise, weights or resampling), which every bootstrap PF pays; with the
                      particles as rows (N, nx), as cuthbert keeps them, and as columns (nx, N),
                      as vehjax keeps them: each state component is then one contiguous vector
                      over the particles, which halves the model's cost on CPU.

The like-for-like ratio is vehjax scan / cuthbert scan. Before any time is printed, the filters'
RMSE against the true states and their mean log-likelihoods are shown: two correct bootstrap PFs
agree to Monte-Carlo error; a large disagreement aborts with exit code 1.

    python benchmarks/bench_particle.py              # or: vehjax bench particle
    python benchmarks/bench_particle.py --runs 2 --steps 50 --particles 100 --repeat 1
"""

from __future__ import annotations

import argparse
import math
import time

import jax
import jax.numpy as jnp
import numpy as np

import vehjax as vj
from vehjax.filters import Resampling
from vehjax.filters.particle import bootstrap_pf

ESS_THRESHOLD = 0.5


def _problem(runs: int, steps: int):
    model = vj.models.Dynamic3DOF(dt=0.01)
    scn = vj.scenarios.sine_steer(model, speed=20.0, amplitude=0.05, frequency=0.5,
                                  duration=steps * model.dt)
    Q = np.diag([0.05, 0.05, 0.01]) ** 2
    R = np.diag([0.2, 0.2, 0.05]) ** 2
    sim = vj.simulate(model, scn, runs=runs, key=jax.random.key(0),
                      process_std=np.sqrt(np.diag(Q)), meas_std=np.sqrt(np.diag(R)))
    x0 = np.asarray(scn.x0) + np.array([0.5, 0.1, 0.02])
    P0 = np.diag([1.0, 0.2, 0.05]) ** 2
    return model, sim, Q, R, x0, P0


def _compile(jitted, *args):
    """(a call of the compiled function that blocks until done, compile time in s)."""
    t0 = time.perf_counter()
    compiled = jitted.lower(*args).compile()
    compile_s = time.perf_counter() - t0
    return (lambda: jax.block_until_ready(compiled(*args))), compile_s


def vehjax_scan(model, sim, Q, R, x0, P0, n_particles, keys):
    est = bootstrap_pf(model, Q, R, n_particles=n_particles,
                       resampling=Resampling(scheme="systematic", ess_threshold=ESS_THRESHOLD))

    def one(key, ys):
        state = est.init(jnp.asarray(x0), jnp.asarray(P0), key=key)

        def body(state, yu):
            state, out = est.step(state, *yu)
            return state, (out.mean, out.cov, out.loglik, out.nis)

        state, (mean, cov, ll, nis) = jax.lax.scan(body, state, (ys, sim.inputs))
        return mean, jnp.sum(ll), state.flag_diverged

    return _compile(jax.jit(jax.vmap(one)), keys, jnp.asarray(sim.measurements))


def _cuthbert_pieces(model, Q, R, x0, P0, n_particles):
    from cuthbert.smc import particle_filter
    from cuthbertlib.resampling import ess_decorator, systematic

    theta = model.theta
    LQ = jnp.linalg.cholesky(jnp.asarray(Q))
    L0 = jnp.linalg.cholesky(jnp.asarray(P0))
    R_inv = jnp.linalg.inv(jnp.asarray(R))
    log_det_2pi_R = float(np.linalg.slogdet(2.0 * np.pi * R)[1])
    x0 = jnp.asarray(x0)

    def init_sample(key):
        return x0 + L0 @ jax.random.normal(key, (3,))

    def propagate_sample(key, x, inputs):
        u, _ = inputs
        return model.transition(x, u, theta) + LQ @ jax.random.normal(key, (3,))

    def log_potential(x_prev, x, inputs):
        u, y = inputs
        e = y - model.observe(x, u, theta)
        return -0.5 * (e @ R_inv @ e) - 0.5 * log_det_2pi_R

    resampling = ess_decorator(systematic.resampling, ESS_THRESHOLD)
    return particle_filter.build_filter(init_sample, propagate_sample, log_potential,
                                        n_particles, resampling)


def cuthbert_scan(model, sim, Q, R, x0, P0, n_particles, keys):
    filt = _cuthbert_pieces(model, Q, R, x0, P0, n_particles)
    us = jnp.asarray(sim.inputs)
    T = us.shape[0]

    def one(key, ys):
        k0, k1 = jax.random.split(key)
        state = filt.init_prepare(key=k0)._replace(model_inputs=(us[0], ys[0]))

        def body(state, inp):
            u, y, k = inp
            state = filt.filter_combine(state, filt.filter_prepare((u, y), key=k))
            w = jax.nn.softmax(state.log_weights)
            mean = w @ state.particles
            d = state.particles - mean
            return state, (mean, (d * w[:, None]).T @ d)

        state, (mean, cov) = jax.lax.scan(body, state, (us, ys, jax.random.split(k1, T)))
        return mean, state.log_normalizing_constant

    return _compile(jax.jit(jax.vmap(one)), keys, jnp.asarray(sim.measurements))


def cuthbert_filter(model, sim, Q, R, x0, P0, n_particles, keys):
    import cuthbert

    filt = _cuthbert_pieces(model, Q, R, x0, P0, n_particles)
    us = jnp.asarray(sim.inputs)

    def one(key, ys):
        k0, k1 = jax.random.split(key)
        return cuthbert.filter(filt, (us, ys), filt.init_prepare(key=k0), key=k1)

    return _compile(jax.jit(jax.vmap(one)), keys, jnp.asarray(sim.measurements))


def model_floor(model, sim, x0, n_particles, keys, rows: bool):
    """The model arithmetic alone: N particles through ``transition`` each step, nothing else.

    Every bootstrap PF pays this; it bounds from below what one on this model can take. With
    ``rows`` the particles are an (N, nx) array, as cuthbert keeps them; otherwise (nx, N), as
    vehjax keeps them (each state component contiguous over the particles).
    """
    axis = 0 if rows else 1
    f = jax.vmap(model.transition, in_axes=(axis, None, None), out_axes=axis)
    theta = model.theta
    shape = (n_particles, 3) if rows else (3, n_particles)
    start = jnp.asarray(x0) if rows else jnp.asarray(x0)[:, None]

    def one(key, ys):
        x = start + 0.1 * jax.random.normal(key, shape)
        first = (lambda x: x[0]) if rows else (lambda x: x[:, 0])
        return jax.lax.scan(lambda x, u: (f(x, u, theta), first(x)), x, sim.inputs)[1]

    return _compile(jax.jit(jax.vmap(one)), keys, jnp.asarray(sim.measurements))


def vehjax_run(model, sim, Q, R, x0, P0, n_particles, key):
    try:
        from vehjax.run import compile_run
    except ImportError:
        return None, float("nan")
    est = bootstrap_pf(model, Q, R, n_particles=n_particles,
                       resampling=Resampling(scheme="systematic", ess_threshold=ESS_THRESHOLD))
    t0 = time.perf_counter()
    prepared = compile_run(est, sim.measurements, sim.inputs, x0=x0, P0=P0, key=key,
                           progress=False)
    compile_s = time.perf_counter() - t0
    return (lambda: prepared(progress=False)), compile_s


def _rmse(est, truth) -> float:
    return float(np.sqrt(np.mean((np.asarray(est) - np.asarray(truth)) ** 2)))


def parser() -> argparse.ArgumentParser:
    """The benchmark's options (``vehjax bench particle --help``)."""
    p = argparse.ArgumentParser(prog="vehjax bench particle", description=__doc__.splitlines()[0])
    p.add_argument("--runs", type=int, default=20, help="Monte-Carlo runs (default %(default)s)")
    p.add_argument("--steps", type=int, default=1000, help="steps per run (default %(default)s)")
    p.add_argument("--particles", type=int, default=1000,
                   help="particles per run (default %(default)s)")
    p.add_argument("--repeat", type=int, default=3,
                   help="timed repeats; the best is reported (default %(default)s)")
    p.add_argument("--no-cuthbert-filter", action="store_true",
                   help="skip cuthbert.filter (it keeps every step's particles in memory; "
                        "default: run it)")
    return p


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    for name in ("runs", "steps", "particles", "repeat"):
        if getattr(args, name) < 1:
            print(f"bench particle: --{name} must be >= 1")
            return 2

    model, sim, Q, R, x0, P0 = _problem(args.runs, args.steps)
    steps = int(sim.measurements.shape[1])
    n_work = args.runs * steps
    keys = jax.random.split(jax.random.key(1), args.runs)
    platform = jax.devices()[0].platform.upper()
    print(f"Bootstrap PF benchmark: {args.runs} runs x {steps} steps x {args.particles} particles, "
          f"Dynamic3DOF (nx = 3), systematic resampling at ESS < N/2, float64, {platform}")

    rows = {}
    rows["vehjax scan"] = vehjax_scan(model, sim, Q, R, x0, P0, args.particles, keys)
    rows["cuthbert scan"] = cuthbert_scan(model, sim, Q, R, x0, P0, args.particles, keys)
    run_fn, run_c = vehjax_run(model, sim, Q, R, x0, P0, args.particles, jax.random.key(1))
    if run_fn is not None:
        rows["vehjax.run"] = (run_fn, run_c)
    if not args.no_cuthbert_filter:
        rows["cuthbert.filter"] = cuthbert_filter(model, sim, Q, R, x0, P0, args.particles, keys)
    rows["model (N, nx)"] = model_floor(model, sim, x0, args.particles, keys, rows=True)
    rows["model (nx, N)"] = model_floor(model, sim, x0, args.particles, keys, rows=False)

    # same work: estimates and log-likelihoods of the two like-for-like drivers
    vj_mean, vj_ll, vj_div = rows["vehjax scan"][0]()
    cb_mean, cb_ll = rows["cuthbert scan"][0]()
    truth = np.asarray(sim.states)
    vj_rmse, cb_rmse = _rmse(vj_mean, truth), _rmse(cb_mean, truth)
    meas_rmse = _rmse(sim.measurements, truth)
    print(f"RMSE of the filtered states vs truth: vehjax {vj_rmse:.4f}, cuthbert {cb_rmse:.4f} "
          f"(raw measurements {meas_rmse:.4f}); mean log-likelihood per run: vehjax "
          f"{float(np.mean(vj_ll)):.1f}, cuthbert {float(np.mean(cb_ll)):.1f}; "
          f"vehjax runs re-initialised: {int(np.sum(vj_div))}")
    ll_gap = abs(float(np.mean(vj_ll)) - float(np.mean(cb_ll)))
    ll_scale = 1.0 + 0.05 * abs(float(np.mean(cb_ll))) + 5.0 * float(np.std(cb_ll))
    if not (np.isfinite(vj_rmse) and abs(vj_rmse - cb_rmse) < 0.25 * cb_rmse + 1e-3
            and ll_gap < ll_scale):
        print("the two filters disagree beyond Monte-Carlo error: timings are not of the same work")
        return 1

    best = {name: math.inf for name in rows}
    for name, (fn, _) in rows.items():
        fn()  # warm
    for _ in range(args.repeat):
        for name, (fn, _) in rows.items():
            t0 = time.perf_counter()
            fn()
            best[name] = min(best[name], time.perf_counter() - t0)

    ref = best["cuthbert scan"]
    print(f"{'':<17}{'compile [s]':>12}{'run [s]':>10}{'ms/run-step':>13}{'vs cuthbert scan':>18}")
    for name, (_, compile_s) in rows.items():
        r = best[name]
        print(f"{name:<17}{compile_s:>12.2f}{r:>10.3f}{r / n_work * 1e3:>13.4f}{r / ref:>18.3f}")
    print("run: compiled run time, best of --repeat (compile apart); ms/run-step: run time per "
          "run and step in milliseconds; vs cuthbert scan: this row's run time divided by "
          "cuthbert scan's (below 1: faster than cuthbert scan, 0.5 = twice as fast)")
    ratio = best["vehjax scan"] / ref
    print(f"vehjax / cuthbert run time (like for like): {ratio:.3f}; the model's transition "
          f"alone takes {best['model (N, nx)'] / ref:.3f} of cuthbert's time with particles "
          f"as rows, {best['model (nx, N)'] / ref:.3f} as columns")
    if "vehjax.run" in best and "cuthbert.filter" in best:
        print(f"vehjax.run / cuthbert.filter (each library's own driver): "
              f"{best['vehjax.run'] / best['cuthbert.filter']:.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
