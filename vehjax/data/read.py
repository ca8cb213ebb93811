"""One entry point for a drive file of any supported format: :func:`read_drive` picks the
reader by the file's suffix (or a ROS 2 bag folder by its ``metadata.yaml``).

==========================  ==========================================  ==================
file                        reader                                      optional extra
==========================  ==========================================  ==================
``.csv``, ``.txt``          :meth:`Drive.from_csv` (``time=``, ...)     none
``.mf4``, ``.mdf``, ``.dat``  :func:`~vehjax.data.mdf.read_mdf`         ``vehjax[mdf]``
``.db3``, ``.mcap``, a bag  :func:`~vehjax.data.rosbag.read_ros2`       ``vehjax[ros]``
``.asc``, ``.blf``,         :func:`~vehjax.data.canlog.read_can`        ``vehjax[can]``
``.log``, ``.trc``          (needs ``dbc=``)
==========================  ==========================================  ==================

``vehjax[logs]`` installs all three libraries.
"""

from __future__ import annotations

from pathlib import Path

from .canlog import read_can
from .drive import Drive
from .mdf import read_mdf
from .rosbag import read_ros2

__all__ = ["read_drive", "drive_format", "SUFFIXES"]

#: suffix -> the format read_drive reads it as.
SUFFIXES = {".csv": "csv", ".txt": "csv", ".mf4": "mdf", ".mdf": "mdf", ".dat": "mdf",
            ".db3": "ros2", ".mcap": "ros2", ".asc": "can", ".blf": "can", ".log": "can",
            ".trc": "can"}


def drive_format(path) -> str:
    """The format :func:`read_drive` reads ``path`` as: ``"csv"``, ``"mdf"``, ``"ros2"`` or
    ``"can"`` (:data:`SUFFIXES`; a folder holding ``metadata.yaml`` is a ROS 2 bag).

    Raises ValueError (naming ``path``) for a path that does not exist or a suffix of no known
    format, listing the known ones."""
    path = Path(path)
    if not path.exists():
        raise ValueError(f"path: {str(path)!r} does not exist")
    kind = "ros2" if path.is_dir() and (path / "metadata.yaml").is_file() else SUFFIXES.get(
        path.suffix.lower())
    if kind is None:
        what = "a folder without metadata.yaml (not a ROS 2 bag)" if path.is_dir() else (
            f"suffix {path.suffix!r}")
        raise ValueError(f"path: {str(path)!r}: {what}; read_drive reads "
                         f"{', '.join(sorted(SUFFIXES))} files and ROS 2 bag folders")
    return kind


def read_drive(path, **options) -> Drive:
    """A :class:`Drive` from ``path``, read by the reader of its format (module docstring).

    ``options`` go to that reader: for a CSV :meth:`Drive.from_csv`'s (``time=``, ``units=``,
    ``reference=``, ...); for MDF ``channels=`` (and ``reference=``, ``units=``); for a ROS 2
    bag ``fields=`` (and ``reference=``, ``stamps=``, ``units=``); for a CAN log ``dbc=`` and
    ``signals=`` (and ``reference=``, ``channel=``, ``units=``, ``reader_options=``).

    Raises ValueError for a path that does not exist or a suffix of no known format (listing
    them), and whatever the reader raises; TypeError for an option the reader does not take.
    """
    kind = drive_format(path)
    if kind == "csv":
        return Drive.from_csv(path, **options)
    if kind == "mdf":
        return read_mdf(path, **options)
    if kind == "ros2":
        return read_ros2(path, **options)
    if "dbc" not in options:
        raise ValueError(f"dbc: reading the CAN log {str(path)!r} needs dbc= (the DBC file "
                         f"that decodes its frames) and signals=")
    return read_can(path, **options)
