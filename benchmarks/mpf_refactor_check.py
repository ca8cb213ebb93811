"""Check that a revision of ``vehjax/filters/marginalized.py`` and the working tree's give the
same estimates, and time both (compiled code only, interleaved, best of ``--repeat``; CPU time
of the process and wall time), in one process.

    python benchmarks/mpf_refactor_check.py --rev 72fcc4f --particles 200 --steps 300 --runs 4

The old module is read with ``git show REV:vehjax/filters/marginalized.py`` and imported as
``vehjax.filters._mpf_old`` (its relative imports resolve in the working tree's package).
Problem: ``vehjax bench marginalized``'s (SingleTrackBank on the berntorp2018 drive), with a few
measurements set missing; the filter of the simulation study (``kalman_states`` "linear" and
"all") and the planar filter.
"""

from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)


def _old_module(rev: str):
    src = subprocess.run(["git", "show", f"{rev}:vehjax/filters/marginalized.py"],
                         capture_output=True, text=True, check=True,
                         cwd=Path(__file__).resolve().parents[1]).stdout
    path = Path("/tmp") / f"_mpf_old_{rev}.py"
    path.write_text(src)
    import vehjax.filters  # noqa: F401

    spec = importlib.util.spec_from_file_location("vehjax.filters._mpf_old", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


def main(argv=None) -> int:
    p = argparse.ArgumentParser()
    p.add_argument("--rev", default="HEAD")
    p.add_argument("--particles", type=int, default=200)
    p.add_argument("--steps", type=int, default=300)
    p.add_argument("--runs", type=int, default=4)
    p.add_argument("--repeat", type=int, default=5)
    args = p.parse_args(argv)
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import bench_marginalized as bm
    from vehjax.filters import marginalized as new

    old = _old_module(args.rev)
    b18, model, U, X, Y = bm._problem(args.runs, args.steps)
    Y = np.array(Y)
    Y[:, 50:60, 2] = np.nan
    Y[:, 100] = np.nan
    x0 = np.zeros(5)
    P0 = np.diag([0.1, 0.5 * b18.DEG, 0.5 * b18.DEG, 0.2 * b18.DEG, 0.2 * b18.DEG]) ** 2
    keys = jax.random.split(jax.random.key(1), args.runs)
    kw = dict(noisy_input="delta", sensors=b18.SENSORS,
              known_std={"phi": b18.PHI_STD, "r_virt": b18.RVIRT_STD},
              linear_states=("phi", "phi_dot", "phi_ddot"), linear_noise_std=b18.BANK_JERK_STD,
              std0={"delta": 2 * b18.STEER_STD, **{s: 2 * b18.SENSOR_STD[s] for s in b18.SENSORS}},
              forgetting=0.995)
    planar = dict(kw, sensors=("ay", "r"), known_std={"r_virt": b18.RVIRT_STD}, linear_states=(),
                  std0={"delta": 2 * b18.STEER_STD, "ay": 0.4, "r": 0.01})
    variants = {"linear": dict(kw), "all": dict(kw, kalman_states="all"), "planar": planar}
    us = jnp.asarray(U)

    def driver(est):
        def one(key, ys):
            state = est.init(jnp.asarray(x0), jnp.asarray(P0), key=key)

            def body(state, yu):
                state, out = est.step(state, *yu)
                return state, (out.mean, out.params, out.loglik, out.nis)

            return jax.lax.scan(body, state, (ys, us))[1]

        f = jax.jit(jax.vmap(one)).lower(keys, jnp.asarray(Y))
        return f.compile(compiler_options=bm._options(est))

    rows = {}
    for name, opts in variants.items():
        for tag, mod in (("old", old), ("new", new)):
            est = mod.marginalized_pf(model, args.particles, **opts)
            t0 = time.perf_counter()
            rows[(name, tag)] = driver(est)
            print(f"{name:7s} {tag}: compiled in {time.perf_counter() - t0:.1f} s", flush=True)
    for name in variants:
        a = jax.block_until_ready(rows[(name, "old")](keys, jnp.asarray(Y)))
        b = jax.block_until_ready(rows[(name, "new")](keys, jnp.asarray(Y)))
        same = all(np.array_equal(np.asarray(x), np.asarray(y), equal_nan=True)
                   for x, y in zip(a, b))
        dmax = max(float(np.nanmax(np.abs(np.asarray(x) - np.asarray(y)))) for x, y in zip(a, b))
        print(f"{name:7s} estimates bitwise equal: {same} (max abs difference {dmax:.3g})")
    best = {k: (np.inf, np.inf) for k in rows}
    for _ in range(args.repeat):
        for k, fn in rows.items():
            c0, w0 = time.process_time(), time.perf_counter()
            jax.block_until_ready(fn(keys, jnp.asarray(Y)))
            c, w = time.process_time() - c0, time.perf_counter() - w0
            best[k] = (min(best[k][0], c), min(best[k][1], w))
    print(f"best of {args.repeat}, N = {args.particles}, {args.runs} runs x {args.steps} steps: "
          f"CPU s / wall s")
    for name in variants:
        (co, wo), (cn, wn) = best[(name, "old")], best[(name, "new")]
        print(f"{name:7s} old {co:.3f} / {wo:.3f}   new {cn:.3f} / {wn:.3f}   "
              f"new/old CPU {cn / co:.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
