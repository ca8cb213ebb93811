"""CAN logs (Vector ASC and BLF, candump ``.log``, PEAK TRC) decoded by a DBC into a
:class:`~vehjax.data.Drive`: frames read by ``python-can``'s log readers, decoded by
``cantools`` (the optional extra: ``pip install "vehjax[can]"``).

Typical use::

    drive = read_can("drive.blf", "car.dbc", {"vx": "ESP_Status.VehicleSpeed",
                                              "delta": "SAS_Data.SteeringAngle"})

A signal is ``"MESSAGE.SIGNAL"`` as the DBC names them; its value is the physical one (the
DBC's scale and offset applied) in the DBC's unit, converted to SI (:data:`vehjax.data.UNITS`;
a signal with no unit in the DBC, or one vehjax does not know, needs ``units=``). A signal of a
multiplexed message has a sample only in the frames whose multiplexer selects it. Error and
remote frames are skipped. Each signal keeps the stamps of its frames; how stamps that go back
or repeat are handled and how the rates meet on one time axis: :mod:`vehjax.data.series`.

Time stamps are what python-can's reader gives: BLF, candump and TRC absolute (seconds since
the epoch for a live recording), ASC relative to the measurement start unless
``relative_timestamp=False`` is passed through ``reader_options``. Limits: a frame shorter than
its DBC message (a log's last line written partly) is refused, naming the message and its time
stamp; python-can's BLF reader stops at the last whole object of a file cut short, so frames in
a cut container are not seen; the message must be found by its frame id and id kind (standard
or extended) as the DBC gives them.
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

import numpy as np

from .drive import Drive
from .series import mapping, require, stamped, to_drive, unknown

__all__ = ["read_can"]


def read_can(path, dbc, signals: Mapping[str, str], *, reference=(), channel=None, units=None,
             reader_options: Mapping | None = None) -> Drive:
    """A drive from a CAN log and a DBC (see the module docstring).

    Args:
        path: the log: ``.asc``, ``.blf``, ``.log`` (candump -l), ``.trc``.
        dbc: the DBC file (or any database cantools loads), or a ``cantools`` Database.
        signals: vehjax signal name -> ``"MESSAGE.SIGNAL"``.
        reference: names (of ``signals``) that go to :attr:`Drive.reference`.
        channel: read only the frames of this channel (as python-can's reader names it, e.g.
            0, 1 or ``"can0"``); None reads all, refusing a message seen on several channels.
        units: vehjax name -> unit, for signals the DBC gives no known unit or to override.
        reader_options: keyword arguments for python-can's reader (e.g. ASC's
            ``relative_timestamp=False``).

    Raises:
        ImportError: cantools or python-can is not installed.
        ValueError: an unreadable log or DBC, an unknown message or signal (listing the near
            names), a message on several channels, a frame shorter than its message, a unit
            that cannot be converted, stamps that go back.
    """
    cantools = require("cantools", "can")
    can = require("can", "can")
    signals = mapping("signals", signals)
    units = dict(units or {})
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"path: {str(path)!r} is not a file")
    db = _database(cantools, dbc)
    wanted = {name: _signal(db, name, spec) for name, spec in signals.items()}
    frames = _frames(can, path, dict(reader_options or {}))
    samples = _decode(frames, wanted, channel, path)
    series = {name: stamped(name, f"signal {signals[name]!r}", t, v, wanted[name][1].unit or "",
                            units) for name, (t, v) in samples.items()}
    return to_drive(series, reference, units, "signals")


def _frames(can, path, options):
    """(index, frame, whether it is the log's last) from python-can's reader, one at a time;
    a reader's error as a ValueError naming the file."""
    try:
        with can.LogReader(str(path), **options) as reader:
            frames = iter(reader)
            frame, k = next(frames, None), 0
            while frame is not None:
                after = next(frames, None)
                yield k, frame, after is None
                frame, k = after, k + 1
    except Exception as exc:                       # python-can raises many kinds
        raise ValueError(f"path: {str(path)!r} is not a readable CAN log ({exc})") from None


def _database(cantools, dbc):
    if isinstance(dbc, cantools.database.can.Database):
        return dbc
    if not isinstance(dbc, (str, Path)) or not Path(dbc).is_file():
        raise ValueError(f"dbc: expected a DBC file or a cantools Database, got {dbc!r}")
    try:
        return cantools.database.load_file(str(dbc))
    except Exception as exc:
        raise ValueError(f"dbc: {str(dbc)!r} cannot be loaded ({exc})") from None


def _signal(db, name, spec):
    message, dot, signal = spec.partition(".")
    if not dot or not message or not signal:
        raise ValueError(f"signals: {name!r}: {spec!r} is not 'MESSAGE.SIGNAL'")
    by_name = {m.name: m for m in db.messages}
    if message not in by_name:
        raise unknown("signals", message, by_name, "the DBC (messages)")
    msg = by_name[message]
    sigs = {s.name: s for s in msg.signals}
    if signal not in sigs:
        raise unknown("signals", signal, sigs, f"the DBC's message {message!r} (signals)")
    return msg, sigs[signal]


def _decode(frames, wanted, channel, path):
    """name -> (t [s], physical values) from one pass over ``frames`` (from :func:`_frames`)."""
    by_id = {}
    for name, (msg, sig) in wanted.items():
        by_id.setdefault((msg.frame_id, bool(msg.is_extended_frame)), (msg, []))[1].append(
            (name, sig.name))
    got = {name: ([], []) for name in wanted}
    seen, kind = {}, {}
    for k, f, last in frames:
        if f.is_error_frame or f.is_remote_frame or (channel is not None and f.channel != channel):
            continue
        hit = by_id.get((f.arbitration_id, bool(f.is_extended_id)))
        if hit is None:
            other = by_id.get((f.arbitration_id, not f.is_extended_id))
            if other is not None:
                kind[other[0].name] = "extended" if f.is_extended_id else "standard"
            continue
        msg, names = hit
        seen.setdefault(msg.name, set()).add(f.channel)
        data = bytes(f.data)
        if len(data) < msg.length:
            raise ValueError(f"path: {str(path)!r}: frame {k} ({msg.name!r} at t = {f.timestamp!r}"
                             f" s) has {len(data)} data bytes, the DBC's message {msg.length}"
                             + (" (the log's last frame: written partly?)" if last else ""))
        try:
            values = msg.decode(data, decode_choices=False, scaling=True)
        except Exception as exc:
            raise ValueError(f"path: {str(path)!r}: frame {k} ({msg.name!r} at t = "
                             f"{f.timestamp!r} s) cannot be decoded ({exc})") from None
        for name, sig in names:
            if sig in values:
                got[name][0].append(f.timestamp)
                got[name][1].append(float(values[sig]))
    _check_found(got, seen, kind, wanted, channel, path)
    return {name: (np.array(t, dtype=float), np.array(v, dtype=float))
            for name, (t, v) in got.items()}


def _check_found(got, seen, kind, wanted, channel, path):
    """Every signal found, every message on one channel; ValueError naming them otherwise."""
    for msg_name, chans in seen.items():
        if len(chans) > 1:
            raise ValueError(f"channel: the message {msg_name!r} is on channels "
                             f"{sorted(chans, key=str)} of {str(path)!r}; pick one with channel=")
    for name, (msg, sig) in wanted.items():
        if not got[name][0]:
            other = (f" (frames of its id {msg.frame_id:#x} are there with a {kind[msg.name]} "
                     f"id, the DBC's is not)" if msg.name in kind else "")
            raise ValueError(f"signals: no frame of {msg.name!r} carries {sig.name!r} in "
                             f"{str(path)!r}" + ("" if channel is None else
                                                 f" on channel {channel!r}") + other)
