"""Small dense algebra written entry by entry, shared by the runs-last Gaussian steps
(:mod:`vehjax.filters.runs_last`) and the marginalized PF (:mod:`vehjax.filters.marginalized`).

A matrix is a nested list of entries and a vector a list; every entry is one array over a batch
axis (the runs, or the particles: (R,) or (N,)) or a Python float. A Python float is a
*structural constant*, known when the step is traced: products with a constant zero or one are
folded away and a constant zero costs nothing. XLA then fuses a whole filter step into a few long
vectorised loops over the batch axis, where vmapped matrix code keeps the batch first and runs
every small matrix operation as a loop over it, which is slower on CPU for 3 x 3 to 8 x 8
matrices (``vehjax bench all`` and ``vehjax bench marginalized`` time the filters built on this).

Cholesky factors and forward substitutions of such nested lists are
:func:`vehjax.lib.linalg.chol_entries` and :func:`~vehjax.lib.linalg.forward_entries`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .linalg import UNROLL_MAX, chol_entries, cholesky, lower_from_entries

__all__ = [
    "is_zero", "is_const", "add", "sub", "mul", "div", "dot", "transpose", "matvec", "matmul",
    "wsum", "sym_entries", "backward_entries", "chol_sym", "chol_masked", "entries", "stack",
    "barrier",
]


def is_zero(a) -> bool:
    """Whether ``a`` is the structural constant zero (a Python float 0.0)."""
    return isinstance(a, float) and a == 0.0


def is_const(a) -> bool:
    """Whether ``a`` is a structural constant: a Python float, known at trace time."""
    return isinstance(a, float)


def add(a, b):
    """a + b, a structural zero on either side skipped."""
    if is_zero(a):
        return b
    if is_zero(b):
        return a
    return a + b


def sub(a, b):
    """a - b, a structural zero on either side skipped."""
    if is_zero(b):
        return a
    if is_zero(a):
        return -b
    return a - b


def mul(a, b):
    """a * b; a structural zero gives the constant 0.0, a structural one the other factor."""
    if is_zero(a) or is_zero(b):
        return 0.0
    if isinstance(a, float) and a == 1.0:
        return b
    if isinstance(b, float) and b == 1.0:
        return a
    return a * b


def div(a, b):
    """a / b; 0.0 when ``a`` is the structural zero (``b`` not looked at)."""
    return 0.0 if is_zero(a) else a / b


def dot(a, b):
    """sum_k a[k] b[k] over two lists of entries, structural zero terms skipped; the constant
    0.0 when every term is one."""
    acc = 0.0
    for ak, bk in zip(a, b):
        acc = add(acc, mul(ak, bk))
    return acc


def transpose(A):
    """A^T of a nested list (m, n) -> (n, m)."""
    return [list(col) for col in zip(*A)]


def matvec(A, x):
    """A x: nested list (m, n) times list (n,) -> list (m,)."""
    return [dot(row, x) for row in A]


def matmul(A, B):
    """A B: nested lists (m, k) and (k, n) -> (m, n)."""
    Bt = transpose(B)
    return [[dot(row, col) for col in Bt] for row in A]


def wsum(weights, terms):
    """sum_i w_i t_i over the non-zero weights (``weights`` numpy or Python constants, e.g. a
    sigma-point rule's); None when every weight is zero."""
    acc = None
    for w, t in zip(weights, terms):
        if w == 0.0:
            continue
        term = t if w == 1.0 else float(w) * t
        acc = term if acc is None else acc + term
    return acc


def sym_entries(entry, n: int):
    """Symmetric nested lists (n, n) from ``entry(i, j)``, asked for j <= i only."""
    out = [[None] * n for _ in range(n)]
    for i in range(n):
        for j in range(i + 1):
            out[i][j] = out[j][i] = entry(i, j)
    return out


def joseph_entries(Ls, W, H, N, Pp):
    """The Joseph-form updated covariance (I - K H) P- (I - K H)^T + K N K^T, entry by entry,
    with K = W^T L^-1 row by row (``Ls`` the lower factor of the innovation covariance, ``W``
    the rows L^-1 C^T of the masked cross-covariance, ``H`` (ny, nx) and ``N`` (ny, ny) the
    linearisation and measurement noise, ``Pp`` (nx, nx) the predicted covariance; nested
    lists). Returns the symmetric nested lists (nx, nx)."""
    nx, ny = len(Pp), len(N)
    K = [backward_entries(Ls, W[i]) for i in range(nx)]  # K = C M S_m^-1, row by row
    A = [[(1.0 if i == j else 0.0) - dot(K[i], [H[a][j] for a in range(ny)])
          for j in range(nx)] for i in range(nx)]
    AP = [[dot(A[i], [Pp[j][k] for j in range(nx)]) for k in range(nx)] for i in range(nx)]
    KN = [[dot(K[i], [N[a][b] for a in range(ny)]) for b in range(ny)] for i in range(nx)]
    return sym_entries(lambda i, l: dot(AP[i], A[l]) + dot(KN[i], K[l]), nx)


def backward_entries(L, b):
    """``L^-T b`` by back substitution; ``L`` nested lists, lower triangular (``L[i][k]`` read
    for k <= i only), ``b`` a list."""
    n = len(b)
    out = [None] * n
    for i in reversed(range(n)):
        t = b[i]
        for k in range(i + 1, n):
            t = t - L[k][i] * out[k]
        out[i] = t / L[i][i]
    return out


def chol_sym(A):
    """Lower Cholesky factor (nested lists) of the symmetric part of ``A`` (nested lists);
    NaN entries where it is not positive definite."""
    return chol_entries(lambda i, j: A[i][i] if i == j else 0.5 * (A[i][j] + A[j][i]), len(A))


def chol_masked(S, obs):
    """Lower Cholesky factor (nested lists) of the symmetric part of ``S`` on the observed rows
    and columns, the identity elsewhere; ``obs`` a list of booleans (scalars or arrays), e.g.
    the observed components of a measurement."""
    def a(i, j):
        eye = 1.0 if i == j else 0.0
        return jnp.where(obs[i] & obs[j], S[i][j] if i == j else 0.5 * add(S[i][j], S[j][i]), eye)
    return chol_entries(a, len(S))


def cholesky_observed(M, obs):
    """:func:`chol_masked` on arrays: the lower Cholesky factor (n, n) of M (n, n) on the
    observed components ``obs`` (n,) bool, the identity elsewhere (all NaN where that is not
    positive definite). Unrolled for n <= UNROLL_MAX, LAPACK beyond."""
    n = M.shape[-1]
    if n == 0 or n > UNROLL_MAX:
        both = obs[:, None] & obs[None, :]
        return cholesky(jnp.where(both, M, jnp.eye(n, dtype=M.dtype)))
    L = chol_masked(entries(M), [obs[i] for i in range(n)])
    return lower_from_entries([[jnp.asarray(L[i][j], M.dtype) if j <= i else None
                                for j in range(n)] for i in range(n)])


def entries(a):
    """Entries of an array along its leading axes: (k, ...) -> list of k arrays (...),
    (m, k, ...) -> nested lists (m, k) of arrays (...)."""
    if a.ndim >= 2 and a.shape[0] * a.shape[1] == 0:
        return [[] for _ in range(a.shape[0])]
    if a.ndim >= 2:
        return [entries(a[i]) if a.ndim >= 3 else a[i] for i in range(a.shape[0])]
    return [a[i] for i in range(a.shape[0])]


def stack(E, like):
    """The inverse of :func:`entries`: a list (k,) or nested lists (m, k) of entries to an array
    (k, *like.shape) or (m, k, *like.shape), each entry (constants too) broadcast to ``like``'s
    shape and cast to its dtype."""
    def one(v):
        return jnp.broadcast_to(jnp.asarray(v, like.dtype), like.shape)
    if E and isinstance(E[0], list):
        return jnp.stack([jnp.stack([one(v) for v in row]) if row else jnp.zeros((0,) + like.shape,
                                                                                 like.dtype)
                          for row in E])
    return jnp.stack([one(v) for v in E]) if E else jnp.zeros((0,) + like.shape, like.dtype)


def barrier(tree, start=None):
    """The array leaves of ``tree`` (structural constants pass through), materialised: they go
    through a while loop whose body multiplies by one and whose trip count (0 or 1) XLA cannot
    know at compile time. Without it XLA on CPU fuses long chains of elementwise producers into
    every consumer and recomputes them there (7x the operation count of the marginalized PF's
    step); ``lax.optimization_barrier`` is removed before fusion on CPU and does not help.

    ``start``: an int32 scalar, 0 at run time but opaque to the compiler; best one that does not
    vary over the runs of a study (from the inputs), so that the loop stays a plain loop under
    ``vmap``. Default: from the first leaf.
    """
    leaves, treedef = jax.tree.flatten(tree)
    idx = [i for i, v in enumerate(leaves) if not is_const(v)]
    if not idx:
        return tree
    arrs = [leaves[i] for i in idx]
    if start is None:
        probe = jnp.ravel(arrs[0])[0]
        start = (probe != probe).astype(jnp.int32)  # 0 unless NaN

    def body(c):
        one = (c[0] >= 0).astype(arrs[0].dtype)  # 1, but not known to the compiler
        return c[0] + 1, [a * one.astype(a.dtype) for a in c[1]]

    _, kept = jax.lax.while_loop(lambda c: c[0] < 1, body, (start, arrs))
    for i, v in zip(idx, kept):
        leaves[i] = v
    return jax.tree.unflatten(treedef, leaves)
