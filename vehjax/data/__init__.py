"""Recorded drives: :class:`Drive` holds your own (from arrays or from a CSV as spreadsheets,
loggers and pandas write it, read by module ``table``; with units, resampled onto a model's grid);
``load_comma2k19`` reads a comma2k19 segment (one ships with vehjax) into a :class:`Drive` on a
uniform time grid, with inputs and measurements for :class:`~vehjax.models.SingleTrackBank`,
checking that its accelerometer reads gravity after mounting; ``read_drive`` (module ``read``)
reads a drive file of any supported format: CSV, MDF4/MDF3 (``read_mdf``), ROS 2 bags and
MCAP (``read_ros2``), CAN logs with a DBC (``read_can``), each through an optional extra;
``prepare_drive`` (module ``prepare``) readies a drive's virtual yaw rate for filtering (bursts
gated, the rear rolling-radius scale removed)."""

from .canlog import read_can
from .comma2k19 import Comma2k19Drive, load_comma2k19
from .drive import UNITS, Drive
from .mdf import read_mdf
from .prepare import (gate_virtual_yaw, online_virtual_scale, pose_virtual_scale, prepare_drive,
                      remove_virtual_scale, virtual_yaw_scale)
from .read import read_drive
from .rosbag import read_ros2

__all__ = ["Drive", "UNITS", "Comma2k19Drive", "load_comma2k19", "prepare_drive",
           "gate_virtual_yaw", "virtual_yaw_scale", "online_virtual_scale", "pose_virtual_scale",
           "remove_virtual_scale", "read_drive", "read_mdf", "read_ros2", "read_can"]
