"""The TOML file of ``vehjax fit`` and ``vehjax estimate``: its sections, keys and checks.

::

    [drive]                       # how the drive file (here a CSV) is read, and mapped
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

The drive file's format (its suffix, or a ROS 2 bag folder: :func:`vehjax.data.read_drive`)
says which [drive] keys read it (:data:`FORMAT_KEYS`); ``units``, ``reference`` and the
mapping keys (:data:`DRIVE_MAPPING`) serve every format, the others only their own (another
format's key is refused, naming the key and the drive file's format)::

    # CSV (.csv, .txt): time, units, reference, columns, delimiter, decimal, encoding
    # MDF4/MDF3 (.mf4, .mdf, .dat): a signal name -> channel, or [channel, group index]
    channels = { steer = "SteeringWheelAngle", speed = ["VehicleSpeed", 1], r = "YawRate" }
    # ROS 2 bag (a folder, .db3, .mcap): a signal name -> "/topic.path.to.field"
    fields = { r = "/imu/data.angular_velocity.z", speed = "/vehicle/twist.twist.linear.x" }
    stamps = "header"             # or "record" (default "header")
    # CAN log (.asc, .blf, .log, .trc): the DBC (a relative path is taken relative to this
    # file's folder) and a signal name -> "MESSAGE.SIGNAL"
    dbc = "car.dbc"
    signals = { speed = "ESP_Status.VehicleSpeed", steer = "SAS_Data.SteeringAngle" }
    channel = 0                   # only this bus channel's frames (default all)

For these formats ``units`` (signal name -> unit) overrides the file's unit, and ``names``
maps the signal names of ``channels``, ``fields`` or ``signals`` onto the model.

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

__all__ = ["read", "check", "FILTERS", "DRIVE_FORMAT", "DRIVE_MAPPING", "FORMAT_KEYS",
           "FORMAT_NEEDS", "FORMAT_LABELS", "SCHEMA", "NOISE_KINDS", "OPTIMIZERS", "STARTS"]

#: the filter families a drive is fitted and estimated with (builders of vehjax.filters)
FILTERS = ("ekf", "ukf", "ckf")
#: vehjax.tune's noise kinds, optimisers (the names of vehjax.tune.options.OPTIMIZERS) and
#: starts, written out so that this module imports no JAX (tests/test_cli_drive.py checks that
#: they agree)
NOISE_KINDS = ("Q", "R", "input")
OPTIMIZERS = ("adam", "lbfgs", "scoring")
STARTS = ("data", "theta")
#: [drive] keys each drive-file format takes, passed to its reader as keyword arguments
#: (the formats as vehjax.data.read.SUFFIXES names them)
FORMAT_KEYS = {
    "csv": ("time", "units", "reference", "columns", "delimiter", "decimal", "encoding"),
    "mdf": ("channels", "units", "reference"),
    "ros2": ("fields", "stamps", "units", "reference"),
    "can": ("dbc", "signals", "channel", "units", "reference"),
}
#: the [drive] keys a format cannot be read without
FORMAT_NEEDS = {"csv": (), "mdf": ("channels",), "ros2": ("fields",), "can": ("dbc", "signals")}
#: the formats in words, for messages
FORMAT_LABELS = {"csv": "a CSV file", "mdf": "an MDF file", "ros2": "a ROS 2 bag",
                 "can": "a CAN log"}
#: [drive] keys that say how the file is read (those of every format)
DRIVE_FORMAT = tuple(dict.fromkeys(k for keys in FORMAT_KEYS.values() for k in keys))
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


def channel_source(key, v):
    """An MDF channel: its name, or ``[name, group index]`` (a tuple) for a name that several
    channel groups hold."""
    if isinstance(v, str) and v.strip():
        return v
    ok = (isinstance(v, (list, tuple)) and len(v) == 2 and isinstance(v[0], str)
          and v[0].strip() and isinstance(v[1], int) and not isinstance(v[1], bool) and v[1] >= 0)
    if not ok:
        _fail(key, f"expected a channel name or [channel name, group index >= 0], got {v!r}")
    return tuple(v)


def bus_channel(key, v):
    """A CAN log's channel as python-can's reader names it: an integer >= 0 or a string."""
    if isinstance(v, int) and not isinstance(v, bool) and v >= 0:
        return v
    if isinstance(v, str) and v.strip():
        return v
    _fail(key, f"expected a channel number >= 0 or a name (e.g. 0 or \"can0\"), got {v!r}")


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
        "channels": table(channel_source), "fields": table(text),
        "stamps": choice(("header", "record")), "dbc": text, "signals": table(text),
        "channel": bus_channel,
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
    return _relative_to(check(raw, path.name, sections), path.parent)


def _relative_to(config: dict, folder: Path) -> dict:
    """``config`` with a relative [drive] dbc path made absolute from ``folder`` (the
    configuration file's), so that it reads from any working directory and from fit.json."""
    dbc = config.get("drive", {}).get("dbc")
    if dbc is None:
        return config
    dbc = Path(dbc).expanduser()
    dbc = dbc if dbc.is_absolute() else (folder / dbc).absolute()
    return {**config, "drive": {**config["drive"], "dbc": str(dbc)}}


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
