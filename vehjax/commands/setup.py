"""From a checked configuration (:mod:`vehjax.commands.config`) to a drive, a model, its
arrays on the model's grid and the filter's starting values; every check that needs the drive
or the model is made here, before anything is compiled, its ValueError naming the key of the
file (``[fit] meas_std: expected 1 value or 2 (one per ay, r), got 3``)."""

from __future__ import annotations

import functools
import importlib
from pathlib import Path
from typing import NamedTuple

import numpy as np

from .. import filters, models, validation
from ..data.drive import Drive
from ..data.read import drive_format, read_drive
from . import config
from .config import DRIVE_FORMAT, DRIVE_MAPPING

__all__ = ["load_drive", "build_model", "model_label", "on_model", "OnGrid", "Start",
           "start_values", "BUILDERS", "with_input_noise"]

#: the filter families by their name in the configuration
BUILDERS = {"ekf": filters.ekf, "ukf": filters.ukf, "ckf": filters.ckf}


def _keyed(section: str, keys, err: ValueError) -> ValueError:
    """``err`` with ``[section] `` in front when its message starts with one of ``keys`` (the
    reader's and Drive's messages name their argument, which is the file's key)."""
    text = str(err)
    if any(text.startswith(f"{k}:") for k in keys):
        return ValueError(f"[{section}] {text}")
    return err


def _format_options(path: Path, kind: str, section: dict) -> dict:
    """The [drive] keys of ``section`` that format ``kind`` reads, as the reader's keyword
    arguments; ValueError naming a key of another format, a key the format needs, a DBC file
    that is not there."""
    label = config.FORMAT_LABELS[kind]
    takes = config.FORMAT_KEYS[kind]
    for key in DRIVE_FORMAT:
        if key in section and key not in takes:
            raise ValueError(f"[drive] {key}: {path.name!r} is {label}, which does not take "
                             f"{key}; {label} takes {', '.join(takes)}")
    for key in config.FORMAT_NEEDS[kind]:
        if key not in section:
            raise ValueError(f"[drive] {key}: missing; {path.name!r} is {label}, read with "
                             f"{' and '.join(config.FORMAT_NEEDS[kind])}")
    options = {k: section[k] for k in takes if k in section}
    if "channels" in options:  # [channel, group] comes back from fit.json as a list
        options["channels"] = {k: v if isinstance(v, str) else tuple(v)
                               for k, v in options["channels"].items()}
    if "dbc" in options:
        dbc = Path(options["dbc"]).expanduser()
        if not dbc.is_file():
            raise ValueError(f"[drive] dbc: {str(dbc)!r} is not a file (a relative path is "
                             f"taken relative to the configuration file's folder)")
        options["dbc"] = dbc
    return options


def load_drive(path, section: dict) -> Drive:
    """The drive file at ``path`` read by :func:`vehjax.data.read_drive` with the [drive]
    section's options for its format (:data:`~vehjax.commands.config.FORMAT_KEYS`: a CSV's
    ``time``, ``columns``, ...; an MDF file's ``channels``; a ROS 2 bag's ``fields`` and
    ``stamps``; a CAN log's ``dbc``, ``signals`` and ``channel``; ``units`` and ``reference``
    for all). ``path`` is a file or a ROS 2 bag folder.

    Raises ValueError naming ``DRIVE`` for a missing file, a suffix of no known format, one
    the reader cannot read and a format whose optional library is not installed (saying which
    extra to install); naming the [drive] key for another format's key, a missing one and what
    the reader refuses (an unknown channel, a unit it cannot convert, ...)."""
    path = Path(path)
    if not path.exists():
        raise ValueError(f"DRIVE: {str(path)!r} is not a file (nor a ROS 2 bag folder)")
    try:
        kind = drive_format(path)
        options = _format_options(path, kind, section)
        return read_drive(path, **options)
    except ImportError as err:
        raise ValueError(f"DRIVE: {str(path)!r} is {config.FORMAT_LABELS[kind]}: {err}") from None
    except ValueError as err:
        text = str(err)
        if text.startswith("path:"):
            raise ValueError("DRIVE:" + text.removeprefix("path:")) from None
        if text.startswith("["):
            raise
        if not any(text.startswith(f"{k}:") for k in DRIVE_FORMAT):
            raise ValueError(f"DRIVE: {str(path)!r}: {text}") from None
        raise _keyed("drive", DRIVE_FORMAT, err) from None


def _factory(name: str):
    """The model class of a built-in ``name`` or the function ``"package.module:factory"``."""
    if ":" not in name:
        if name not in models.REGISTRY:
            raise ValueError(f"[model] name: unknown model {name!r}; built-in models: "
                             f"{', '.join(sorted(models.REGISTRY))}, or a function of yours "
                             f"as 'package.module:factory'")
        return models.REGISTRY[name]
    module, _, attr = name.partition(":")
    try:
        found = getattr(importlib.import_module(module), attr, None)
    except ImportError as err:
        raise ValueError(f"[model] name: cannot import {module!r} ({err})") from None
    if not callable(found):
        raise ValueError(f"[model] name: {module!r} has no function {attr!r}")
    return found


def build_model(section: dict, drive_dt: float | None):
    """The model of the [model] section: ``factory(dt=dt, **options)``, with output biases
    and the ``theta`` values by name. ``dt`` [s] defaults to the drive's step (``drive_dt``,
    None for non-uniform stamps: then dt is required)."""
    dt = section.get("dt", drive_dt)
    if dt is None:
        raise ValueError("[model] dt: the drive's time stamps are not uniform; give the "
                         "model's step dt [s]")
    make = _factory(section["name"])
    try:
        model = make(dt=float(dt), **section.get("options", {}))
    except TypeError as err:
        raise ValueError(f"[model] options: {err}") from None
    except ValueError as err:
        raise ValueError(f"[model] options: {err}") from None
    try:
        validation.model(model)
    except ValueError as err:
        raise ValueError(f"[model] name: {section['name']!r} did not return a model ({err})") \
            from None
    if "output_biases" in section:
        model = models.with_output_biases(model, validation.names(
            "[model] output_biases", section["output_biases"], model.output_names))
    theta = validation.keyed("[model] theta", section.get("theta"), model.param_names,
                             "parameters")
    try:
        return model.with_theta(**theta) if theta else model
    except ValueError as err:
        raise ValueError(f"[model] theta: {str(err).removeprefix('with_theta: ')}") from None


def model_label(section: dict) -> str:
    """The [model] section's model in words: ``"SingleTrack"``, ``"SingleTrack with biases on
    ay, r"``."""
    biases = section.get("output_biases", ())
    return section["name"] + (f" with biases on {', '.join(biases)}" if biases else "")


class OnGrid(NamedTuple):
    """A drive on the model's grid: ``t`` (T,) [s], ``inputs`` (T, nu), ``measurements``
    (T, ny) in the model's order and units (NaN missing), and the resampled drive."""

    t: np.ndarray
    inputs: np.ndarray
    measurements: np.ndarray
    drive: Drive


def on_model(drive: Drive, model, section: dict) -> OnGrid:
    """``drive`` cut to [start, stop] and mapped onto ``model`` (:meth:`Drive.for_model`
    with the section's ``names``, ``missing_outputs`` and ``max_gap``) on the model's grid
    (resampled unless every signal is already on it: a multi-rate drive's slower signals are
    interpolated between their own samples)."""
    try:
        if "start" in section or "stop" in section:
            drive = drive.between(section.get("start"), section.get("stop"))
        if not drive.on_grid(float(model.dt)):
            drive = drive.resample(float(model.dt), max_gap=section.get("max_gap"))
        us, ys = drive.for_model(model, section.get("names"),
                                 missing_outputs=section.get("missing_outputs", ()))
    except ValueError as err:
        raise _keyed("drive", (*DRIVE_MAPPING, "start, stop"), err) from None
    return OnGrid(drive.t, us, ys, drive)


def _per(key: str, values, names) -> np.ndarray:
    """One value per name: one value serves every name."""
    values = np.asarray(values, dtype=float)
    if values.size == 1:
        return np.full(len(names), float(values[0]))
    if values.size != len(names):
        raise ValueError(f"{key}: expected 1 value or {len(names)} (one per "
                         f"{', '.join(names)}), got {values.size}")
    return values


class Start(NamedTuple):
    """The filter's starting values: Q (nx, nx), R (ny, ny), x0 (nx,), P0 (nx, nx), the
    input noise (stds by input name) or None."""

    Q: np.ndarray
    R: np.ndarray
    x0: np.ndarray
    P0: np.ndarray
    input_noise: dict | None


def start_values(model, section: dict) -> Start:
    """The [fit] section's noise and prior as covariances (stds squared), checked against the
    model's states, outputs and inputs."""
    states, outputs = model.state_names, model.output_names
    Q = np.diag(_per("[fit] process_std", section["process_std"], states) ** 2)
    R = np.diag(_per("[fit] meas_std", section["meas_std"], outputs) ** 2)
    x0 = _per("[fit] x0", section.get("x0", (0.0,)), states)
    P0 = np.diag(_per("[fit] P0_std", section["P0_std"], states) ** 2)
    noise = validation.keyed("[fit] input_noise", section.get("input_noise"),
                             model.input_names, "inputs") or None
    return Start(Q, R, x0, P0, noise)


def with_input_noise(builder, input_noise):
    """The builder with its ``input_noise`` option when there is one,
    ``functools.partial(builder, input_noise=...)``; else the builder itself."""
    if input_noise is None:
        return builder
    if isinstance(input_noise, dict):
        return functools.partial(builder, input_noise={k: float(v)
                                                       for k, v in input_noise.items()})
    return functools.partial(builder, input_noise=np.asarray(input_noise, dtype=float))
