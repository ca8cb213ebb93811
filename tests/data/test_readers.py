"""The drive readers on files written by the formats' own libraries into tmp_path: asammdf's MDF4
and MDF3 (two channel groups at different rates, units deg and km/h), rosbags' ROS 2 bags
(sqlite3 and MCAP; sensor_msgs/Imu, geometry_msgs/TwistStamped, a message without header, a
user's message), cantools-encoded frames of a DBC written here (scaling, units, a multiplexed
message) that python-can writes as ASC, BLF and candump logs. Each is read back to the numbers
that went in, converted by the test's own factors, compared with numpy; the shipped RAV4 drive
goes through MDF4 and a ROS 2 bag and comes back as the same Drive with the same for_model
arrays. Multi-rate resampling is checked against numpy.interp on each signal's own samples."""

import gc
import math

import numpy as np
import pytest

import vehjax  # noqa: F401  (float64)
from vehjax.data import Drive, load_comma2k19, read_can, read_drive, read_mdf, read_ros2
from vehjax.models import SingleTrack, SingleTrackBank

DEG = math.pi / 180.0
KMH = 1.0 / 3.6


@pytest.fixture(scope="module")
def rav4():
    return load_comma2k19().to_drive()


def _at(drive, name, t):
    """The values of ``name`` at the stamps ``t`` (which must be in drive.t)."""
    idx = np.searchsorted(drive.t, t)
    np.testing.assert_array_equal(drive.t[idx], t)
    return drive.signals.get(name, drive.reference.get(name))[idx]


# -- MDF --------------------------------------------------------------------------------------
def _write_mdf(asammdf, path, version, t_fast, steer_deg, t_slow, speed_kmh, extra=()):
    mdf = asammdf.MDF(version=version)
    mdf.append([asammdf.Signal(steer_deg, t_fast, name="SteerAngle", unit="deg")])
    mdf.append([asammdf.Signal(speed_kmh, t_slow, name="VehSpeed", unit="km/h"), *extra])
    mdf.save(str(path), overwrite=True)
    mdf.close()


@pytest.mark.parametrize("version,suffix", [("4.10", ".mf4"), ("3.30", ".mdf")])
def test_mdf_two_groups_at_their_own_rates(tmp_path, version, suffix):
    asammdf = pytest.importorskip("asammdf")
    t_fast = 5.0 + 0.01 * np.arange(200)                  # 100 Hz
    t_slow = 5.003 + 0.1 * np.arange(20)                  # 10 Hz, offset
    steer = 30.0 * np.sin(t_fast)
    speed = 50.0 + 2.0 * np.arange(20.0)
    torque = asammdf.Signal(np.ones(20), t_slow, name="Torque", unit="lbf ft")
    yaw = asammdf.Signal(np.arange(20.0), t_slow, name="YawRate", unit="°/s")
    path = tmp_path / f"run{suffix}"
    _write_mdf(asammdf, path, version, t_fast, steer, t_slow, speed, extra=[torque, yaw])
    d = read_drive(path, channels={"delta": "SteerAngle", "vx": "VehSpeed"})
    np.testing.assert_array_equal(d.t, np.union1d(t_fast, t_slow))
    np.testing.assert_allclose(_at(d, "delta", t_fast), steer * DEG, rtol=1e-15)
    np.testing.assert_allclose(_at(d, "vx", t_slow), speed * KMH, rtol=1e-15)
    assert d.units == {"delta": "rad", "vx": "m/s"}
    assert np.isnan(_at(d, "vx", t_fast[1:10])).all()       # no sample there: NaN, not moved
    assert d.intervals == pytest.approx({"delta": 0.01, "vx": 0.1})
    # resampling interpolates the slow signal between its own samples (not NaN after 0.025 s)
    r = d.resample(0.01, start=5.01, stop=6.9)
    np.testing.assert_allclose(r.signals["vx"], np.interp(r.t, t_slow, speed * KMH), rtol=1e-12)
    np.testing.assert_allclose(r.signals["delta"], np.interp(r.t, t_fast, steer * DEG),
                               rtol=1e-12, atol=1e-15)
    u, y = r.for_model(SingleTrack(dt=0.01), missing_outputs=("ay", "r"))   # (delta, vx)
    np.testing.assert_array_equal(u, np.stack([r.signals["delta"], r.signals["vx"]], axis=1))
    assert np.isnan(y).all() and len(r.t) == 190
    with pytest.raises(ValueError, match=r"'tq' \(channel 'Torque' \(group 1\)\) is in 'lbf ft'"):
        read_mdf(path, {"tq": "Torque"})
    tq = read_mdf(path, {"tq": "Torque", "r": "YawRate"}, units={"tq": "N m"})
    np.testing.assert_array_equal(tq.signals["tq"], np.ones(20))
    np.testing.assert_allclose(tq.signals["r"], np.arange(20.0) * DEG, rtol=1e-15)
    assert tq.units == {"tq": "N m", "r": "rad/s"}


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")   # asammdf's
def test_mdf_errors_name_the_channel(tmp_path):                                 # __del__, cut file
    asammdf = pytest.importorskip("asammdf")
    t = np.arange(10) * 0.1
    path = tmp_path / "run.mf4"
    _write_mdf(asammdf, path, "4.10", t, t, t, t)
    with pytest.raises(ValueError, match=r"no 'SteerAngel'.*near names: \['SteerAngle'\]"):
        read_mdf(path, {"delta": "SteerAngel"})
    with pytest.raises(ValueError, match=r"'time' is in the channel groups \[0, 1\]"):
        read_mdf(path, {"x": "time"})
    d = read_mdf(path, {"x": ("time", 1)}, units={"x": "s"})
    np.testing.assert_array_equal(d.signals["x"], t)
    with pytest.raises(ValueError, match="reference: 'nope' is not a name of channels"):
        read_mdf(path, {"delta": "SteerAngle"}, reference=("nope",))
    cut = tmp_path / "cut.mf4"
    cut.write_bytes(path.read_bytes()[:200])
    with pytest.raises(ValueError, match="cut.mf4"):
        read_mdf(cut, {"delta": "SteerAngle"})
    gc.collect()                                  # asammdf's half-opened file, here


def test_mdf_invalid_samples_are_nan_at_their_stamps(tmp_path):
    asammdf = pytest.importorskip("asammdf")
    t = 0.1 * np.arange(6)
    bits = np.array([0, 1, 0, 0, 1, 0], bool)
    mdf = asammdf.MDF(version="4.10")
    mdf.append([asammdf.Signal(np.arange(6.0), t, name="A", unit="mm", invalidation_bits=bits)])
    mdf.save(str(tmp_path / "inv.mf4"), overwrite=True)
    mdf.close()
    d = read_mdf(tmp_path / "inv.mf4", {"a": "A"})
    np.testing.assert_array_equal(d.t, t)
    np.testing.assert_array_equal(d.signals["a"], np.where(bits, np.nan, np.arange(6.0) * 1e-3))
    assert d.intervals["a"] == pytest.approx(0.1)


def test_mdf_stamps_that_go_back_or_repeat(tmp_path):
    asammdf = pytest.importorskip("asammdf")
    t = np.array([0.0, 0.1, 0.2, 0.2, 0.3])
    path = tmp_path / "dup.mf4"
    steer, speed = np.array([1.0, 2, 3, 3, 4]), np.array([1.0, 2, 3, 9, 4])
    _write_mdf(asammdf, path, "4.10", t, steer, t, speed)
    d = read_mdf(path, {"delta": "SteerAngle"})            # a sample written twice: dropped
    np.testing.assert_array_equal(d.t, [0.0, 0.1, 0.2, 0.3])
    np.testing.assert_allclose(d.signals["delta"], np.array([1.0, 2, 3, 4]) * DEG)
    with pytest.raises(ValueError, match=r"'vx': .* two samples at t = 0.2 s .* 3.0 and 9.0"):
        read_mdf(path, {"vx": "VehSpeed"})
    back = tmp_path / "back.mf4"
    tb = np.array([0.0, 0.1, 0.05, 0.3])
    _write_mdf(asammdf, back, "4.10", tb, tb, tb, tb)
    with pytest.raises(ValueError, match=r"'delta': the time stamps of channel 'SteerAngle' "
                                         r"\(group 0\) go back 1 time.*0.1 -> 0.05"):
        read_mdf(back, {"delta": "SteerAngle"})


# -- ROS 2 ------------------------------------------------------------------------------------
def _typestore():
    typesys = pytest.importorskip("rosbags.typesys")
    return typesys.get_typestore(typesys.Stores.ROS2_HUMBLE)


def _stamp(store, ns):
    return store.types["std_msgs/msg/Header"](
        stamp=store.types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9),
        frame_id="base_link")


def _imu(store, ns, wz, ay):
    ty = store.types
    v3 = ty["geometry_msgs/msg/Vector3"]
    return ty["sensor_msgs/msg/Imu"](
        header=_stamp(store, ns), orientation=ty["geometry_msgs/msg/Quaternion"](
            x=0.0, y=0.0, z=0.0, w=1.0), orientation_covariance=np.zeros(9),
        angular_velocity=v3(x=0.0, y=0.0, z=wz), angular_velocity_covariance=np.full(9, 0.5),
        linear_acceleration=v3(x=0.0, y=ay, z=9.81), linear_acceleration_covariance=np.zeros(9))


def _twist(store, ns, vx):
    ty = store.types
    v3 = ty["geometry_msgs/msg/Vector3"]
    return ty["geometry_msgs/msg/TwistStamped"](
        header=_stamp(store, ns), twist=ty["geometry_msgs/msg/Twist"](
            linear=v3(x=vx, y=0.0, z=0.0), angular=v3(x=0.0, y=0.0, z=0.0)))


def _bag(path, storage, topics):
    """A ROS 2 bag at ``path``: topics = {topic: (msgtype, [(record ns, message), ...])}."""
    rosbag2 = pytest.importorskip("rosbags.rosbag2")
    store = _typestore()
    plugin = {"sqlite3": rosbag2.StoragePlugin.SQLITE3, "mcap": rosbag2.StoragePlugin.MCAP}
    with rosbag2.Writer(path, version=9, storage_plugin=plugin[storage]) as w:
        for topic, (msgtype, msgs) in topics.items():
            conn = w.add_connection(topic, msgtype, typestore=store)
            for ns, msg in msgs:
                w.write(conn, ns, store.serialize_cdr(msg, msgtype))


@pytest.fixture(params=["sqlite3", "mcap"])
def imu_bag(tmp_path, request):
    store = _typestore()
    t0 = 1_700_000_000 * 10**9
    imu_ns = t0 + 10**7 * np.arange(50)                   # 100 Hz header stamps
    tw_ns = t0 + 3 * 10**6 + 5 * 10**7 * np.arange(10)     # 20 Hz
    wz, ay, vx = 0.01 * np.arange(50), np.cos(np.arange(50.0)), 10.0 + np.arange(10.0)
    f64 = store.types["std_msgs/msg/Float64"]
    topics = {
        "/imu/data": ("sensor_msgs/msg/Imu", [(int(n) + 2 * 10**6, _imu(store, int(n), w, a))
                                              for n, w, a in zip(imu_ns, wz, ay)]),
        "/vehicle/twist": ("geometry_msgs/msg/TwistStamped",
                           [(int(n) + 10**6, _twist(store, int(n), v)) for n, v in zip(tw_ns, vx)]),
        "/steer_deg": ("std_msgs/msg/Float64", [(int(n), f64(data=3.0 * k))
                                                for k, n in enumerate(tw_ns)]),
    }
    path = tmp_path / f"bag_{request.param}"
    _bag(path, request.param, topics)
    return path, imu_ns / 1e9, tw_ns / 1e9, wz, ay, vx


FIELDS = {"r": "/imu/data.angular_velocity.z", "ay": "/imu/data.linear_acceleration.y",
          "vx": "/vehicle/twist.twist.linear.x"}


def test_ros2_imu_and_twist_at_their_header_stamps(imu_bag):
    path, t_imu, t_tw, wz, ay, vx = imu_bag
    d = read_drive(path, fields=FIELDS)
    assert d.units == {"r": "rad/s", "ay": "m/s^2", "vx": "m/s"}
    np.testing.assert_array_equal(d.t, np.union1d(t_imu, t_tw))
    np.testing.assert_array_equal(_at(d, "r", t_imu), wz)
    np.testing.assert_array_equal(_at(d, "ay", t_imu), ay)
    np.testing.assert_array_equal(_at(d, "vx", t_tw), vx)
    assert d.intervals == pytest.approx({"r": 0.01, "ay": 0.01, "vx": 0.05})
    rec = read_ros2(path, FIELDS, stamps="record")          # 2 ms and 1 ms after the stamps
    np.testing.assert_allclose(rec.t, np.union1d(t_imu + 0.002, t_tw + 0.001), rtol=0, atol=1e-6)
    np.testing.assert_array_equal(_at(rec, "vx", rec.t[np.isfinite(rec.signals["vx"])]), vx)
    # the storage file itself, and a message without header (record time) given its unit
    store_file = next(p for p in path.iterdir() if p.suffix in (".db3", ".mcap"))
    steer = read_drive(store_file, fields={"steer": "/steer_deg.data", **FIELDS},
                       units={"steer": "deg"}, reference=("steer",))
    np.testing.assert_allclose(_at(steer, "steer", t_tw), 3.0 * np.arange(10) * DEG, rtol=1e-15)
    np.testing.assert_array_equal(_at(steer, "vx", t_tw), vx)


def test_ros2_errors_name_the_topic_and_field(imu_bag):
    path = imu_bag[0]
    with pytest.raises(ValueError, match=r"no '/imu/dta'.*near names: \['/imu/data'\]"):
        read_ros2(path, {"r": "/imu/dta.angular_velocity.z"})
    with pytest.raises(ValueError, match=r"no 'angular_velocty' in the message of '/imu/data' "
                                         r"\(sensor_msgs/msg/Imu\).*'angular_velocity'"):
        read_ros2(path, {"r": "/imu/data.angular_velocty.z"})
    with pytest.raises(ValueError, match=r"is geometry_msgs/msg/Vector3, not a number.*'x', 'y'"):
        read_ros2(path, {"r": "/imu/data.angular_velocity"})
    with pytest.raises(ValueError, match=r"'cov' \(field '/imu/data.angular_velocity_covariance"
                                         r".8'\) has no unit"):
        read_ros2(path, {"cov": "/imu/data.angular_velocity_covariance.8"})
    cov = read_ros2(path, {"cov": "/imu/data.angular_velocity_covariance.8"}, units={"cov": "-"})
    np.testing.assert_array_equal(cov.signals["cov"], np.full(50, 0.5))
    with pytest.raises(ValueError, match="stamps: expected 'header' or 'record'"):
        read_ros2(path, FIELDS, stamps="sensor")
    with pytest.raises(ValueError, match="'/topic.path.to.field'"):
        read_ros2(path, {"r": "imu"})


def _odometry(store, ns, x, vx, wz):
    ty = store.types
    v3, point = ty["geometry_msgs/msg/Vector3"], ty["geometry_msgs/msg/Point"]
    pose = ty["geometry_msgs/msg/Pose"](position=point(x=x, y=0.0, z=0.0),
                                        orientation=ty["geometry_msgs/msg/Quaternion"](
                                            x=0.0, y=0.0, z=0.0, w=1.0))
    twist = ty["geometry_msgs/msg/Twist"](linear=v3(x=vx, y=0.0, z=0.0),
                                          angular=v3(x=0.0, y=0.0, z=wz))
    return ty["nav_msgs/msg/Odometry"](
        header=_stamp(store, ns), child_frame_id="base_link",
        pose=ty["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
        twist=ty["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=np.zeros(36)))


def _fix(store, ns, lat, lon, alt):
    ty = store.types
    return ty["sensor_msgs/msg/NavSatFix"](
        header=_stamp(store, ns), status=ty["sensor_msgs/msg/NavSatStatus"](status=0, service=1),
        latitude=lat, longitude=lon, altitude=alt, position_covariance=np.zeros(9),
        position_covariance_type=0)


def test_ros2_odometry_and_navsatfix_in_rep103_units(tmp_path):
    store = _typestore()
    odo_ns, fix_ns = 10**9 + 2 * 10**7 * np.arange(10), 10**9 + 2 * 10**8 * np.arange(3)
    x, vx, wz = np.arange(10.0), 5.0 + np.arange(10.0), 0.1 * np.arange(10)
    lat, lon, alt = 48.1 + 1e-5 * np.arange(3), 11.5 + 2e-5 * np.arange(3), 500.0 + np.arange(3)
    _bag(tmp_path / "bag", "mcap", {
        "/odom": ("nav_msgs/msg/Odometry", [(int(n), _odometry(store, int(n), *v))
                                            for n, *v in zip(odo_ns, x, vx, wz)]),
        "/fix": ("sensor_msgs/msg/NavSatFix", [(int(n), _fix(store, int(n), *v))
                                               for n, *v in zip(fix_ns, lat, lon, alt)])})
    d = read_ros2(tmp_path / "bag", {
        "x": "/odom.pose.pose.position.x", "vx": "/odom.twist.twist.linear.x",
        "r": "/odom.twist.twist.angular.z", "qw": "/odom.pose.pose.orientation.w",
        "lat": "/fix.latitude", "lon": "/fix.longitude", "alt": "/fix.altitude"},
        reference=("lat", "lon", "alt"))
    assert d.units == {"x": "m", "vx": "m/s", "r": "rad/s", "qw": "-", "lat": "rad",
                       "lon": "rad", "alt": "m"}
    t_odo, t_fix = odo_ns / 1e9, fix_ns / 1e9
    for name, want in (("x", x), ("vx", vx), ("r", wz), ("qw", np.ones(10))):
        np.testing.assert_array_equal(_at(d, name, t_odo), want)
    np.testing.assert_allclose(_at(d, "lat", t_fix), lat * DEG, rtol=1e-15)
    np.testing.assert_allclose(_at(d, "lon", t_fix), lon * DEG, rtol=1e-15)
    np.testing.assert_array_equal(_at(d, "alt", t_fix), alt)
    assert sorted(d.reference) == ["alt", "lat", "lon"]


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_ros2_a_bag_cut_short(tmp_path, storage):
    store = _typestore()
    _bag(tmp_path / "bag", storage, {"/imu": ("sensor_msgs/msg/Imu", [
        (n, _imu(store, n, 0.0, 0.0)) for n in range(1, 200)])})
    data = next(p for p in (tmp_path / "bag").iterdir() if p.suffix in (".db3", ".mcap"))
    data.write_bytes(data.read_bytes()[: data.stat().st_size * 2 // 3])
    with pytest.raises(ValueError, match=r"path: '.*bag' is not a readable ROS 2 bag"):
        read_ros2(tmp_path / "bag", {"r": "/imu.angular_velocity.z"})


def test_ros2_header_stamps_that_go_back(tmp_path):
    store = _typestore()
    ns = [10**9, 2 * 10**9, 15 * 10**8]
    _bag(tmp_path / "bag", "sqlite3", {"/imu": ("sensor_msgs/msg/Imu", [
        (k, _imu(store, n, 0.0, 0.0)) for k, n in zip((1, 2, 3), ns)])})
    with pytest.raises(ValueError, match=r"'r': the time stamps of field '/imu.angular_velocity"
                                         r".z' \(header stamps; stamps='record' reads the "
                                         r"record times\) go back 1 time.*2.0 -> 1.5"):
        read_ros2(tmp_path / "bag", {"r": "/imu.angular_velocity.z"})


# -- CAN --------------------------------------------------------------------------------------
DBC = """VERSION ""

NS_ :

BS_:

BU_: ECU

BO_ 256 VehicleDynamics: 8 ECU
 SG_ VehicleSpeed : 0|16@1+ (0.01,0) [0|655.35] "km/h" Vector__XXX
 SG_ YawRate : 16|16@1- (0.01,0) [-327.68|327.67] "deg/s" Vector__XXX
 SG_ SteerAngle : 32|16@1- (0.1,-5) [-3281.8|3271.7] "deg" Vector__XXX
 SG_ Counter : 48|8@1+ (1,0) [0|255] "" Vector__XXX

BO_ 2147484160 WheelSpeeds: 8 ECU
 SG_ Index M : 0|8@1+ (1,0) [0|255] "" Vector__XXX
 SG_ FrontLeft m0 : 8|16@1+ (0.01,0) [0|655.35] "km/h" Vector__XXX
 SG_ RearLeft m1 : 8|16@1+ (0.01,0) [0|655.35] "km/h" Vector__XXX
"""

SIGNALS = {"vx": "VehicleDynamics.VehicleSpeed", "r": "VehicleDynamics.YawRate",
           "delta": "VehicleDynamics.SteerAngle", "v_fl": "WheelSpeeds.FrontLeft",
           "v_rl": "WheelSpeeds.RearLeft"}


@pytest.fixture
def can_frames(tmp_path):
    cantools = pytest.importorskip("cantools")
    can = pytest.importorskip("can")
    dbc = tmp_path / "car.dbc"
    dbc.write_text(DBC)
    db = cantools.database.load_file(str(dbc))
    dyn, wheels = db.get_message_by_name("VehicleDynamics"), db.get_message_by_name("WheelSpeeds")
    t = 1_700_000_000.0 + 0.02 * np.arange(20)
    n = np.arange(20)
    speed, yaw, steer, wheel = 50.0 + 0.25 * n, -3.5 + 0.5 * n, 12.3 - n, 40.0 + 0.5 * n
    frames = []
    for k in range(20):
        frames.append(can.Message(timestamp=t[k], arbitration_id=dyn.frame_id, channel=0,
                                  is_extended_id=False,
                                  data=dyn.encode({"VehicleSpeed": speed[k], "YawRate": yaw[k],
                                                   "SteerAngle": steer[k], "Counter": k})))
        which = ("FrontLeft", "RearLeft")[k % 2]
        frames.append(can.Message(timestamp=t[k] + 0.01, arbitration_id=wheels.frame_id,
                                  is_extended_id=True, channel=0,
                                  data=wheels.encode({"Index": k % 2, which: wheel[k]})))
    return can, dbc, frames, t, speed, yaw, steer, wheel


def _log(can, path, frames):
    with can.Logger(str(path)) as w:
        for f in frames:
            w.on_message_received(f)
    return path


@pytest.mark.parametrize("suffix", [".asc", ".blf", ".log", ".trc"])
def test_can_log_decoded_by_the_dbc(tmp_path, can_frames, suffix):
    can, dbc, frames, t, speed, yaw, steer, wheel = can_frames
    path = _log(can, tmp_path / f"drive{suffix}", frames)
    options = {"relative_timestamp": False} if suffix == ".asc" else None
    d = read_drive(path, dbc=dbc, signals=SIGNALS, reader_options=options)
    assert d.units == {"vx": "m/s", "r": "rad/s", "delta": "rad", "v_fl": "m/s", "v_rl": "m/s"}
    rows = np.flatnonzero(np.isfinite(d.signals["vx"]))
    np.testing.assert_allclose(d.t[rows], t, rtol=0, atol=2e-6)    # BLF keeps 1 ns, ASC 1 us
    np.testing.assert_allclose(d.signals["vx"][rows], speed * KMH, rtol=1e-12)
    np.testing.assert_allclose(d.signals["r"][rows], yaw * DEG, rtol=1e-12)
    np.testing.assert_allclose(d.signals["delta"][rows], steer * DEG, rtol=1e-12)
    # the multiplexed signals: each only in the frames whose index selects it
    fl, rl = np.isfinite(d.signals["v_fl"]), np.isfinite(d.signals["v_rl"])
    assert fl.sum() == 10 and rl.sum() == 10 and not (fl & rl).any()
    np.testing.assert_allclose(d.t[fl], t[::2] + 0.01, rtol=0, atol=2e-6)
    np.testing.assert_allclose(d.signals["v_fl"][fl], wheel[::2] * KMH, rtol=1e-12)
    np.testing.assert_allclose(d.signals["v_rl"][rl], wheel[1::2] * KMH, rtol=1e-12)
    assert d.intervals["v_fl"] == pytest.approx(0.04, abs=1e-5)
    assert d.intervals["vx"] == pytest.approx(0.02, abs=1e-5)
    r = d.resample(0.01, start=t[0] + 0.01, stop=t[-1])           # the slow wheel interpolated
    np.testing.assert_allclose(r.signals["v_fl"][:-1], np.interp(
        r.t[:-1], d.t[fl], d.signals["v_fl"][fl]), rtol=1e-12)


def test_can_asc_relative_stamps_by_default(tmp_path, can_frames):
    can, dbc, frames, t, speed, *_ = can_frames
    d = read_can(_log(can, tmp_path / "drive.asc", frames), dbc, {"vx": SIGNALS["vx"]})
    np.testing.assert_allclose(d.t, t - t[0], rtol=0, atol=2e-6)


def test_can_errors(tmp_path, can_frames):
    can, dbc, frames, *_ = can_frames
    path = _log(can, tmp_path / "drive.log", frames)
    with pytest.raises(ValueError, match=r"no 'VehicleDynamic' in the DBC \(messages\); near "
                                         r"names: \['VehicleDynamics'\]"):
        read_can(path, dbc, {"vx": "VehicleDynamic.VehicleSpeed"})
    with pytest.raises(ValueError, match=r"no 'Speed'.*'VehicleDynamics'.*'VehicleSpeed'"):
        read_can(path, dbc, {"vx": "VehicleDynamics.Speed"})
    with pytest.raises(ValueError, match=r"'n' \(signal 'VehicleDynamics.Counter'\) has no unit"):
        read_can(path, dbc, {"n": "VehicleDynamics.Counter"})
    n = read_can(path, dbc, {"n": "VehicleDynamics.Counter"}, units={"n": "-"})
    np.testing.assert_array_equal(n.signals["n"], np.arange(20.0))
    with pytest.raises(ValueError, match="needs dbc="):
        read_drive(path, signals=SIGNALS)
    # the last line written partly: refused, naming the message and its time
    text = path.read_text().rstrip("\n")
    cut = tmp_path / "cut.log"
    cut.write_text(text[:-6] + "\n")
    with pytest.raises(ValueError, match=r"frame 39 \('WheelSpeeds' at t = .*\) has 6 data bytes"
                                         r", the DBC's message 8 \(the log's last frame"):
        read_can(cut, dbc, SIGNALS)
    junk = tmp_path / "junk.blf"
    junk.write_bytes(b"not a binary log" * 8)
    with pytest.raises(ValueError, match=r"junk.blf' is not a readable CAN log"):
        read_can(junk, dbc, SIGNALS)
    # frames out of order, and one message on two channels
    swapped = frames[:4] + [frames[6], frames[5], frames[4]] + frames[7:]
    with pytest.raises(ValueError, match=r"'vx': the time stamps of signal 'VehicleDynamics."
                                         r"VehicleSpeed' go back"):
        read_can(_log(can, tmp_path / "back.log", swapped), dbc, {"vx": SIGNALS["vx"]})
    two = [f if k % 4 else can.Message(timestamp=f.timestamp, arbitration_id=f.arbitration_id,
                                       is_extended_id=False, data=f.data, channel=1)
           for k, f in enumerate(frames)]
    both = _log(can, tmp_path / "two.blf", two)
    with pytest.raises(ValueError, match=r"'VehicleDynamics' is on channels \[0, 1\].*channel="):
        read_can(both, dbc, {"vx": SIGNALS["vx"]})
    one = read_can(both, dbc, {"vx": SIGNALS["vx"]}, channel=1)
    assert np.isfinite(one.signals["vx"]).sum() == 10


# -- the shipped drive through MDF4, a ROS 2 bag and a CAN log --------------------------------
def _same_drive(d, rav4, t_atol=0.0):
    np.testing.assert_allclose(d.t, rav4.t, rtol=0, atol=t_atol)
    assert d.signals.keys() == rav4.signals.keys() and d.reference.keys() == rav4.reference.keys()
    for k in rav4.signals:
        np.testing.assert_array_equal(d.signals[k], rav4.signals[k], err_msg=k)
    for k in rav4.reference:
        np.testing.assert_array_equal(d.reference[k], rav4.reference[k], err_msg=k)
    assert d.units == rav4.units
    assert d.dt == pytest.approx(rav4.dt, rel=1e-9)
    model = SingleTrackBank(dt=0.01)
    for a, b in zip(d.for_model(model, missing_outputs=("phi",)),
                    rav4.for_model(model, missing_outputs=("phi",))):
        np.testing.assert_array_equal(a, b)


def test_rav4_through_mdf4(tmp_path, rav4):
    asammdf = pytest.importorskip("asammdf")
    mdf = asammdf.MDF(version="4.10")
    for group in (rav4.signals, rav4.reference):
        mdf.append([asammdf.Signal(v, rav4.t, name=k, unit=rav4.units[k])
                    for k, v in group.items()])
    mdf.save(str(tmp_path / "rav4.mf4"), overwrite=True)
    mdf.close()
    names = [*rav4.signals, *rav4.reference]
    d = read_drive(tmp_path / "rav4.mf4", channels={k: k for k in names},
                   reference=tuple(rav4.reference))
    _same_drive(d, rav4)


def test_rav4_through_a_ros2_bag(tmp_path, rav4):
    typesys = pytest.importorskip("rosbags.typesys")
    store = _typestore()
    names = [*rav4.signals, *rav4.reference]
    msgdef = "std_msgs/Header header\n" + "".join(f"float64 {k}\n" for k in names)
    store.register(typesys.get_types_from_msg(msgdef, "vehjax_test_msgs/msg/Drive"))
    cls = store.types["vehjax_test_msgs/msg/Drive"]
    cols = {k: rav4.signals.get(k, rav4.reference.get(k)) for k in names}
    ns = np.round(rav4.t * 1e9).astype(np.int64)
    msgs = [(int(n) + 5000, cls(header=_stamp(store, int(n)),
                                **{k: float(cols[k][i]) for k in names}))
            for i, n in enumerate(ns)]
    rosbag2 = pytest.importorskip("rosbags.rosbag2")
    mcap = rosbag2.StoragePlugin.MCAP
    with rosbag2.Writer(tmp_path / "bag", version=9, storage_plugin=mcap) as w:
        conn = w.add_connection("/drive", "vehjax_test_msgs/msg/Drive", typestore=store)
        for n, m in msgs:
            w.write(conn, n, store.serialize_cdr(m, conn.msgtype))
    d = read_drive(tmp_path / "bag", fields={k: f"/drive.{k}" for k in names},
                   units=dict(rav4.units), reference=tuple(rav4.reference))
    _same_drive(d, rav4, t_atol=1e-9)                             # stamps kept to the ns


def _double_dbc(names, units) -> str:
    """A DBC with one 8-byte message per signal, each an IEEE double (SIG_VALTYPE_ 2): the
    values go through CAN exactly."""
    lines = ['VERSION ""', "", "NS_ :", "", "BS_:", "", "BU_: ECU", ""]
    for i, k in enumerate(names):
        lines += [f"BO_ {256 + i} M_{k}: 8 ECU",
                  f' SG_ {k} : 0|64@1- (1,0) [0|0] "{units[k]}" Vector__XXX', ""]
    lines += [f"SIG_VALTYPE_ {256 + i} {k} : 2;" for i, k in enumerate(names)]
    return "\n".join(lines) + "\n"


def test_rav4_through_a_can_log(tmp_path, rav4):
    """The shipped drive's first 20 s (2,000 samples of its 24 signals: 48,000 frames) as CAN
    frames that cantools encodes by a DBC, written by python-can as a candump log, read back:
    the values exactly, the stamps to the log's microsecond."""
    cantools = pytest.importorskip("cantools")
    can = pytest.importorskip("can")
    part = rav4.between(stop=rav4.t[0] + 19.995)
    names = [*part.signals, *part.reference]
    cols = {k: part.signals.get(k, part.reference.get(k)) for k in names}
    (tmp_path / "rav4.dbc").write_text(_double_dbc(names, part.units))
    db = cantools.database.load_file(str(tmp_path / "rav4.dbc"))
    frames = [can.Message(timestamp=float(t), arbitration_id=256 + i, is_extended_id=False,
                          channel=0, data=db.get_message_by_name(f"M_{k}").encode(
                              {k: float(cols[k][j])}))
              for j, t in enumerate(part.t) for i, k in enumerate(names)]
    path = _log(can, tmp_path / "rav4.log", frames)   # candump: absolute stamps, to the us
    d = read_drive(path, dbc=tmp_path / "rav4.dbc",
                   signals={k: f"M_{k}.{k}" for k in names}, reference=tuple(part.reference))
    np.testing.assert_allclose(d.t, part.t, rtol=0, atol=5e-7)
    assert d.units == part.units and d.reference.keys() == part.reference.keys()
    for k in names:                                           # the doubles, exactly
        np.testing.assert_array_equal(d.signals.get(k, d.reference.get(k)), cols[k], err_msg=k)
    model = SingleTrackBank(dt=0.01)  # on the model's grid: stamps off by < 0.5 us
    for a, b in zip(d.for_model(model, missing_outputs=("phi",)),
                    part.for_model(model, missing_outputs=("phi",))):
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-6)


# -- read_drive, the extras, Drive.intervals -------------------------------------------------
def test_read_drive_dispatch_and_unknown_formats(tmp_path, rav4):
    short = rav4.between(stop=rav4.t[0] + 0.5)
    short.to_csv(tmp_path / "d.csv")
    d = read_drive(tmp_path / "d.csv", reference=tuple(rav4.reference))
    np.testing.assert_array_equal(d.signals["vx"], short.signals["vx"])
    (tmp_path / "d.xlsx").write_bytes(b"")
    with pytest.raises(ValueError, match=r"suffix '.xlsx'; read_drive reads .*\.mf4"):
        read_drive(tmp_path / "d.xlsx")
    (tmp_path / "folder").mkdir()
    with pytest.raises(ValueError, match="without metadata.yaml"):
        read_drive(tmp_path / "folder")
    with pytest.raises(ValueError, match="does not exist"):
        read_drive(tmp_path / "none.mf4")


def test_a_missing_library_names_its_extra(tmp_path, monkeypatch):
    import vehjax.data.series as series

    def absent(name):
        raise ImportError(name)

    monkeypatch.setattr(series.importlib, "import_module", absent)
    for call, extra in ((lambda: read_mdf(tmp_path / "a.mf4", {"x": "X"}), "mdf"),
                        (lambda: read_ros2(tmp_path, {"x": "/a.b"}), "ros"),
                        (lambda: read_can(tmp_path / "a.asc", "a.dbc", {"x": "A.B"}), "can")):
        with pytest.raises(ImportError, match=rf'pip install "vehjax\[{extra}\]"'):
            call()


def test_a_uniform_grid_at_epoch_stamps_is_uniform():
    t = 1.7e9 + 0.01 * np.arange(500)                     # steps uniform to float64's 2.4e-7 s
    assert np.ptp(np.diff(t)) > 1e-8                      # more than 1e-6 of the step
    d = Drive(t=t, signals={"a": np.ones(500)}, units={"a": "m"})
    assert d.dt == pytest.approx(0.01, rel=1e-6)
    r = d.resample(0.02)
    assert r.dt == pytest.approx(0.02, rel=1e-4) and np.all(r.signals["a"] == 1.0)


def test_drive_intervals_set_each_signals_gap():
    t = np.arange(11) * 0.1
    slow = np.where(np.arange(11) % 5 == 0, t, np.nan)       # samples at 0, 0.5, 1.0 s
    d = Drive(t=t, signals={"a": t, "b": slow}, units={"a": "m", "b": "m"})
    assert d.intervals == {}
    assert np.isnan(d.resample(0.1).signals["b"][1:5]).all()      # today's rule: 2.5 x 0.1 s
    di = Drive(t=t, signals={"a": t, "b": slow}, units={"a": "m", "b": "m"},
               intervals={"b": 0.5})
    np.testing.assert_allclose(di.resample(0.1).signals["b"], t, atol=1e-15)
    np.testing.assert_allclose(di.resample(0.1).signals["a"], t, atol=1e-15)
    assert di.between(0.2, 0.8).intervals == {"b": 0.5} and di.resample(0.1).intervals == {}
    assert np.isnan(di.resample(0.1, max_gap=0.3).signals["b"][1:5]).all()
    with pytest.raises(ValueError, match="intervals: 'c' is not a signal"):
        Drive(t=t, signals={"a": t}, units={"a": "m"}, intervals={"c": 0.1})
    with pytest.raises(ValueError, match=r"intervals\['a'\]: expected a positive"):
        Drive(t=t, signals={"a": t}, units={"a": "m"}, intervals={"a": 0.0})
