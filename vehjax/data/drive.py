"""Your own recorded drive: named signals with units on a time axis, mapped onto a model.

A :class:`Drive` holds time stamps ``t`` [s] (strictly increasing, any rate, not necessarily
uniform) and named signals on them, every one stored in SI units (rad, rad/s, m/s, m/s^2, ...):
the units given when the drive is made are converted once (deg -> rad, deg/s -> rad/s,
km/h -> m/s, g -> m/s^2, ...; :data:`UNITS` lists the known ones). A NaN sample is a missing one.
Signals used only to judge an estimate (a sideslip from an INS, a pose-derived velocity) go in
``reference`` so that they cannot be mistaken for a model input by name.

Typical use::

    drive = Drive.from_csv("lap.csv", time="time", units={"time": "s", "steer": "deg",
                           "speed": "km/h", "ay": "g", "yaw_rate": "deg/s"},
                           reference=("beta_ins",))
    us, ys = drive.for_model(model, names={"steer": "delta", "speed": "vx", "yaw_rate": "r"})

``for_model`` resamples onto the model's ``dt`` (:meth:`Drive.resample`: linear interpolation,
NaN across gaps longer than ``max_gap`` and outside a signal's recorded span) and returns the
inputs (T, nu) and the measurements (T, ny) in the model's order. :func:`vehjax.data.load_comma2k19`
is one producer of a Drive (``load_comma2k19().to_drive()`` gives one with model-named columns);
:func:`vehjax.data.read_drive` reads MDF4/MDF3 files, ROS 2 bags and CAN logs into one, each
signal at its own rate (:attr:`Drive.intervals`).

Files are read as spreadsheets, loggers and pandas write them (:mod:`vehjax.data.table`: a
byte-order mark, CRLF, quoted headers, blank lines, separators at the end of every line, the
separator sniffed); a column name given twice or left empty is refused, and so is a cell that is
neither a number nor missing (an empty cell, ``nan`` or ``NA``), naming the column and the row.
"""

from __future__ import annotations

import csv
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping

import numpy as np

from .table import is_missing, parse_cells, read_table

__all__ = ["Drive", "UNITS", "to_si", "declared_units", "numeric_column"]

#: Standard gravity [m/s^2], the unit "g" of accelerometers.
STANDARD_GRAVITY = 9.80665

#: unit -> (SI unit, factor): value_SI = factor * value.
UNITS = {
    "s": ("s", 1.0), "ms": ("s", 1e-3), "us": ("s", 1e-6), "ns": ("s", 1e-9),
    "m": ("m", 1.0), "km": ("m", 1e3), "mm": ("m", 1e-3), "cm": ("m", 1e-2),
    "m/s": ("m/s", 1.0), "km/h": ("m/s", 1.0 / 3.6), "kph": ("m/s", 1.0 / 3.6),
    "mph": ("m/s", 0.44704),
    "m/s^2": ("m/s^2", 1.0), "g": ("m/s^2", STANDARD_GRAVITY),
    "rad": ("rad", 1.0), "deg": ("rad", math.pi / 180.0),
    "rad/s": ("rad/s", 1.0), "deg/s": ("rad/s", math.pi / 180.0),
    "rpm": ("rad/s", 2.0 * math.pi / 60.0),
    "rad/s^2": ("rad/s^2", 1.0), "deg/s^2": ("rad/s^2", math.pi / 180.0),
    "N": ("N", 1.0), "kN": ("N", 1e3), "N m": ("N m", 1.0), "Nm": ("N m", 1.0),
    "kg": ("kg", 1.0), "-": ("-", 1.0), "1": ("-", 1.0), "%": ("-", 1e-2),
    # spellings that measurement files (MDF) and DBCs use for the same units
    "°": ("rad", math.pi / 180.0), "°/s": ("rad/s", math.pi / 180.0),
    "°/s^2": ("rad/s^2", math.pi / 180.0), "°/s²": ("rad/s^2", math.pi / 180.0),
    "deg/s²": ("rad/s^2", math.pi / 180.0), "rad/s²": ("rad/s^2", 1.0),
    "m/s²": ("m/s^2", 1.0), "m/s2": ("m/s^2", 1.0), "1/min": ("rad/s", 2.0 * math.pi / 60.0),
}

#: "name [unit]": the unit is the last bracketed group, so a name may hold brackets ("a[1] [m]")
_HEADER = re.compile(r"^\s*(?P<name>.*?)\s*\[(?P<unit>[^\[\]]*)\]\s*$")


def to_si(name: str, values, unit: str):
    """``values`` converted from ``unit`` to its SI unit: (array, SI unit string).

    ValueError naming ``name`` for a unit not in :data:`UNITS`.
    """
    if not isinstance(unit, str) or unit.strip() not in UNITS:
        raise ValueError(f"units: unknown unit {unit!r} for {name!r}; known units: "
                         f"{', '.join(sorted(UNITS))}")
    si, factor = UNITS[unit.strip()]
    return np.asarray(values, dtype=float) * factor, si


def check_time(t, what: str = "t") -> np.ndarray:
    """``t`` as a 1-D float array of at least 2 finite, strictly increasing time stamps;
    ValueError naming ``what`` (an argument or a file) and the first bad sample otherwise."""
    try:
        t = np.array(t, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{what}: expected a 1-D array of time stamps in seconds") from None
    if t.ndim != 1 or len(t) < 2:
        raise ValueError(f"{what}: expected a 1-D array of at least 2 time stamps, got shape "
                         f"{t.shape}")
    if not np.all(np.isfinite(t)):
        i = int(np.flatnonzero(~np.isfinite(t))[0])
        raise ValueError(f"{what}: non-finite time stamps, the first {t[i]!r} at sample {i}")
    bad = np.flatnonzero(np.diff(t) <= 0.0)
    if bad.size:
        i = int(bad[0])
        raise ValueError(f"{what}: time stamps must be strictly increasing; {bad.size} steps are "
                         f"not, the first at index {i}: {t[i]!r} -> {t[i + 1]!r} s")
    return t


def _uniform_step(t: np.ndarray) -> float | None:
    """The common step of ``t`` [s] if every step equals it to 1e-6 relative (or to the
    rounding of float64 stamps as large as ``t``'s, for stamps since the epoch), else None."""
    d = np.diff(t)
    step = (t[-1] - t[0]) / (len(t) - 1)
    return float(step) if np.all(np.abs(d - step) <= _step_tolerance(t, step)) else None


def _step_tolerance(t: np.ndarray, step: float) -> float:
    """1e-6 of ``step``, or 8 float64 roundings of the largest stamp if that is more (a
    uniform grid at t ~ 1.7e9 s, the epoch, is uniform to about 2e-7 s only)."""
    return max(1e-6 * step, 8.0 * np.finfo(float).eps * float(np.max(np.abs(t))))


def _grid_points(t0: float, t1: float, dt: float) -> int:
    """Points of the grid t0, t0 + dt, ... <= t1 [s], the last one counted where it misses t1
    by float64 rounding only (of stamps as large as t0, t1: since the epoch, about 2e-7 s)."""
    slack = max(1e-12 * (t1 - t0), 8.0 * np.finfo(float).eps * max(abs(t0), abs(t1))) / dt
    return int(math.floor((t1 - t0) / dt + slack)) + 1


def interpolate_with_gaps(t_new, t, y, max_gap: float) -> np.ndarray:
    """Linear interpolation of samples (t, y) at ``t_new`` [s], NaN where it would bridge a gap.

    Only finite samples of ``y`` are used. A point of ``t_new`` gets NaN when it lies outside
    the span of the finite samples, or strictly inside an interval between two consecutive
    finite samples that is longer than ``max_gap`` [s]. Points on a sample get its value.
    """
    t_new = np.asarray(t_new, dtype=float)
    ok = np.isfinite(y)
    ts, ys = t[ok], y[ok]
    out = np.full(t_new.shape, np.nan)
    if ts.size == 0:
        return out
    inside = (t_new >= ts[0]) & (t_new <= ts[-1])
    out[inside] = np.interp(t_new[inside], ts, ys)
    if ts.size > 1:
        j = np.clip(np.searchsorted(ts, t_new, side="right"), 1, ts.size - 1)
        lo, hi = ts[j - 1], ts[j]
        on_sample = (t_new == lo) | (t_new == hi)
        out[inside & ((hi - lo) > max_gap) & ~on_sample] = np.nan
    return out


@dataclass(frozen=True, eq=False, kw_only=True)
class Drive:
    """A recorded drive: time stamps and named signals in SI units (NaN = missing).

    Frozen; its arrays are read-only.

    Attributes:
        t: (T,) time stamps [s], strictly increasing (any rate).
        signals: name -> (T,) array in SI units.
        units: name -> SI unit string, for every key of ``signals`` and ``reference``.
        reference: name -> (T,) array: signals for validation only (default none).
        dt: the grid step [s] when ``t`` is uniform (to 1e-6 relative, or to float64's
            rounding of stamps that large), else None; filled in when not given.
        intervals: name -> that signal's own median sample interval [s] (default none). A
            drive read from a log (:func:`vehjax.data.read_drive`) holds signals recorded at
            different rates on one time axis, the union of all their time stamps, each signal
            NaN at the stamps where it has no sample; its intervals tell :meth:`resample` how
            far apart that signal's samples are meant to be, so that a 10 Hz signal is
            interpolated between its own samples and NaN only across its own gaps (longer than
            2.5 of its intervals). A signal without one uses ``t``'s median step, as a drive
            from arrays or a CSV does.

    Make one with :meth:`from_arrays` or :meth:`from_csv` (they convert units); the
    constructor takes arrays already in SI units.
    """

    t: np.ndarray
    signals: Mapping[str, np.ndarray]
    units: Mapping[str, str]
    reference: Mapping[str, np.ndarray] = field(default_factory=dict)
    dt: float | None = None
    intervals: Mapping[str, float] = field(default_factory=dict)

    def __post_init__(self):
        t = check_time(self.t)
        groups = {}
        for arg in ("signals", "reference"):
            group = getattr(self, arg)
            if not isinstance(group, Mapping):
                raise ValueError(f"{arg}: expected a mapping name -> (T,) array, got {group!r}")
            for k in group:
                _check_name(arg, k)
            groups[arg] = {k: _column(arg, k, v, len(t)) for k, v in group.items()}
        both = set(groups["signals"]) & set(groups["reference"])
        if both:
            raise ValueError(f"reference: names also in signals: {sorted(both)}")
        units = dict(self.units)
        for name in (*groups["signals"], *groups["reference"]):
            if name not in units:
                raise ValueError(f"units: no unit for {name!r}")
            if units[name] not in {si for si, _ in UNITS.values()}:
                raise ValueError(f"units: {name!r} has {units[name]!r}, not an SI unit of "
                                 f"UNITS (use from_arrays / from_csv to convert)")
        step = _uniform_step(t)
        if self.dt is not None and (step is None or abs(float(self.dt) - step)
                                    > _step_tolerance(t, step)):
            raise ValueError(f"dt: {self.dt!r} s does not match the time stamps' step {step}")
        intervals = _intervals(self.intervals, {**groups["signals"], **groups["reference"]})
        t.setflags(write=False)
        object.__setattr__(self, "intervals", intervals)
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "signals", groups["signals"])
        object.__setattr__(self, "reference", groups["reference"])
        object.__setattr__(self, "units", units)
        object.__setattr__(self, "dt", step if self.dt is None else float(self.dt))

    # -- making one -------------------------------------------------------------------------
    @classmethod
    def from_arrays(cls, t, values: Mapping, units: Mapping, *, reference=(),
                    time_unit: str = "s") -> "Drive":
        """A drive from arrays: ``t`` (T,) in ``time_unit``, ``values`` name -> (T,) in
        ``units[name]`` (every name needs one; see :data:`UNITS`). Names listed in
        ``reference`` go to :attr:`reference`.

        A column may hold text (a column read from a file): numbers as ``float`` reads them,
        and missing samples (NaN) as NaN, None, an empty string, ``"nan"`` (any case) or
        ``"NA"`` (:data:`vehjax.data.table.MISSING`); any other text (``"n/a"``) is refused.
        Raises ValueError for a missing or unknown unit, a misshaped column, a cell that is not
        a number (naming the column and the row), time stamps that are not strictly increasing.
        """
        if not isinstance(values, Mapping) or not isinstance(units, Mapping):
            raise ValueError("values, units: expected mappings name -> array and name -> unit")
        reference = _names("reference", reference, values)
        t, _ = to_si("t", check_time(t), time_unit)
        sig, ref, si_units = {}, {}, {}
        for name, v in values.items():
            _check_name("values", name)
            if name not in units:
                raise ValueError(f"units: no unit for {name!r}; give units={{{name!r}: ...}}")
            v = numeric_column("values", name, v)
            (ref if name in reference else sig)[name], si_units[name] = to_si(name, v, units[name])
        return cls(t=t, signals=sig, reference=ref, units=si_units)

    @classmethod
    def from_csv(cls, path, time: str = "t", units: Mapping | None = None, *, columns=None,
                 reference=(), delimiter: str | None = None, decimal: str = ".",
                 encoding: str | None = None) -> "Drive":
        """A drive from a delimited text file with a header row of column names.

        Reads files the way spreadsheets, loggers and pandas write them
        (:mod:`vehjax.data.table`): UTF-8 with or without a byte-order mark, CRLF or LF line
        ends, quoted headers and fields, blank lines anywhere, separators at the end of every
        line; the separator (``,`` ``;`` tab ``|``) is sniffed unless ``delimiter`` is given.
        A header may carry its unit in brackets, ``"steer [deg]"``; ``units`` (name -> unit)
        gives or overrides them, the time column's too (default s). A missing sample (NaN) is an
        empty cell, ``nan`` (any case) or ``NA``. ``columns`` selects the columns to read
        (default all); ``reference`` names those that go to :attr:`reference`.

        Args:
            decimal: ``"."`` (default) or ``","`` for files with decimal commas (semicolon
                separated, as a spreadsheet in a German or French locale writes them).
            encoding: None (UTF-8, or UTF-16 with a byte-order mark) or a codec name.

        Raises ValueError naming a missing column, an unnamed or duplicated column name, a
        column without a unit or with an unknown one, a cell that is not a number (the column,
        the data row and the file line), missing or non-increasing time stamps (the lines).
        """
        path = Path(path)
        if not path.is_file():
            raise ValueError(f"path: {str(path)!r} is not a file")
        if decimal not in (".", ","):
            raise ValueError(f"decimal: expected '.' or ',', got {decimal!r}")
        table = read_table(path, delimiter, encoding)
        names, header_units = _split_units(path, table.names)
        units = dict(units or {})
        unknown = [k for k in units if k not in names]
        if unknown:
            raise ValueError(f"units: no column {unknown[0]!r} in {str(path)!r}; columns: {names}")
        given = dict(header_units, **units)
        want = list(names) if columns is None else list(_names("columns", columns, names))
        if time not in names:
            hint = _separator_hint(table)
            raise ValueError(f"time: no column {time!r} in {str(path)!r}; columns: {names}{hint}")
        want = [c for c in want if c != time]
        for c in want:
            if c not in given:
                raise ValueError(f"units: no unit for column {c!r}: give units={{{c!r}: ...}} "
                                 f"or write it in the header as '{c} [unit]'")
        if len(table.lines) < 2:
            raise ValueError(f"path: {str(path)!r}: fewer than 2 rows of data")

        def where(k):
            return f"path: {str(path)!r}, data row {k + 1}, line {table.lines[k]}"

        cells = {c: table.cells[table.names[names.index(c)]] for c in [time] + want}
        try:
            data = {time: parse_cells(time, cells[time], where, decimal, table.delimiter)}
        except ValueError as exc:
            raise ValueError(f"{exc}; time stamps are numbers in the time column's unit (convert "
                             f"date-times to seconds first, e.g. with pandas: (pd.to_datetime(col)"
                             f" - pd.to_datetime(col)[0]).dt.total_seconds())") from None
        data.update({c: parse_cells(c, cells[c], where, decimal, table.delimiter) for c in want})
        _check_csv_time(data[time], time, where)
        return cls.from_arrays(data[time], {c: data[c] for c in want}, {c: given[c] for c in want},
                               reference=reference, time_unit=given.get(time, "s"))

    def to_csv(self, path) -> None:
        """Write ``t`` and every signal and reference column, headers ``"name [unit]"``, missing
        samples as empty fields, UTF-8; :meth:`from_csv` reads it back (pass ``reference=``).

        :attr:`intervals` are not written: a multi-rate drive read back resamples every signal
        with ``t``'s median step as its gap unless ``max_gap=`` is given."""
        names = [*self.signals, *self.reference]
        if "t" in names:
            raise ValueError("path: to_csv writes the time column as 't [s]', and a signal is "
                             "named 't' too; rename it (from_csv would refuse the two columns)")
        cols = [self.t] + [self.signals.get(n, self.reference.get(n)) for n in names]
        with open(path, "w", newline="", encoding="utf-8") as fh:
            w = csv.writer(fh)
            w.writerow(["t [s]"] + [f"{n} [{self.units[n]}]" for n in names])
            for row in np.stack(cols, axis=1):
                w.writerow(["" if np.isnan(v) else repr(float(v)) for v in row])

    # -- time -------------------------------------------------------------------------------
    def resample(self, dt: float, *, start=None, stop=None, max_gap=None) -> "Drive":
        """This drive on the uniform grid start, start + dt, ... <= stop [s].

        Every signal is interpolated linearly from its own finite samples
        (:func:`interpolate_with_gaps`); grid points inside a gap longer than ``max_gap`` [s]
        (default 2.5 median sample intervals of ``t``, so one dropped sample is bridged, two
        are not; for a signal in :attr:`intervals`, 2.5 of its own interval) or outside the
        signal's recorded span are NaN. No anti-alias filtering: to downsample noisy signals by
        a large factor, average them first. The result has no :attr:`intervals` (every signal
        is on the grid).

        Args:
            dt: grid step [s], > 0.
            start, stop: grid ends [s], inside [t[0], t[-1]] (default those).
            max_gap: longest gap [s] interpolated across, > 0, for every signal.
        """
        dt = _positive("dt", dt)
        lo, hi = float(self.t[0]), float(self.t[-1])
        t0 = lo if start is None else _within("start", start, lo, hi)
        t1 = hi if stop is None else _within("stop", stop, lo, hi)
        if not t1 > t0:
            raise ValueError(f"stop: {t1} s is not after start = {t0} s")
        median = float(np.median(np.diff(self.t)))
        step = 2.5 * median
        given = self._max_gap(max_gap)
        n = _grid_points(t0, t1, dt)
        if n < 2:
            raise ValueError(f"dt: {dt} s gives fewer than 2 samples between {t0} and {t1} s")
        grid = t0 + dt * np.arange(n)
        grid[-1] = min(grid[-1], t1)  # a last point past t1 by rounding only: on t1

        def on_grid(group):
            return {k: interpolate_with_gaps(grid, self.t, v, gap(k)) for k, v in group.items()}

        def gap(k):
            if given is not None:
                return given
            return 2.5 * self.intervals[k] if k in self.intervals else step

        return Drive(t=grid, signals=on_grid(self.signals), reference=on_grid(self.reference),
                     units=dict(self.units), dt=dt)

    def on_grid(self, dt: float) -> bool:
        """Whether every signal is sampled on the uniform grid of step ``dt`` [s]: ``t`` is
        uniform with that step (to 1e-9 relative) and no signal of :attr:`intervals` has another
        interval (a multi-rate drive whose stamps happen to be uniform still has its slower
        signals NaN between their samples). :meth:`for_model` resamples a drive that is not."""
        dt = float(dt)
        if self.dt is None or abs(self.dt - dt) > 1e-9 * dt:
            return False
        return all(abs(v - dt) <= 1e-6 * dt for v in self.intervals.values())

    def between(self, start=None, stop=None) -> "Drive":
        """The samples with start <= t <= stop [s] (no resampling), at least 2.

        A slow signal of a multi-rate drive (:attr:`intervals`) loses its samples outside too,
        so it may start after ``start``: to cut a window onto a grid, use
        ``resample(dt, start=, stop=)``, which interpolates from the samples around the ends."""
        keep = np.ones(len(self.t), bool)
        if start is not None:
            keep &= self.t >= float(start)
        if stop is not None:
            keep &= self.t <= float(stop)
        if keep.sum() < 2:
            raise ValueError(f"start, stop: fewer than 2 samples in [{start}, {stop}] s")
        return Drive(t=self.t[keep], signals={k: v[keep] for k, v in self.signals.items()},
                     reference={k: v[keep] for k, v in self.reference.items()},
                     units=dict(self.units), intervals=dict(self.intervals))

    def _max_gap(self, max_gap) -> float | None:
        """``max_gap`` [s] checked: None, or a number > 0 longer than the drive's median sample
        interval (else every interval would be a gap); ValueError naming it."""
        if max_gap is None:
            return None
        given, median = _positive("max_gap", max_gap), float(np.median(np.diff(self.t)))
        if given <= median * (1.0 + 1e-9):  # every interval a gap, NaN
            raise ValueError(f"max_gap: {given:g} s is not longer than the drive's sample "
                             f"interval ({median:g} s, the median): every sample would be a gap; "
                             f"give more than {median:g} s (default 2.5 intervals)")
        return given

    # -- a model's arrays -------------------------------------------------------------------
    def for_model(self, model, names: Mapping | None = None, *, missing_outputs=(),
                  max_gap=None):
        """(inputs (T, nu), measurements (T, ny)) for ``model`` on its grid, in its order.

        The drive is resampled to ``model.dt`` unless it is already on that grid
        (:meth:`on_grid`; a multi-rate drive is resampled, its slower signals interpolated).
        Each model input and output is read from the signal of the same name, or from the column
        that ``names`` (column name -> model name) maps onto it. Units are matched only where
        the model declares them (:func:`declared_units`): there the column's SI unit must be the
        SI unit of the model's, and the column is converted to the model's unit (a column given
        in deg feeds a model input in rad, or in deg if the model declares deg). Where the model
        declares none (a :class:`~vehjax.models.Model` built without ``units=``, or a name left
        out of it) the column goes in unchecked, in its SI unit; declare units with
        ``Model(..., units={"delta": "rad", "ay": "m/s^2"})`` to have them checked. Missing
        samples of the measurements stay NaN (a filter skips them); inputs must be complete.

        A :attr:`reference` channel feeds a model output only when ``names`` maps it there
        (``names={"ref_vy": "vy"}`` for a model with a reference output, e.g.
        ``SingleTrack(references=("vy",))``), never by its name alone and never an input. A drive
        without the reference runs such a model with ``missing_outputs=("vy",)``: that column
        is NaN, which filters skip.

        Args:
            model: any vehjax model (``dt``, ``input_names``/``output_names``, optionally
                ``input_units``/``output_units``, or a Model's ``units=``).
            names: column name (a signal, or a reference channel for an output) -> model
                input/output name.
            missing_outputs: model outputs with no column in this drive, returned as NaN
                (e.g. a bank angle that was not measured); any other absent one is an error.
            max_gap: passed to :meth:`resample` (checked by its rule also when the drive is
                on the model's grid already and is not resampled).

        Raises:
            ValueError: an unknown name in ``names``, a model input or output with no column,
                mismatched units (saying how to declare a Model's units), a declared unit not in
                :data:`UNITS`, NaN inputs (naming the input and the first time).
        """
        names = dict(names or {})
        for col, target in names.items():
            if col in self.reference and col not in self.signals:
                if target not in model.output_names:
                    raise ValueError(f"names: the reference channel {col!r} can feed a model "
                                     f"output only ({model.output_names}), not {target!r}")
                continue
            if col not in self.signals:
                raise ValueError(f"names: no signal {col!r} in this drive; signals: "
                                 f"{sorted(self.signals)}, reference: {sorted(self.reference)}")
            if target not in (*model.input_names, *model.output_names):
                raise ValueError(f"names: {target!r} is not an input or output of the model "
                                 f"({model.input_names}, {model.output_names})")
        _one_column_each(names)
        self._max_gap(max_gap)  # checked even when the drive is on the grid already
        missing_outputs = _names("missing_outputs", missing_outputs, model.output_names)
        drive = self if self.on_grid(float(model.dt)) else self.resample(float(model.dt),
                                                                         max_gap=max_gap)
        source = {target: col for col, target in names.items()}
        hint = _declare_hint if _keyword_units(model) else None
        u = drive._columns("input", model.input_names, declared_units(model, "input"), source,
                           (), hint)
        bad = ~np.isfinite(u)
        if bad.any():
            k, j = np.argwhere(bad)[0]
            raise ValueError(f"inputs: {int(bad[:, j].sum())} missing samples of input "
                             f"{model.input_names[j]!r}, the first at t = {drive.t[k]:.6g} s; cut "
                             f"the drive with between() or fill the gap")
        y = drive._columns("output", model.output_names, declared_units(model, "output"),
                           source, missing_outputs, hint)
        return u, y

    def _columns(self, kind, targets, units, source, absent, hint):
        cols = []
        for target, unit in zip(targets, units):
            col = source.get(target, target)
            if target in absent:
                cols.append(np.full(len(self.t), np.nan))
                continue
            mapped_reference = target in source and col in self.reference
            if col not in self.signals and not mapped_reference:
                raise ValueError(
                    f"names: the model's {kind} {target!r} has no signal; map a column onto it "
                    f"with names={{'<column>': {target!r}}}"
                    + (" or list it in missing_outputs" if kind == "output" else "")
                    + f" (signals: {sorted(self.signals)}"
                    + (f"; reference channels, for outputs: {sorted(self.reference)}"
                       if kind == "output" and self.reference else "") + ")")
            values = self.reference[col] if mapped_reference else self.signals[col]
            if unit is None:                      # the model declares no unit: no check
                cols.append(values)
                continue
            if UNITS[unit][0] != self.units[col]:
                raise ValueError(
                    f"units: signal {col!r} is in {self.units[col]!r} but the model's {kind} "
                    f"{target!r} is in {unit!r}; map a column in {UNITS[unit][0]!r} onto it"
                    + (hint(target, self.units[col]) if hint else ""))
            cols.append(values / UNITS[unit][1])
        return np.stack(cols, axis=1)

    def __repr__(self) -> str:
        rate = f"dt = {self.dt} s" if self.dt is not None else "non-uniform"
        return (f"Drive({len(self.t)} samples, t = {self.t[0]:.3f}..{self.t[-1]:.3f} s, {rate}, "
                f"signals {sorted(self.signals)}, reference {sorted(self.reference)})")


def declared_units(model, kind: str) -> tuple:
    """The unit the model declares for each of its ``kind`` ("input" or "output") names, None
    where it declares none.

    A :class:`~vehjax.models.Model` declares the names in its ``units=`` mapping (every other
    name: None, though its ``input_units`` reads "-" there); any other model declares
    ``<kind>_units`` when it has one entry per name (the built-in models do), else nothing.
    ValueError for a declared unit that :data:`UNITS` does not know (it could not be checked).
    """
    names = tuple(getattr(model, f"{kind}_names"))
    if _keyword_units(model):
        declared = dict(model.units)
        units = tuple(declared.get(n) for n in names)
    else:
        units = tuple(getattr(model, f"{kind}_units", ()) or ())
        units = units if len(units) == len(names) else (None,) * len(names)
    for n, u in zip(names, units):
        if u is not None and (not isinstance(u, str) or u.strip() not in UNITS):
            raise ValueError(
                f"model: its {kind} {n!r} declares the unit {u!r}, which vehjax.data.UNITS does "
                f"not know, so a column cannot be checked against it; declare one of "
                f"{', '.join(sorted(UNITS))} or leave {n!r} out of the model's units=")
    return tuple(None if u is None else u.strip() for u in units)


def _keyword_units(model) -> bool:
    """Whether the model declares its units by a ``units=`` keyword (a :class:`Model`)."""
    own = getattr(model, "units", None)
    return isinstance(own, Mapping) or (isinstance(own, tuple) and all(
        isinstance(p, tuple) and len(p) == 2 for p in own))


def _declare_hint(target, column_unit) -> str:
    return (f", or, if the model's unit is not what you meant, declare it where the model is "
            f"built: Model(..., units={{{target!r}: {column_unit!r}}}) (a Model declares units "
            f"only for the names in units=; names left out are not checked)")


def _split_units(path, header) -> tuple[list, dict]:
    """Names and bracketed units of a header; ValueError for two columns of one name."""
    names, units = [], {}
    for i, h in enumerate(header):
        m = _HEADER.match(h)
        name = m["name"] if m else h.strip()
        if not name:
            raise ValueError(f"path: {str(path)!r}: column {i + 1} ({h!r}) has no name")
        if name in names:
            raise ValueError(f"path: {str(path)!r}: the header names {name!r} twice (columns "
                             f"{names.index(name) + 1} and {i + 1}: {header[names.index(name)]!r} "
                             f"and {h!r}); give every column its own name")
        if m:
            units[name] = m["unit"].strip()
        names.append(name)
    return names, units


def _separator_hint(table) -> str:
    """A hint when the header reads as one column holding another candidate separator."""
    if len(table.names) == 1:
        found = [d for d in ",;\t|" if d in table.names[0] and d != table.delimiter]
        if found:
            return (f" (the header reads as one column with separator {table.delimiter!r}; the "
                    f"file seems separated by {found[0]!r}: pass delimiter={found[0]!r})")
    return ""


def _check_csv_time(t, name, where) -> None:
    """Time stamps read from a file: every row has one, strictly increasing (naming lines)."""
    bad = np.flatnonzero(~np.isfinite(t))
    if bad.size:
        raise ValueError(f"{where(int(bad[0]))}: time column {name!r} has no time stamp "
                         f"({float(t[bad[0]])}); every data row needs one")
    down = np.flatnonzero(np.diff(t) <= 0.0)
    if down.size:
        k = int(down[0])
        raise ValueError(f"{where(k + 1)}: time stamps must be strictly increasing; "
                         f"{down.size} steps are not, the first {float(t[k])} -> {float(t[k + 1])} "
                         f"(data rows {k + 1} and {k + 2})")


def numeric_column(arg: str, name, value) -> np.ndarray:
    """``value`` as a float array; text cells read as :func:`vehjax.data.table.parse_cells`
    does (None is missing too); ValueError naming ``arg``, the column ``name`` and the row."""
    try:
        a = np.asarray(value)
    except (TypeError, ValueError):
        raise ValueError(f"{arg}: {name!r} is not a numeric column") from None
    if a.dtype.kind not in "USO":
        try:
            return np.asarray(a, dtype=float)
        except (TypeError, ValueError):
            raise ValueError(f"{arg}: {name!r} is not a numeric column (dtype {a.dtype})") from None
    if a.ndim != 1:
        raise ValueError(f"{arg}: {name!r} has shape {a.shape}, expected a 1-D column")
    out = np.empty(len(a))
    for k, v in enumerate(a.tolist()):
        if v is None or (isinstance(v, str) and is_missing(v)):
            out[k] = math.nan
            continue
        try:
            if not isinstance(v, (str, int, float, np.number)):
                raise TypeError
            out[k] = float(v)
        except (TypeError, ValueError):
            raise ValueError(f"{arg}: row {k + 1} (index {k}): not a number in column {name!r}: "
                             f"{v!r} (a missing sample is NaN, None, '', 'nan' or 'NA')") from None
    return out


def _check_name(arg, name) -> None:
    """A signal name: a non-empty string without surrounding spaces (a file's header keeps it)."""
    if not isinstance(name, str) or not name.strip() or name != name.strip():
        raise ValueError(f"{arg}: names must be non-empty strings without surrounding spaces "
                         f"(they become a file's column names), got {name!r}")


def _column(arg, name, value, n):
    try:
        a = np.array(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{arg}: {name!r} is not numeric") from None
    if a.shape != (n,):
        raise ValueError(f"{arg}: {name!r} has shape {a.shape}, expected ({n},) like t")
    if np.any(np.isinf(a)):
        k = int(np.flatnonzero(np.isinf(a))[0])
        raise ValueError(f"{arg}: {name!r} has infinite values, the first {float(a[k])} at row "
                         f"{k + 1} (index {k}) (use NaN for missing samples)")
    a.setflags(write=False)
    return a


def _intervals(intervals, names) -> dict:
    """``intervals`` checked: a mapping of signal or reference names to positive seconds."""
    if not isinstance(intervals, Mapping):
        raise ValueError(f"intervals: expected a mapping name -> seconds, got {intervals!r}")
    out = {}
    for k, v in intervals.items():
        if k not in names:
            raise ValueError(f"intervals: {k!r} is not a signal or reference of this drive")
        out[k] = _positive(f"intervals[{k!r}]", v)
    return out


def _one_column_each(names: dict) -> None:
    """ValueError naming ``names`` and the columns where two map onto one model name (one
    would be dropped silently)."""
    seen = {}
    for col, target in names.items():
        if target in seen:
            raise ValueError(f"names: columns {seen[target]!r} and {col!r} both map onto "
                             f"{target!r}; map one column onto each model input or output")
        seen[target] = col


def _names(arg, value, known):
    value = (value,) if isinstance(value, str) else tuple(value)
    unknown = [v for v in value if v not in known]
    if unknown:
        raise ValueError(f"{arg}: unknown name(s) {unknown}; expected some of {list(known)}")
    return value


def _positive(name, value) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        v = float("nan")
    if not math.isfinite(v) or v <= 0.0:
        raise ValueError(f"{name}: expected a positive number of seconds, got {value!r}")
    return v


def _within(name, value, lo, hi) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        v = float("nan")
    if not (math.isfinite(v) and lo <= v <= hi):
        raise ValueError(f"{name}: {value!r} s is outside the drive [{lo}, {hi}] s")
    return v
