"""ASAM MDF measurement files (MDF4 ``.mf4``, MDF3 ``.mdf``/``.dat``, as Vector CANape and
CANalyzer, ETAS INCA and dSPACE write them) read as a :class:`~vehjax.data.Drive` through
``asammdf`` (the optional extra: ``pip install "vehjax[mdf]"``).

Typical use::

    drive = read_mdf("run.mf4", {"delta": "SteeringWheelAngle", "vx": "VehicleSpeed",
                                 "r": "YawRate"}, reference=("beta_ins",))

Each channel is read with its own master (time) channel, so channel groups recorded at
different rates keep their own stamps; their physical values (the file's conversion applied)
and their unit from the file are converted to SI (:data:`vehjax.data.UNITS`). Samples the file
marks invalid (invalidation bits) are NaN at their stamps (asammdf's default would drop them).
How stamps that go back or repeat are handled, and how the rates meet on one time axis:
:mod:`vehjax.data.series`.

Limits: numeric scalar channels only (a text, byte-array or structure channel is refused);
a channel name found in several groups must be given as ``(name, group index)``; the time
stamps are the master channel's seconds, as stored (no start-time offset is added).
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

import numpy as np

from .drive import Drive
from .series import mapping, require, stamped, to_drive, unknown

__all__ = ["read_mdf"]


def read_mdf(path, channels: Mapping[str, str], *, reference=(), units=None) -> Drive:
    """A drive from an MDF4 or MDF3 file.

    Args:
        path: the ``.mf4`` / ``.mdf`` / ``.dat`` file.
        channels: vehjax signal name -> channel name in the file, or -> ``(channel name,
            group index)`` for a name that several channel groups hold.
        reference: names (of ``channels``) that go to :attr:`Drive.reference`.
        units: vehjax name -> unit, overriding the file's unit for that channel (a channel
            with no unit or one :data:`~vehjax.data.UNITS` does not know needs one).

    Raises:
        ImportError: asammdf is not installed.
        ValueError: an unreadable file, an unknown channel (listing the near names), a channel
            in several groups without its group, a non-numeric channel, a unit that cannot be
            converted (naming the channel and its unit), stamps that go back.
    """
    asammdf = require("asammdf", "mdf")
    channels = mapping("channels", channels, allow_tuple=True)
    units = dict(units or {})
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"path: {str(path)!r} is not a file")
    try:
        mdf = asammdf.MDF(str(path))
    except Exception as exc:                      # asammdf raises many kinds for a bad file
        raise ValueError(f"path: {str(path)!r} is not a readable MDF file ({exc})") from None
    try:
        series = {name: _channel(mdf, path, name, source, units)
                  for name, source in channels.items()}
    finally:
        mdf.close()
    return to_drive(series, reference, units, "channels")


def _channel(mdf, path, name, source, units):
    channel, group = (source, None) if isinstance(source, str) else source
    where = f"{str(path)!r}"
    found = mdf.channels_db.get(channel)
    if not found:
        raise unknown("channels", channel, mdf.channels_db, where)
    groups = sorted({g for g, _ in found})
    if group is None and len(groups) > 1:
        raise ValueError(f"channels: {channel!r} is in the channel groups {groups} of {where}; "
                         f"give {name!r}: ({channel!r}, group index)")
    if group is not None and group not in groups:
        raise ValueError(f"channels: {channel!r} is in the channel groups {groups} of {where}, "
                         f"not in group {group!r}")
    group = groups[0] if group is None else group
    index = next(i for g, i in found if g == group)
    try:
        sig = mdf.get(channel, group=group, index=index, ignore_invalidation_bits=True)
    except Exception as exc:
        raise ValueError(f"channels: {channel!r} (group {group}) of {where} cannot be read "
                         f"({exc}); is the file cut short?") from None
    samples = np.asarray(sig.samples)
    if samples.dtype.kind not in "biuf" or samples.ndim != 1:
        raise ValueError(f"channels: {channel!r} of {where} holds {samples.dtype} samples of "
                         f"shape {samples.shape[1:]}, not one number per time stamp")
    values = samples.astype(float)
    bits = getattr(sig, "invalidation_bits", None)
    if bits is not None:
        values[np.asarray(bits, dtype=bool)] = np.nan
    source = f"channel {channel!r} (group {group})"
    return stamped(name, source, sig.timestamps, values, sig.unit or "", units)
