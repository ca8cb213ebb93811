"""One run against the floor: vehjax's one-run paths per step against a scalar C EKF of the
same model on the same data.

The model is ``vehjax.models.SingleTrack(tyres="linear")`` at its nominal values (nx = 2:
lateral velocity, yaw rate; ny = 2: lateral acceleration, yaw rate; RK4, 2 substeps of 5 ms),
the data :mod:`vehjax.studies.limit_drive`'s variant A (``--duration`` s at 100 Hz, measured steering
and speed as inputs). The floor is the EKF log-likelihood written in C, scalar by scalar
(the affine single-track derivative, its RK4 map and the RK4 map's Jacobian, a 2 x 2
innovation covariance inverted in closed form), compiled with ``gcc -O2`` at the first run
(a C compiler on the PATH is needed; the row is skipped without one) and called through
ctypes. Its log-likelihood is checked against ``vehjax.filter``'s before any timing
(relative difference <= 1e-9).

Rows, each timed through the public API, compile apart, interleaved (one call of each per
round, ``--repeat`` rounds, the best kept), in us per step and as a ratio to the floor:

    filter EKF    ``jax.jit`` of ``vehjax.filter(ekf(...)).loglik``, one run
    filter UKF    the same with ``vehjax.filters.ukf``
    run EKF       ``vehjax.compile_run`` of the EKF with one run (its compiled study called)
    loss          ``jax.jit`` of ``vehjax.tune.objective(...).loss``: the value (cf, cr and
                  the two measurement variances fitted: 4 numbers)
    loss+grad     ``jax.jit(jax.value_and_grad(objective.loss))`` (reverse mode)
    loss+grad fwd the value and the gradient by forward-mode tangents
                  (:func:`vehjax.tune.program.forward_scores`, the program ``tune.fit``
                  compiles)

    python benchmarks/bench_floor.py                 # or: vehjax bench floor
    python benchmarks/bench_floor.py --duration 20 --repeat 2
"""

from __future__ import annotations

import argparse
import ctypes
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np

import vehjax
from vehjax.models import SingleTrack
from vehjax.tune import program

C_SOURCE = r"""
#include <math.h>
typedef struct { double m, iz, lf, lr, cf, cr; } car;

static void deriv(const car *c, double vx, double d, const double *x, double *k, int affine) {
    double ff = c->cf * ((affine ? d : 0.0) - (x[0] + c->lf * x[1]) / vx);
    double fr = c->cr * (c->lr * x[1] - x[0]) / vx;
    k[0] = (ff + fr) / c->m - vx * x[1];
    k[1] = (c->lf * ff - c->lr * fr) / c->iz;
}

/* one RK4 step of h; affine = 0: the linear part only (the Jacobian's columns) */
static void rk4(const car *c, double vx, double d, double h, double *x, int affine) {
    double k1[2], k2[2], k3[2], k4[2], t[2];
    deriv(c, vx, d, x, k1, affine);
    t[0] = x[0] + 0.5 * h * k1[0]; t[1] = x[1] + 0.5 * h * k1[1]; deriv(c, vx, d, t, k2, affine);
    t[0] = x[0] + 0.5 * h * k2[0]; t[1] = x[1] + 0.5 * h * k2[1]; deriv(c, vx, d, t, k3, affine);
    t[0] = x[0] + h * k3[0]; t[1] = x[1] + h * k3[1]; deriv(c, vx, d, t, k4, affine);
    x[0] += h / 6.0 * (k1[0] + 2.0 * k2[0] + 2.0 * k3[0] + k4[0]);
    x[1] += h / 6.0 * (k1[1] + 2.0 * k2[1] + 2.0 * k3[1] + k4[1]);
}

double ekf_loglik(const double *theta, double dt, int substeps, const double *Q, const double *R,
                  const double *ys, const double *us, long T, const double *x0, const double *P0) {
    car c = {theta[0], theta[1], theta[2], theta[3], theta[4], theta[5]};
    double x[2] = {x0[0], x0[1]};
    double P[4] = {P0[0], P0[1], P0[2], P0[3]};
    double h = dt / substeps, ll = 0.0;
    for (long t = 0; t < T; ++t) {
        double d = us[2 * t], vx = us[2 * t + 1];
        double e0[2] = {1.0, 0.0}, e1[2] = {0.0, 1.0};
        for (int s = 0; s < substeps; ++s) {
            rk4(&c, vx, d, h, x, 1); rk4(&c, vx, d, h, e0, 0); rk4(&c, vx, d, h, e1, 0);
        }
        double F[4] = {e0[0], e1[0], e0[1], e1[1]};             /* F = [e0 e1] */
        double FP[4] = {F[0] * P[0] + F[1] * P[2], F[0] * P[1] + F[1] * P[3],
                        F[2] * P[0] + F[3] * P[2], F[2] * P[1] + F[3] * P[3]};
        P[0] = FP[0] * F[0] + FP[1] * F[1] + Q[0]; P[1] = FP[0] * F[2] + FP[1] * F[3] + Q[1];
        P[2] = FP[2] * F[0] + FP[3] * F[1] + Q[2]; P[3] = FP[2] * F[2] + FP[3] * F[3] + Q[3];
        /* observe: ay = Fy / m (affine in x), r */
        double a0 = -(c.cf + c.cr) / (c.m * vx), a1 = (c.cr * c.lr - c.cf * c.lf) / (c.m * vx);
        double ay = a0 * x[0] + a1 * x[1] + c.cf * d / c.m;
        double H[4] = {a0, a1, 0.0, 1.0};
        double HP[4] = {H[0] * P[0] + H[1] * P[2], H[0] * P[1] + H[1] * P[3], P[2], P[3]};
        double S[4] = {HP[0] * H[0] + HP[1] * H[1] + R[0], HP[0] * H[2] + HP[1] * H[3] + R[1],
                       HP[2] * H[0] + HP[3] * H[1] + R[2], HP[2] * H[2] + HP[3] * H[3] + R[3]};
        double det = S[0] * S[3] - S[1] * S[2];
        double Si[4] = {S[3] / det, -S[1] / det, -S[2] / det, S[0] / det};
        double e[2] = {ys[2 * t] - ay, ys[2 * t + 1] - x[1]};
        ll += -0.5 * (e[0] * (Si[0] * e[0] + Si[1] * e[1]) + e[1] * (Si[2] * e[0] + Si[3] * e[1])
                      + log(det) + 2.0 * log(2.0 * M_PI));
        /* K = P H^T S^-1 = HP^T S^-1 */
        double K[4] = {HP[0] * Si[0] + HP[2] * Si[2], HP[0] * Si[1] + HP[2] * Si[3],
                       HP[1] * Si[0] + HP[3] * Si[2], HP[1] * Si[1] + HP[3] * Si[3]};
        x[0] += K[0] * e[0] + K[1] * e[1]; x[1] += K[2] * e[0] + K[3] * e[1];
        double Pn[4] = {P[0] - (K[0] * HP[0] + K[1] * HP[2]), P[1] - (K[0] * HP[1] + K[1] * HP[3]),
                        P[2] - (K[2] * HP[0] + K[3] * HP[2]), P[3] - (K[2] * HP[1] + K[3] * HP[3])};
        P[0] = Pn[0]; P[3] = Pn[3]; P[1] = P[2] = 0.5 * (Pn[1] + Pn[2]);
    }
    return ll;
}
"""

X0, P0 = np.zeros(2), np.diag([0.1, 0.01])
Q = np.diag([1e-4, 1e-5])
R = np.diag([0.1, 1e-4])


def c_floor():
    """The C EKF log-likelihood as a Python function (compiled once into a temporary folder),
    or None without a C compiler."""
    cc = shutil.which("gcc") or shutil.which("cc")
    if cc is None:
        return None
    folder = Path(tempfile.mkdtemp(prefix="vehjax_floor_"))
    (folder / "ekf.c").write_text(C_SOURCE)
    subprocess.run([cc, "-O2", "-shared", "-fPIC", "-o", str(folder / "ekf.so"),
                    str(folder / "ekf.c"), "-lm"], check=True)
    lib = ctypes.CDLL(str(folder / "ekf.so"))
    f = lib.ekf_loglik
    dp = ctypes.POINTER(ctypes.c_double)
    f.argtypes = [dp, ctypes.c_double, ctypes.c_int, dp, dp, dp, dp, ctypes.c_long, dp, dp]
    f.restype = ctypes.c_double

    def ptr(a):
        return np.ascontiguousarray(a, dtype=np.float64).ctypes.data_as(dp)

    def loglik(model, ys, us):
        keep = [np.ascontiguousarray(a, dtype=np.float64) for a in
                (model.theta, Q, R, ys, us, X0, P0)]
        return f(ptr(keep[0]), model.dt, model.substeps, ptr(keep[1]), ptr(keep[2]),
                 ptr(keep[3]), ptr(keep[4]), len(ys), ptr(keep[5]), ptr(keep[6]))

    return loglik


def contenders(model, ys, us):
    """{row: (callable, what it was compiled with)} of vehjax's paths, each compiled here."""
    yj, uj = jnp.asarray(ys), jnp.asarray(us)
    out = {}
    for name, build in (("filter EKF", vehjax.filters.ekf), ("filter UKF", vehjax.filters.ukf)):
        est = build(model, Q, R)
        fn = jax.jit(lambda y, u, e=est: jnp.sum(vehjax.filter(e, y, u, x0=X0, P0=P0).loglik))
        out[name] = (fn, (yj, uj))
    compiled = vehjax.compile_run(vehjax.filters.ekf(model, Q, R), ys[None], us, x0=X0, P0=P0,
                                  progress=False)
    out["run EKF"] = (lambda: compiled().states, ())
    obj, setup = vehjax.tune.prepare(
        vehjax.filters.ekf, model, Q, R, ys, us, x0=X0, P0=P0,
        params=vehjax.tune.Fitted(("cf", "cr"), noise=("R",)))  # the objective of
    # vehjax.tune.objective and its per-step form, which the fit's forward-mode program
    # differentiates
    out["loss"] = (jax.jit(lambda z, d: obj.loss(z, d)[0]), (obj.z0, obj.data))
    out["loss+grad"] = (jax.jit(jax.value_and_grad(lambda z, d: obj.loss(z, d)[0])),
                        (obj.z0, obj.data))
    flat, unravel = jax.flatten_util.ravel_pytree(obj.z0)

    def fwd(f, d):
        ll, dll, _ = program.forward_scores(lambda g, dd: setup.per_step(unravel(g), dd), f, d)
        return -jnp.sum(ll) / obj.n_steps, -jnp.sum(dll.reshape(f.shape[0], -1), 1) / obj.n_steps

    out["loss+grad fwd"] = (jax.jit(fwd), (flat, obj.data))
    return out


def timed(fn, args) -> float:
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    return time.perf_counter() - t0


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="vehjax bench floor",
                                description="vehjax's one-run paths per step against a scalar "
                                            "C EKF of the same model on the same data")
    p.add_argument("--duration", type=float, default=200.0,
                   help="s of the drive at 100 Hz (default 200: 20,000 steps)")
    p.add_argument("--repeat", type=int, default=5, help="interleaved rounds (default 5)")
    return p


def main(argv=None) -> int:
    a = parser().parse_args(argv)
    if a.duration <= 0 or a.repeat < 1:
        raise SystemExit("vehjax bench floor: --duration must be > 0 and --repeat >= 1")
    drive = vehjax.studies.limit_drive.limit_drive("A", duration=a.duration, seed=0)
    ys, us = np.asarray(drive.measurements), np.asarray(drive.inputs)
    model = SingleTrack(tyres="linear", theta=tuple(drive.body.values()) +
                        tuple(np.asarray(SingleTrack().theta)[4:]))
    T = len(ys)
    floor = c_floor()
    ll_vehjax = float(jnp.sum(vehjax.filter(vehjax.filters.ekf(model, Q, R), ys, us, x0=X0,
                                            P0=P0).loglik))
    if floor is not None:
        ll_c = floor(model, ys, us)
        rel = abs(ll_c - ll_vehjax) / abs(ll_vehjax)
        print(f"# log-likelihood: C {ll_c:.10f}, vehjax.filter {ll_vehjax:.10f} "
              f"(relative difference {rel:.1e})")
        if not rel <= 1e-9:
            raise SystemExit("vehjax bench floor: the C floor and vehjax.filter disagree")
    rows = contenders(model, ys, us)
    compile_s = {k: timed(fn, args) for k, (fn, args) in rows.items()}  # first call: compile
    best = {k: np.inf for k in rows}
    best_c = np.inf
    for _ in range(a.repeat):
        if floor is not None:
            t0 = time.perf_counter()
            floor(model, ys, us)
            best_c = min(best_c, time.perf_counter() - t0)
        for k, (fn, args) in rows.items():
            best[k] = min(best[k], timed(fn, args))
    print(f"# {T} steps, SingleTrack linear (nx = 2, ny = 2), float64, {jax.devices()[0]}; "
          f"best of {a.repeat} interleaved rounds; first call (compile + one run) apart")
    print(f"{'row':<15} {'us/step':>9} {'x floor':>9} {'first call s':>13}")
    c_us = best_c / T * 1e6
    if floor is not None:
        print(f"{'C floor':<15} {c_us:9.3f} {1.0:9.1f} {'-':>13}")
    for k in rows:
        us_step = best[k] / T * 1e6
        ratio = f"{us_step / c_us:9.1f}" if floor is not None else f"{'-':>9}"
        print(f"{k:<15} {us_step:9.3f} {ratio} {compile_s[k]:13.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
