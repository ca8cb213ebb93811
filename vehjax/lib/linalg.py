"""The small-matrix kernels every filter shares: Cholesky, forward substitution, symmetrisation.

Vehicle models have a handful of states and outputs. For n <= 8 the textbook Cholesky and forward
substitution are written out entry by entry; under ``vmap`` over runs (or with extra leading
axes) every entry is one vector, so XLA fuses the whole factorisation into a few vectorised loops
instead of one LAPACK call per run and matrix. Larger n go to ``jnp.linalg`` /
``jax.scipy.linalg``. Same algorithm, rounding-level differences.

The entry-wise cores :func:`chol_entries` and :func:`forward_entries` work on nested lists of
arrays of any one shape, so the same code serves matrices with the batch axes first
(:func:`cholesky`, :func:`solve_lower`: (..., n, n)) and the runs-last layout of
:mod:`vehjax.filters.runs_last` (every entry an (R,) vector).
"""

from __future__ import annotations

import jax.numpy as jnp
from jax.scipy.linalg import solve_triangular

#: Largest dimension for which the kernels are unrolled (n^3 / 6 scalar ops at trace time).
UNROLL_MAX = 8


def sym(A):
    """(A + A^T) / 2 over the last two axes."""
    return 0.5 * (A + jnp.swapaxes(A, -1, -2))


def chol_entries(a, n: int):
    """Lower Cholesky factor as nested lists ``L[i][j]`` (j <= i) of the symmetric matrix whose
    entries ``a(i, j)`` returns (arrays of one shape; only i >= j is asked for).

    A non-positive or NaN pivot gives NaN in that column and every later one, as LAPACK's
    failure does under ``jnp.linalg.cholesky``; callers test ``isfinite``.
    """
    L = [[None] * n for _ in range(n)]
    for j in range(n):
        d = a(j, j)
        for k in range(j):
            d = d - L[j][k] * L[j][k]
        L[j][j] = jnp.sqrt(jnp.where(d > 0, d, jnp.nan))
        for i in range(j + 1, n):
            t = a(i, j)
            for k in range(j):
                t = t - L[i][k] * L[j][k]
            L[i][j] = t / L[j][j]
    return L


def forward_entries(L, b):
    """``L^-1 b`` by forward substitution: ``L`` nested lists (lower, ``L[i][k]`` for k <= i),
    ``b`` a list of n arrays broadcasting against the entries of L."""
    out = []
    for i in range(len(b)):
        t = b[i]
        for k in range(i):
            t = t - L[i][k] * out[k]
        out.append(t / L[i][i])
    return out


def cholesky(A):
    """Lower Cholesky factor of symmetric positive-definite ``A`` (..., n, n).

    ``A`` is symmetrised first; a matrix that is not positive definite (or not finite) gives a
    factor with NaN entries. Unrolled for n <= 8.
    """
    n = A.shape[-1]
    if A.shape[-2] != n:
        raise ValueError(f"A: expected a square matrix (..., n, n), got shape {A.shape}")
    if n == 0 or n > UNROLL_MAX:
        L = jnp.linalg.cholesky(sym(A))
        return jnp.where(jnp.all(jnp.isfinite(L), axis=(-2, -1))[..., None, None], L, jnp.nan)

    def a(i, j):
        return A[..., i, i] if i == j else 0.5 * (A[..., i, j] + A[..., j, i])

    return lower_from_entries(chol_entries(a, n))


def lower_from_entries(L):
    """The (..., n, n) array of a lower Cholesky factor given as nested lists ``L[i][j]``
    (j <= i, arrays of one shape), zeros above the diagonal; all NaN where any entry is not
    finite (as :func:`cholesky` fails)."""
    n = len(L)
    zero = jnp.zeros_like(L[0][0])  # entries above the diagonal are not read
    out = jnp.stack(
        [jnp.stack([L[i][j] if j <= i else zero for j in range(n)], axis=-1) for i in range(n)],
        axis=-2,
    )
    ok = jnp.all(jnp.isfinite(out), axis=(-2, -1))
    return jnp.where(ok[..., None, None], out, jnp.nan)


def solve_lower(L, b):
    """``L^-1 b`` for lower-triangular ``L`` (..., n, n) and ``b`` (..., n) or (..., n, k).

    Forward substitution, unrolled over rows for n <= 8 (the upper triangle of L is not read).
    """
    n = L.shape[-1]
    vec = b.ndim == L.ndim - 1
    if L.shape[-2] != n or b.shape[-1 if vec else -2] != n:
        raise ValueError(f"b: expected shape (..., {n}) or (..., {n}, k), got shape {b.shape}")
    if n == 0 or n > UNROLL_MAX:
        X = solve_triangular(L, b[..., None] if vec else b, lower=True)
        return X[..., 0] if vec else X
    B = b[..., None] if vec else b
    Le = [[L[..., i, k, None] for k in range(i + 1)] for i in range(n)]
    X = jnp.stack(forward_entries(Le, [B[..., i, :] for i in range(n)]), axis=-2)
    return X[..., 0] if vec else X


def logdet_from_chol(L):
    """log det(L L^T) from a lower Cholesky factor (..., n, n)."""
    return 2.0 * jnp.sum(jnp.log(jnp.diagonal(L, axis1=-2, axis2=-1)), axis=-1)


def cholesky_succeeds(a, n: int):
    """Whether the Cholesky factorisation of the symmetric n x n matrix whose entries ``a(i, j)``
    returns (arrays of one shape, i >= j) succeeds: a bool array of the entries' shape. A
    non-positive or NaN pivot makes every later column NaN (:func:`chol_entries`), the last
    pivot included, so that pivot tells. The one positive-definiteness test: :func:`is_pd`
    applies it to matrices with the batch axes first, :func:`vehjax.filters.runs_last.runs_pd`
    to the runs-last layout."""
    L = chol_entries(a, n)
    return jnp.isfinite(L[n - 1][n - 1])


def is_pd(C):
    """Whether a square matrix (..., n, n) is finite and positive definite (its Cholesky
    succeeds); a bool of the batch shape. An empty matrix is positive definite."""
    if C.shape[-1] == 0:
        return jnp.ones(C.shape[:-2], bool)
    finite = jnp.all(jnp.isfinite(C), axis=(-2, -1))
    n = C.shape[-1]
    if n > UNROLL_MAX:
        return finite & jnp.all(jnp.isfinite(cholesky(C)), axis=(-2, -1))
    return finite & cholesky_succeeds(
        lambda i, j: C[..., i, i] if i == j else 0.5 * (C[..., i, j] + C[..., j, i]), n)
