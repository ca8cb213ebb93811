"""The TOML file of ``vehjax fit`` and ``vehjax estimate``: its sections, keys and checks.

::

    [drive]                       # how the drive file is read, and mapped onto the model
    time = "time"                 # the time column (default "t")
    units = { time = "ms", steer = "deg", speed = "km/h" }   # column -> unit (else the header's)
    reference = ["beta_ins"]      # columns for validation only
    names = { steer = "delta", speed = "vx", acc_y = "ay", yaw_rate = "r" }  # column -> model
    max_gap = 0.05                # s: longer gaps are not interpolated across (default 2.5 steps)

    [model]
    name = "SingleTrack"          # vehjax.models.REGISTRY, or "package.module:factory"
    dt = 0.01                     # s (default: the drive's step, when uniform)
    options = { tyres = "linear" }            # keyword arguments of the model's constructor
    theta = { m = 1520.0, iz = 2600.0 }       # spec values [the parameters' units]

    [fit]
    params = ["cf", "cr"]         # model parameters to fit (default none: the noise only)
    noise = ["R"]                 # which of Q, R, input to fit (default Q, R)
    filter = "ekf"                # ekf, ukf or ckf (default ekf)
    process_std = [0.01, 0.001]   # per step, in state units: one value or one per state
    meas_std = [0.3, 0.005]       # in output units: one value or one per output
    P0_std = [0.1, 0.01]          # the prior's std around x0 (default x0: zeros)

    [estimate]
    smooth = false                # run the smoother instead of the filter

Every key is checked here, before the drive is read: an unknown section or key, or a value
of the wrong kind, is a ValueError naming the file, the section and the key
(``car.toml [fit] parms: unknown key; ...``). What needs the model (parameter names, one value
per state) is checked by :mod:`vehjax.commands.setup`, still before anything is compiled.

This module imports nothing but the standard library: the command line's parser uses its
names (:data:`FILTERS`) at ``vehjax --help``, which must not import JAX. Its checks are
therefore its own, of TOML's value kinds (str, int, float, bool, arrays, tables).
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

__all__ = ["read", "check", "FILTERS", "DRIVE_FORMAT", "DRIVE_MAPPING", "SCHEMA",
           "NOISE_KINDS", "OPTIMIZERS", "STARTS"]

#: the filter families a drive is fitted and estimated with (builders of vehjax.filters)
FILTERS = ("ekf", "ukf", "ckf")
#: vehjax.tune's noise kinds and optimisers, written out so that this module imports no JAX
#: (tests/test_cli_drive.py checks that they agree)
NOISE_KINDS = ("Q", "R", "input")
OPTIMIZERS = ("adam", "lbfgs", "scoring")
STARTS = ("data", "theta")
#: [drive] keys that say how the file is read: passed to the reader as keyword arguments
DRIVE_FORMAT = ("time", "units", "reference", "columns", "delimiter", "decimal", "encoding")
#: [drive] keys that say how the drive is mapped onto the model (Drive.for_model, between)
DRIVE_MAPPING = ("names", "missing_outputs", "max_gap", "start", "stop")


def _fail(key: str, message: str):
    raise ValueError(f"{key}: {message}")


def text(key, v) -> str:
    if not isinstance(v, str) or not v.strip():
        _fail(key, f"expected a non-empty string, got {v!r}")
    return v


def number(key, v, low=-math.inf, low_open=False) -> float:
    """A finite int or float (not a bool) >= low (> low with ``low_open``)."""
    ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
    if not ok or (v <= low if low_open else v < low):
        bound = "" if low == -math.inf else (f" > {low:g}" if low_open else f" >= {low:g}")
        _fail(key, f"expected a finite number{bound}, got {v!r}")
    return float(v)


def positive(key, v) -> float:
    return number(key, v, 0.0, low_open=True)


def integer(key, v) -> int:
    if not isinstance(v, int) or isinstance(v, bool) or v < 1:
        _fail(key, f"expected an integer >= 1, got {v!r}")
    return v


def flag(key, v) -> bool:
    if not isinstance(v, bool):
        _fail(key, f"expected true or false, got {v!r}")
    return v


def choice(options):
    def check_choice(key, v) -> str:
        if not isinstance(v, str) or v not in options:
            _fail(key, f"expected one of {', '.join(options)}, got {v!r}")
        return v
    return check_choice


def names(key, v, known=None) -> tuple:
    """A list of unique non-empty strings (one string is one name), each in ``known``."""
    v = [v] if isinstance(v, str) else v
    if not isinstance(v, (list, tuple)) or not all(isinstance(n, str) and n.strip() for n in v):
        _fail(key, f"expected a list of names (strings), got {v!r}")
    if len(set(v)) != len(v):
        _fail(key, f"names must be unique, got {list(v)}")
    bad = [n for n in v if known is not None and n not in known]
    if bad:
        _fail(key, f"unknown name(s) {bad}; expected some of {', '.join(known)}")
    return tuple(v)


def numbers(low=-math.inf, low_open=False):
    """One number or a non-empty list of them (each as :func:`number`)."""
    def check_numbers(key, v) -> tuple:
        v = [v] if not isinstance(v, list) else v
        if not v:
            _fail(key, "expected a number or a list of numbers, got an empty list")
        return tuple(number(f"{key}[{i}]" if len(v) > 1 else key, x, low, low_open)
                     for i, x in enumerate(v))
    return check_numbers


def table(kind):
    """A table name -> value, each value checked by ``kind`` (its key ``key.name``)."""
    def check_table(key, v) -> dict:
        if not isinstance(v, dict):
            _fail(key, f"expected a table name -> value, got {v!r}")
        return {k: kind(f"{key}.{k}", x) for k, x in v.items()}
    return check_table


def plain(key, v):
    """A value of TOML's plain kinds (string, number, bool, a list or table of them); lists
    become tuples (a model's options are hashable)."""
    if isinstance(v, list):
        return tuple(plain(f"{key}[{i}]", x) for i, x in enumerate(v))
    if isinstance(v, dict):
        return {k: plain(f"{key}.{k}", x) for k, x in v.items()}
    if not isinstance(v, (str, int, float, bool)):
        _fail(key, f"expected a string, number, boolean or a list of them, got {v!r}")
    return v


def bound_pair(key, v) -> tuple:
    """``[low, high]``: two numbers, low < high (``inf`` and ``-inf`` for an open end)."""
    ok = isinstance(v, list) and len(v) == 2 and all(
        isinstance(x, (int, float)) and not isinstance(x, bool) and not math.isnan(x) for x in v)
    if not ok or not v[0] < v[1]:
        _fail(key, f"expected [low, high] with low < high (inf for no bound), got {v!r}")
    return float(v[0]), float(v[1])


SCHEMA = {
    "drive": {
        "time": text, "units": table(text), "reference": names, "columns": names,
        "delimiter": text, "decimal": choice((".", ",")), "encoding": text,
        "names": table(text), "missing_outputs": names, "max_gap": positive,
        "start": number, "stop": number,
    },
    "model": {"name": text, "dt": positive, "options": table(plain), "theta": table(number),
              "output_biases": names},
    "fit": {
        "params": names, "bounds": table(bound_pair),
        "noise": lambda k, v: names(k, v, NOISE_KINDS), "filter": choice(FILTERS),
        "process_std": numbers(0.0), "meas_std": numbers(0.0, low_open=True),
        "input_noise": table(positive), "x0": numbers(), "P0_std": numbers(0.0, low_open=True),
        "fit_x0": flag, "start": choice(STARTS), "compare": flag, "release": flag,
        "steps": integer, "optimizer": choice(OPTIMIZERS), "gtol": positive,
    },
    "estimate": {"smooth": flag},
}
#: what ``vehjax fit`` needs in [fit] (there is no default a model's units would make sensible)
REQUIRED = {"model": ("name",), "fit": ("process_std", "meas_std", "P0_std")}


def check(raw: dict, where: str, sections=tuple(SCHEMA)) -> dict:
    """The sections of ``raw`` (a parsed TOML document) checked key by key against
    :data:`SCHEMA`: ``{section: {key: value}}`` with every section of ``sections`` present
    (empty when absent). ``where`` (the file's name) starts every message."""
    unknown = [s for s in raw if s not in sections]
    if unknown:
        listed = ", ".join(f"[{s}]" for s in sections)
        raise ValueError(f"{where}: unknown section [{unknown[0]}]; expected {listed}")
    out = {}
    for section in sections:
        body = raw.get(section, {})
        if not isinstance(body, dict):
            raise ValueError(f"{where} {section}: expected a section [{section}], got {body!r}")
        schema = SCHEMA[section]
        for key in body:
            if key not in schema:
                raise ValueError(f"{where} [{section}] {key}: unknown key; expected one of "
                                 f"{', '.join(schema)}")
        out[section] = {k: schema[k](f"{where} [{section}] {k}", v) for k, v in body.items()}
    return out


def read(path, sections=tuple(SCHEMA)) -> dict:
    """The TOML file at ``path`` read and checked (:func:`check`); ValueError naming the file
    for a missing file or a TOML syntax error (with its line and column)."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"--config: {str(path)!r} is not a file")
    try:
        with open(path, "rb") as fh:
            raw = tomllib.load(fh)
    except tomllib.TOMLDecodeError as err:
        raise ValueError(f"{path.name}: not a valid TOML file: {err}") from None
    return check(raw, path.name, sections)


def require(config: dict, where: str) -> None:
    """ValueError naming the first key of :data:`REQUIRED` that ``config`` lacks."""
    for section, keys in REQUIRED.items():
        for key in keys:
            if key not in config.get(section, {}):
                raise ValueError(f"{where} [{section}] {key}: missing; "
                                 + ("give it in the file or with --model" if key == "name"
                                    else "give it in the file"))


def override(config: dict, section: str, key: str, value, option: str) -> dict:
    """``config`` with ``[section] key`` set to a command-line ``value`` (None: left as it
    is), checked as the file's value is, its errors naming ``option``."""
    if value is None:
        return config
    checked = SCHEMA[section][key](option, value)
    return {**config, section: {**config.get(section, {}), key: checked}}
