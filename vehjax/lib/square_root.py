"""A square root of a covariance: L with L L^T = A, for a constant (numpy) or traced (jax) A.

The filters build their constant noise factors once, in numpy, when a builder is called, and a
calibrated covariance is factorised in the trace; a constant that is only positive
semi-definite (a process noise with zero variance on a noise-free state) has no Cholesky factor
and gets the symmetric square root of its eigen-decomposition instead.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

__all__ = ["chol_const"]


def chol_const(A):
    """A square root L with L L^T = A: the lower Cholesky factor, in numpy for a constant, in jax
    for a traced matrix; for a constant that is only positive semi-definite (a Q with zero
    variances for noise-free states) V diag(sqrt(w)) from its eigen-decomposition."""
    if not isinstance(A, np.ndarray):
        return jnp.linalg.cholesky(A)
    try:
        return np.linalg.cholesky(A)
    except np.linalg.LinAlgError:
        w, V = np.linalg.eigh(A)
        return V * np.sqrt(np.maximum(w, 0.0))[None, :]
