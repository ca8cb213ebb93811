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
    filter EKF res  ``vehjax.filter`` of the EKF called as a user calls it, its whole result
                  (states, covariances, log-likelihoods, flags) on the host: what run gives
    run EKF       ``vehjax.compile_run`` of the EKF with one run (its compiled study called)
    loss          ``jax.jit`` of ``vehjax.tune.objective(...).loss``: the value (cf, cr and
                  the two measurement variances fitted: 4 numbers)
    loss+grad     ``jax.jit(jax.value_and_grad(objective.loss))`` (reverse mode)
    loss+grad fwd the value and the gradient by forward-mode tangents
                  (:func:`vehjax.tune.program.forward_scores`, the program ``tune.fit``
                  compiles)

``--model 3dof``: the same filter and run rows on :class:`vehjax.models.Dynamic3DOF` (nx = 3:
vx, vy, r, all measured; five inputs; linear tyres through the arctangent slip angles, RK4 in
one step of 10 ms) against a second C EKF (:data:`C_SOURCE_3DOF`: the derivative's Jacobian
by hand, the RK4 map's by the chain rule through the four stages, a 3 x 3 Cholesky), on a sine
steer simulated ten times finer than the filter's step. For this model a C UKF too
(:data:`C_SOURCE_3DOF`'s ``ukf_loglik``: the unscented rule with alpha 1, beta 2, kappa 0, seven
points through RK4, fresh points for the update, vehjax's defaults), checked likewise; the
column "x C same" sets each vehjax row beside the C filter of its own kind.

    python benchmarks/bench_floor.py                 # or: vehjax bench floor
    python benchmarks/bench_floor.py --duration 20 --repeat 2
``--model user``: the filter and run rows on a model as a user writes it,
:class:`vehjax.models.Model` of plain jnp functions (:func:`user_problem`), with no C floor.

    python benchmarks/bench_floor.py --model 3dof
    python benchmarks/bench_floor.py --model user
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
from vehjax.models import Dynamic3DOF, SingleTrack
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

C_SOURCE_3DOF = r"""
#include <math.h>
typedef struct { double m, cx, cy, lf, lr, iz, ca; } car;

/* the 3-DOF derivative (vx, vy, r)' and its Jacobian J (row-major 3 x 3) at x, inputs u =
   (s_fl, s_fr, s_rl, s_rr, delta): linear tyres, alpha_f = d - atan((vy + lf r) / vx),
   alpha_r = -atan((vy - lr r) / vx) */
static void deriv(const car *c, const double *x, const double *u, double *f, double *J) {
    double vx = x[0], vy = x[1], r = x[2], d = u[4];
    double af_arg = (vy + c->lf * r) / vx, ar_arg = (vy - c->lr * r) / vx;
    double fxf = c->cx * u[0] + c->cx * u[1], fxr = c->cx * u[2] + c->cx * u[3];
    double fyf = 2.0 * c->cy * (d - atan(af_arg)), fyr = 2.0 * c->cy * (-atan(ar_arg));
    double cs = cos(d), sn = sin(d);
    double fx = fxf * cs - fyf * sn + fxr - c->ca * vx * vx;
    double fy = fxf * sn + fyf * cs + fyr;
    double mz = c->lf * (fxf * sn + fyf * cs) - c->lr * fyr;
    f[0] = vy * r + fx / c->m; f[1] = -vx * r + fy / c->m; f[2] = mz / c->iz;
    double gf = 1.0 / (1.0 + af_arg * af_arg), gr = 1.0 / (1.0 + ar_arg * ar_arg);
    double daf[3] = {gf * af_arg / vx, -gf / vx, -gf * c->lf / vx};   /* d alpha_f / dx */
    double dar[3] = {gr * ar_arg / vx, -gr / vx, gr * c->lr / vx};    /* d alpha_r / dx */
    double dkin0[3] = {0.0, r, vy}, dkin1[3] = {-r, 0.0, -vx};
    for (int k = 0; k < 3; ++k) {
        double dfyf = 2.0 * c->cy * daf[k], dfyr = 2.0 * c->cy * dar[k];
        double dfx = -dfyf * sn - (k == 0 ? 2.0 * c->ca * vx : 0.0);
        J[k] = dkin0[k] + dfx / c->m;
        J[3 + k] = dkin1[k] + (dfyf * cs + dfyr) / c->m;
        J[6 + k] = (c->lf * dfyf * cs - c->lr * dfyr) / c->iz;
    }
}

static void matmul3(const double *A, const double *B, double *C) {
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            C[3 * i + j] = A[3 * i] * B[j] + A[3 * i + 1] * B[3 + j] + A[3 * i + 2] * B[6 + j];
}

/* one RK4 step of h from x (in place) and its Jacobian F = d x_new / d x */
static void rk4(const car *c, const double *u, double h, double *x, double *F) {
    double k[4][3], D[9], M[9], dk[4][9], t[3];
    deriv(c, x, u, k[0], dk[0]);
    for (int s = 1; s < 4; ++s) {
        double a = s < 3 ? 0.5 * h : h;
        for (int i = 0; i < 3; ++i) t[i] = x[i] + a * k[s - 1][i];
        for (int i = 0; i < 9; ++i) M[i] = (i % 4 == 0 ? 1.0 : 0.0) + a * dk[s - 1][i];
        deriv(c, t, u, k[s], D);
        matmul3(D, M, dk[s]);
    }
    for (int i = 0; i < 3; ++i)
        x[i] += h / 6.0 * (k[0][i] + 2.0 * k[1][i] + 2.0 * k[2][i] + k[3][i]);
    for (int i = 0; i < 9; ++i)
        F[i] = (i % 4 == 0 ? 1.0 : 0.0) + h / 6.0 * (dk[0][i] + 2.0 * dk[1][i] + 2.0 * dk[2][i]
                                                     + dk[3][i]);
}

double ekf_loglik(const double *theta, double dt, int substeps, const double *Q, const double *R,
                  const double *ys, const double *us, long T, const double *x0, const double *P0) {
    car c = {theta[0], theta[1], theta[2], theta[3], theta[4], theta[5], theta[6]};
    double x[3] = {x0[0], x0[1], x0[2]}, P[9], F[9], G[9], FP[9], ll = 0.0, h = dt / substeps;
    for (int i = 0; i < 9; ++i) P[i] = P0[i];
    for (long t = 0; t < T; ++t) {
        const double *u = us + 5 * t, *y = ys + 3 * t;
        for (int s = 0; s < substeps; ++s) {
            rk4(&c, u, h, x, F);
            matmul3(F, P, FP);
            for (int i = 0; i < 3; ++i)                         /* P = F P F^T (+ Q below) */
                for (int j = 0; j < 3; ++j)
                    G[3 * i + j] = FP[3 * i] * F[3 * j] + FP[3 * i + 1] * F[3 * j + 1]
                                   + FP[3 * i + 2] * F[3 * j + 2];
            for (int i = 0; i < 9; ++i) P[i] = G[i];
        }
        for (int i = 0; i < 9; ++i) P[i] += Q[i];
        /* observe the states (H = I): S = P + R, its Cholesky factor L (lower) */
        double S[9], L[9] = {0}, e[3], a[3], Si[9];
        for (int i = 0; i < 9; ++i) S[i] = P[i] + R[i];
        L[0] = sqrt(S[0]); L[3] = S[3] / L[0]; L[6] = S[6] / L[0];
        L[4] = sqrt(S[4] - L[3] * L[3]); L[7] = (S[7] - L[6] * L[3]) / L[4];
        L[8] = sqrt(S[8] - L[6] * L[6] - L[7] * L[7]);
        for (int i = 0; i < 3; ++i) e[i] = y[i] - x[i];
        a[0] = e[0] / L[0]; a[1] = (e[1] - L[3] * a[0]) / L[4];     /* a = L^-1 e */
        a[2] = (e[2] - L[6] * a[0] - L[7] * a[1]) / L[8];
        ll += -0.5 * (a[0] * a[0] + a[1] * a[1] + a[2] * a[2])
              - log(L[0] * L[4] * L[8]) - 1.5 * log(2.0 * M_PI);
        /* S^-1 from L: the columns of L^-T L^-1 */
        for (int j = 0; j < 3; ++j) {
            double b[3] = {j == 0, j == 1, j == 2}, z[3];
            z[0] = b[0] / L[0]; z[1] = (b[1] - L[3] * z[0]) / L[4];
            z[2] = (b[2] - L[6] * z[0] - L[7] * z[1]) / L[8];
            double w2 = z[2] / L[8], w1 = (z[1] - L[7] * w2) / L[4];
            double w0 = (z[0] - L[3] * w1 - L[6] * w2) / L[0];
            Si[j] = w0; Si[3 + j] = w1; Si[6 + j] = w2;
        }
        double K[9], Pn[9];
        matmul3(P, Si, K);                                          /* K = P S^-1 */
        for (int i = 0; i < 3; ++i) x[i] += K[3 * i] * e[0] + K[3 * i + 1] * e[1] + K[3 * i + 2] * e[2];
        matmul3(K, P, Pn);                                          /* P = P - K P */
        for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j) G[3 * i + j] = P[3 * i + j] - Pn[3 * i + j];
        for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j) P[3 * i + j] = 0.5 * (G[3 * i + j] + G[3 * j + i]);
    }
    return ll;
}

/* the derivative alone (the UKF needs no Jacobian) */
static void deriv_f(const car *c, const double *x, const double *u, double *f) {
    double J[9];
    deriv(c, x, u, f, J);
}

/* 3 x 3 Cholesky factor (lower, row-major) of the symmetric part of A */
static void chol3(const double *A, double *L) {
    double a10 = 0.5 * (A[3] + A[1]), a20 = 0.5 * (A[6] + A[2]), a21 = 0.5 * (A[7] + A[5]);
    for (int i = 0; i < 9; ++i) L[i] = 0.0;
    L[0] = sqrt(A[0]); L[3] = a10 / L[0]; L[6] = a20 / L[0];
    L[4] = sqrt(A[4] - L[3] * L[3]); L[7] = (a21 - L[6] * L[3]) / L[4];
    L[8] = sqrt(A[8] - L[6] * L[6] - L[7] * L[7]);
}

/* the 7 sigma points of N(x, L L^T) (unscented rule, alpha 1, beta 2, kappa 0: points 0 and
   +-sqrt(3) e_j) as rows of X */
static void points3(const double *x, const double *L, double X[7][3]) {
    double s = sqrt(3.0);
    for (int i = 0; i < 3; ++i) X[0][i] = x[i];
    for (int j = 0; j < 3; ++j)
        for (int i = 0; i < 3; ++i) {
            X[1 + j][i] = x[i] + s * L[3 * i + j];
            X[4 + j][i] = x[i] - s * L[3 * i + j];
        }
}

/* weighted mean m and covariance P (+ N) of the rows of Y: wm = (0, 1/6 ...), wc = (2, 1/6 ...) */
static void moments3(double Y[7][3], const double *N, double *m, double *P) {
    static const double wm[7] = {0.0, 1.0 / 6, 1.0 / 6, 1.0 / 6, 1.0 / 6, 1.0 / 6, 1.0 / 6};
    static const double wc[7] = {2.0, 1.0 / 6, 1.0 / 6, 1.0 / 6, 1.0 / 6, 1.0 / 6, 1.0 / 6};
    for (int i = 0; i < 3; ++i) {
        m[i] = 0.0;
        for (int k = 0; k < 7; ++k) m[i] += wm[k] * Y[k][i];
    }
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) {
            double a = 0.0;
            for (int k = 0; k < 7; ++k) a += wc[k] * (Y[k][i] - m[i]) * (Y[k][j] - m[j]);
            P[3 * i + j] = a + N[3 * i + j];
        }
}

/* The UKF log-likelihood (the additive-noise UKF: points of N(x, P) through RK4, their moments
   + Q; fresh points of N(x-, P-) through h(x) = x, S = their covariance + R, C = their cross
   covariance; the update through S's Cholesky factor Ls: w = Ls^-1 e, W = Ls^-1 C^T,
   x = x- + W^T w, P = P- - W^T W) */
double ukf_loglik(const double *theta, double dt, int substeps, const double *Q, const double *R,
                  const double *ys, const double *us, long T, const double *x0, const double *P0) {
    car c = {theta[0], theta[1], theta[2], theta[3], theta[4], theta[5], theta[6]};
    double x[3] = {x0[0], x0[1], x0[2]}, P[9], L[9], X[7][3], ll = 0.0, h = dt / substeps;
    for (int i = 0; i < 9; ++i) P[i] = P0[i];
    for (long t = 0; t < T; ++t) {
        const double *u = us + 5 * t, *y = ys + 3 * t;
        chol3(P, L);
        points3(x, L, X);
        for (int k = 0; k < 7; ++k)
            for (int s = 0; s < substeps; ++s) {           /* RK4 of each point */
                double k1[3], k2[3], k3[3], k4[3], z[3], *v = X[k];
                deriv_f(&c, v, u, k1);
                for (int i = 0; i < 3; ++i) z[i] = v[i] + 0.5 * h * k1[i];
                deriv_f(&c, z, u, k2);
                for (int i = 0; i < 3; ++i) z[i] = v[i] + 0.5 * h * k2[i];
                deriv_f(&c, z, u, k3);
                for (int i = 0; i < 3; ++i) z[i] = v[i] + h * k3[i];
                deriv_f(&c, z, u, k4);
                for (int i = 0; i < 3; ++i)
                    v[i] += h / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i]);
            }
        double xp[3], Pp[9], yh[3], S[9], C[9], Ls[9], e[3], w[3], W[9];
        moments3(X, Q, xp, Pp);
        for (int i = 0; i < 3; ++i)                          /* symmetric P- */
            for (int j = 0; j < i; ++j) Pp[3 * i + j] = Pp[3 * j + i] = 0.5 * (Pp[3 * i + j] + Pp[3 * j + i]);
        chol3(Pp, L);
        points3(xp, L, X);
        moments3(X, R, yh, S);                               /* h(x) = x: Z = X */
        for (int i = 0; i < 3; ++i)                          /* C = Cov(x, z) about xp, yh */
            for (int j = 0; j < 3; ++j) {
                double a = 0.0;
                for (int k = 0; k < 7; ++k)
                    a += (k ? 1.0 / 6 : 2.0) * (X[k][i] - xp[i]) * (X[k][j] - yh[j]);
                C[3 * i + j] = a;
            }
        chol3(S, Ls);
        for (int i = 0; i < 3; ++i) e[i] = y[i] - yh[i];
        w[0] = e[0] / Ls[0]; w[1] = (e[1] - Ls[3] * w[0]) / Ls[4];
        w[2] = (e[2] - Ls[6] * w[0] - Ls[7] * w[1]) / Ls[8];
        for (int i = 0; i < 3; ++i) {                        /* column i of W: Ls^-1 C[i, :] */
            const double *ci = C + 3 * i;
            W[i] = ci[0] / Ls[0]; W[3 + i] = (ci[1] - Ls[3] * W[i]) / Ls[4];
            W[6 + i] = (ci[2] - Ls[6] * W[i] - Ls[7] * W[3 + i]) / Ls[8];
        }
        for (int i = 0; i < 3; ++i) x[i] = xp[i] + W[i] * w[0] + W[3 + i] * w[1] + W[6 + i] * w[2];
        for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j)
                P[3 * i + j] = Pp[3 * i + j] - (W[i] * W[j] + W[3 + i] * W[3 + j] + W[6 + i] * W[6 + j]);
        ll += -0.5 * (w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
              - log(Ls[0] * Ls[4] * Ls[8]) - 1.5 * log(2.0 * M_PI);
    }
    return ll;
}
"""

X0, P0 = np.zeros(2), np.diag([0.1, 0.01])
Q = np.diag([1e-4, 1e-5])
R = np.diag([0.1, 1e-4])


def c_floor(source: str = C_SOURCE, Q=Q, R=R, x0=X0, P0=P0, symbol: str = "ekf_loglik"):
    """The C log-likelihood ``symbol`` of ``source`` (:data:`C_SOURCE`'s ``ekf_loglik``,
    :data:`C_SOURCE_3DOF`'s ``ekf_loglik`` and ``ukf_loglik``) with the noise ``Q``, ``R`` and
    the prior ``x0``, ``P0`` as a Python function ``(model, ys, us)`` (compiled once into a
    temporary folder), or None without a C compiler."""
    cc = shutil.which("gcc") or shutil.which("cc")
    if cc is None:
        return None
    folder = Path(tempfile.mkdtemp(prefix="vehjax_floor_"))
    (folder / "ekf.c").write_text(source)
    subprocess.run([cc, "-O2", "-shared", "-fPIC", "-o", str(folder / "ekf.so"),
                    str(folder / "ekf.c"), "-lm"], check=True)
    lib = ctypes.CDLL(str(folder / "ekf.so"))
    f = getattr(lib, symbol)
    dp = ctypes.POINTER(ctypes.c_double)
    f.argtypes = [dp, ctypes.c_double, ctypes.c_int, dp, dp, dp, dp, ctypes.c_long, dp, dp]
    f.restype = ctypes.c_double

    def ptr(a):
        return np.ascontiguousarray(a, dtype=np.float64).ctypes.data_as(dp)

    def loglik(model, ys, us):
        keep = [np.ascontiguousarray(a, dtype=np.float64) for a in
                (model.theta, Q, R, ys, us, x0, P0)]
        return f(ptr(keep[0]), model.dt, getattr(model, "substeps", 1), ptr(keep[1]), ptr(keep[2]),
                 ptr(keep[3]), ptr(keep[4]), len(ys), ptr(keep[5]), ptr(keep[6]))

    return loglik


def filter_rows(model, ys, us, Q, R, x0, P0):
    """{row: (callable, its arguments)}: ``vehjax.filter`` with the EKF and the UKF, and
    ``vehjax.compile_run`` of the EKF with one run."""
    yj, uj = jnp.asarray(ys), jnp.asarray(us)
    out = {}
    for name, build in (("filter EKF", vehjax.filters.ekf), ("filter UKF", vehjax.filters.ukf)):
        est = build(model, Q, R)
        fn = jax.jit(lambda y, u, e=est: jnp.sum(vehjax.filter(e, y, u, x0=x0, P0=P0).loglik))
        out[name] = (fn, (yj, uj))
    est = vehjax.filters.ekf(model, Q, R)
    # the whole result on the host, as run gives it: the like-for-like row for run's
    out["filter EKF res"] = (lambda: np.asarray(vehjax.filter(est, yj, uj, x0=x0, P0=P0).states),
                             ())
    compiled = vehjax.compile_run(est, ys[None], us, x0=x0, P0=P0, progress=False)
    out["run EKF"] = (lambda: compiled().states, ())
    return out


def contenders(model, ys, us):
    """{row: (callable, what it was compiled with)} of vehjax's paths on the single-track
    problem, each compiled here: :func:`filter_rows` and the fit's loss rows."""
    out = filter_rows(model, ys, us, Q, R, X0, P0)
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
    p.add_argument("--model", choices=tuple(PROBLEMS), default="single_track",
                   help="single_track (default; the filter, run and fit rows), 3dof "
                        "(Dynamic3DOF: the filter and run rows, C EKF and UKF floors) or user "
                        "(a Model of plain jnp functions: the filter and run rows, no floor)")
    return p


def single_track_problem(duration: float, seed: int = 0):
    """(label, model, ys, us, Q, R, x0, P0, C source) of the single-track rows: the limit
    drive's variant A (``duration`` s at 100 Hz), the linear-tyre model at its body values."""
    drive = vehjax.studies.limit_drive.limit_drive("A", duration=duration, seed=seed)
    ys, us = np.asarray(drive.measurements), np.asarray(drive.inputs)
    model = SingleTrack(tyres="linear", theta=tuple(drive.body.values()) +
                        tuple(np.asarray(SingleTrack().theta)[4:]))
    return ("SingleTrack linear (nx = 2, ny = 2)", model, ys, us, Q, R, X0, P0, C_SOURCE)


def three_dof_problem(duration: float, seed: int = 0, fine: int = 10):
    """The same for :class:`vehjax.models.Dynamic3DOF` (nx = 3, its states measured, RK4 at
    dt = 0.01 s): a sine steer (0.03 rad, 0.4 Hz) from 20 m/s simulated ``fine`` times finer
    (``vehjax.simulate`` at dt / fine, every ``fine``-th sample kept) with process noise, and
    noisy measurements of (vx, vy, r)."""
    model = Dynamic3DOF(dt=0.01)
    sim_model = Dynamic3DOF(dt=model.dt / fine)
    scn = vehjax.scenarios.sine_steer(sim_model, speed=20.0, amplitude=0.03, frequency=0.4,
                                      duration=duration)
    sim = vehjax.simulate(sim_model, scn, runs=1, key=jax.random.key(seed),
                          process_std=np.array([0.003, 0.003, 3e-4]),
                          meas_std=np.array([0.1, 0.05, 0.005]))
    ys = np.asarray(sim.measurements[0])[fine - 1::fine]
    us = np.asarray(sim.inputs)[::fine][:len(ys)]
    Q3, R3 = np.diag([1e-4, 1e-4, 1e-6]), np.diag([0.01, 0.0025, 2.5e-5])
    x0, P0 = np.array([20.0, 0.0, 0.0]), np.diag([1.0, 0.1, 0.01])
    return ("Dynamic3DOF (nx = 3, ny = 3)", model, ys, us, Q3, R3, x0, P0, C_SOURCE_3DOF)


def _user_derivative(x, u, th):
    """A three-state car as a user writes it, plain jnp: (vx, vy, r)' under steer and a
    longitudinal acceleration input, linear tyres through the arctangent slip angles."""
    m, iz, lf, lr, cf, cr = th
    vx, vy, r = x
    delta, ax = u
    fyf = cf * (delta - jnp.arctan((vy + lf * r) / vx))
    fyr = -cr * jnp.arctan((vy - lr * r) / vx)
    return jnp.stack([ax + vy * r - fyf * jnp.sin(delta) / m,
                      -vx * r + (fyf * jnp.cos(delta) + fyr) / m,
                      (lf * fyf * jnp.cos(delta) - lr * fyr) / iz])


def user_problem(duration: float, seed: int = 0):
    """The same rows on a user's :class:`vehjax.models.Model` of plain jnp functions (two Euler
    sub-steps of 5 ms; outputs vx, r, ay), another car and excitation (a modulated steer, a slow
    acceleration), a wider prior; no C floor (the rows' "x floor" columns are left empty)."""
    th = np.array([1650.0, 2900.0, 1.2, 1.6, 9.0e4, 1.1e5])

    def f(x, u, th):
        for _ in range(2):
            x = x + 0.005 * _user_derivative(x, u, th)
        return x

    def h(x, u, th):
        return jnp.stack([x[0], x[2], _user_derivative(x, u, th)[1] + x[0] * x[2]])

    model = vehjax.models.Model(transition=f, observe=h, dt=0.01, state_names=("vx", "vy", "r"),
                                param_names=("m", "iz", "lf", "lr", "cf", "cr"),
                                input_names=("delta", "ax"), output_names=("vx", "r", "ay"),
                                theta=th)
    t = np.arange(int(round(duration / model.dt))) * model.dt
    us = np.stack([0.04 * np.sin(2 * np.pi * 0.3 * t) * np.sin(2 * np.pi * 0.05 * t),
                   0.3 * np.cos(2 * np.pi * 0.02 * t)], axis=1)
    xs = jax.lax.scan(lambda x, u: (f(x, u, th),) * 2, jnp.array([25.0, 0.0, 0.0]),
                      jnp.asarray(us))[1]
    std = np.array([0.05, 0.003, 0.2])
    ys = np.asarray(jax.vmap(lambda x, u: h(x, u, th))(xs, jnp.asarray(us)))
    ys = ys + np.random.default_rng(seed).normal(size=ys.shape) * std
    return ("a user's Model, plain jnp (nx = 3, ny = 3)", model, ys, us,
            np.diag([1e-4, 1e-4, 1e-6]), np.diag(std ** 2), np.array([25.0, 0.0, 0.0]),
            4.0 * np.diag([1.0, 0.1, 0.01]), None)


PROBLEMS = {"single_track": single_track_problem, "3dof": three_dof_problem,
            "user": user_problem}


def check_floor(name, floor, est, model, ys, us, x0, P0) -> None:
    """Print the C log-likelihood beside ``vehjax.filter``'s with ``est``; SystemExit when
    they differ by more than 1e-9 relative (the floor would time other work)."""
    ll_vehjax = float(jnp.sum(vehjax.filter(est, ys, us, x0=x0, P0=P0).loglik))
    ll_c = floor(model, ys, us)
    rel = abs(ll_c - ll_vehjax) / abs(ll_vehjax)
    print(f"# log-likelihood, {name}: C {ll_c:.10f}, vehjax.filter {ll_vehjax:.10f} "
          f"(relative difference {rel:.1e})")
    if not rel <= 1e-9:
        raise SystemExit(f"vehjax bench floor: the C {name} and vehjax.filter disagree")


def main(argv=None) -> int:
    a = parser().parse_args(argv)
    if a.duration <= 0 or a.repeat < 1:
        raise SystemExit("vehjax bench floor: --duration must be > 0 and --repeat >= 1")
    label, model, ys, us, Qm, Rm, x0, P0m, source = PROBLEMS[a.model](a.duration)
    T = len(ys)
    # the C filters: the EKF (the floor), and for the 3-DOF model also the UKF, beside which
    # vehjax's UKF row is set
    kinds = {"EKF": vehjax.filters.ekf} if a.model == "single_track" else \
        {"EKF": vehjax.filters.ekf, "UKF": vehjax.filters.ukf}
    floors = {}
    for k, build in (kinds.items() if source is not None else ()):
        floor = c_floor(source, Qm, Rm, x0, P0m, f"{k.lower()}_loglik")
        if floor is not None:  # None: no C compiler
            check_floor(k, floor, build(model, Qm, Rm), model, ys, us, x0, P0m)
            floors[k] = floor
    rows = (contenders(model, ys, us) if a.model == "single_track" else
            filter_rows(model, ys, us, Qm, Rm, x0, P0m))
    compile_s = {k: timed(fn, args) for k, (fn, args) in rows.items()}  # first call: compile
    best = {k: np.inf for k in rows}
    best_c = {k: np.inf for k in floors}
    for _ in range(a.repeat):
        for k, floor in floors.items():
            t0 = time.perf_counter()
            floor(model, ys, us)
            best_c[k] = min(best_c[k], time.perf_counter() - t0)
        for k, (fn, args) in rows.items():
            best[k] = min(best[k], timed(fn, args))
    print(f"# {T} steps, {label}, float64, {jax.devices()[0]}; "
          f"best of {a.repeat} interleaved rounds; first call (compile + one run) apart")
    print(f"{'row':<15} {'us/step':>9} {'x floor':>9} {'x C same':>9} {'first call s':>13}")
    c_us = {k: v / T * 1e6 for k, v in best_c.items()}
    ratio = lambda v, k: f"{v / c_us[k]:9.1f}" if k in c_us else f"{'-':>9}"  # noqa: E731
    for k in floors:
        name = "C floor" if k == "EKF" else f"C {k}"
        print(f"{name:<15} {c_us[k]:9.3f} {ratio(c_us[k], 'EKF')} {1.0:9.1f} {'-':>13}")
    for k in rows:
        us_step = best[k] / T * 1e6
        same = k.split()[1] if k.startswith(("filter", "run")) else None
        print(f"{k:<15} {us_step:9.3f} {ratio(us_step, 'EKF')} {ratio(us_step, same)} "
              f"{compile_s[k]:13.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
