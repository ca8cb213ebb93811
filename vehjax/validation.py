"""Validation of user arguments before anything is traced: the one set of checks that every
public entry point (``filter``, ``run``/``compile_run``, ``simulate``, ``tune``, the data
loaders, the filter builders) calls, so that an array is accepted or refused alike everywhere.

Each function checks one kind of argument and raises ``ValueError`` whose message starts with
the argument's name and says what was expected. The rules:

* Arrays are real: complex, bool, string and object arrays are refused; integers become
  float64, float32 stays float32.
* Non-finite values: in measurements NaN marks a missing component (the filters skip it) and
  +-inf is refused; in everything else (inputs, x0, P0, theta0, covariances, parameters) any
  NaN or +-inf is refused. Messages name the first bad value and its index.
* Traced values (under ``jit``, ``vmap``, ``grad``) have only their dtype and shape checked;
  their values are not known. A filter given +-inf measurements under a trace treats them as
  missing, like NaN (every filter skips any non-finite component).

This module imports nothing of vehjax's (the model check is by attribute name), so that
:mod:`vehjax.models.base` can use it at import time.
"""

from __future__ import annotations

import functools
import operator

import jax
import numpy as np


def is_tracer(a) -> bool:
    return isinstance(a, jax.core.Tracer)


def number(name: str, value, low: float = -np.inf, high: float = np.inf, *,
           low_open: bool = True, high_open: bool = True, what: str | None = None) -> float:
    """A finite float in the interval (low, high), ends open or closed as given. A bool or a
    string (``"0.5"``) is refused, not read as a number. ``what`` replaces the message's
    "a finite number in (low, high)", e.g. "a positive, finite standard deviation"."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        v = float("nan")
    ok = np.isfinite(v) and (v > low if low_open else v >= low) and (
        v < high if high_open else v <= high)
    if isinstance(value, (bool, np.bool_, str, bytes)) or not ok:
        lo, hi = "(" if low_open else "[", ")" if high_open else "]"
        what = f"a finite number in {lo}{low}, {high}{hi}" if what is None else what
        raise ValueError(f"{name}: expected {what}, got {value!r}")
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


def flag(name: str, value, *, allow_none: bool = False) -> bool | None:
    """``value`` as a bool if it is one (Python's or numpy's), else ValueError naming ``name``:
    a string such as ``"no"`` is truthy in Python, so it is refused rather than read as True.
    With ``allow_none`` None passes as None (an option whose default is decided later)."""
    if allow_none and value is None:
        return None
    if not isinstance(value, (bool, np.bool_)):
        expected = "None, True or False" if allow_none else "True or False"
        raise ValueError(f"{name}: expected {expected}, got {value!r}")
    return bool(value)


def record(name: str, value, cls):
    """An option record: ``value`` if it is a ``cls``, ``cls()`` (its defaults) for None, else
    ValueError naming ``name`` (the records check their own fields when made)."""
    if value is None:
        return cls()
    if not isinstance(value, cls):
        raise ValueError(f"{name}: expected {cls.__module__.rsplit('.', 1)[0]}.{cls.__name__}"
                         f"(...), got {value!r}")
    return value


def builder_options(builder) -> tuple:
    """(the filter builder, its options): a builder's own options are given with it,
    ``functools.partial(builder, **options)``, which is (builder, options); any other callable
    is (builder, {}). ValueError naming ``builder`` for anything else (not callable, or a
    partial with positional arguments). :mod:`vehjax.tune` and :mod:`vehjax.calibrate` take
    their builders so."""
    if isinstance(builder, functools.partial) and not builder.args:
        return builder.func, dict(builder.keywords)
    if not callable(builder) or isinstance(builder, functools.partial):
        raise ValueError(f"builder: expected a filter builder builder(model, Q, R), its options "
                         f"given with functools.partial(builder, **options), got {builder!r}")
    return builder, {}


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
    A = np.array(_real(name, value), dtype=float)
    if allow_diag and A.shape == (n,):
        A = np.diag(A)
    if A.shape != (n, n):
        raise ValueError(f"{name}: expected shape {expect}, got shape {A.shape}")
    if not np.all(np.isfinite(A)):
        raise ValueError(f"{name}: expected finite entries, found {first_bad(A, ~np.isfinite(A))}")
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


def first_bad(a: np.ndarray, bad: np.ndarray) -> str:
    """'nan at index (1, 0)': the value and index of the first True of ``bad`` (row-major)."""
    idx = tuple(int(i) for i in np.argwhere(bad)[0])
    return f"{a[idx].item()!r} at index {idx}"


def _real(arg: str, value):
    """``value`` as a real numeric array (numpy, or the tracer itself): ValueError naming
    ``arg`` for complex, bool, strings, objects and ragged sequences."""
    if is_tracer(value):
        a = value
    else:
        try:
            a = np.asarray(value)
        except Exception:  # ragged lists and the like
            raise ValueError(
                f"{arg}: expected a numeric array, got {type(value).__name__}") from None
    dt = np.dtype(a.dtype)
    real = np.issubdtype(dt, np.floating) or np.issubdtype(dt, np.integer)
    if dt == bool or not real:
        what = "complex values" if np.issubdtype(dt, np.complexfloating) else f"dtype {dt}"
        raise ValueError(f"{arg}: expected a real numeric array, got {what}")
    return a


def array(arg: str, value, allow_nan: bool = False, *, missing: bool = False) -> np.ndarray:
    """A real floating numpy array from ``value`` (integers become float64, float32 stays).

    The one rule for non-finite values: refused, naming ``arg``, the first bad value and its
    index; with ``missing`` (measurements) NaN passes (a missing component) and +-inf is still
    refused (more likely a fault than a gap). ``allow_nan`` lets every non-finite value pass
    (the caller decides). Complex, bool, string and object arrays are refused. A traced
    ``value`` is returned as it is after its dtype is checked (its values are not known).
    """
    a = _real(arg, value)
    if is_tracer(a):
        return a
    if not np.issubdtype(a.dtype, np.floating):
        a = a.astype(np.float64)
    if allow_nan:
        return a
    bad = np.isinf(a) if missing else ~np.isfinite(a)
    if np.any(bad):
        hint = "; mark missing components with NaN (a filter skips them)" if missing else ""
        raise ValueError(f"{arg}: expected {'no +-inf' if missing else 'finite values'}, found "
                         f"{first_bad(a, bad)}{hint}")
    return a


def shaped(arg: str, value, shape: tuple, allow_nan: bool = True) -> np.ndarray:
    """:func:`array` of exactly ``shape``: each entry a size, or None for any size >= 1.
    Non-finite values pass (the caller's rule) unless ``allow_nan`` is False."""
    a = array(arg, value, allow_nan=allow_nan)
    if a.ndim != len(shape) or any(a.shape[i] != n if n is not None else a.shape[i] < 1
                                   for i, n in enumerate(shape)):
        want = ", ".join("n" if n is None else str(n) for n in shape)
        raise ValueError(f"{arg}: expected shape ({want}{',' if len(shape) == 1 else ''}), got "
                         f"{a.shape}")
    return a


def batched_cov(arg: str, P: np.ndarray):
    """ValueError unless P, (n, n) or (R, n, n), is symmetric positive definite (each of its
    matrices); for (R, n, n) the message names the first bad run, ``P0[3]: ...``."""
    P = np.asarray(P, dtype=np.float64)
    sym = np.swapaxes(P, -1, -2)
    scale = max(float(np.max(np.abs(P))) if P.size else 0.0, np.finfo(np.float64).tiny)
    asym = ~np.isclose(P, sym, rtol=0.0, atol=1e-9 * scale).reshape(P.shape[:-2] + (-1,)).all(-1)
    if np.any(asym):
        where = f"{arg}[{int(np.flatnonzero(asym)[0])}]" if P.ndim == 3 else arg
        raise ValueError(f"{where}: expected a symmetric matrix" + (
            f" (runs {np.flatnonzero(asym)[:10].tolist()} of {arg} are not)" if P.ndim == 3 else ""))
    if P.shape[-1] == 0:
        return
    try:
        np.linalg.cholesky(0.5 * (P + sym))
    except np.linalg.LinAlgError:
        low = np.linalg.eigvalsh(0.5 * (P + sym))
        if P.ndim == 3:
            bad = np.flatnonzero(~(low.min(axis=-1) > 0))
            raise ValueError(
                f"{arg}[{int(bad[0])}]: expected positive-definite covariances; runs "
                f"{bad[:10].tolist()} of {arg} are not (eigenvalues of the first "
                f"{low[bad[0]]})") from None
        raise ValueError(f"{arg}: expected a positive-definite covariance, got eigenvalues "
                         f"{low}") from None


#: ``runs`` of :func:`prior` and :func:`per_run`: a leading runs axis of any length.
ANY_RUNS = -1


def _runs_ok(shape: tuple, shared: tuple, runs) -> bool:
    if shape == shared:
        return True
    if runs is None or len(shape) != len(shared) + 1 or shape[1:] != shared:
        return False
    return runs == ANY_RUNS or shape[0] == runs


def per_run(arg: str, value, shared: tuple, runs=None, what: str = ""):
    """A real array of shape ``shared``, or ``(runs,) + shared`` one per run (``runs`` None:
    shared only; :data:`ANY_RUNS`: any number), finite; traced values by dtype and shape."""
    a = array(arg, value)
    if not _runs_ok(tuple(np.shape(a)), shared, runs):
        alt = ("" if runs is None else " or " + (f"(runs,) + {shared}" if runs == ANY_RUNS
                                                 else f"{(runs,) + shared} (one per run)"))
        raise ValueError(f"{arg}: expected shape {shared}{alt}{what and ' for ' + what}, "
                         f"got shape {np.shape(a)}")
    return a


def covariance(arg: str, value, n: int, runs=None, what: str = ""):
    """A covariance argument (P0, P_theta0): (n, n), (n,) variances, or (runs, n, n) one per
    run; symmetric positive definite, finite. Returns it as a matrix (variances made diagonal),
    numpy when concrete, the traced array otherwise (shape checked only).

    Per-run variances, (runs, n), are not a form of their own: when ``runs == n`` they would
    read as one (n, n) matrix, so they are refused in every case with a message saying how
    to give them (the diagonal matrices, (runs, n, n)).
    """
    a = array(arg, value)
    shape = tuple(np.shape(a))
    if shape == (n,):
        if not is_tracer(a) and np.any(a <= 0):
            raise ValueError(f"{arg}: expected positive variances, found "
                             f"{first_bad(a, a <= 0)}")
        a = jax.numpy.diag(a) if is_tracer(a) else np.diag(a)
        shape = (n, n)
    hint = (f"; per-run variances (runs, {n}) are given as diagonal matrices (runs, {n}, {n}), "
            f"e.g. variances[:, :, None] * np.eye({n})")
    if not _runs_ok(shape, (n, n), runs):
        alt = ("" if runs is None else " or " + (f"(runs, {n}, {n})" if runs == ANY_RUNS
                                                 else f"({runs}, {n}, {n}) (one per run)"))
        per_run_vars = runs is not None and len(shape) == 2 and shape[1] == n
        raise ValueError(f"{arg}: expected shape ({n}, {n}), ({n},) variances{alt}"
                         f"{what and ' for ' + what}, got shape {np.shape(value)}"
                         + (hint if per_run_vars else ""))
    if is_tracer(a):
        return a
    scale = max(float(np.max(np.abs(a))), np.finfo(float).tiny) if a.size else 1.0
    if a.ndim == 2 and not np.allclose(a, a.T, rtol=0.0, atol=1e-9 * scale):
        # with as many runs as states, per-run variances (runs, n) have this shape
        raise ValueError(f"{arg}: expected a symmetric ({n}, {n}) matrix, got a non-symmetric "
                         f"one" + (hint if runs in (n, ANY_RUNS) else ""))
    batched_cov(arg, a)
    return a


def prior(nx: int, x0, P0, runs=None):
    """Check the state prior: x0 (nx,) and P0 (nx, nx) or (nx,) variances, or one per run
    ((runs, nx), (runs, nx, nx); ``runs`` as in :func:`per_run`). Returns (x0, P0) with P0 a
    matrix, numpy when concrete (traced values are checked by dtype and shape only). The one
    check of x0/P0 for every entry point (filter, run, tune, the filters' init, scenarios)."""
    what = f"nx = {nx} states"
    x0 = per_run("x0", x0, (nx,), runs, what)
    P0 = covariance("P0", P0, nx, runs, what)
    return x0, P0


def theta_prior(names: tuple, theta0, P_theta0, runs=None):
    """Check a parameter prior theta0 (p,) and P_theta0 (p, p) or (p,) variances (or one per
    run) of the parameters ``names``; None stays None. Returns (theta0, P_theta0)."""
    what = f"parameters {tuple(names)}"
    p = len(names)
    th = None if theta0 is None else per_run("theta0", theta0, (p,), runs, what)
    Pth = None if P_theta0 is None else covariance("P_theta0", P_theta0, p, runs, what)
    return th, Pth


def initial_params(names: tuple, theta0, P_theta0, runs=None, *, has_prior: bool,
                   label: str = "estimator", model_theta: bool = True):
    """The parameter arguments of ``filter``/``run``: (theta0, P_theta0) checked.

    For a filter that estimates the parameters ``names`` (p > 0): theta0 (p,) and P_theta0
    (p, p) or (p,) variances (or one per run). A filter with a prior of its own
    (``has_prior``) takes both or neither; one without takes P_theta0 always and theta0
    optionally (None: the filter starts from the model's nominal values). For a state-only filter (``names`` empty): theta0, when
    given, replaces the model's parameter vector, (np,) or (runs, np), real and finite (its
    length is checked against the model by the filter's ``init``); P_theta0 must be None.
    Without ``model_theta`` (``run``: a study's filter is built on the model it runs at, and a
    wrong length could only be found by tracing) a state-only filter takes no theta0 at all.
    """
    if not names:
        if theta0 is not None and not model_theta:
            raise ValueError(
                f"theta0: {label} estimates no parameters; pass None, and build the filter on "
                f"model.with_theta(...) to run it at other model parameters (vehjax.filter "
                f"takes theta0 for one run)")
        if P_theta0 is not None:
            raise ValueError(f"P_theta0: {label} estimates no parameters; pass None (theta0 "
                             f"alone replaces the model's parameters)")
        if theta0 is None:
            return None, None
        th = array("theta0", theta0)
        if np.ndim(th) != 1 and not (runs is not None and np.ndim(th) == 2 and (
                runs == ANY_RUNS or np.shape(th)[0] == runs)):
            alt = "" if runs is None else " or (runs, np) one per run"
            raise ValueError(f"theta0: expected the model's parameters, shape (np,){alt}, got "
                             f"shape {np.shape(th)}")
        return th, None
    if P_theta0 is None and (theta0 is not None or not has_prior):
        raise ValueError(f"P_theta0: required" + (" with theta0" if theta0 is not None else "")
                         + f", {label} estimates parameters {tuple(names)}; pass P_theta0 "
                         f"(p, p) or (p,) variances")
    if theta0 is None and P_theta0 is not None and has_prior:
        raise ValueError(f"theta0: required with P_theta0 ({label} has a prior of its own: "
                         f"pass both or neither)")
    return theta_prior(names, theta0, P_theta0, runs)


def data(measurements, inputs, ny, nu, runs: str):
    """Check a study's data: measurements and inputs, concrete or traced.

    Args:
        measurements: ``runs == "one"``: (T, ny); ``"many"``: (R, T, ny); ``"either"``: one of
            the two. NaN components are missing; +-inf, complex and non-numeric refused.
        inputs: (T, nu) shared by the runs, or (R, T, nu) one per run (not for "one"); None
            when the model has none (nu == 0).
        ny, nu: the widths the filter expects, or None (not checked).

    Returns:
        (ys, us): ys as given in rank; us (T, 0) zeros when ``inputs`` is None.
    """
    ys = array("measurements", measurements, missing=True)
    rank = {"one": (2,), "many": (3,), "either": (2, 3)}[runs]
    shape = tuple(np.shape(ys))
    if len(shape) not in rank or 0 in shape[:-1]:
        want = {"one": "(T, ny) with T >= 1 for one run (for a study of several runs use "
                       "vehjax.run)",
                "many": "(runs, steps, ny) with none zero; for a single run pass "
                        "measurements[None]",
                "either": "(T, ny) for one run or (R, T, ny) for R runs, T >= 1"}[runs]
        raise ValueError(f"measurements: expected shape {want}, got {shape}")
    T = shape[-2]
    R = shape[0] if len(shape) == 3 else None
    if ny is not None and shape[-1] != ny:
        raise ValueError(f"measurements: expected {ny} columns (the model's outputs), "
                         f"got shape {shape}")
    if inputs is None:
        if nu:
            alt = "" if R is None else f" shared or ({R}, {T}, {nu}) per run"
            raise ValueError(f"inputs: required, shape ({T}, {nu}){alt} for this model's "
                             f"{nu} inputs")
        return ys, np.zeros((T, 0), ys.dtype) if not is_tracer(ys) else jax.numpy.zeros(
            (T, 0), ys.dtype)
    us = array("inputs", inputs)
    ushape = tuple(np.shape(us))
    n = "nu" if nu is None else nu
    if len(ushape) in (2, 3) and nu is not None and ushape[-1] != nu:
        raise ValueError(f"inputs: expected {nu} columns (the model's inputs), shape ({T}, {nu})"
                         + ("" if R is None else f" or ({R}, {T}, {nu})") + f", got {ushape}")
    if not (len(ushape) == 2 and ushape[0] == T) and not (
            R is not None and len(ushape) == 3 and ushape[:2] == (R, T)):
        alt = "" if R is None else f" (shared by all runs) or ({R}, {T}, {n}) (one per run)"
        hint = "; for a single input pass inputs[:, None]" if len(ushape) == 1 else ""
        raise ValueError(f"inputs: expected shape ({T}, {n}){alt} to match measurements "
                         f"{shape}, got {ushape}{hint}")
    return ys, us


#: What a model must offer (:class:`vehjax.models.base.ModelProtocol`, checked here by name so
#: that this module imports nothing of vehjax's).
MODEL_ATTRS = ("dt", "theta", "state_names", "input_names", "param_names", "output_names",
               "transition", "observe")


def model(value):
    """``value`` if it has what :class:`vehjax.models.base.ModelProtocol` asks for (and, for a
    model class of the user's own, its functions return real arrays of the declared shapes),
    else ValueError naming ``model``. Models that checked themselves at construction declare it
    with a class attribute ``shapes_checked = True`` (every vehjax model)."""
    if isinstance(value, type) or not all(hasattr(value, a) for a in MODEL_ATTRS):
        raise ValueError(
            f"model: expected a vehjax model (transition, observe, theta and the names of its "
            f"states, inputs, parameters and outputs), got {type(value).__name__}"
        )
    if not getattr(type(value), "shapes_checked", False):
        model_shapes(value)
    return value


def model_shapes(model) -> None:
    """ValueError naming ``transition`` or ``observe`` when the model's functions do not map
    (nx,), (nu,), (np,) float64 arrays to real floating (nx,) and (ny,) arrays (traced once,
    by shape and dtype: a function returning complex numbers is refused)."""
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
        dtype = np.dtype(out.dtype)
        if not np.issubdtype(dtype, np.floating):
            raise ValueError(f"{name}: expected it to return real floating values, got dtype "
                             f"{dtype}")


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


def in_domain(arg: str, theta, domains) -> None:
    """ValueError naming ``arg``, the parameter, its value and its domain unless every value of
    a concrete ``theta`` ((p,) or (R, p), one row per run) lies in its parameter's domain.

    ``domains`` is a model's :class:`vehjax.models.domains.ParamDomains` (read by attribute:
    ``names``, ``intervals``, ``owner``, ``inside``), or None (no domains declared: nothing is
    checked). Traced values and a ``theta`` whose last axis is not p long (someone else's error)
    are not checked. The message shows the first offending value (row-major), the interval in
    mathematical notation ('(' open, '[' closed) and the interval's note, formatted with
    ``name``, ``value`` and ``minus`` (its negative), e.g. how to convert a sign convention.
    """
    if domains is None or is_tracer(theta) or theta is None:
        return
    th = np.asarray(theta, dtype=float)
    p = len(domains.names)
    if th.ndim not in (1, 2) or th.shape[-1] != p:
        return
    ok = domains.inside(th)
    if np.all(ok):
        return
    flat = np.argwhere(~ok.reshape(-1, p))[0]
    row, j = int(flat[0]), int(flat[1])
    value = float(th.reshape(-1, p)[row, j])
    dom = domains.intervals[j]
    where = f" (run {row})" if th.ndim == 2 else ""
    name = domains.names[j]
    note = dom.note.format(name=name, value=f"{value:g}", minus=f"{-value:g}") if dom.note else ""
    raise ValueError(
        f"{arg}: parameter {name!r} = {value:g}{where} is outside its domain "
        f"{dom.text()} in {domains.owner}" + (f": {note}" if note else "")
    )
