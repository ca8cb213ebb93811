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
