"""ROS 2 bags (sqlite3 ``.db3`` or MCAP ``.mcap`` storage, a bag folder with its
``metadata.yaml`` or the storage file itself) read as a :class:`~vehjax.data.Drive` through
``rosbags`` (the optional extra: ``pip install "vehjax[ros]"``).

Typical use::

    drive = read_ros2("drive_bag/", {"r": "/imu/data.angular_velocity.z",
                                     "ay": "/imu/data.linear_acceleration.y",
                                     "vx": "/vehicle/twist.twist.linear.x"})

A field is ``"/topic.path.to.field"``: the topic, then the attribute path into its message,
an integer picking an element of an array (``"/odom.pose.covariance.0"``). Any message type
works, a user's own too when the bag stores its definition (MCAP and ROS 2 Iron+ bags do).

Time stamps: ``stamps="header"`` (default) takes each message's ``header.stamp``, the time the
sensor sampled; a message without a header (``std_msgs/Float64``, ``geometry_msgs/Twist``)
takes its record time. ``stamps="record"`` takes the record time (when the bag wrote it) for
every message. Both are seconds as stored (for a live recording: since the Unix epoch,
resolution about 0.2 us at today's epoch in float64); no offset is removed.

Units follow REP 103 and are known for the common message types' fields: sensor_msgs/Imu
(``angular_velocity`` rad/s, ``linear_acceleration`` m/s^2, ``orientation`` quaternion -),
sensor_msgs/NavSatFix (``latitude``/``longitude`` deg, converted to rad; ``altitude`` m), and
wherever they appear inside a message: geometry_msgs Twist (``linear`` m/s, ``angular``
rad/s), Accel (m/s^2, rad/s^2), Point (m), Vector3 inside those, Quaternion (-), so
TwistStamped, TwistWithCovarianceStamped, nav_msgs/Odometry and PoseStamped are covered. Any
other field (``std_msgs/Float64.data``, a covariance, a user's message) needs its unit in
``units=``. How stamps that go back or repeat within a field are handled, and how the rates
meet on one time axis: :mod:`vehjax.data.series`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

import numpy as np

from .drive import Drive
from .series import mapping, require, stamped, to_drive, unknown

__all__ = ["read_ros2"]

#: message type -> its first field on the path -> unit (REP 103); see the module docstring.
FIELD_UNITS = {
    "sensor_msgs/msg/Imu": {"angular_velocity": "rad/s", "linear_acceleration": "m/s^2",
                            "orientation": "-"},
    "sensor_msgs/msg/NavSatFix": {"latitude": "deg", "longitude": "deg", "altitude": "m"},
    "geometry_msgs/msg/Twist": {"linear": "m/s", "angular": "rad/s"},
    "geometry_msgs/msg/Accel": {"linear": "m/s^2", "angular": "rad/s^2"},
    "geometry_msgs/msg/Point": {"x": "m", "y": "m", "z": "m"},
    "geometry_msgs/msg/Quaternion": {"x": "-", "y": "-", "z": "-", "w": "-"},
}


def read_ros2(path, fields: Mapping[str, str], *, reference=(), stamps: str = "header",
              units=None) -> Drive:
    """A drive from a ROS 2 bag (see the module docstring for the field syntax and units).

    Args:
        path: a bag folder (holding ``metadata.yaml``), or a ``.db3`` / ``.mcap`` file.
        fields: vehjax signal name -> ``"/topic.path.to.field"``.
        reference: names (of ``fields``) that go to :attr:`Drive.reference`.
        stamps: ``"header"`` (the messages' ``header.stamp``; the record time for a message
            without a header) or ``"record"`` (the record time).
        units: vehjax name -> unit of that field, for fields of no known unit or to override.

    Raises:
        ImportError: rosbags is not installed.
        ValueError: an unreadable bag, an unknown topic or field (listing the near ones), a
            topic without messages, a message that cannot be decoded (naming the topic and its
            record time), a field of no known unit, stamps that go back.
    """
    highlevel = require("rosbags.highlevel", "ros")
    typesys = require("rosbags.typesys", "ros")
    fields = mapping("fields", fields)
    if stamps not in ("header", "record"):
        raise ValueError(f"stamps: expected 'header' or 'record', got {stamps!r}")
    units = dict(units or {})
    path = Path(path)
    if not path.exists():
        raise ValueError(f"path: {str(path)!r} does not exist")
    wanted = {name: _split(name, spec) for name, spec in fields.items()}
    store = typesys.get_typestore(typesys.Stores.ROS2_HUMBLE)
    try:
        reader = highlevel.AnyReader([path], default_typestore=store)
        reader.open()
    except Exception as exc:                      # rosbags raises its own kinds
        raise ValueError(f"path: {str(path)!r} is not a readable ROS 2 bag ({exc})") from None
    try:
        samples = _read(reader, path, wanted, stamps)
    finally:
        reader.close()
    hint = " (header stamps; stamps='record' reads the record times)"
    series = {name: stamped(name, f"field {fields[name]!r}", t, v, unit, units,
                            clock=hint if header else "")
              for name, (t, v, unit, header) in samples.items()}
    return to_drive(series, reference, units, "fields")


def _split(name, spec):
    topic, dot, field = spec.partition(".")
    if not topic.startswith("/") or not dot or not field or "" in field.split("."):
        raise ValueError(f"fields: {name!r}: {spec!r} is not '/topic.path.to.field' (e.g. "
                         f"'/imu/data.angular_velocity.z')")
    return topic, tuple(field.split("."))


def _read(reader, path, wanted, stamps):
    """name -> (t [s], values, unit from FIELD_UNITS or '', whether the stamps are header
    stamps) from one pass over the bag."""
    topics = {c.topic for c in reader.connections}
    for name, (topic, _) in wanted.items():
        if topic not in topics:
            raise unknown("fields", topic, topics, f"the bag {str(path)!r} (topics)")
    conns = [c for c in reader.connections if c.topic in {t for t, _ in wanted.values()}]
    got = {name: ([], []) for name in wanted}
    unit, header = {}, {}
    for conn, record, raw in _messages(reader, conns, path):
        try:
            msg = reader.deserialize(raw, conn.msgtype)
        except Exception as exc:
            raise ValueError(f"fields: a message on {conn.topic!r} recorded at {record} ns "
                             f"cannot be decoded as {conn.msgtype} ({exc}); is its definition "
                             f"missing from the bag, or the bag cut short?") from None
        t, from_header = _stamp(msg, record, stamps)
        for name, (topic, field) in wanted.items():
            if topic != conn.topic:
                continue
            value, found = _field(name, msg, field, conn)
            unit.setdefault(name, found)
            header[name] = from_header
            got[name][0].append(t)
            got[name][1].append(value)
    for name, (topic, _) in wanted.items():
        if not got[name][0]:
            raise ValueError(f"fields: the topic {topic!r} of {name!r} has no messages in "
                             f"{str(path)!r}")
    return {name: (np.array(ts), np.array(vs, dtype=float), unit[name], header[name])
            for name, (ts, vs) in got.items()}


def _messages(reader, conns, path):
    """The bag's (connection, record time [ns], raw message) of ``conns``; a storage error
    (a file cut short, a corrupt chunk) as a ValueError naming the bag."""
    try:
        yield from reader.messages(connections=conns)
    except Exception as exc:                      # rosbags raises its own kinds
        raise ValueError(f"path: {str(path)!r}: the bag cannot be read to its end ({exc}); is "
                         f"it cut short?") from None


def _stamp(msg, record, stamps) -> tuple:
    """(the message's time [s], whether it is its header stamp)."""
    header = getattr(msg, "header", None)
    if stamps == "header" and header is not None and hasattr(header, "stamp"):
        return (int(header.stamp.sec) * 10**9 + int(header.stamp.nanosec)) / 1e9, True
    return int(record) / 1e9, False


def _field(name, msg, field, conn):
    """(the number at ``field`` of ``msg``, its unit by FIELD_UNITS or '')."""
    value, unit = msg, ""
    for k, part in enumerate(field):
        rules = FIELD_UNITS.get(getattr(value, "__msgtype__", None), {})
        unit = rules.get(part, unit)
        where = ".".join(field[:k]) or "the message"
        if part.lstrip("-").isdigit() and isinstance(value, (np.ndarray, list, tuple)):
            i = int(part)
            if not -len(value) <= i < len(value):
                raise ValueError(f"fields: {name!r}: {where} of {conn.topic!r} has "
                                 f"{len(value)} elements; {i} is out of range")
            value = value[i]
            continue
        if not hasattr(value, "__dataclass_fields__") or part not in value.__dataclass_fields__:
            names = _names(value)
            raise unknown("fields", part, names, f"{where} of {conn.topic!r} "
                          f"({getattr(value, '__msgtype__', type(value).__name__)})")
        value = getattr(value, part)
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.number)):
        sub = _names(value)
        raise ValueError(f"fields: {name!r}: {'.'.join(field)} of {conn.topic!r} is "
                         f"{getattr(value, '__msgtype__', type(value).__name__)}, not a number"
                         + (f"; pick one of its fields {sub}" if sub else ""))
    return float(value), unit


def _names(value) -> list:
    return [n for n in getattr(value, "__dataclass_fields__", ()) if not n.startswith("__")]
