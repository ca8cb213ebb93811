"""Error and consistency metrics of a Monte-Carlo study.

Estimates are ``(R, T, n)`` arrays (runs, steps, components), e.g. ``out.states`` or
``out.params`` of :func:`vehjax.run`. ``truth`` is anything that broadcasts to the estimates
with numpy's rules: ``(R, T, n)`` (``sim.states``), ``(T, n)``, ``(n,)`` for constant true
parameters, or ``theta[:, None, :]`` for per-run constants ``(R, n)``. Results are in the units of
the compared quantities and are numpy arrays.

``mask`` (R,) bool selects the runs to include, e.g. ``mask=~out.diverged``: excluded runs do not
enter averages over runs, and per-run results are NaN for them.

Consistency (Bar-Shalom, Li & Kirubarajan, 2001, sec. 5.4): for a consistent filter the NEES of
an n-state estimate is chi-square with n degrees of freedom and the NIS with ``n_obs``; the
average over N runs, times N, is chi-square with the summed degrees of freedom. ``chi2_bounds``
gives the two-sided probability region of that average and ``consistency`` checks it step by step.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "rmse",
    "mae",
    "nees",
    "chi2_bounds",
    "consistency",
    "Consistency",
    "convergence_time",
    "final_error",
    "confidence_interval",
    "Interval",
]

_AXES = ("all", "run", "time")


# ----------------------------------------------------------------------------------------------
# Argument checks


def _estimates(arg: str, x) -> np.ndarray:
    x = np.asarray(x)
    if x.ndim != 3:
        raise ValueError(
            f"{arg}: expected shape (runs, steps, n), got {x.shape}; for one run pass x[None]"
        )
    if not np.issubdtype(x.dtype, np.number) or np.iscomplexobj(x):
        raise ValueError(f"{arg}: expected a real numeric array, got dtype {x.dtype}")
    return x


def _truth(truth, shape) -> np.ndarray:
    truth = np.asarray(truth)
    try:
        return np.broadcast_to(truth, shape)
    except ValueError:
        raise ValueError(
            f"truth: shape {truth.shape} does not broadcast to the estimates' shape {shape}; "
            f"expected (R, T, n), (T, n), (n,) or (R, 1, n)"
        ) from None


def _mask(mask, R: int) -> np.ndarray:
    if mask is None:
        return np.ones(R, bool)
    m = np.asarray(mask)
    if m.shape != (R,) or m.dtype != bool:
        raise ValueError(
            f"mask: expected a bool array of shape ({R},) (True = include), got {m.dtype} {m.shape}"
        )
    return m


def _errors(estimates, truth, mask):
    est = _estimates("estimates", estimates)
    err = est - _truth(truth, est.shape)
    return err, _mask(mask, est.shape[0])


def _reduce(values, mask, axis: str):
    """Mean of ``values`` (R, T, n) over runs and time ("all"), time ("run") or runs ("time")."""
    if axis not in _AXES:
        raise ValueError(f"axis: expected one of {_AXES}, got {axis!r}")
    if axis == "run":
        out = values.mean(axis=1)
        return np.where(mask[:, None], out, np.nan)
    kept = values[mask]
    if kept.shape[0] == 0:
        shape = values.shape[2:] if axis == "all" else values.shape[1:]
        return np.full(shape, np.nan)
    return kept.mean(axis=(0, 1)) if axis == "all" else kept.mean(axis=0)


# ----------------------------------------------------------------------------------------------
# Errors


def rmse(estimates, truth, *, axis: str = "all", mask=None) -> np.ndarray:
    """Root-mean-square error per component.

    Args:
        estimates: (R, T, n).
        truth: broadcastable to (R, T, n).
        axis: "all": over runs and time, (n,); "run": over time, one row per run, (R, n);
            "time": over runs, one row per step, (T, n).
        mask: (R,) bool, runs to include.
    """
    err, m = _errors(estimates, truth, mask)
    return np.sqrt(_reduce(err**2, m, axis))


def mae(estimates, truth, *, axis: str = "all", mask=None) -> np.ndarray:
    """Mean absolute error per component; shapes as :func:`rmse`."""
    err, m = _errors(estimates, truth, mask)
    return _reduce(np.abs(err), m, axis)


def final_error(
    estimates, truth, *, window: int = 1, relative: bool = False, mask=None
) -> np.ndarray:
    """Signed error at the end of each run, (R, n), averaged over the last ``window`` steps.

    With ``relative=True`` the error is divided by ``|truth|`` (a fraction, not a percentage).
    NaN rows for runs excluded by ``mask``.
    """
    err, m = _errors(estimates, truth, mask)
    T = err.shape[1]
    is_int = isinstance(window, (int, np.integer)) and not isinstance(window, bool)
    if not is_int or not 1 <= window <= T:
        raise ValueError(f"window: expected an integer in [1, {T}], got {window!r}")
    if relative:
        err = err / np.abs(_truth(truth, err.shape))
    out = err[:, T - window :].mean(axis=1)
    return np.where(m[:, None], out, np.nan)


def convergence_time(estimates, truth, tol, dt: float, *, t0: float = 0.0, mask=None) -> np.ndarray:
    """Time after which the absolute error stays within ``tol`` until the end, (R, n), s.

    The estimate at step index k is taken to be at time ``t0 + k * dt``; the result is the time
    of the first step from which every later error is within ``tol`` (``t0`` if always within),
    ``np.inf`` if the error at the last step is outside (never converged), NaN for runs excluded by
    ``mask``. A NaN error counts as outside.

    Args:
        estimates: (R, T, n).
        truth: broadcastable to (R, T, n).
        tol: absolute tolerance, scalar or (n,), in the components' units (for a relative one
            pass ``rel * np.abs(true_value)``).
        dt: step period, s (> 0).
    """
    err, m = _errors(estimates, truth, mask)
    dt = float(dt)
    if not np.isfinite(dt) or dt <= 0:
        raise ValueError(f"dt: expected a positive, finite number of seconds, got {dt}")
    tol = np.asarray(tol, dtype=float)
    if tol.shape not in ((), (err.shape[2],)) or not np.all(tol >= 0):
        raise ValueError(
            f"tol: expected a non-negative scalar or shape ({err.shape[2]},), got {tol}"
        )
    outside = ~(np.abs(err) <= tol)  # NaN -> outside
    T = err.shape[1]
    any_out = outside.any(axis=1)
    last_out = T - 1 - np.argmax(outside[:, ::-1], axis=1)  # last index outside (valid if any_out)
    first_in = np.where(any_out, last_out + 1, 0)
    time = np.where(first_in >= T, np.inf, t0 + first_in * dt)
    return np.where(m[:, None], time, np.nan)


# ----------------------------------------------------------------------------------------------
# Consistency


@jax.jit
def _nees(x, P, truth):
    e = x - truth
    L = jnp.linalg.cholesky(0.5 * (P + jnp.swapaxes(P, -1, -2)))
    z = jax.scipy.linalg.solve_triangular(L, e[..., None], lower=True)[..., 0]
    return jnp.sum(z**2, axis=-1)


def nees(states, covariances, truth) -> np.ndarray:
    """Normalised estimation error squared e' P^-1 e per run and step, (R, T).

    Args:
        states: (R, T, nx), e.g. ``out.states``.
        covariances: (R, T, nx, nx), e.g. ``out.covariances`` (``return_covariances=True``).
        truth: broadcastable to (R, T, nx).

    NaN where a covariance is not positive definite.
    """
    x = _estimates("states", states)
    P = np.asarray(covariances)
    if P.shape != x.shape + (x.shape[2],):
        raise ValueError(f"covariances: expected shape {x.shape + (x.shape[2],)}, got {P.shape}")
    return np.asarray(_nees(x, P, _truth(truth, x.shape)))


def _bisect(cdf, q, hi, iters: int = 110):
    """Solve cdf(x) = q on [0, hi] by bisection (elementwise; cdf increasing)."""

    def body(_, lohi):
        lo, hi = lohi
        mid = 0.5 * (lo + hi)
        below = cdf(mid) < q
        return jnp.where(below, mid, lo), jnp.where(below, hi, mid)

    lo, hi = jax.lax.fori_loop(0, iters, body, (jnp.zeros_like(hi), hi))
    return 0.5 * (lo + hi)


@jax.jit
def _gammainc_ppf(q, a):
    """x with P(a, x) = q, P the regularised lower incomplete gamma function; a > 0."""
    # P(a, a + 40 sqrt(a) + 100) is 1 to double precision for every a > 0.
    hi = a + 40.0 * jnp.sqrt(a) + 100.0
    return _bisect(lambda x: jax.scipy.special.gammainc(a, x), q, hi)


@jax.jit
def _student_t_ppf(q, nu):
    """t with F(t) = q in [0.5, 1 - 1e-15) for Student's t with ``nu`` >= 1 degrees of freedom."""

    def cdf(t):
        return 1.0 - 0.5 * jax.scipy.special.betainc(0.5 * nu, 0.5, nu / (nu + t * t))

    return _bisect(cdf, q, jnp.full_like(nu, 1e16), iters=200)


def _bucketed(fn, q, p, pad_p: float) -> np.ndarray:
    """``fn(q, p)`` elementwise on broadcast arrays, padded to a power-of-two length so that a
    Python process compiles ``fn`` for a few sizes only."""
    q, p = np.broadcast_arrays(np.asarray(q, float), np.asarray(p, float))
    n = q.size
    size = max(16, 1 << (n - 1).bit_length())
    qf = np.full(size, 0.75)
    pf = np.full(size, pad_p)
    qf[:n], pf[:n] = q.ravel(), p.ravel()
    return np.asarray(fn(jnp.asarray(qf), jnp.asarray(pf)))[:n].reshape(q.shape)


def _chi2_ppf(q, dof) -> np.ndarray:
    """Chi-square quantile for probability ``q`` in (0, 1) and ``dof`` >= 0 (0 gives 0)."""
    dof = np.asarray(dof, float)
    x = 2.0 * _bucketed(_gammainc_ppf, q, np.where(dof > 0, 0.5 * dof, 1.0), 1.0)
    return np.where(dof > 0, x, 0.0)


def _check_prob(prob) -> float:
    prob = float(prob)
    if not 0.0 < prob < 1.0:
        raise ValueError(f"prob: expected a probability in (0, 1), got {prob}")
    return prob


def chi2_bounds(dof, n_runs=1, prob: float = 0.95):
    """Two-sided ``prob`` region (low, high) of a chi-square statistic averaged over runs.

    If each of ``n_runs`` independent statistics is chi-square with ``dof`` degrees of freedom,
    their average lies in ``[low, high]`` with probability ``prob``:
    ``low = chi2.ppf((1 - prob) / 2, dof * n_runs) / n_runs`` and ``high`` likewise with
    ``(1 + prob) / 2``. ``dof`` and ``n_runs`` may be arrays (broadcast); returns arrays of
    that shape (floats for scalars).
    """
    prob = _check_prob(prob)
    dof = np.asarray(dof, float)
    n = np.asarray(n_runs, float)
    if np.any(dof < 0) or np.any(~np.isfinite(dof)):
        raise ValueError(f"dof: expected non-negative degrees of freedom, got {dof}")
    if np.any(n < 1) or np.any(~np.isfinite(n)):
        raise ValueError(f"n_runs: expected a number of runs >= 1, got {n}")
    total = dof * n
    low = _chi2_ppf(0.5 * (1.0 - prob), total) / n
    high = _chi2_ppf(0.5 * (1.0 + prob), total) / n
    if low.ndim == 0:
        return float(low), float(high)
    return low, high


class Consistency(NamedTuple):
    """Run-averaged NEES or NIS per step with its chi-square region.

    Attributes:
        mean: average over the included runs, (T,).
        low, high: ``prob`` region of that average for a consistent filter, (T,).
        inside: fraction of steps whose average lies in [low, high] (steps without data skipped).
    """

    mean: np.ndarray
    low: np.ndarray
    high: np.ndarray
    inside: float


def consistency(values, dof, *, prob: float = 0.95, mask=None) -> Consistency:
    """Check run-averaged NEES/NIS against its chi-square region, step by step.

    Args:
        values: (R, T), e.g. ``nees(...)`` or ``out.nis``; NaN entries (a diverged run's steps)
            are left out of that step's average.
        dof: degrees of freedom per entry, scalar (nx for NEES) or broadcastable to (R, T)
            (``out.n_obs`` for NIS, which changes with missing measurements).
        prob: probability of the two-sided region.
        mask: (R,) bool, runs to include.

    At step t with N_t included runs and D_t summed degrees of freedom, the region is
    ``[chi2.ppf((1-prob)/2, D_t), chi2.ppf((1+prob)/2, D_t)] / N_t``.
    """
    prob = _check_prob(prob)
    v = np.asarray(values, float)
    if v.ndim != 2:
        raise ValueError(f"values: expected shape (runs, steps), got {v.shape}")
    try:
        d = np.broadcast_to(np.asarray(dof, float), v.shape)
    except ValueError:
        raise ValueError(
            f"dof: shape {np.shape(dof)} does not broadcast to values {v.shape}"
        ) from None
    if np.any(d < 0):
        raise ValueError("dof: expected non-negative degrees of freedom")
    use = _mask(mask, v.shape[0])[:, None] & ~np.isnan(v)
    n = use.sum(axis=0)
    total = np.where(use, v, 0.0).sum(axis=0)
    D = np.where(use, d, 0.0).sum(axis=0)
    has = n > 0
    safe_n = np.maximum(n, 1)
    mean = np.where(has, total / safe_n, np.nan)
    low = np.where(has, _chi2_ppf(0.5 * (1.0 - prob), D) / safe_n, np.nan)
    high = np.where(has, _chi2_ppf(0.5 * (1.0 + prob), D) / safe_n, np.nan)
    ok = (mean >= low) & (mean <= high)
    inside = float(ok[has].mean()) if has.any() else float("nan")
    return Consistency(mean, low, high, inside)


# ----------------------------------------------------------------------------------------------
# Tables


class Interval(NamedTuple):
    """Mean and confidence interval over runs: ``mean ± half_width`` = [low, high]."""

    mean: np.ndarray
    half_width: np.ndarray
    low: np.ndarray
    high: np.ndarray


def confidence_interval(x, *, axis: int = 0, level: float = 0.95, mask=None) -> Interval:
    """Mean over runs and its Student-t confidence interval, for tables.

    Args:
        x: array whose ``axis`` indexes runs, e.g. ``rmse(..., axis="run")`` of shape (R, n).
            NaN entries are ignored (so runs excluded elsewhere, or masked here, drop out).
        axis: the run axis.
        level: confidence level in (0, 1).
        mask: (R,) bool along ``axis``, runs to include.

    Returns:
        :class:`Interval` of arrays of ``x``'s shape without ``axis``; half-width is
        ``t_{(1+level)/2, n-1} * s / sqrt(n)`` with n the non-NaN count (NaN when n < 2).
    """
    level = float(level)
    if not 0.0 < level < 1.0:
        raise ValueError(f"level: expected a confidence level in (0, 1), got {level}")
    x = np.asarray(x, float)
    if x.ndim == 0:
        raise ValueError("x: expected at least one axis of runs")
    try:
        x = np.moveaxis(x, axis, 0)
    except (np.exceptions.AxisError, TypeError):
        raise ValueError(f"axis: {axis!r} is not an axis of x with shape {x.shape}") from None
    m = _mask(mask, x.shape[0]).reshape((-1,) + (1,) * (x.ndim - 1))
    x = np.where(m, x, np.nan)
    n = np.sum(~np.isnan(x), axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(n > 0, np.nansum(x, axis=0) / np.maximum(n, 1), np.nan)
        dev = np.where(np.isnan(x), 0.0, x - mean)
        sd = np.sqrt(np.sum(dev**2, axis=0) / np.maximum(n - 1, 1))
        t = _bucketed(_student_t_ppf, 0.5 * (1.0 + level), np.maximum(n - 1, 1), 1.0)
        half = np.where(n >= 2, t * sd / np.sqrt(np.maximum(n, 1)), np.nan)
    return Interval(mean, half, mean - half, mean + half)
