"""Shared by the bank tests: SingleTrackBank's equations (eq. 1-3) written out in numpy, an
independent reference for the jax model, and the exact Kalman filter of its linear-Gaussian
form with paper 004's noise (the reference for the marginalized PF with known noise)."""

import math

import numpy as np

from vehjax.models.bank import G


def continuous_matrices(vx, th):
    """Continuous x' = A x + B delta of the linear single-track model with road bank at speed
    vx [m/s], th = (m, iz, lf, lr, cf, cr); states (vy, r, phi, phi_dot, phi_ddot)."""
    m, iz, lf, lr, cf, cr = th
    a = np.zeros((5, 5))
    a[0, 0] = -(cf + cr) / (m * vx)
    a[0, 1] = -vx + (lr * cr - lf * cf) / (m * vx)
    a[0, 2] = -G
    a[1, 0] = (lr * cr - lf * cf) / (iz * vx)
    a[1, 1] = -(lf**2 * cf + lr**2 * cr) / (iz * vx)
    a[2, 3] = a[3, 4] = 1.0
    b = np.array([cf / m, lf * cf / iz, 0.0, 0.0, 0.0])
    return a, b


def discrete_matrices(th, vx, dt):
    """Exact RK4 discretisation of the linear SingleTrackBank at speed vx, step dt, in numpy:
    X+ = Ad X + Bd delta, y = C X + Dd delta (eq. 1-3 and the ay, r, roll_rate, phi, r_virt
    outputs)."""
    m, iz, lf, lr, cf, cr = np.asarray(th)
    a, b = continuous_matrices(vx, (m, iz, lf, lr, cf, cr))
    M = dt * a
    Ad = sum(np.linalg.matrix_power(M, k) / math.factorial(k) for k in range(5))
    Bd = dt * sum(np.linalg.matrix_power(M, k) / math.factorial(k + 1) for k in range(4)) @ b
    C = np.zeros((5, 5))
    C[0, 0], C[0, 1] = -(cf + cr) / (m * vx), (lr * cr - lf * cf) / (m * vx)
    C[1, 1] = C[4, 1] = 1.0
    C[2, 3] = C[3, 2] = 1.0
    Dd = np.array([cf / m, 0.0, 0.0, 0.0, 0.0])
    return Ad, Bd, C, Dd


def exact_kalman(th, vx, dt, Y, delta, mu_w, sig_w, sigma_phi, bias, std, x0, P0, bank_gain):
    """Kalman filter of the linear-Gaussian SingleTrackBank at speed vx with the white steering
    error w_t ~ N(mu_w, sig_w^2) entering the transition and the observation alike (eq. 6-9),
    white bank jerk of std sigma_phi through ``bank_gain`` (eq. 3), outputs with constant
    ``bias`` and white noise of std ``std`` (5 each). State (x_t, w_t); components NaN in every
    run are skipped. Y (R, T, 5), delta (T,) the measured steering. Returns the filtered means
    (R, T, 5) and covariances (T, 5, 5) of x_t."""
    Ad, Bd, C, Dd = discrete_matrices(th, vx, dt)
    F = np.zeros((6, 6))
    F[:5, :5] = Ad
    G = np.zeros((6, 2))
    G[:5, 0], G[5, 0], G[:5, 1] = Bd * sig_w, sig_w, np.asarray(bank_gain) * sigma_phi
    Q = G @ G.T
    H = np.concatenate([C, Dd[:, None]], 1)
    Rm = np.diag(np.asarray(std, float) ** 2)
    b = np.asarray(bias, float)
    runs, T, _ = Y.shape
    m = np.tile(np.r_[x0, mu_w], (runs, 1))
    P = np.zeros((6, 6))
    P[:5, :5] = P0
    means, covs = np.zeros((runs, T, 5)), np.zeros((T, 5, 5))
    for t in range(T):
        m = m @ F.T + np.r_[Bd * (delta[t] + mu_w), mu_w]
        P = F @ P @ F.T + Q
        o = ~np.isnan(Y[0, t])  # the same components missing in every run
        Ho = H[o]
        S = Ho @ P @ Ho.T + Rm[np.ix_(o, o)]
        K = np.linalg.solve(S, Ho @ P).T
        m = m + (Y[:, t, o] - m @ Ho.T - Dd[o] * delta[t] - b[o]) @ K.T
        P = P - K @ S @ K.T
        P = 0.5 * (P + P.T)
        means[:, t], covs[t] = m[:, :5], P[:5, :5]
    return means, covs
