"""vehjax.data.load_comma2k19: the shipped RAV4 segment checked against physics, a synthetic folder
with known values, and bad input."""

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

import vehjax  # noqa: F401  (float64)
from vehjax.data import Drive, load_comma2k19
from vehjax.models import Dynamic3DOF, SingleTrackBank

G = 9.81
SEGMENT = Path(vehjax.__file__).parent / "data" / "comma2k19_rav4"
MODEL = SingleTrackBank(dt=0.01)


def _ma(x, n):
    """Moving average over n samples ('valid' part)."""
    return np.convolve(x, np.ones(n) / n, mode="valid")


def _corr(a, b):
    return float(np.corrcoef(a, b)[0, 1])


@pytest.fixture(scope="module")
def drive():
    return load_comma2k19()


# -- the shipped segment --------------------------------------------------------------------------
def test_shipped_segment_files():
    names = {p.relative_to(SEGMENT).as_posix() for p in SEGMENT.rglob("*") if p.is_file()}
    assert {"LICENSE_comma2k19_MIT.txt", "PROVENANCE.md", "README_comma2k19.md",
            "global_pose/frame_orientations", "processed_log/IMU/gyro_bias/value",
            "processed_log/CAN/wheel_speed/t"} <= names
    assert len(names) == 22


def test_shapes_units_and_model_arrays(drive):
    assert isinstance(drive, Drive)
    n = len(drive.t)
    assert drive.dt == pytest.approx(0.01)
    assert 5900 < n < 6000                                     # ~60 s at 100 Hz
    for group in (drive.signals, drive.reference):
        for name, a in group.items():
            assert a.shape == (n,), name
            assert np.all(np.isfinite(a)), name
            assert name in drive.units
    assert set(drive.units) == set(drive.signals) | set(drive.reference)
    assert drive.units["steering_wheel_angle"] == "rad"
    assert drive.units["gyro_z"] == "rad/s" and drive.units["accel_y"] == "m/s^2"
    assert drive.units["roll"] == "rad" and drive.units["vx"] == "m/s"
    u, y = drive.inputs(MODEL), drive.measurements(MODEL)
    assert u.shape == (n, 2) and y.shape == (n, 5)
    assert np.all(np.isnan(y[:, 3]))                           # phi: no bank sensor
    assert np.all(np.isfinite(np.delete(y, 3, axis=1)))
    np.testing.assert_array_equal(y[:, 0], drive.signals["accel_y"])
    np.testing.assert_array_equal(y[:, 1], drive.signals["gyro_z"])
    np.testing.assert_array_equal(y[:, 2], drive.signals["gyro_x"])
    assert np.all(u[:, 0] > 7.0)                               # vx > 0 all along (8-20 m/s)
    # steering wheel within -5..3 deg (PROVENANCE), road wheel = / 16.88
    assert np.degrees(np.abs(u[:, 1])).max() < 5.0 / 16.88 + 1e-9
    np.testing.assert_allclose(u[:, 1] * 16.88, drive.signals["steering_wheel_angle"])
    with pytest.raises(dataclasses.FrozenInstanceError):
        drive.dt = 0.02
    with pytest.raises(ValueError):
        drive.t[0] = 0.0


def test_time_grid_inside_every_signal(drive):
    t = drive.t
    assert np.all(np.diff(t) > 0)
    np.testing.assert_allclose(np.diff(t), 0.01, atol=1e-9)
    for rel in ("processed_log/CAN/speed/t", "processed_log/CAN/steering_angle/t",
                "processed_log/CAN/wheel_speed/t", "processed_log/IMU/gyro/t",
                "processed_log/IMU/accelerometer/t", "global_pose/frame_times"):
        ts = np.load(SEGMENT / rel)
        assert ts[0] <= t[0] and t[-1] <= ts[-1], rel
    tp = np.load(SEGMENT / "global_pose/frame_times")
    assert t[0] >= 0.5 * (tp[0] + tp[1]) and t[-1] <= 0.5 * (tp[-2] + tp[-1])
    # the steering file's own samples come back at their own times (linear interpolation)
    ts = np.load(SEGMENT / "processed_log/CAN/steering_angle/t")
    sw = np.load(SEGMENT / "processed_log/CAN/steering_angle/value")
    np.testing.assert_allclose(drive.signals["steering_wheel_angle"],
                               np.radians(np.interp(t, ts, sw)))


def test_mount_angles(drive):
    deg = {k: math.degrees(v) for k, v in drive.mount.items()}
    # the pose velocity has ~ -1.1 m/s on the device's down axis at ~17 m/s: ~4 deg nose down
    assert 3.0 < deg["pitch"] < 4.5
    assert abs(deg["roll"]) < 2.0 and abs(deg["yaw"]) < 2.0
    # the mount puts the pose velocity on the car's x axis: near-zero side and vertical parts
    ref = drive.reference
    assert abs(ref["vz"].mean()) < 0.01 and np.sqrt(np.mean(ref["vz"] ** 2)) < 0.15
    assert abs(ref["vy"].mean()) < 0.01 and np.sqrt(np.mean(ref["vy"] ** 2)) < 0.1
    np.testing.assert_allclose(np.hypot(ref["vx"], np.hypot(ref["vy"], ref["vz"])),
                               ref["speed"], rtol=1e-4)   # interpolated separately
    # specific force at ~zero mean acceleration: ~ +g on the car's up axis, little elsewhere
    acc = drive.signals
    assert abs(acc["accel_z"].mean() - G) < 0.3
    assert abs(acc["accel_x"].mean()) < 0.3 and abs(acc["accel_y"].mean()) < 0.15
    # passing the estimate back reproduces the drive
    again = load_comma2k19(mount=drive.mount)
    np.testing.assert_allclose(again.signals["accel_y"], acc["accel_y"], atol=1e-12)


def test_reference_yaw_rate_zero_on_straights(drive):
    r_ref = _ma(drive.reference["yaw_rate"], 100)
    sw = np.degrees(_ma(drive.signals["steering_wheel_angle"], 100))
    straight = np.abs(sw - np.median(sw)) < 0.3                # wheel within 0.3 deg of centre
    assert 0.2 < straight.mean() < 0.9
    on_straight = np.degrees(np.abs(r_ref[straight]).mean())
    in_bends = np.degrees(np.abs(r_ref[~straight]).mean())
    assert on_straight < 0.1                                   # deg/s: radius > 10 km at 17 m/s
    assert on_straight < 0.6 * in_bends


def test_speed_sources_agree(drive):
    vx = drive.inputs(MODEL)[:, 0]
    rear = 0.5 * (drive.signals["wheel_speed_rl"] + drive.signals["wheel_speed_rr"])
    np.testing.assert_array_equal(vx, rear)
    for other in (drive.signals["speed_can"], drive.reference["speed"]):
        assert abs(vx.mean() / other.mean() - 1.0) < 0.02
        assert np.mean(np.abs(vx - other)) / other.mean() < 0.02


def test_gyro_against_pose_yaw_rate(drive):
    gz, r_ref = drive.signals["gyro_z"], drive.reference["yaw_rate"]
    assert _corr(_ma(gz, 50), _ma(r_ref, 50)) > 0.9            # 0.5 s averages
    assert _corr(gz, r_ref) > 0.7                              # raw 100 Hz
    off = drive.gyro_offset_vs_reference
    assert off == pytest.approx(np.mean(gz - r_ref))
    assert abs(math.degrees(off)) < 0.1                        # deg/s
    # gyro_bias is Android's already-subtracted estimate, not this offset: its yaw part is
    # -3.9 deg/s (yaw = -z in the device frame), two orders of magnitude larger
    bias = np.load(SEGMENT / "processed_log/IMU/gyro_bias/value")
    assert np.all(bias == bias[0])
    assert math.degrees(-bias[0, 2]) == pytest.approx(-3.92, abs=0.01)
    assert abs(bias[0, 2]) > 50 * abs(off)


def test_lateral_acceleration_and_roll_against_pose(drive):
    ay = drive.signals["accel_y"]
    ref = drive.reference
    centripetal = ref["vx"] * ref["yaw_rate"]
    # on average: the accelerometer's lateral offset (~0.08 m/s^2) is left in, to be learned
    assert abs(ay.mean() - centripetal.mean()) < 0.15
    # over time: specific force = vx r + g sin(roll), roll > 0 left side up
    model_ay = centripetal + G * np.sin(ref["roll"])
    assert _corr(_ma(ay, 100), _ma(model_ay, 100)) > 0.85
    assert _corr(_ma(ay, 100), _ma(model_ay, 100)) > _corr(_ma(ay, 100), _ma(centripetal, 100))
    assert np.degrees(np.abs(ref["roll"])).max() < 3.0


def test_input_and_virtual_yaw_rate_signs(drive):
    r_ref = _ma(drive.reference["yaw_rate"], 100)
    delta = _ma(drive.inputs(MODEL)[:, 1], 100)
    assert _corr(delta, r_ref) > 0.7                           # delta > 0 steers left, r > 0
    r_virt = _ma(drive.measurements(MODEL)[:, 4], 100)
    assert _corr(r_virt, r_ref) > 0.6                          # same sign as the gyro's
    wide = drive.measurements(MODEL, track=2 * 1.61)[:, 4]
    np.testing.assert_allclose(wide, 0.5 * drive.measurements(MODEL)[:, 4])


def test_start_stop_and_rate(drive):
    d = load_comma2k19(rate=50.0, start=drive.t[0] + 10.0, stop=drive.t[0] + 20.0)
    assert d.dt == pytest.approx(0.02) and len(d.t) == 501
    assert d.t[0] == pytest.approx(drive.t[0] + 10.0)
    assert d.t[-1] == pytest.approx(drive.t[0] + 20.0)
    np.testing.assert_allclose(d.signals["gyro_z"][::5][:-1], drive.signals["gyro_z"][1000:2000:10],
                               atol=1e-9)
    with pytest.raises(ValueError, match="model"):             # dt 0.02 vs the model's 0.01
        d.inputs(MODEL)


# -- a synthetic folder with known values ---------------------------------------------------------
def _rx(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _ry(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rz(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _quat_wxyz(r):
    """Rotation matrix -> unit quaternion (w, x, y, z), w >= 0 (Shepperd)."""
    tr = np.trace(r)
    i = int(np.argmax([tr, r[0, 0], r[1, 1], r[2, 2]]))
    if i == 0:
        w = 0.5 * math.sqrt(1 + tr)
        q = [w, (r[2, 1] - r[1, 2]) / (4 * w), (r[0, 2] - r[2, 0]) / (4 * w),
             (r[1, 0] - r[0, 1]) / (4 * w)]
    else:
        j, k = (i % 3), ((i + 1) % 3)
        a = i - 1
        s = 2 * math.sqrt(1 + 2 * r[a, a] - tr)
        q = [0.0] * 4
        q[0] = (r[k, j] - r[j, k]) / s
        q[1 + a] = s / 4
        q[1 + j] = (r[j, a] + r[a, j]) / s
        q[1 + k] = (r[k, a] + r[a, k]) / s
    q = np.array(q)
    return q if q[0] >= 0 else -q


SYN = dict(speed=15.0, yaw_rate=0.05, gyro_bias=0.002, steer_deg=12.0, track=1.61,
           mount=(math.radians(1.0), math.radians(3.0), math.radians(-0.5)), t0=1000.0)


def _write(folder, rel, t, value):
    d = folder / rel
    d.mkdir(parents=True, exist_ok=True)
    with open(d / "t", "wb") as f:
        np.save(f, np.asarray(t, dtype=float))
    with open(d / "value", "wb") as f:
        np.save(f, np.asarray(value, dtype=float))


def _synthetic(folder: Path) -> Path:
    """4 s of a level circle: constant speed, yaw rate, steering; device mounted at SYN['mount']."""
    v, r, t0 = SYN["speed"], SYN["yaw_rate"], SYN["t0"]
    lat, lon = math.radians(37.7), math.radians(-122.5)
    a, e2 = 6378137.0, (1 / 298.257223563) * (2 - 1 / 298.257223563)
    n = a / math.sqrt(1 - e2 * math.sin(lat) ** 2)
    p0 = np.array([n * math.cos(lat) * math.cos(lon), n * math.cos(lat) * math.sin(lon),
                   n * (1 - e2) * math.sin(lat)])
    east = np.array([-math.sin(lon), math.cos(lon), 0.0])
    north = np.array([-math.sin(lat) * math.cos(lon), -math.sin(lat) * math.sin(lon),
                      math.cos(lat)])
    up = np.cross(east, north)
    enu = np.stack([east, north, up], axis=1)
    roll, pitch, yaw = SYN["mount"]
    flip = np.diag([1.0, -1.0, -1.0])
    v_from_d = _rz(yaw) @ _ry(pitch) @ _rx(roll) @ flip       # vehicle FLU <- device FRD

    tp = t0 + np.arange(81) * 0.05                             # pose, 20 Hz
    psi = 0.3 + r * (tp - t0)
    rad = v / r
    xy = np.stack([rad * np.sin(psi), -rad * np.cos(psi), 0 * psi], axis=1)
    xy -= xy[0]                                                # starts at p0
    pos = p0 + xy @ enu.T
    vel = np.stack([v * np.cos(psi), v * np.sin(psi), 0 * psi], axis=1) @ enu.T
    quats = np.array([_quat_wxyz(enu @ _rz(ps) @ v_from_d) for ps in psi])
    (folder / "global_pose").mkdir(parents=True)
    for name, arr in (("frame_times", tp), ("frame_positions", pos), ("frame_velocities", vel),
                      ("frame_orientations", quats)):
        with open(folder / "global_pose" / name, "wb") as f:
            np.save(f, arr)

    tc = t0 + np.arange(321) * 0.0125                          # CAN, 80 Hz
    half = 0.5 * r * SYN["track"]
    _write(folder, "processed_log/CAN/speed", tc, np.full((len(tc), 1), v))
    _write(folder, "processed_log/CAN/steering_angle", tc, np.full(len(tc), SYN["steer_deg"]))
    _write(folder, "processed_log/CAN/wheel_speed", tc,
           np.tile([v - half, v + half, v - half, v + half], (len(tc), 1)))
    ti = t0 + 0.003 + np.arange(400) * 0.01                    # IMU, 100 Hz, own clock phase
    w_v = np.array([0.0, 0.0, r + SYN["gyro_bias"]])
    f_v = np.array([0.0, v * r, G])                            # specific force, level circle
    _write(folder, "processed_log/IMU/gyro", ti, np.tile(v_from_d.T @ w_v, (len(ti), 1)))
    _write(folder, "processed_log/IMU/accelerometer", ti, np.tile(v_from_d.T @ f_v, (len(ti), 1)))
    return folder


@pytest.fixture
def synthetic(tmp_path):
    return _synthetic(tmp_path / "seg")


def test_synthetic_folder_returns_known_values(synthetic):
    d = load_comma2k19(synthetic)
    v, r = SYN["speed"], SYN["yaw_rate"]
    assert d.t[0] >= SYN["t0"] + 0.025 and d.t[-1] <= SYN["t0"] + 3.975
    np.testing.assert_allclose(np.diff(d.t), 0.01, atol=1e-9)
    # The synthetic circle lies in the tangent plane at its start, while the loader's local
    # vertical follows the WGS84 normal under the car, which turns by distance / R_earth
    # (~1e-5 rad over these 60 m): hence the 2e-5 rad (and g * 2e-5 m/s^2) tolerances below.
    tol_ang, tol_acc = 2e-5, 2e-4
    assert list(d.mount) == ["roll", "pitch", "yaw"]
    np.testing.assert_allclose(list(d.mount.values()), SYN["mount"], atol=tol_ang)
    s, ref = d.signals, d.reference
    np.testing.assert_allclose(s["speed_can"], v)
    np.testing.assert_allclose(s["steering_wheel_angle"], math.radians(SYN["steer_deg"]))
    np.testing.assert_allclose(s["wheel_speed_rr"] - s["wheel_speed_rl"], r * SYN["track"])
    np.testing.assert_allclose(s["gyro_z"], r + SYN["gyro_bias"], atol=1e-9)
    np.testing.assert_allclose(s["gyro_x"], 0.0, atol=1e-6)
    np.testing.assert_allclose(s["accel_y"], v * r, atol=tol_acc)
    np.testing.assert_allclose(s["accel_z"], G, atol=tol_acc)
    np.testing.assert_allclose(ref["yaw_rate"], r, rtol=1e-6)
    np.testing.assert_allclose(ref["vx"], v, rtol=1e-9)
    np.testing.assert_allclose(ref["vy"], 0.0, atol=v * tol_ang)
    np.testing.assert_allclose(ref["vz"], 0.0, atol=v * tol_ang)
    np.testing.assert_allclose(ref["speed"], v, rtol=1e-9)
    np.testing.assert_allclose(ref["roll"], 0.0, atol=tol_ang)
    assert d.gyro_offset_vs_reference == pytest.approx(SYN["gyro_bias"], abs=1e-8)

    u = d.inputs(MODEL, steer_ratio=16.88)
    np.testing.assert_allclose(u[:, 0], v)
    np.testing.assert_allclose(u[:, 1], math.radians(SYN["steer_deg"]) / 16.88)
    y = d.measurements(MODEL, track=SYN["track"])
    want = np.array([v * r, r + SYN["gyro_bias"], 0.0, np.nan, r])
    np.testing.assert_allclose(y, np.tile(want, (len(d.t), 1)), atol=tol_acc)

    # a known mount, passed in, is used as given; a zero mount leaves the IMU in the device
    # frame turned to forward-left-up
    d0 = load_comma2k19(synthetic, mount=(0.0, 0.0, 0.0))
    assert d0.mount == {"roll": 0.0, "pitch": 0.0, "yaw": 0.0}
    assert abs(d0.signals["accel_x"][0]) > 0.4                 # g sin(3 deg) leaks forward


# -- bad input ------------------------------------------------------------------------------------
def test_missing_folder_and_file(synthetic, tmp_path):
    with pytest.raises(ValueError, match="folder"):
        load_comma2k19(tmp_path / "nowhere")
    (synthetic / "processed_log/IMU/gyro/t").unlink()
    with pytest.raises(ValueError, match=r"IMU/gyro/t.*missing"):
        load_comma2k19(synthetic)


def test_non_increasing_time_stamps(synthetic):
    path = synthetic / "processed_log/CAN/steering_angle/t"
    t = np.load(path)
    t[10] = t[9]
    with open(path, "wb") as f:
        np.save(f, t)
    with pytest.raises(ValueError, match=r"steering_angle/t.*increasing"):
        load_comma2k19(synthetic)


def test_misshaped_or_unreadable_file(synthetic):
    path = synthetic / "processed_log/CAN/wheel_speed/value"
    with open(path, "wb") as f:
        np.save(f, np.zeros((5, 4)))
    with pytest.raises(ValueError, match=r"wheel_speed/value.*shape"):
        load_comma2k19(synthetic)
    path.write_bytes(b"not numpy")
    with pytest.raises(ValueError, match=r"wheel_speed/value"):
        load_comma2k19(synthetic)


def test_grid_outside_the_recording(synthetic):
    with pytest.raises(ValueError, match="start"):
        load_comma2k19(synthetic, start=SYN["t0"])            # before the pose's first rate
    with pytest.raises(ValueError, match="stop"):
        load_comma2k19(synthetic, stop=SYN["t0"] + 10.0)
    with pytest.raises(ValueError, match="stop"):
        load_comma2k19(synthetic, start=SYN["t0"] + 2.0, stop=SYN["t0"] + 1.0)
    with pytest.raises(ValueError, match="start"):
        load_comma2k19(synthetic, start="soon")


@pytest.mark.parametrize("rate", [0.0, -100.0, float("nan"), float("inf"), "fast"])
def test_bad_rate(synthetic, rate):
    with pytest.raises(ValueError, match="rate"):
        load_comma2k19(synthetic, rate=rate)


def test_bad_model_and_keywords(drive, synthetic):
    with pytest.raises(ValueError, match="model"):
        drive.inputs(Dynamic3DOF())
    with pytest.raises(ValueError, match="model"):
        drive.measurements(Dynamic3DOF())
    with pytest.raises(ValueError, match="model"):
        drive.inputs(SingleTrackBank(dt=0.02))
    with pytest.raises(ValueError, match="steer_ratio"):
        drive.inputs(MODEL, steer_ratio=0.0)
    with pytest.raises(ValueError, match="track"):
        drive.measurements(MODEL, track=-1.61)
    with pytest.raises(ValueError, match="mount"):
        load_comma2k19(synthetic, mount=(0.0, 0.0))
    with pytest.raises(ValueError, match="mount"):
        load_comma2k19(synthetic, mount=(0.0, float("nan"), 0.0))


# -- gravity after mounting ------------------------------------------------------------------------
def test_mount_in_degrees_given_as_radians_refused(drive):
    deg = tuple(math.degrees(v) for v in drive.mount.values())    # ~ (1.25, 3.77, 0.90)
    with pytest.raises(ValueError, match=r"mount: with \(roll, pitch, yaw\) = \(1\.25\d*, "
                                         r"3\.76\d*, 0\.90\d*\) rad gravity reads -2\.87\d* m/s\^2"
                                         r".*if these angles are degrees, mount=numpy\.radians"):
        load_comma2k19(mount=deg)
    # the module docstring's figures, in radians, load with gravity on the car's up axis
    d = load_comma2k19(mount=np.radians([1.25, 3.77, 0.90]))
    assert abs(d.signals["accel_z"].mean() - G) < 0.3
    assert abs(d.signals["accel_y"].mean()) < 0.15


def test_gravity_checked_on_a_synthetic_folder(synthetic):
    roll, pitch, yaw = (math.degrees(a) for a in SYN["mount"])    # (1, 3, -0.5): as radians
    f_dev = np.load(synthetic / "processed_log/IMU/accelerometer/value").mean(axis=0)
    up = (_rz(yaw) @ _ry(pitch) @ _rx(roll) @ np.diag([1.0, -1.0, -1.0]) @ f_dev)[2]
    assert up < 8.0                                               # the test's own rotation
    with pytest.raises(ValueError, match=rf"mount: .* gravity reads {up:+.4g} m/s\^2 on the "
                                         rf"car's up axis.*expected \+9\.81 \+- 1\.5"):
        load_comma2k19(synthetic, mount=(roll, pitch, yaw))
    with pytest.raises(ValueError, match=r"gravity reads -9\.\d* m/s\^2"):   # upside down
        load_comma2k19(synthetic, mount=(math.pi, 0.0, 0.0))
    load_comma2k19(synthetic, mount=SYN["mount"])                 # in radians: loads
    # an accelerometer in g: refused naming the file, whatever the mount
    path = synthetic / "processed_log/IMU/accelerometer/value"
    in_g = np.load(path) / 9.80665
    with open(path, "wb") as f:
        np.save(f, in_g)
    with pytest.raises(ValueError, match=r"accelerometer/value: its mean specific force is "
                                         r"1\.0\d* m/s\^2, expected gravity.*in g\?"):
        load_comma2k19(synthetic)
