"""Shared by the filter tests: data from a linear-Gaussian model x' = A x + B u + w, y = H x + v."""

import numpy as np


def linear_gaussian_data(A, B, H, Q, R, x0, P0, T, seed=0):
    """Measurements (T, ny) and inputs (T, nu) of one run, inputs drawn N(0, 1)."""
    rng = np.random.default_rng(seed)
    us = rng.normal(size=(T, B.shape[1]))
    x = x0 + rng.multivariate_normal(np.zeros(len(x0)), P0)
    ys = []
    for t in range(T):
        x = A @ x + B @ us[t] + rng.multivariate_normal(np.zeros(len(x0)), Q)
        ys.append(H @ x + rng.multivariate_normal(np.zeros(H.shape[0]), R))
    return np.array(ys), us


def scalar_kalman_loglik(a, q, r, ys, us, x0=0.0, p0=1.0):
    """Exact log p(y_1:T) of x' = a x + u + w (var q), y = x + v (var r), x_0 ~ N(x0, p0): the
    textbook scalar Kalman filter in numpy (predict with u_t, then update with y_t)."""
    x, P, total = x0, p0, 0.0
    for t in range(len(ys)):
        x, P = a * x + us[t, 0], a * a * P + q
        S = P + r
        e = ys[t, 0] - x
        total += -0.5 * (e * e / S + np.log(2 * np.pi * S))
        K = P / S
        x, P = x + K * e, (1 - K) * P
    return total


def fd_hessian(fn, p, rel=1e-4, floor=0.0):
    """Central finite-difference Hessian of fn at p (numpy), steps rel * max(|p_i|, floor)."""
    p = np.asarray(p, dtype=float)
    h = rel * np.maximum(np.abs(p), floor)
    n = len(p)
    H = np.zeros((n, n))
    for i in range(n):
        for j in range(n):
            ei, ej = np.eye(n)[i] * h[i], np.eye(n)[j] * h[j]
            H[i, j] = (fn(p + ei + ej) - fn(p + ei - ej) - fn(p - ei + ej)
                       + fn(p - ei - ej)) / (4 * h[i] * h[j])
    return 0.5 * (H + H.T)
