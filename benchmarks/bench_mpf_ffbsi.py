"""The marginalized PF's smoother on the recorded RAV4 drive (``vehjax reproduce berntorp2018
--drive``'s data and filter, issue #29 item 2): ancestor tracing against Rao-Blackwellised
backward simulation (``vehjax.smooth(..., method=vehjax.smoothers.FFBSi(...))``,
:mod:`vehjax.smoothers.marginalized`).

The drive is prepared as ``vehjax reproduce berntorp2018 --drive`` does with its defaults
(:func:`vehjax.data.prepare_drive`: virtual yaw rate's scale error removed offline, gated at
5 deg/s; :class:`VirtualScaleBank`, the ``bank`` variant,
``kalman_states="linear"``, forgetting 0.999). For each method: compile + first call, then a
second call with another key (run time), and per time the number of distinct particle slots
(``n_unique``) and particles by value (``n_distinct``) the M trajectories pass through and the
backward ESS; the smoothed offset and biases at the end of the drive.

    python benchmarks/bench_mpf_ffbsi.py                       # N = 500, M = 100, whole drive
    python benchmarks/bench_mpf_ffbsi.py --particles 100 --paths 20 --seconds 5
"""

from __future__ import annotations

import argparse
import time

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--particles", type=int, default=500)
    p.add_argument("--paths", type=int, default=100)
    p.add_argument("--seconds", type=float, default=None, help="first seconds of the drive")
    p.add_argument("--methods", default="ancestor,ffbsi")
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args()
    import vehjax as vj
    from vehjax.studies.banked_road import DEG, build_drive_filter

    drive = vj.data.load_comma2k19()
    model = vj.models.SingleTrackBank(dt=drive.dt)
    U, Y = vj.data.prepare_drive(drive, model, seconds=a.seconds, gate=5.0 * DEG)
    T = len(U)
    est = build_drive_filter(vj.models.VirtualScaleBank(dt=drive.dt), a.particles,
                             variant="bank", kalman_states="linear")
    P0 = np.diag([0.1, 0.5 * DEG, 1e-3, 1e-3, 1e-3, 1e-12]) ** 2
    print(f"RAV4 drive: T = {T} steps, N = {a.particles}, M = {a.paths}")
    for method in a.methods.split(","):
        fn = jax.jit(lambda y, u, k, method=method: vj.smooth(
            est, y, u, x0=np.zeros(6), P0=P0, key=k,
            method=vj.smoothers.methods.BY_NAME[method](n_trajectories=a.paths)))
        times = []
        for r in range(2):
            t0 = time.perf_counter()
            sm = fn(Y, U, jax.random.fold_in(jax.random.key(a.seed), 29 + r))
            jax.block_until_ready(sm.states)
            times.append(time.perf_counter() - t0)
        nu, nd = np.asarray(sm.n_unique), np.asarray(sm.n_distinct)
        be = np.asarray(sm.backward_ess)
        at = sorted({0, 1, 10, 100, T // 4, T // 2, 3 * T // 4, T - 2, T - 1} & set(range(T)))
        print(f"{method}: first call (compile + run) {times[0]:.1f} s, second call "
              f"{times[1]:.1f} s, diverged {bool(sm.diverged)}")
        print(f"  t            {at}")
        print(f"  n_unique     {nu[at].tolist()}")
        print(f"  n_distinct   {nd[at].tolist()}")
        print(f"  backward ESS {np.round(be[at], 2).tolist()}")
        print(f"  mean backward ESS over t {be.mean():.2f}, median n_distinct {np.median(nd):.0f}")
        pr = np.asarray(sm.params)
        print("  smoothed statistics at t = 0 and T - 1: " + ", ".join(
            f"{n} {pr[0, i]:+.4g} / {pr[-1, i]:+.4g}" for i, n in enumerate(est.param_names)))


if __name__ == "__main__":
    main()
