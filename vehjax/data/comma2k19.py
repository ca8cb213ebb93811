"""Recorded drives in the comma2k19 layout, resampled for :class:`~vehjax.models.SingleTrackBank`.

``load_comma2k19(folder=None)`` reads one comma2k19 segment folder (``None``: the 60 s Toyota
RAV4 highway segment shipped in ``vehjax/data/comma2k19_rav4``, MIT licence, see its
PROVENANCE.md) and returns a :class:`Drive`: every signal linearly interpolated onto one uniform
time grid, the phone IMU rotated into the car's frame, and pose-derived references for
validation. Files are NumPy arrays without extension: ``<signal>/t`` (seconds on the device's
boot clock) and ``<signal>/value``. Needed files::

    processed_log/CAN/speed/{t,value}            m/s, (N,) or (N, 1)
    processed_log/CAN/steering_angle/{t,value}   steering-wheel angle, deg, (N,)
    processed_log/CAN/wheel_speed/{t,value}      [FL, FR, RL, RR], m/s, (N, 4)
    processed_log/IMU/gyro/{t,value}             device frame [forward, right, down], rad/s, (N, 3)
    processed_log/IMU/accelerometer/{t,value}    device frame, specific force, m/s^2, (N, 3)
    global_pose/frame_times                      s, (M,)
    global_pose/frame_orientations               quaternions (w, x, y, z), (M, 4)
    global_pose/frame_positions                  ECEF, m, (M, 3)
    global_pose/frame_velocities                 ECEF, m/s, (M, 3)

Frames and conventions
----------------------
* Device frame D = [forward, right, down] (comma2k19 README), the frame of the IMU *and* of the
  pose (the pose is that of the device's camera).
* Vehicle frame V = x forward, y left, z up (ISO 8855, as in ``vehjax.models``).
* Pose quaternion: **w first**, Hamilton, and the rotation matrix it gives maps device vectors to
  ECEF (``v_ecef = R(q) v_device``; openpilot's ``rot_from_quat`` is ``ecef_from_local``). Of the
  four readings (w first or last, matrix or its transpose) only this one puts the shipped
  segment's velocity along the device's forward axis and the local up along -down; the pose's
  body rates then match the gyro, with no time shift.
* Local vertical: WGS84 geodetic up at the pose's ECEF position.

IMU mounting (``Drive.mount``)
------------------------------
The device is not aligned with the car. Its attitude in V is ``R_VF = Rz(yaw) Ry(pitch)
Rx(roll)`` applied to the device's axes turned to forward-left-up (``F = diag(1, -1, -1)``), so a
device vector goes to V as ``R_VF F v_D``. Estimated from the pose (unless ``mount`` is given):
the car's x axis is the direction of the summed pose velocity in D (frames faster than 1 m/s;
yaw and pitch), its z axis the pose's local vertical in D made orthogonal to x (roll, assuming
the car's mean roll over the segment is zero: the mean road cross-fall ends up in it). The roll
is taken from the pose, not from gravity, so that an accelerometer offset stays visible in
``ay`` for a filter to learn. Found on the shipped segment: roll = +1.25 deg, pitch = +3.77 deg,
yaw = +0.90 deg.

Either way the loader checks the result against gravity: the accelerometer's mean specific force
over the file must read 9.81 m/s^2 in size and on the car's up axis (``GRAVITY``,
``GRAVITY_TOLERANCE`` = 1.5 m/s^2); a ``mount`` given in degrees where radians are due, or an
accelerometer in g, is refused saying so.

References (``Drive.reference``, for validation only): from ``global_pose``, the yaw rate about
the local vertical (relative to ECEF: Earth's rotation is not in it but is in the gyro), the
camera's velocity in V, the speed and the car's roll relative to the local level frame (> 0 left
side up, the sign of the model's bank angle phi). ``processed_log/IMU/gyro_bias`` is not read:
it is Android's bias of the uncalibrated gyro, already subtracted from ``gyro``.

Vehicle figures used by default (openpilot's values for this car, per PROVENANCE.md): steer ratio
16.88; rear track 1.61 m (a plausible RAV4 value, not in the log).

See docs/comma2k19.md for the checks behind each convention on the shipped segment (the four
quaternion readings, the rate correlations and lags), the mount's derivation and the gravity-
based alternative, the references' spread, the gyro_bias investigation and the track regression.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping

import numpy as np

from .. import validation
from ..models.bank import SingleTrackBank, virtual_yaw_rate
from .drive import Drive, check_time

__all__ = ["Comma2k19Drive", "load_comma2k19"]

_PACKAGED = Path(__file__).resolve().parent / "comma2k19_rav4"

#: device [forward, right, down] -> device [forward, left, up]
_F = np.diag([1.0, -1.0, -1.0])

_WGS84_A = 6378137.0
_WGS84_F = 1.0 / 298.257223563
_WGS84_E2 = _WGS84_F * (2.0 - _WGS84_F)

#: pose frames slower than this are left out of the mount estimate [m/s]
_MIN_SPEED = 1.0

#: gravity [m/s^2] and the tolerance [m/s^2] within which the accelerometer's mean specific force
#: over the whole file must read it, in size and on the car's up axis after mounting (+g: z up).
#: 1.5 m/s^2 admits a mean tilt of the car (grade, cross-fall, mounting error) up to ~30 deg
#: and a mean acceleration up to ~1.5 m/s^2; a mount given in degrees as radians, an upside-down
#: mount or an accelerometer in g fails it.
GRAVITY = 9.81
GRAVITY_TOLERANCE = 1.5

_UNITS = {
    "speed_can": "m/s",
    "steering_wheel_angle": "rad",
    "wheel_speed_fl": "m/s",
    "wheel_speed_fr": "m/s",
    "wheel_speed_rl": "m/s",
    "wheel_speed_rr": "m/s",
    "gyro_x": "rad/s",
    "gyro_y": "rad/s",
    "gyro_z": "rad/s",
    "accel_x": "m/s^2",
    "accel_y": "m/s^2",
    "accel_z": "m/s^2",
    # references
    "yaw_rate": "rad/s",
    "vx": "m/s",
    "vy": "m/s",
    "vz": "m/s",
    "speed": "m/s",
    "roll": "rad",
}


@dataclass(frozen=True, eq=False, kw_only=True)
class Comma2k19Drive(Drive):
    """One recorded drive on a uniform time grid (returned by :func:`load_comma2k19`).

    A :class:`~vehjax.data.Drive` with the segment's IMU mount and pose offset; its raw signals
    keep their comma2k19 names, and :meth:`to_drive` gives a plain Drive with model-named
    columns (``delta``, ``vx``, ``ay``, ``r``, ...) for :meth:`~vehjax.data.Drive.for_model`.

    Frozen; its arrays are read-only (treat the dicts as read-only too).

    Attributes:
        t: (T,) grid times [s] on the recording's own clock (the device boot time of its ``t``
            files), strictly increasing with step ``dt``, inside every used signal's time span.
        dt: grid step [s] (1 / rate).
        signals: name -> (T,) array, every one linearly interpolated from its own time stamps
            onto ``t`` (all are continuous signals; CAN ~83 Hz, IMU ~104 Hz):

            * ``speed_can`` [m/s]: the CAN vehicle speed;
            * ``steering_wheel_angle`` [rad]: steering-WHEEL angle (the file's degrees converted),
              > 0 steers left (checked: it correlates +0.78 with the pose yaw rate, +0.87
              with 1 s averages);
            * ``wheel_speed_fl``, ``_fr``, ``_rl``, ``_rr`` [m/s]: wheel speeds (linear,
              0.01 km/h resolution);
            * ``gyro_x``, ``gyro_y``, ``gyro_z`` [rad/s]: angular rate in the vehicle frame (x
              forward, y left, z up): roll rate, pitch rate, yaw rate;
            * ``accel_x``, ``accel_y``, ``accel_z`` [m/s^2]: specific force (acceleration minus
              gravity, so about +9.8 on z at rest) in the vehicle frame.
        reference: name -> (T,) array, derived from the pose (20 Hz) and interpolated likewise;
            for validation only: ``yaw_rate`` [rad/s] about the local vertical, ``vx``, ``vy``,
            ``vz`` [m/s] the camera's velocity in the vehicle frame, ``speed`` [m/s] its norm,
            ``roll`` [rad] the car's roll relative to the local level frame (> 0 left side up).
        units: name -> unit string, for every key of ``signals`` and ``reference``.
        mount: ``roll``, ``pitch``, ``yaw`` [rad] of the IMU/device relative to the car (ZYX,
            see the module docstring; shipped segment: +1.25, +3.77, +0.90 deg).
        gyro_offset_vs_reference: mean over the grid of ``gyro_z - reference["yaw_rate"]``
            [rad/s] (shipped segment: +5.8e-4 rad/s = +0.033 deg/s).
        folder: the folder read.
    """

    t: np.ndarray
    dt: float
    signals: Mapping[str, np.ndarray]
    reference: Mapping[str, np.ndarray]
    units: Mapping[str, str]
    mount: Mapping[str, float]
    gyro_offset_vs_reference: float
    folder: str

    def inputs(self, model, steer_ratio: float = 16.88) -> np.ndarray:
        """Model inputs on the grid, (T, nu) = (T, 2) for SingleTrackBank: (vx [m/s], delta [rad]).

        ``vx`` is the mean of the rear wheel speeds: the rear wheels are not steered and carry
        little or no drive torque (the RAV4 is front-driven, or with AWD mostly so), so they
        roll at the car's longitudinal speed at the rear axle, which is vx anywhere on the
        centre line; they are also the sensors of eq. 10's ``r_virt``, and the paper takes vx
        from the wheel speeds. The CAN speed would do as well (on the shipped segment the rear
        mean is 0.10 % below it and 0.95 % below the pose speed). ``delta`` is the
        steering-wheel angle divided by ``steer_ratio`` (default 16.88, this car's), > 0 steers
        left. The model needs vx > 0: cut standstill out with ``start``/``stop``.
        """
        self._check_model(model)
        steer_ratio = _positive("steer_ratio", steer_ratio)
        s = self.signals
        vx = 0.5 * (s["wheel_speed_rl"] + s["wheel_speed_rr"])
        delta = s["steering_wheel_angle"] / steer_ratio
        return np.stack([vx, delta], axis=1)

    def measurements(self, model, track: float = 1.61) -> np.ndarray:
        """Measurements on the grid in the model's output order, (T, ny) = (T, 5).

        For SingleTrackBank: ``ay`` = ``accel_y`` [m/s^2] and ``r`` = ``gyro_z`` [rad/s] and
        ``roll_rate`` = ``gyro_x`` [rad/s] (IMU in the vehicle frame, not bias corrected),
        ``phi`` = NaN (the log has no bank-angle sensor), ``r_virt`` [rad/s] =
        :func:`~vehjax.models.virtual_yaw_rate` of the rear wheel speeds (linear speeds, so
        the wheel radius is 1) with ``track`` the rear track width [m] (default 1.61, a RAV4
        value; the data's own regression gives 1.56 to 1.64). Its sign matches the gyro's:
        correlation with the pose yaw rate +0.76 with 0.5 s and +0.84 with 1 s averages (0.36
        at 0.1 s: the 0.01 km/h wheel-speed resolution is 0.1 deg/s of r_virt). It carries a
        -0.24 deg/s offset on the shipped segment (rear rolling radii differing by ~0.04 %).
        """
        self._check_model(model)
        track = _positive("track", track)
        s = self.signals
        r_virt = np.asarray(virtual_yaw_rate(s["wheel_speed_rl"], s["wheel_speed_rr"], 1.0, track))
        nan = np.full_like(self.t, np.nan)
        return np.stack([s["accel_y"], s["gyro_z"], s["gyro_x"], nan, r_virt], axis=1)

    def _check_model(self, model) -> None:
        if not isinstance(model, SingleTrackBank):
            raise ValueError(
                f"model: expected a SingleTrackBank (the only model this drive's signals map "
                f"onto), got {type(model).__name__}")
        if abs(float(model.dt) - self.dt) > 1e-9 * self.dt:
            raise ValueError(
                f"model: its dt = {model.dt} s differs from the drive's grid step {self.dt} s; "
                f"build it with dt=drive.dt or load with rate=1/model.dt")

    def to_drive(self, steer_ratio: float = 16.88, track: float = 1.61) -> Drive:
        """A plain :class:`~vehjax.data.Drive` with the raw signals, model-named columns and the
        references prefixed ``ref_`` (``ref_vy``, ``ref_yaw_rate``, ...: the pose's).

        Model-named columns (for SingleTrack, SingleTrackBank and your own models):
        ``delta`` [rad] = steering-wheel angle / ``steer_ratio``, ``vx`` [m/s] = mean rear wheel
        speed (see :meth:`inputs`), ``ay`` [m/s^2] = ``accel_y``, ``r`` [rad/s] = ``gyro_z``,
        ``roll_rate`` [rad/s] = ``gyro_x``, ``r_virt`` [rad/s] as in :meth:`measurements`.
        """
        steer_ratio, track = _positive("steer_ratio", steer_ratio), _positive("track", track)
        s = self.signals
        derived = {
            "delta": s["steering_wheel_angle"] / steer_ratio,
            "vx": 0.5 * (s["wheel_speed_rl"] + s["wheel_speed_rr"]),
            "ay": s["accel_y"], "r": s["gyro_z"], "roll_rate": s["gyro_x"],
            "r_virt": np.asarray(virtual_yaw_rate(s["wheel_speed_rl"], s["wheel_speed_rr"], 1.0,
                                                  track)),
        }
        units = {"delta": "rad", "vx": "m/s", "ay": "m/s^2", "r": "rad/s", "roll_rate": "rad/s",
                 "r_virt": "rad/s"}
        units.update({k: self.units[k] for k in s})
        units.update({"ref_" + k: self.units[k] for k in self.reference})
        return Drive(t=self.t, signals={**s, **derived}, units=units, dt=self.dt,
                     reference={"ref_" + k: v for k, v in self.reference.items()})

    def __repr__(self) -> str:
        return (f"Comma2k19Drive({len(self.t)} samples, t = {self.t[0]:.3f}..{self.t[-1]:.3f} s, "
                f"dt = {self.dt} s, folder = {self.folder!r})")


def load_comma2k19(folder=None, rate: float = 100.0, *, start=None, stop=None,
                   mount=None) -> Comma2k19Drive:
    """Load a comma2k19 segment folder onto a uniform grid (see the module docstring).

    Args:
        folder: the segment folder (holding ``processed_log/`` and ``global_pose/``); None for
            the RAV4 segment shipped with vehjax.
        rate: grid rate [Hz], > 0 (default 100, the SingleTrackBank default dt of 0.01 s).
        start, stop: first and last grid time [s] on the recording's clock; default the span
            where every needed signal (CAN speed, steering, wheel speeds, gyro, accelerometer,
            pose and the pose's finite-difference yaw rate) exists. Both must lie inside it: the
            loader never extrapolates.
        mount: the IMU's (roll, pitch, yaw) [rad] relative to the car, a 3-sequence or a
            mapping like ``Drive.mount``; None estimates it from the pose. In radians: angles
            in degrees go through ``numpy.radians`` first.

    Raises:
        ValueError: a missing folder or file, an unreadable or misshaped array, non-finite or
            non-increasing time stamps (naming the file); a non-positive ``rate``; ``start`` /
            ``stop`` outside the recording; a bad ``mount``; an accelerometer that does not
            read gravity: the mean specific force over the file must be :data:`GRAVITY` to
            :data:`GRAVITY_TOLERANCE` in size (else naming the file) and, after mounting, on
            the car's up axis with the sign of z up (else naming ``mount`` and the gravity
            found, and saying when the angles converted from degrees would pass).
    """
    rate = _positive("rate", rate)
    dt = 1.0 / rate
    if folder is None:
        folder = _PACKAGED
    folder = Path(folder)
    if not folder.is_dir():
        raise ValueError(f"folder: {str(folder)!r} is not a directory")

    series = {
        "speed": _load_series(folder, "processed_log/CAN/speed", 1),
        "steer": _load_series(folder, "processed_log/CAN/steering_angle", 1),
        "wheels": _load_series(folder, "processed_log/CAN/wheel_speed", 4),
        "gyro": _load_series(folder, "processed_log/IMU/gyro", 3),
        "accel": _load_series(folder, "processed_log/IMU/accelerometer", 3),
    }
    tp = _load_times(folder, "global_pose/frame_times")
    pose = _pose(folder, tp, mount)
    _check_gravity(folder, series["accel"][1], pose["v_from_d"], mount)
    t = _grid(series, tp, pose["tm"], start, stop, dt, rate, folder)
    signals = _signals(t, series, pose["v_from_d"])
    reference = _references(t, tp, pose)
    for a in (t, *signals.values(), *reference.values()):
        a.setflags(write=False)
    offset = float(np.mean(signals["gyro_z"] - reference["yaw_rate"]))
    roll, pitch, yaw = pose["mount"]
    return Comma2k19Drive(
        t=t, dt=dt,
        signals=signals,
        reference=reference,
        units=dict(_UNITS),
        mount={"roll": roll, "pitch": pitch, "yaw": yaw},
        gyro_offset_vs_reference=offset,
        folder=str(folder),
    )


# -- the pose, the grid, resampling ---------------------------------------------------------------
def _pose(folder: Path, tp: np.ndarray, mount) -> dict:
    """The pose's rotations, local level and body rates: the IMU mount (estimated or given), the
    yaw rate about the local vertical (at the frames' midpoints ``tm``), the velocity in the
    car frame and the roll, on the pose's own time stamps ``tp``."""
    quat = _load_values(folder, "global_pose/frame_orientations", len(tp), 4)
    pos = _load_values(folder, "global_pose/frame_positions", len(tp), 3)
    vel = _load_values(folder, "global_pose/frame_velocities", len(tp), 3)
    norm = np.linalg.norm(quat, axis=1)
    if not np.all(np.isfinite(norm)) or np.any(norm < 1e-6):
        raise ValueError(f"{folder / 'global_pose/frame_orientations'}: zero or non-finite "
                         f"quaternions")
    r_ed = _rot_from_quat(quat / norm[:, None])          # ECEF <- device FRD, (M, 3, 3)
    enu = _enu_basis(pos)                                # (M, 3, 3), columns east, north, up
    up = enu[:, :, 2]
    v_dev = np.einsum("mji,mj->mi", r_ed, vel)           # R^T v: velocity in device FRD

    if mount is None:
        r_vf = _estimate_mount(v_dev, np.einsum("mji,mj->mi", r_ed, up), folder)
    else:
        r_vf = _mount_matrix(mount)

    # body rate between frames k and k+1 in device FRD; the same vector in ECEF is R_k w
    d_r = np.einsum("mji,mjk->mik", r_ed[:-1], r_ed[1:])
    w_dev = _log_so3(d_r) / np.diff(tp)[:, None]
    w_ecef = np.einsum("mij,mj->mi", r_ed[:-1], w_dev)
    up_mid = up[:-1] + up[1:]
    up_mid /= np.linalg.norm(up_mid, axis=1, keepdims=True)

    r_ev = np.einsum("mij,kj->mik", r_ed @ _F, r_vf)     # ECEF <- vehicle: R_ED F R_VF^T
    r_nv = np.einsum("mji,mjk->mik", enu, r_ev)          # ENU <- vehicle
    return dict(mount=_euler_zyx(r_vf), v_from_d=r_vf @ _F,   # vehicle <- device FRD
                yaw_rate=np.sum(w_ecef * up_mid, axis=1), tm=0.5 * (tp[:-1] + tp[1:]),
                v_veh=np.einsum("mji,mj->mi", r_ev, vel), speed=np.linalg.norm(vel, axis=1),
                roll=np.arctan2(r_nv[:, 2, 1], r_nv[:, 2, 2]))


def _grid(series, tp, tm, start, stop, dt, rate, folder) -> np.ndarray:
    """The uniform time grid over the span where every signal exists (or [start, stop])."""
    spans = [(s[0][0], s[0][-1]) for s in series.values()] + [(tp[0], tp[-1]), (tm[0], tm[-1])]
    lo = max(a for a, _ in spans)
    hi = min(b for _, b in spans)
    if not lo < hi:
        raise ValueError(f"folder: {str(folder)!r}: the signals' time spans do not overlap")
    t0 = lo if start is None else _time_arg("start", start, lo, hi)
    t1 = hi if stop is None else _time_arg("stop", stop, lo, hi)
    if not t1 > t0:
        raise ValueError(f"stop: {t1} s is not after start = {t0} s")
    n = int(math.floor((t1 - t0) / dt + 1e-9)) + 1
    t = t0 + dt * np.arange(n)
    if t[-1] > hi:                                        # rounding at the end
        t = t[:-1]
    if len(t) < 2:
        raise ValueError(f"rate: {rate} Hz gives fewer than 2 samples between {t0} and {t1} s")
    return t


def _signals(t, series, v_from_d) -> dict:
    """The CAN and IMU signals on the grid, the IMU rotated into the car frame."""
    def interp(ts, y):
        return np.interp(t, ts, y)

    ts, sp = series["speed"]
    tst, st = series["steer"]
    tw, wheels = series["wheels"]
    tg, gyro = series["gyro"]
    ta, acc = series["accel"]
    gyro_v = np.stack([interp(tg, gyro[:, k]) for k in range(3)], axis=1) @ v_from_d.T
    acc_v = np.stack([interp(ta, acc[:, k]) for k in range(3)], axis=1) @ v_from_d.T
    return {
        "speed_can": interp(ts, sp[:, 0]),
        "steering_wheel_angle": np.radians(interp(tst, st[:, 0])),
        "wheel_speed_fl": interp(tw, wheels[:, 0]),
        "wheel_speed_fr": interp(tw, wheels[:, 1]),
        "wheel_speed_rl": interp(tw, wheels[:, 2]),
        "wheel_speed_rr": interp(tw, wheels[:, 3]),
        "gyro_x": gyro_v[:, 0], "gyro_y": gyro_v[:, 1], "gyro_z": gyro_v[:, 2],
        "accel_x": acc_v[:, 0], "accel_y": acc_v[:, 1], "accel_z": acc_v[:, 2],
    }


def _references(t, tp, pose) -> dict:
    """The pose's references on the grid (yaw rate, velocity in the car frame, speed, roll)."""
    v_veh = pose["v_veh"]
    return {
        "yaw_rate": np.interp(t, pose["tm"], pose["yaw_rate"]),
        "vx": np.interp(t, tp, v_veh[:, 0]),
        "vy": np.interp(t, tp, v_veh[:, 1]),
        "vz": np.interp(t, tp, v_veh[:, 2]),
        "speed": np.interp(t, tp, pose["speed"]),
        "roll": np.interp(t, tp, pose["roll"]),
    }


def _check_gravity(folder: Path, acc: np.ndarray, v_from_d: np.ndarray, mount) -> None:
    """The accelerometer's mean specific force reads gravity, +GRAVITY on the car's up axis
    after mounting (to GRAVITY_TOLERANCE); ValueError saying what is off otherwise."""
    f = acc.mean(axis=0)                                  # device frame, the whole file
    size = float(np.linalg.norm(f))
    want = f"{GRAVITY} +- {GRAVITY_TOLERANCE} m/s^2"
    if abs(size - GRAVITY) > GRAVITY_TOLERANCE:
        in_g = " (is it in g? comma2k19 stores m/s^2)" if abs(size - 1.0) < 0.2 else ""
        raise ValueError(f"{folder / 'processed_log/IMU/accelerometer/value'}: its mean specific "
                         f"force is {size:.4g} m/s^2, expected gravity, {want}{in_g}")
    up = float((v_from_d @ f)[2])
    if abs(up - GRAVITY) <= GRAVITY_TOLERANCE:
        return
    if mount is None:
        raise ValueError(f"{folder}: with the IMU mount estimated from the pose, gravity reads "
                         f"{up:+.4g} m/s^2 on the car's up axis, expected +{want}: the pose and "
                         f"the IMU disagree on the device's axes; pass mount=(roll, pitch, yaw)")
    vals = _mount_angles(mount)
    hint = ""
    up_deg = float((_mount_matrix(np.radians(vals)) @ _F @ f)[2])
    if abs(up_deg - GRAVITY) <= GRAVITY_TOLERANCE:
        hint = (f"; if these angles are degrees, mount=numpy.radians("
                f"{tuple(round(v, 6) for v in vals)}) reads {up_deg:+.4g} m/s^2")
    raise ValueError(f"mount: with (roll, pitch, yaw) = {tuple(round(v, 6) for v in vals)} rad "
                     f"gravity reads {up:+.4g} m/s^2 on the car's up axis (the accelerometer's "
                     f"mean specific force, +g at rest with z up), expected +{want}; mount is in "
                     f"radians{hint}")


# -- file reading -------------------------------------------------------------------------------
def _load_array(path: Path) -> np.ndarray:
    if not path.is_file():
        raise ValueError(f"{path}: missing file")
    try:
        a = np.load(path, allow_pickle=False)
    except (OSError, ValueError, TypeError, EOFError) as exc:
        raise ValueError(f"{path}: not a readable numeric NumPy array ({exc})") from None
    # real numbers only (complex, bool, text refused, naming the file); values checked by the
    # callers, with the first bad sample
    return np.asarray(validation.array(str(path), a, allow_nan=True), dtype=float)


def _load_times(folder: Path, rel: str) -> np.ndarray:
    path = folder / rel
    return check_time(_load_array(path), str(path))


def _load_values(folder: Path, rel: str, n: int, ncol: int) -> np.ndarray:
    path = folder / rel
    v = _load_array(path)
    if v.ndim == 1 and ncol == 1:
        v = v[:, None]
    if v.ndim != 2 or v.shape != (n, ncol):
        raise ValueError(f"{path}: expected shape ({n}, {ncol}) to match its time stamps, got "
                         f"{v.shape}")
    bad = ~np.isfinite(v)
    if np.any(bad):  # NaN or inf in a recording is a fault of the file, not a missing value
        i, j = (int(k) for k in np.argwhere(bad)[0])
        raise ValueError(f"{path}: expected finite values, found {v[i, j]!r} at sample {i} "
                         f"(column {j}); {int(bad.any(axis=1).sum())} of {n} samples are bad")
    return v


def _load_series(folder: Path, rel: str, ncol: int):
    t = _load_times(folder, rel + "/t")
    return t, _load_values(folder, rel + "/value", len(t), ncol)


# -- argument checks ----------------------------------------------------------------------------
def _positive(name: str, value) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected a positive number, got {value!r}") from None
    if not math.isfinite(v) or v <= 0.0:
        raise ValueError(f"{name}: expected a positive, finite number, got {value!r}")
    return v


def _time_arg(name: str, value, lo: float, hi: float) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected a time in seconds, got {value!r}") from None
    if not (math.isfinite(v) and lo <= v <= hi):
        raise ValueError(f"{name}: {value!r} s is outside the recording's common span "
                         f"[{lo!r}, {hi!r}] s (no extrapolation)")
    return v


# -- geometry -----------------------------------------------------------------------------------
def _rot_from_quat(q: np.ndarray) -> np.ndarray:
    """(M, 4) unit Hamilton quaternions (w, x, y, z) -> (M, 3, 3) rotation matrices."""
    w, x, y, z = q.T
    r = np.empty((len(q), 3, 3))
    r[:, 0, 0] = 1 - 2 * (y * y + z * z)
    r[:, 0, 1] = 2 * (x * y - w * z)
    r[:, 0, 2] = 2 * (x * z + w * y)
    r[:, 1, 0] = 2 * (x * y + w * z)
    r[:, 1, 1] = 1 - 2 * (x * x + z * z)
    r[:, 1, 2] = 2 * (y * z - w * x)
    r[:, 2, 0] = 2 * (x * z - w * y)
    r[:, 2, 1] = 2 * (y * z + w * x)
    r[:, 2, 2] = 1 - 2 * (x * x + y * y)
    return r


def _log_so3(r: np.ndarray) -> np.ndarray:
    """(M, 3, 3) rotations -> (M, 3) rotation vectors (angle < pi)."""
    cos = np.clip((np.trace(r, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    ang = np.arccos(cos)
    vee = np.stack([r[:, 2, 1] - r[:, 1, 2], r[:, 0, 2] - r[:, 2, 0], r[:, 1, 0] - r[:, 0, 1]], 1)
    sin = np.sin(ang)
    scale = np.where(ang > 1e-8, ang / (2.0 * np.where(sin == 0.0, 1.0, sin)), 0.5)
    return vee * scale[:, None]


def _enu_basis(p: np.ndarray) -> np.ndarray:
    """(M, 3) ECEF positions [m] -> (M, 3, 3), columns the WGS84 geodetic east, north, up."""
    x, y, z = p.T
    lon = np.arctan2(y, x)
    rho = np.hypot(x, y)
    lat = np.arctan2(z, rho * (1.0 - _WGS84_E2))
    for _ in range(6):                                    # converges to < 1e-12 rad near ground
        s = np.sin(lat)
        n = _WGS84_A / np.sqrt(1.0 - _WGS84_E2 * s * s)
        h = np.where(np.abs(np.cos(lat)) > 1e-9, rho / np.cos(lat) - n, np.abs(z) - n)
        lat = np.arctan2(z, rho * (1.0 - _WGS84_E2 * n / (n + h)))
    cl, sl, co, so = np.cos(lat), np.sin(lat), np.cos(lon), np.sin(lon)
    east = np.stack([-so, co, np.zeros_like(lon)], axis=1)
    north = np.stack([-sl * co, -sl * so, cl], axis=1)
    up = np.stack([cl * co, cl * so, sl], axis=1)
    return np.stack([east, north, up], axis=2)


def _estimate_mount(v_dev: np.ndarray, up_dev: np.ndarray, folder: Path) -> np.ndarray:
    """R_VF (vehicle <- device forward-left-up) from the pose velocity and up, in device FRD."""
    moving = np.linalg.norm(v_dev, axis=1) > _MIN_SPEED
    if np.count_nonzero(moving) < 2:
        raise ValueError(f"folder: {str(folder)!r}: the pose never moves faster than "
                         f"{_MIN_SPEED} m/s, so the IMU mount cannot be estimated; pass mount=")
    x = (v_dev[moving] @ _F).sum(axis=0)
    x /= np.linalg.norm(x)
    z = (up_dev[moving] @ _F).mean(axis=0)
    z -= np.dot(z, x) * x
    z /= np.linalg.norm(z)
    y = np.cross(z, x)
    return np.stack([x, y, z])


def _mount_angles(mount) -> tuple[float, float, float]:
    """(roll, pitch, yaw) [rad] of a ``mount`` argument; ValueError naming it otherwise."""
    try:
        if isinstance(mount, Mapping):
            vals = [float(mount[k]) for k in ("roll", "pitch", "yaw")]
        else:
            vals = [float(v) for v in mount]
    except (TypeError, ValueError, KeyError):
        raise ValueError(f"mount: expected (roll, pitch, yaw) in rad, got {mount!r}") from None
    if len(vals) != 3 or not all(math.isfinite(v) for v in vals):
        raise ValueError(f"mount: expected 3 finite angles (roll, pitch, yaw) in rad, got "
                         f"{mount!r}")
    return tuple(vals)


def _mount_matrix(mount) -> np.ndarray:
    """R_VF = Rz(yaw) Ry(pitch) Rx(roll) of a ``mount`` argument."""
    roll, pitch, yaw = _mount_angles(mount)
    cr, sr, cp, sp, cy, sy = (math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch),
                              math.cos(yaw), math.sin(yaw))
    rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    return rz @ ry @ rx


def _euler_zyx(r: np.ndarray) -> tuple[float, float, float]:
    """(roll, pitch, yaw) [rad] of r = Rz(yaw) Ry(pitch) Rx(roll)."""
    roll = math.atan2(r[2, 1], r[2, 2])
    pitch = -math.asin(max(-1.0, min(1.0, r[2, 0])))
    yaw = math.atan2(r[1, 0], r[0, 0])
    return roll, pitch, yaw
