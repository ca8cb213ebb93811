"""Signals each recorded on its own time stamps, put on one :class:`~vehjax.data.Drive` without
moving a sample: the common part of the log readers (:mod:`vehjax.data.mdf`,
:mod:`vehjax.data.rosbag`, :mod:`vehjax.data.canlog`).

A reader hands over, per vehjax signal name, its time stamps [s], its values and the unit the
file gives them. Here:

* Time stamps within one signal must not go back: a step back is a ValueError naming the signal,
  where it came from (channel, topic field, CAN signal), the sample and both stamps. A stamp that
  repeats with the same value (a logger writing one sample twice; NaN equals NaN) is dropped;
  a stamp that repeats with another value is a ValueError. Nothing is sorted or shifted.
* Units: the file's unit, or the one ``units=`` gives for that name, converted to SI with
  :func:`~vehjax.data.drive.to_si`; a unit :data:`~vehjax.data.UNITS` does not know is refused
  naming the signal, its source and the unit.
* The drive's ``t`` is the union of every signal's stamps; each signal is NaN at the stamps
  where it has no sample, and its median sample interval goes to :attr:`Drive.intervals`, so
  that resampling (``for_model``) interpolates it between its own samples and NaNs it only
  across gaps longer than 2.5 of its intervals.
"""

from __future__ import annotations

import difflib
import importlib
from typing import Mapping

import numpy as np

from .drive import UNITS, Drive, to_si

__all__ = ["require", "mapping", "unknown", "stamped", "to_drive"]


def require(module: str, extra: str):
    """The optional library ``module``, imported; ImportError naming the extra to install."""
    try:
        return importlib.import_module(module)
    except ImportError:
        raise ImportError(f"reading this file format needs the optional library {module!r}: "
                          f"pip install \"vehjax[{extra}]\"") from None


def mapping(arg: str, value, *, allow_tuple: bool = False) -> dict:
    """``value`` as a non-empty dict vehjax name -> source (a non-empty string; with
    ``allow_tuple`` also a tuple whose first item is one); ValueError naming ``arg``."""
    if not isinstance(value, Mapping) or not value:
        raise ValueError(f"{arg}: expected a non-empty mapping vehjax signal name -> name in "
                         f"the file, got {value!r}")
    for k, v in value.items():
        ok = isinstance(v, str) or (allow_tuple and isinstance(v, tuple) and len(v) == 2
                                    and isinstance(v[0], str))
        if not isinstance(k, str) or not k.strip() or k != k.strip() or not ok or not (
                v if isinstance(v, str) else v[0]):
            raise ValueError(f"{arg}: {k!r}: {v!r} is not a signal name -> name in the file")
    return dict(value)


def unknown(what: str, name: str, available, where: str) -> ValueError:
    """A ValueError for ``name`` not found among ``available``, listing the near ones."""
    available = sorted(set(available))
    close = difflib.get_close_matches(name, available, n=6, cutoff=0.5)
    shown = close or available[:12]
    more = "" if close or len(available) <= 12 else f" (and {len(available) - 12} more)"
    label = "near names" if close else "available"
    return ValueError(f"{what}: no {name!r} in {where}; {label}: {shown}{more}")


def stamped(name: str, source: str, t, values, unit: str, units: Mapping,
            clock: str = "") -> tuple:
    """(t [s], values in SI, SI unit) of one signal, its stamps checked (see the module);
    ``clock`` follows ``source`` in the messages about its stamps (which clock they are)."""
    t = np.asarray(t, dtype=float).ravel()
    try:
        v = np.asarray(values, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name!r}: {source} is not numeric (dtype "
                         f"{np.asarray(values).dtype})") from None
    if v.shape != t.shape:
        raise ValueError(f"{name!r}: {source} has samples of shape {v.shape[1:]} (one number per "
                         f"time stamp is read; pick one element)")
    given = units.get(name, unit)
    if not isinstance(given, str) or given.strip() not in UNITS:
        said = "has no unit" if given == "" else f"is in {given!r}, a unit vehjax.data.UNITS " \
            "does not know"
        raise ValueError(f"units: {name!r} ({source}) {said}; give its unit with "
                         f"units={{{name!r}: '...'}} (one of "
                         f"{', '.join(sorted(UNITS))})")
    if not np.all(np.isfinite(t)):
        k = int(np.flatnonzero(~np.isfinite(t))[0])
        raise ValueError(f"{name!r}: {source} has a non-finite time stamp at sample {k}")
    t, v = _drop_repeats(name, source + clock, t, v)
    if t.size < 2:
        raise ValueError(f"{name!r}: {source} has {t.size} sample(s); at least 2 are needed")
    v, si = to_si(name, v, given)
    return t, v, si


def _drop_repeats(name, source, t, v):
    d = np.diff(t)
    back = np.flatnonzero(d < 0.0)
    if back.size:
        k = int(back[0])
        raise ValueError(f"{name!r}: the time stamps of {source} go back {back.size} time(s), "
                         f"the first at sample {k + 1}: {float(t[k])!r} -> {float(t[k + 1])!r} s "
                         f"(read the file in parts, or fix its clock; vehjax does not reorder "
                         f"samples)")
    same = np.flatnonzero(d == 0.0)
    if same.size == 0:
        return t, v
    equal = (v[same] == v[same + 1]) | (np.isnan(v[same]) & np.isnan(v[same + 1]))
    if not np.all(equal):
        k = int(same[~equal][0])
        raise ValueError(f"{name!r}: {source} has two samples at t = {float(t[k])!r} s (samples "
                         f"{k} and {k + 1}) with different values {float(v[k])!r} and "
                         f"{float(v[k + 1])!r}")
    keep = np.ones(t.size, bool)
    keep[same + 1] = False
    return t[keep], v[keep]


def to_drive(series: Mapping, reference, units: Mapping, arg: str) -> Drive:
    """A Drive from ``series`` (name -> (t, SI values, SI unit) as :func:`stamped` gives):
    ``t`` the union of the stamps, NaN where a signal has no sample, its median interval in
    :attr:`Drive.intervals`. ``reference`` names (of ``arg``'s keys) go to ``Drive.reference``."""
    reference = (reference,) if isinstance(reference, str) else tuple(reference)
    for name in (*reference, *units):
        if name not in series:
            raise ValueError(f"{'reference' if name in reference else 'units'}: {name!r} is "
                             f"not a name of {arg} ({sorted(series)})")
    t = np.unique(np.concatenate([s[0] for s in series.values()]))
    signals, ref, si_units, intervals = {}, {}, {}, {}
    for name, (ts, v, si) in series.items():
        col = np.full(t.size, np.nan)
        col[np.searchsorted(t, ts)] = v
        (ref if name in reference else signals)[name] = col
        si_units[name] = si
        intervals[name] = float(np.median(np.diff(ts)))
    return Drive(t=t, signals=signals, reference=ref, units=si_units, intervals=intervals)
