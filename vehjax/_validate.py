"""Validation of user arguments before anything is traced: one module for every builder.

Each function checks one kind of argument and raises ``ValueError`` whose message starts with
the argument's name and says what was expected. Traced values (a builder called inside a
function being differentiated, as when tuning Q and R) have only their shapes checked.
"""

from __future__ import annotations

import operator

import jax
import numpy as np


def is_tracer(a) -> bool:
    return isinstance(a, jax.core.Tracer)


def number(name: str, value, low: float = -np.inf, high: float = np.inf, *,
           low_open: bool = True, high_open: bool = True) -> float:
    """A finite float in the interval (low, high), ends open or closed as given."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        v = float("nan")
    ok = np.isfinite(v) and (v > low if low_open else v >= low) and (
        v < high if high_open else v <= high)
    if isinstance(value, (bool, np.bool_)) or not ok:
        lo, hi = "(" if low_open else "[", ")" if high_open else "]"
        raise ValueError(f"{name}: expected a finite number in {lo}{low}, {high}{hi}, got {value!r}")
    return v


def integer(name: str, value, low: int = 1, high: int | None = None) -> int:
    """An int (not a bool) with low <= value (<= high)."""
    try:
        n = operator.index(value)
    except TypeError:
        n = None
    if isinstance(value, (bool, np.bool_)) or n is None or n < low or (high is not None and n > high):
        rng = f">= {low}" + ("" if high is None else f" and <= {high}")
        raise ValueError(f"{name}: expected an integer {rng}, got {value!r}")
    return int(n)


def choice(name: str, value, options) -> str:
    if not isinstance(value, str) or value not in options:
        raise ValueError(f"{name}: expected one of {tuple(options)}, got {value!r}")
    return value


def names(name: str, value, known, *, allow_empty: bool = False) -> tuple[str, ...]:
    """A tuple of unique names, each in ``known``; one string is one name."""
    known = tuple(known)
    if isinstance(value, str):
        value = (value,)
    try:
        out = tuple(value)
    except TypeError:
        raise ValueError(f"{name}: expected a sequence of names from {known}, got {value!r}") from None
    if not all(isinstance(n, str) for n in out):
        raise ValueError(f"{name}: expected names (strings), got {out!r}")
    if not out and not allow_empty:
        raise ValueError(f"{name}: expected at least one name from {known}, got none")
    if len(set(out)) != len(out):
        raise ValueError(f"{name}: names must be unique, got {out!r}")
    unknown = [n for n in out if n not in known]
    if unknown:
        raise ValueError(f"{name}: unknown name(s) {unknown}; expected names from {known}")
    return out


def keyed(name: str, value, known, what: str = "names") -> dict:
    """A dict whose keys are among ``known`` (None is {}); ValueError naming ``name``."""
    if value is None:
        return {}
    if not isinstance(value, dict) and not hasattr(value, "keys"):
        raise ValueError(f"{name}: expected a dict name -> value or None, got {value!r}")
    bad = [k for k in value if k not in known]
    if bad:
        raise ValueError(f"{name}: unknown name(s) {bad}; expected {what} from {tuple(known)}")
    return dict(value)


def cov(name: str, value, n: int, allow_diag: bool = True, allow_psd: bool = False):
    """A symmetric positive-definite (n, n) covariance from ``value``, as a float64 numpy array.

    ``value`` is (n, n), or (n,) variances of a diagonal covariance when ``allow_diag``. With
    ``allow_psd`` a positive semi-definite matrix (zero variances: noise-free components) is
    accepted. A traced ``value`` has only its shape checked and is returned as a symmetrised
    jax array.
    """
    expect = f"({n}, {n})" + (f" or ({n},) variances" if allow_diag else "")
    if is_tracer(value):
        if np.shape(value) not in (((n,), (n, n)) if allow_diag else ((n, n),)):
            raise ValueError(f"{name}: expected shape {expect}, got shape {np.shape(value)}")
        A = jax.numpy.diag(value) if value.ndim == 1 else value
        return 0.5 * (A + A.T)
    if isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name}: expected a numeric array, got {value!r}")
    try:
        A = np.array(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected a numeric array, got {value!r}") from None
    if allow_diag and A.shape == (n,):
        A = np.diag(A)
    if A.shape != (n, n):
        raise ValueError(f"{name}: expected shape {expect}, got shape {A.shape}")
    if not np.all(np.isfinite(A)):
        raise ValueError(f"{name}: expected finite entries, got {A}")
    scale = np.max(np.abs(A)) if A.size else 0.0
    if not np.allclose(A, A.T, rtol=1e-8, atol=1e-12 * scale):
        raise ValueError(f"{name}: expected a symmetric matrix, got {A}")
    A = 0.5 * (A + A.T)
    if A.size and allow_psd:
        w = np.linalg.eigvalsh(A)
        if w.min() < -1e-12 * max(scale, np.finfo(float).tiny):
            raise ValueError(f"{name}: expected a positive semi-definite covariance, got "
                             f"eigenvalues {w}")
        return A
    try:
        np.linalg.cholesky(A)
    except np.linalg.LinAlgError:
        raise ValueError(
            f"{name}: expected a positive-definite covariance, got eigenvalues "
            f"{np.linalg.eigvalsh(A)}"
        ) from None
    return A


def array(arg: str, value, allow_nan: bool = False) -> np.ndarray:
    """A real floating numpy array from ``value`` (integers become float64); finite unless
    ``allow_nan`` (then NaN and inf pass; the caller decides)."""
    try:
        a = np.asarray(value)
    except Exception:  # ragged lists and the like
        raise ValueError(f"{arg}: expected a numeric array, got {type(value).__name__}") from None
    real = np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)
    if a.dtype == bool or not real:
        raise ValueError(f"{arg}: expected a real numeric array, got dtype {a.dtype}")
    if not np.issubdtype(a.dtype, np.floating):
        a = a.astype(np.float64)
    if not allow_nan and not np.all(np.isfinite(a)):
        raise ValueError(f"{arg}: expected finite values, found NaN or inf")
    return a


def batched_cov(arg: str, P: np.ndarray):
    """ValueError naming ``arg`` unless P, (n, n) or (R, n, n), is symmetric positive definite
    (each of its matrices)."""
    sym = np.swapaxes(P, -1, -2)
    scale = max(float(np.max(np.abs(P))), np.finfo(np.float64).tiny)
    if not np.allclose(P, sym, rtol=0.0, atol=1e-9 * scale):
        raise ValueError(f"{arg}: expected a symmetric matrix (or one per run)")
    if P.shape[-1] == 0:
        return
    try:
        np.linalg.cholesky(0.5 * (P + sym).astype(np.float64))
    except np.linalg.LinAlgError:
        if P.ndim == 3:
            low = np.linalg.eigvalsh(0.5 * (P + sym).astype(np.float64)).min(axis=-1)
            bad = np.flatnonzero(low <= 0)
            raise ValueError(
                f"{arg}: expected positive-definite covariances; runs {bad[:10].tolist()} are not"
            ) from None
        raise ValueError(f"{arg}: expected a positive-definite covariance") from None


def prior(nx: int, x0, P0):
    """Check x0 (nx,) and P0 (nx, nx) or (nx,) variances; traced values by shape only."""
    if np.ndim(x0) != 1 or np.shape(x0)[0] != nx:
        raise ValueError(f"x0: expected shape ({nx},), got shape {np.shape(x0)}")
    if np.shape(P0) not in ((nx, nx), (nx,)):
        raise ValueError(
            f"P0: expected shape ({nx}, {nx}) or ({nx},) variances, got shape {np.shape(P0)}"
        )
    if not is_tracer(x0) and not np.all(np.isfinite(np.asarray(x0, dtype=float))):
        raise ValueError("x0: expected finite values")
    if not is_tracer(P0):
        cov("P0", P0, nx)


def model(value):
    """``value`` if it satisfies :class:`vehjax.models.base.ModelProtocol` (and, for a model
    class of the user's own, its functions return the declared shapes), else ValueError."""
    from .models.base import BaseModel, ModelProtocol

    if not isinstance(value, ModelProtocol):
        raise ValueError(
            f"model: expected a vehjax model (transition, observe, theta and the names of its "
            f"states, inputs, parameters and outputs), got {type(value).__name__}"
        )
    if not isinstance(value, BaseModel):  # vehjax's own models check at construction
        model_shapes(value)
    return value


def model_shapes(model) -> None:
    """ValueError naming ``transition`` or ``observe`` when the model's functions do not map
    (nx,), (nu,), (np,) arrays to (nx,) and (ny,) arrays (traced once, by shape)."""
    nx, nu = len(model.state_names), len(model.input_names)
    ny, n_par = len(model.output_names), len(model.param_names)
    sd = jax.ShapeDtypeStruct
    args = (sd((nx,), np.float64), sd((nu,), np.float64), sd((n_par,), np.float64))
    for name, fn, n, what in (("transition", model.transition, nx, "states"),
                              ("observe", model.observe, ny, "outputs")):
        try:
            out = jax.eval_shape(fn, *args)
        except Exception as e:  # the user's function failed on arrays of the declared shapes
            raise ValueError(
                f"{name}: calling it with x ({nx},), u ({nu},), theta ({n_par},) failed: "
                f"{type(e).__name__}: {e}"
            ) from None
        shape = getattr(out, "shape", None)
        if shape != (n,):
            raise ValueError(
                f"{name}: expected it to return shape ({n},) for the model's {n} {what}, "
                f"got {shape if shape is not None else type(out).__name__}"
            )


def key(value, n: int):
    """``jax.random.split(value, n)``, or ValueError naming ``key`` when ``value`` is no PRNG key
    (an int such as 0, say)."""
    if not isinstance(value, jax.Array) or isinstance(value, (bool, int, float)):
        raise ValueError(f"key: expected a JAX PRNG key such as jax.random.key(0), got {value!r}")
    try:
        return jax.random.split(value, n)
    except Exception:
        raise ValueError(
            f"key: expected a JAX PRNG key such as jax.random.key(0), got {value!r}"
        ) from None
