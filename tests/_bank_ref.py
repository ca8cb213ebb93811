"""Shared by the bank tests: SingleTrackBank's equations (eq. 1-3) written out in numpy, an
independent reference for the jax model."""

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
