"""``vehjax fit`` and ``vehjax estimate`` on drive files of the log formats (in process, through
``vehjax.cli.main``): the simulated drives of tests/test_cli_drive.py (a linear single-track car
integrated exactly, white measurement noise) written by the formats' own libraries:

* MDF4 by asammdf: two channel groups at different rates (steering, ay and the yaw rate at
  100 Hz, the speed at 20 Hz), units deg, m/s², deg/s and km/h; `vehjax fit` end to end;
* a ROS 2 bag by rosbags: sensor_msgs/Imu at 100 Hz (header stamps since the epoch),
  geometry_msgs/TwistStamped at 50 Hz, the steering as std_msgs/Float64 in deg;
* a CAN log (Vector ASC) by python-can, its frames encoded by cantools with a DBC written here.

Each estimate is checked against :func:`vehjax.filter` run in Python on the same Drive
(:func:`vehjax.data.read_drive`, then :meth:`Drive.for_model`), and against the simulated truth.
Bad [drive] keys are refused in one line with exit code 2 before anything is compiled.
"""

import math
import sys

import numpy as np
import pytest
from test_cli_drive import CONFIG, DT, _refused, check_stiffnesses, fit_in, truth

import vehjax
from vehjax import cli
from vehjax.data import Drive, read_drive

asammdf = pytest.importorskip("asammdf")

#: CONFIG's [model] and [fit] sections, for a [drive] section of another format
MODEL_FIT = CONFIG[CONFIG.index("[model]"):]
NAMES = 'names = { steer = "delta", speed = "vx", acc_y = "ay", yaw_rate = "r" }\n'
MDF_DRIVE = ('[drive]\nchannels = { steer = "SteerAngle", speed = ["VehSpeed", 1], '
             'acc_y = "LatAcc", yaw_rate = "YawRate", beta_true = "beta_true" }\n'
             'reference = ["beta_true"]\n'
             'units = { beta_true = "rad" }\n' + NAMES)
ROS_DRIVE = ('[drive]\nfields = { steer = "/steering.data", '
             'speed = "/vehicle/twist.twist.linear.x", acc_y = "/imu/data.linear_acceleration.y", '
             'yaw_rate = "/imu/data.angular_velocity.z" }\n'
             'units = { steer = "deg" }\nstamps = "header"\n' + NAMES)
CAN_DRIVE = ('[drive]\ndbc = "car.dbc"\nchannel = 0\nsignals = { steer = "Steering.SteerAngle", '
             'speed = "Speed.VehSpeed", acc_y = "Imu.LatAccel", yaw_rate = "Imu.YawRate" }\n'
             + NAMES)
DBC = """VERSION ""

NS_ :

BS_:

BU_: ECU

BO_ 256 Steering: 2 ECU
 SG_ SteerAngle : 0|16@1- (0.001,0) [-32.768|32.767] "deg" Vector__XXX

BO_ 512 Imu: 4 ECU
 SG_ YawRate : 0|16@1- (0.01,0) [-327.68|327.67] "deg/s" Vector__XXX
 SG_ LatAccel : 16|16@1- (0.001,0) [-32.768|32.767] "m/s^2" Vector__XXX

BO_ 768 Speed: 2 ECU
 SG_ VehSpeed : 0|16@1+ (0.01,0) [0|655.35] "km/h" Vector__XXX
"""


def write_mdf(path, seed, steps):
    """The drive as an MDF4 file: group 0 at 100 Hz (steering [deg], ay [m/s²], yaw rate
    [deg/s], the true sideslip [rad] with no unit in the file), group 1 the speed [km/h] at
    20 Hz (every fifth stamp, the first and the last among them). Returns the truth."""
    t, delta, vx, xs, ys = truth(seed, steps)
    slow = np.arange(0, steps, 5)
    Signal = asammdf.Signal
    mdf = asammdf.MDF(version="4.10")
    mdf.append([Signal(np.degrees(delta), t, name="SteerAngle", unit="deg"),
                Signal(ys[:, 0], t, name="LatAcc", unit="m/s²"),
                Signal(np.degrees(ys[:, 1]), t, name="YawRate", unit="deg/s"),
                Signal(np.arctan(xs[:, 0] / vx), t, name="beta_true", unit="")])
    mdf.append([Signal(3.6 * vx[slow], t[slow], name="VehSpeed", unit="km/h")])
    mdf.save(str(path), overwrite=True)
    mdf.close()
    return t, delta, vx, xs, ys


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """`vehjax fit` on an MDF4 drive: (folder, the fit.json content)."""
    d = tmp_path_factory.mktemp("mdf_fit")
    write_mdf(d / "drive1.mf4", seed=1, steps=501)
    return d, fit_in(d, "drive1.mf4", MDF_DRIVE + MODEL_FIT)


def test_fit_on_an_mdf4_file_recovers_the_stiffnesses(fitted):
    d, content = fitted
    check_stiffnesses(content)
    assert content["drive"]["channels"]["speed"] == ["VehSpeed", 1]
    assert "drive1.mf4 (501 steps of 0.01 s" in (d / "fit" / "report.txt").read_text()


def _reference(content, drive, names):
    """vehjax.filter with the fitted EKF, built here from fit.json's numbers, on ``drive``:
    (grid t, states (T, 2), stds (T, 2))."""
    theta = [content["model"]["theta"][k] for k in ("m", "iz", "lf", "lr", "cf", "cr")]
    model = vehjax.models.SingleTrack(dt=DT, theta=theta)
    ekf = vehjax.filters.ekf(model, np.array(content["filter"]["Q"]),
                             np.array(content["filter"]["R"]))
    us, ys = drive.for_model(model, names)
    ref = vehjax.filter(ekf, ys, us, x0=np.array(content["x0"]), P0=np.array(content["P0"]))
    stds = np.sqrt(np.diagonal(np.asarray(ref.covariances), axis1=1, axis2=2))
    return drive.resample(DT).t, np.asarray(ref.states), stds


def _estimate_equals_the_reference(fitted, drive_path, toml, tmp_path, read, xs, vx):
    d, content = fitted
    code = cli.main(["estimate", str(drive_path), "--fit", str(d / "fit" / "fit.json"),
                     "--config", str(toml), "--out", str(tmp_path / "est")])
    assert code == 0
    est = Drive.from_csv(tmp_path / "est" / "estimates.csv")
    names = {"steer": "delta", "speed": "vx", "acc_y": "ay", "yaw_rate": "r"}
    t, states, stds = _reference(content, read(), names)
    np.testing.assert_allclose(est.t, t, rtol=1e-15, atol=0)
    for i, n in enumerate(("vy", "r")):
        np.testing.assert_allclose(est.signals[n], states[:, i], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(est.signals[f"{n}_std"], stds[:, i], rtol=1e-9)
    # the grid starts at the first stamp, the truth's, and keeps the last one, though stamps
    # since the epoch put t[-1] - t[0] a rounding under (T - 1) dt
    n = len(est.t)
    assert n == len(vx), (n, len(vx))
    beta_true = np.arctan(xs[:n, 0] / vx[:n])
    rms = math.sqrt(np.mean((np.arctan(est.signals["vy"] / vx[:n]) - beta_true) ** 2))
    assert rms < 0.1 * np.std(beta_true), np.degrees(rms)
    return est


def _bag(path, seed, steps):
    """The drive as a ROS 2 bag (sqlite3): Imu at 100 Hz (header stamps since the epoch, its
    records 1 ms later), TwistStamped at 50 Hz, the steering in deg as Float64 (no header: its
    record times). Returns the truth and the first stamp [s]."""
    rosbag2 = pytest.importorskip("rosbags.rosbag2")
    typesys = pytest.importorskip("rosbags.typesys")
    ty = typesys.get_typestore(typesys.Stores.ROS2_HUMBLE)
    T = ty.types
    t, delta, vx, xs, ys = truth(seed, steps)
    t0 = 1_700_000_000 * 10**9
    ns = t0 + 10**7 * np.arange(1, steps + 1)

    def header(n):
        return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](
            sec=int(n) // 10**9, nanosec=int(n) % 10**9), frame_id="base_link")

    def v3(x=0.0, y=0.0, z=0.0):
        return T["geometry_msgs/msg/Vector3"](x=x, y=y, z=z)

    imu = [(int(n) + 10**6, T["sensor_msgs/msg/Imu"](
        header=header(n), orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0,
                                                                       w=1.0),
        orientation_covariance=np.zeros(9), angular_velocity=v3(z=r),
        angular_velocity_covariance=np.zeros(9), linear_acceleration=v3(y=ay, z=9.81),
        linear_acceleration_covariance=np.zeros(9))) for n, ay, r in zip(ns, *ys.T)]
    twist = [(int(n), T["geometry_msgs/msg/TwistStamped"](
        header=header(n), twist=T["geometry_msgs/msg/Twist"](linear=v3(x=v), angular=v3())))
        for n, v in zip(ns[::2], vx[::2])]
    steer = [(int(n), T["std_msgs/msg/Float64"](data=float(np.degrees(a))))
             for n, a in zip(ns, delta)]
    topics = {"/imu/data": ("sensor_msgs/msg/Imu", imu), "/steering": ("std_msgs/msg/Float64",
                                                                       steer),
              "/vehicle/twist": ("geometry_msgs/msg/TwistStamped", twist)}
    with rosbag2.Writer(path, version=9, storage_plugin=rosbag2.StoragePlugin.SQLITE3) as w:
        for topic, (msgtype, msgs) in topics.items():
            conn = w.add_connection(topic, msgtype, typestore=ty)
            for n, msg in msgs:
                w.write(conn, n, ty.serialize_cdr(msg, msgtype))
    return (t, delta, vx, xs, ys), ns[0] / 1e9


def test_estimate_on_a_ros2_bag_equals_vehjax_filter(fitted, tmp_path):
    (t, delta, vx, xs, ys), start = _bag(tmp_path / "bag", seed=2, steps=401)
    (tmp_path / "bag.toml").write_text(ROS_DRIVE)
    fields = {"steer": "/steering.data", "speed": "/vehicle/twist.twist.linear.x",
              "acc_y": "/imu/data.linear_acceleration.y",
              "yaw_rate": "/imu/data.angular_velocity.z"}
    est = _estimate_equals_the_reference(
        fitted, tmp_path / "bag", tmp_path / "bag.toml", tmp_path,
        lambda: read_drive(tmp_path / "bag", fields=fields, units={"steer": "deg"}), xs, vx)
    assert est.t[0] == start


def _asc(path, seed, steps):
    """The drive as a Vector ASC log of the DBC's frames: Steering and Imu at 100 Hz, Speed at
    50 Hz, on channel 0 (python-can's numbering), stamps from 0. Returns the truth."""
    cantools = pytest.importorskip("cantools")
    can = pytest.importorskip("can")
    db = cantools.database.load_string(DBC, "dbc")
    t, delta, vx, xs, ys = truth(seed, steps)
    frames = []
    for k in range(steps):
        sent = [("Steering", {"SteerAngle": np.degrees(delta[k])}),
                ("Imu", {"YawRate": np.degrees(ys[k, 1]), "LatAccel": ys[k, 0]})]
        if k % 2 == 0:
            sent.append(("Speed", {"VehSpeed": 3.6 * vx[k]}))
        for name, values in sent:
            msg = db.get_message_by_name(name)
            frames.append(can.Message(timestamp=100.0 + t[k], arbitration_id=msg.frame_id,
                                      is_extended_id=False, channel=0, data=msg.encode(values)))
    with can.Logger(str(path)) as w:
        for f in frames:
            w.on_message_received(f)
    return t, delta, vx, xs, ys


def test_estimate_on_a_can_log_equals_vehjax_filter(fitted, tmp_path, monkeypatch):
    """The DBC's relative path is taken from the configuration's folder, not the working
    directory."""
    t, delta, vx, xs, ys = _asc(tmp_path / "drive.asc", seed=3, steps=401)
    (tmp_path / "cfg").mkdir()
    (tmp_path / "cfg" / "car.dbc").write_text(DBC)
    (tmp_path / "cfg" / "can.toml").write_text(CAN_DRIVE)
    (tmp_path / "elsewhere").mkdir()
    monkeypatch.chdir(tmp_path / "elsewhere")
    signals = {"steer": "Steering.SteerAngle", "speed": "Speed.VehSpeed",
               "acc_y": "Imu.LatAccel", "yaw_rate": "Imu.YawRate"}
    est = _estimate_equals_the_reference(
        fitted, tmp_path / "drive.asc", tmp_path / "cfg" / "can.toml", tmp_path,
        lambda: read_drive(tmp_path / "drive.asc", dbc=tmp_path / "cfg" / "car.dbc",
                           signals=signals, channel=0), xs, vx)
    np.testing.assert_allclose(est.t, t - t[0], rtol=0, atol=2e-6)   # ASC: from its first frame


# ---- bad input: one line, exit code 2, nothing written ---------------------------------------

@pytest.fixture(scope="module")
def small_mdf(tmp_path_factory):
    path = tmp_path_factory.mktemp("small_mdf") / "drive.mf4"
    write_mdf(path, seed=4, steps=51)
    return path


BAD_MDF = [
    (MDF_DRIVE + 'fields = { r = "/imu.angular_velocity.z" }\n',
     ["car.toml [drive] fields", "'drive.mf4' is an MDF file, which does not take fields",
      "channels, units, reference"]),
    (MDF_DRIVE + 'time = "t"\n', ["car.toml [drive] time", "an MDF file"]),
    (MDF_DRIVE.replace('"SteerAngle"', '"SteerAngel"'),
     ["car.toml [drive] channels", "no 'SteerAngel'", "SteerAngle"]),
    (MDF_DRIVE.replace('["VehSpeed", 1]', '["VehSpeed", 0]'),
     ["car.toml [drive] channels", "'VehSpeed' is in the channel groups [1]"]),
    (MDF_DRIVE.replace('["VehSpeed", 1]', '["VehSpeed", -1]'),
     ["car.toml [drive] channels.speed", "group index >= 0"]),
    (MDF_DRIVE.replace('units = { beta_true = "rad" }', 'units = { beta_true = "furlong" }'),
     ["car.toml [drive] units", "'beta_true'", "'furlong'"]),
    (MDF_DRIVE.replace('units = { beta_true = "rad" }\n', ""),
     ["car.toml [drive] units", "'beta_true'", "has no unit"]),
    ("[drive]\n" + NAMES, ["car.toml [drive] channels: missing", "an MDF file"]),
    (MDF_DRIVE + 'dbc = "car.dbc"\n', ["car.toml [drive] dbc", "an MDF file"]),
]


@pytest.mark.parametrize("drive, words", BAD_MDF)
def test_bad_drive_keys_for_an_mdf_file_are_one_line(small_mdf, tmp_path, capsys, drive, words):
    (tmp_path / "car.toml").write_text(drive + MODEL_FIT)
    _refused(capsys, ["fit", str(small_mdf), "--config", str(tmp_path / "car.toml"), "--out",
                      str(tmp_path / "out")], words, tmp_path / "out")


def test_bad_drive_keys_of_other_formats_are_one_line(small_mdf, tmp_path, capsys, monkeypatch):
    out = tmp_path / "out"
    (tmp_path / "drive.csv").write_text("t [s],x [m]\n0,1\n0.01,2\n")
    (tmp_path / "drive.asc").write_text("")
    cases = [
        ("drive.csv", ROS_DRIVE, ["car.toml [drive] fields", "'drive.csv' is a CSV file"]),
        ("drive.asc", CAN_DRIVE, ["car.toml [drive] dbc", "car.dbc' is not a file",
                                  "relative to the configuration file's folder"]),
        ("drive.asc", CAN_DRIVE.replace('dbc = "car.dbc"\n', ""),
         ["car.toml [drive] dbc: missing", "a CAN log"]),
        ("drive.asc", CAN_DRIVE.replace("channel = 0", "channel = true"),
         ["car.toml [drive] channel", "channel number"]),
        ("drive.asc", CAN_DRIVE + 'stamps = "record"\n',
         ["car.toml [drive] stamps", "a CAN log"]),
        ("drive.mf4", ROS_DRIVE.replace('"header"', '"sensor"'),
         ["car.toml [drive] stamps", "header, record"]),
    ]
    for drive, section, words in cases:
        (tmp_path / "car.toml").write_text(section + MODEL_FIT)
        path = small_mdf if drive == "drive.mf4" else tmp_path / drive
        _refused(capsys, ["fit", str(path), "--config", str(tmp_path / "car.toml"), "--out",
                          str(out)], words, out)
    # the format's library missing: which extra installs it
    (tmp_path / "car.toml").write_text(MDF_DRIVE + MODEL_FIT)
    monkeypatch.setitem(sys.modules, "asammdf", None)
    _refused(capsys, ["fit", str(small_mdf), "--config", str(tmp_path / "car.toml"), "--out",
                      str(out)], ["DRIVE: ", "drive.mf4' is an MDF file", "'asammdf'",
                                  'pip install "vehjax[mdf]"'], out)


def test_estimate_refuses_the_fits_mdf_keys_for_a_csv(fitted, tmp_path, capsys):
    """The fit's [drive] section (MDF channels) serves another MDF file, not a CSV."""
    d, _ = fitted
    (tmp_path / "drive.csv").write_text("t [s],x [m]\n0,1\n0.01,2\n")
    _refused(capsys, ["estimate", str(tmp_path / "drive.csv"), "--fit",
                      str(d / "fit" / "fit.json"), "--out", str(tmp_path / "out")],
             ["fit.json [drive] channels", "a CSV file"], tmp_path / "out")


def test_a_multi_rate_drive_on_uniform_stamps_is_resampled_for_the_model():
    """A 20 Hz signal among 100 Hz ones whose stamps all fall on the 100 Hz grid: the union is
    uniform, yet for_model interpolates the slow signal (numpy.interp on its own samples)
    instead of handing NaN inputs to the model."""
    t = 0.01 * np.arange(21)
    vx = np.full(21, np.nan)
    vx[::5] = 20.0 + np.arange(5.0)
    d = Drive(t=t, signals={"delta": np.sin(t), "vx": vx}, units={"delta": "rad", "vx": "m/s"},
              intervals={"delta": 0.01, "vx": 0.05})
    assert d.dt == pytest.approx(0.01) and not d.on_grid(0.01)
    assert Drive(t=t, signals={"delta": np.sin(t)}, units={"delta": "rad"}).on_grid(0.01)
    u, y = d.for_model(vehjax.models.SingleTrack(dt=0.01), missing_outputs=("ay", "r"))
    np.testing.assert_allclose(u[:, 1], np.interp(t, t[::5], vx[::5]), rtol=1e-14)
    np.testing.assert_allclose(u[:, 0], np.sin(t), rtol=1e-14, atol=1e-16)
    assert np.isnan(y).all()


def test_the_fits_drive_section_reads_another_mdf_file(fitted, small_mdf):
    """fit.json's [drive] (a [channel, group] pair back from JSON as a list) reads another
    MDF file as read_drive does with the same options."""
    from vehjax.commands import setup

    drive = setup.load_drive(small_mdf, fitted[1]["drive"])
    ref = read_drive(small_mdf, channels={"steer": "SteerAngle", "speed": ("VehSpeed", 1),
                                          "acc_y": "LatAcc", "yaw_rate": "YawRate",
                                          "beta_true": "beta_true"},
                     reference=("beta_true",), units={"beta_true": "rad"})
    np.testing.assert_array_equal(drive.t, ref.t)
    assert drive.units == ref.units and drive.intervals == ref.intervals
    for group in ("signals", "reference"):
        a, b = getattr(drive, group), getattr(ref, group)
        assert sorted(a) == sorted(b)
        for k in a:
            np.testing.assert_array_equal(a[k], b[k])
    assert drive.units["speed"] == "m/s" and drive.intervals["speed"] == pytest.approx(0.05)
