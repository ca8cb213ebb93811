"""The textbook sideslip observer: a linear single-track Kalman filter with the spec values, in
plain numpy, independent of vehjax's filters (a peer to judge them by).

Reference: the Kalman-filter baseline of Leanza, Reina & Blanco-Claraco, "A Factor-Graph-Based
Approach to Vehicle Sideslip Angle Estimation", Sensors 21(16) 5409, 2021: the linear bicycle
model with linear tyres, the vehicle's nominal (data-sheet) parameters, the yaw rate (and here
the lateral acceleration) measured, and the model's error entering through the steering angle.
Their states are (sideslip, yaw rate) with an Euler step; these are (vy, r), sideslip
arctan(vy / vx), discretised as below (at 200 Hz the difference is far below the filter's
error).

Model (states x = (vy [m/s], r [rad/s]), input delta [rad] road-wheel steer, vx [m/s] given)::

    x' = A(vx) x + B delta,   y = (ay, r) = C(vx) x + D delta
    A = [[-(cf + cr) / (m vx), (lr cr - lf cf) / (m vx) - vx],
         [(lr cr - lf cf) / (iz vx), -(lf^2 cf + lr^2 cr) / (iz vx)]]
    B = (cf / m, lf cf / iz);  C = [[-(cf + cr) / (m vx), (lr cr - lf cf) / (m vx)], [0, 1]];
    D = (cf / m, 0)

Each step holds (delta, vx) over dt and discretises by ``substeps`` classical RK4 steps of the
linear system (Phi = P(hA)^n with P(M) = I + M + M^2/2 + M^3/6 + M^4/24, Gamma the matching
input map): the discretisation of ``vehjax.models.SingleTrack``'s transition, so that on the
same values this filter equals vehjax's EKF on the linear model to rounding (tested). The
steering noise sigma_delta enters as Gamma sigma_delta^2 Gamma^T: scaled by the stiffness
through B. Each step predicts with u_t, then updates with y_t (vehjax's order).

Untuned noise (:data:`TEXTBOOK_NOISE`): sensor data-sheet values, not fitted. Textbook
cornering stiffnesses from the axle loads: :func:`vehjax.studies.second_car.textbook_stiffness`.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from vehjax.studies.second_car import textbook_stiffness  # noqa: F401  (the spec sheet's stiffnesses)

#: Untuned standard deviations: ay [m/s^2], r [rad/s], the steering noise delta [rad]; and a
#: small process noise on (vy [m/s], r [rad/s]) per step.
TEXTBOOK_NOISE = {"ay": 0.5, "r": np.deg2rad(0.5), "delta": np.deg2rad(0.5),
                  "q": (1e-3, np.deg2rad(0.01))}



class ObserverResult(NamedTuple):
    """states (T, 2) filtered (vy, r); covariances (T, 2, 2); loglik (T,) log p(y_t | y_1:t-1);
    nis (T,) normalised innovation squared (2 degrees of freedom)."""

    states: np.ndarray
    covariances: np.ndarray
    loglik: np.ndarray
    nis: np.ndarray


def linear_matrices(spec: dict, vx: float):
    """(A (2, 2), B (2,), C (2, 2), D (2,)) of the linear single-track model at speed vx."""
    m, iz, lf, lr, cf, cr = (spec[k] for k in ("m", "iz", "lf", "lr", "cf", "cr"))
    a11, a12 = -(cf + cr) / (m * vx), (lr * cr - lf * cf) / (m * vx)
    A = np.array([[a11, a12 - vx], [(lr * cr - lf * cf) / (iz * vx),
                                    -(lf**2 * cf + lr**2 * cr) / (iz * vx)]])
    return A, np.array([cf / m, lf * cf / iz]), np.array([[a11, a12], [0.0, 1.0]]), np.array(
        [cf / m, 0.0])


def discretise(A, B, dt: float, substeps: int = 2):
    """(Phi, Gamma): the map x -> Phi x + Gamma delta of ``substeps`` RK4 steps of x' = A x +
    B delta over ``dt`` with delta held."""
    h = dt / substeps
    M = h * A
    eye = np.eye(len(A))
    M2 = M @ M
    step = eye + M + M2 / 2 + M2 @ M / 6 + M2 @ M2 / 24
    gain = h * (eye + M / 2 + M2 / 6 + M2 @ M / 24) @ B
    Phi, Gamma = eye, np.zeros_like(B)
    for _ in range(substeps):
        Phi, Gamma = step @ Phi, step @ Gamma + gain
    return Phi, Gamma


def kalman_step(x, P, y, delta, vx, spec, dt, Q, R, steer_var, substeps):
    """One predict (u_t) and update (y_t) of the linear KF: (x, P, loglik, nis). A NaN
    component of y is skipped."""
    A, B, C, D = linear_matrices(spec, vx)
    Phi, Gamma = discretise(A, B, dt, substeps)
    x = Phi @ x + Gamma * delta
    P = Phi @ P @ Phi.T + Q + steer_var * np.outer(Gamma, Gamma)
    ok = np.isfinite(y)
    if not ok.any():
        return x, P, 0.0, np.nan
    H, Rk = C[ok], R[np.ix_(ok, ok)]
    e = y[ok] - H @ x - D[ok] * delta
    S = H @ P @ H.T + Rk
    K = np.linalg.solve(S, H @ P).T
    x = x + K @ e
    J = np.eye(2) - K @ H
    P = J @ P @ J.T + K @ Rk @ K.T
    w = np.linalg.solve(S, e)
    nis = float(e @ w)
    loglik = -0.5 * (nis + np.linalg.slogdet(2.0 * np.pi * S)[1])
    return x, 0.5 * (P + P.T), loglik, nis


def textbook_observer(ys, us, spec: dict, dt: float, noise: dict | None = None, x0=None,
                      P0=None, substeps: int = 2) -> ObserverResult:
    """Run the textbook observer over a drive.

    Args:
        ys: (T, 2) measured (ay [m/s^2], r [rad/s]); NaN for missing.
        us: (T, 2) measured (delta [rad], vx [m/s]); vx > 0.
        spec: {"m", "iz", "lf", "lr", "cf", "cr"} (kg, kg m^2, m, m, N/rad, N/rad).
        dt: sampling period [s].
        noise: overrides of :data:`TEXTBOOK_NOISE`.
        x0: (2,) state before the first step (zeros); P0: (2, 2) or (2,) variances
            (default diag(0.1, 0.01)).
        substeps: RK4 steps per sample (:func:`discretise`).
    """
    nz = {**TEXTBOOK_NOISE, **(noise or {})}
    R = np.diag([nz["ay"] ** 2, nz["r"] ** 2])
    Q = np.diag(np.square(nz["q"]))
    x = np.zeros(2) if x0 is None else np.asarray(x0, float)
    P = np.diag([0.1, 0.01]) if P0 is None else np.asarray(P0, float)
    P = np.diag(P) if P.ndim == 1 else P
    ys, us = np.asarray(ys, float), np.asarray(us, float)
    T = len(ys)
    states, covs, ll, nis = np.zeros((T, 2)), np.zeros((T, 2, 2)), np.zeros(T), np.zeros(T)
    for t in range(T):
        x, P, ll[t], nis[t] = kalman_step(x, P, ys[t], us[t, 0], us[t, 1], spec, dt, Q, R,
                                          nz["delta"] ** 2, substeps)
        states[t], covs[t] = x, P
    return ObserverResult(states, covs, ll, nis)
