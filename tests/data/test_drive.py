"""vehjax.data.Drive: the shipped segment round-trips through arrays and a CSV written here in
other units, resampling against numpy.interp and a gap rule written out here, unit conversion by
the test's own factors, and the errors."""

import csv
import math

import numpy as np
import pytest

import vehjax  # noqa: F401  (float64)
from vehjax.data import Drive, load_comma2k19
from vehjax.models import SingleTrack, SingleTrackBank


@pytest.fixture(scope="module")
def rav4():
    return load_comma2k19().to_drive()


def _write_csv(path, header, columns):
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        for row in zip(*columns):
            w.writerow(["" if np.isnan(v) else repr(float(v)) for v in row])


# -- the shipped segment ---------------------------------------------------------------------
def test_comma2k19_is_a_drive_and_its_model_columns(rav4):
    raw = load_comma2k19()
    assert isinstance(raw, Drive) and raw.dt == pytest.approx(0.01)
    bank = SingleTrackBank(dt=0.01)
    u, y = rav4.for_model(bank, missing_outputs=("phi",))
    np.testing.assert_array_equal(u, raw.inputs(bank))
    np.testing.assert_array_equal(y, raw.measurements(bank))
    u2, y2 = rav4.for_model(SingleTrack(dt=0.01))
    np.testing.assert_array_equal(u2, u[:, ::-1])                   # (delta, vx)
    np.testing.assert_array_equal(y2, y[:, :2])                     # (ay, r)
    np.testing.assert_array_equal(rav4.reference["ref_vy"], raw.reference["vy"])
    assert rav4.units["ref_yaw_rate"] == "rad/s"


def test_round_trip_through_arrays_and_a_csv_in_other_units(rav4, tmp_path):
    s = rav4.signals
    t_ms = (rav4.t - rav4.t[0]) * 1000.0
    cols = {"steer [deg]": np.degrees(s["delta"]), "speed [km/h]": s["vx"] * 3.6,
            "ay [g]": s["ay"] / 9.80665, "r [deg/s]": np.degrees(s["r"]),
            "vy_ref [m/s]": rav4.reference["ref_vy"]}
    path = tmp_path / "drive.csv"
    _write_csv(path, ["time [ms]", *cols], [t_ms, *cols.values()])
    d = Drive.from_csv(path, time="time", reference=("vy_ref",))
    assert d.units == {"steer": "rad", "speed": "m/s", "ay": "m/s^2", "r": "rad/s",
                       "vy_ref": "m/s"}
    np.testing.assert_allclose(d.t, rav4.t - rav4.t[0], rtol=0, atol=1e-12)
    for mine, theirs in (("steer", "delta"), ("speed", "vx"), ("ay", "ay"), ("r", "r")):
        np.testing.assert_allclose(d.signals[mine], s[theirs], rtol=1e-13, atol=1e-300)
    assert d.dt == pytest.approx(0.01)
    model = SingleTrack(dt=0.01)
    u, y = d.for_model(model, names={"steer": "delta", "speed": "vx"})
    u0, y0 = rav4.for_model(model)
    np.testing.assert_allclose(u, u0, rtol=1e-13)
    np.testing.assert_allclose(y, y0, rtol=1e-13)
    # the same drive from arrays, and to_csv -> from_csv: identical
    a = Drive.from_arrays(t_ms, {k.split()[0]: v for k, v in cols.items()},
                          {k.split()[0]: k.split()[1][1:-1] for k in cols},
                          reference="vy_ref", time_unit="ms")
    for k in a.signals:
        np.testing.assert_array_equal(a.signals[k], d.signals[k])
    a.to_csv(tmp_path / "again.csv")
    b = Drive.from_csv(tmp_path / "again.csv", reference=("vy_ref",))
    np.testing.assert_array_equal(b.t, a.t)
    for k in a.signals:
        np.testing.assert_array_equal(b.signals[k], a.signals[k])
    np.testing.assert_array_equal(b.reference["vy_ref"], a.reference["vy_ref"])


# -- resampling ------------------------------------------------------------------------------
def _expected(grid, t, y, max_gap):
    """The gap rule written out: linear between the two finite samples around each point, NaN
    outside them or when they are more than max_gap apart (a point on a sample keeps it)."""
    ok = np.isfinite(y)
    ts, ys = t[ok], y[ok]
    out = np.empty(len(grid))
    for i, g in enumerate(grid):
        hit = np.flatnonzero(ts == g)
        if hit.size:
            out[i] = ys[hit[0]]
            continue
        k = np.searchsorted(ts, g)
        if k == 0 or k == len(ts) or ts[k] - ts[k - 1] > max_gap:
            out[i] = np.nan
        else:
            w = (g - ts[k - 1]) / (ts[k] - ts[k - 1])
            out[i] = (1 - w) * ys[k - 1] + w * ys[k]
    return out


def test_resample_irregular_stamps_against_numpy_interp():
    rng = np.random.default_rng(3)
    t = np.cumsum(rng.uniform(0.008, 0.016, 400))                   # ~83 Hz, jittered
    y = np.sin(2 * np.pi * 0.8 * t) + 0.1 * rng.standard_normal(t.size)
    d = Drive.from_arrays(t, {"y": y, "z": 2 * y}, {"y": "m/s", "z": "deg"})
    assert d.dt is None
    r = d.resample(0.01)
    assert r.dt == pytest.approx(0.01)
    np.testing.assert_allclose(np.diff(r.t), 0.01, rtol=1e-9)
    assert r.t[0] == t[0] and r.t[-1] <= t[-1] < r.t[-1] + 0.01
    np.testing.assert_allclose(r.signals["y"], np.interp(r.t, t, y), rtol=1e-14, atol=1e-15)
    np.testing.assert_allclose(r.signals["z"], np.radians(np.interp(r.t, t, 2 * y)), rtol=1e-14)
    r2 = d.resample(0.05, start=1.0, stop=3.0)
    assert r2.t[0] == 1.0 and r2.t[-1] == pytest.approx(3.0)
    np.testing.assert_allclose(r2.signals["y"], np.interp(r2.t, t, y), rtol=1e-14)


def test_gaps_become_nan_and_short_ones_are_bridged():
    rng = np.random.default_rng(4)
    t = np.arange(300) * 0.02 + rng.uniform(-0.002, 0.002, 300)    # 50 Hz
    t = np.delete(t, np.arange(100, 130))                           # a 0.62 s hole in the log
    y = np.cos(t)
    y[50] = np.nan                                                  # one dropped sample: bridged
    y[200:206] = np.nan                                             # six: a gap
    d = Drive.from_arrays(t, {"y": y}, {"y": "m"})
    for max_gap in (None, 0.05, 0.3):
        r = d.resample(0.01, max_gap=max_gap)
        gap = 2.5 * np.median(np.diff(t)) if max_gap is None else max_gap
        want = _expected(r.t, t, y, gap)
        np.testing.assert_allclose(r.signals["y"], want, rtol=1e-13, atol=1e-15)
        assert np.isnan(want).any() and np.isfinite(want).sum() > 400
    r = d.resample(0.01)
    hole = (r.t > t[99]) & (r.t < t[100])
    assert hole.sum() > 55 and np.all(np.isnan(r.signals["y"][hole]))
    near50 = (r.t > t[49]) & (r.t < t[51])
    assert np.all(np.isfinite(r.signals["y"][near50]))


def test_for_model_resamples_and_keeps_missing_measurements():
    t = np.arange(0.0, 2.0, 0.02)
    ay = np.sin(t)
    ay[40:60] = np.nan
    d = Drive.from_arrays(t, {"steer": np.full(t.size, 2.0), "v": np.full(t.size, 72.0),
                              "ay": ay, "yaw": np.full(t.size, 5.0)},
                          {"steer": "deg", "v": "km/h", "ay": "m/s^2", "yaw": "deg/s"})
    u, y = d.for_model(SingleTrack(dt=0.01), names={"steer": "delta", "v": "vx", "yaw": "r"})
    assert u.shape == (199, 2) and y.shape == (199, 2)
    np.testing.assert_allclose(u[:, 0], math.radians(2.0), rtol=1e-15)
    np.testing.assert_allclose(u[:, 1], 20.0, rtol=1e-15)
    np.testing.assert_allclose(y[:, 1], math.radians(5.0), rtol=1e-15)
    assert np.isnan(y[80:120, 0]).all() and np.isfinite(y[:78, 0]).all()


# -- errors ----------------------------------------------------------------------------------
def test_errors(tmp_path):
    t = np.arange(5) * 0.1
    ok = {"a": np.ones(5)}
    with pytest.raises(ValueError, match="t: time stamps must be strictly increasing"):
        Drive.from_arrays(t[[0, 1, 3, 2, 4]], ok, {"a": "m"})
    with pytest.raises(ValueError, match="strictly increasing"):
        Drive.from_arrays(t[[0, 1, 1, 2, 3]], ok, {"a": "m"})
    with pytest.raises(ValueError, match="units: unknown unit 'furlong'"):
        Drive.from_arrays(t, ok, {"a": "furlong"})
    with pytest.raises(ValueError, match="units: no unit for 'a'"):
        Drive.from_arrays(t, ok, {})
    with pytest.raises(ValueError, match="shape"):
        Drive.from_arrays(t, {"a": np.ones(4)}, {"a": "m"})
    with pytest.raises(ValueError, match="reference"):
        Drive.from_arrays(t, ok, {"a": "m"}, reference=("b",))
    with pytest.raises(ValueError, match="dt"):
        Drive.from_arrays(t, ok, {"a": "m"}).resample(0.0)
    d = Drive.from_arrays(t, {"delta": np.zeros(5), "vx": np.ones(5), "ay": np.zeros(5)},
                          {"delta": "rad", "vx": "m/s", "ay": "m/s^2"})
    model = SingleTrack(dt=0.1)
    with pytest.raises(ValueError, match="output 'r' has no signal"):
        d.for_model(model)
    assert d.for_model(model, missing_outputs=("r",))[1].shape == (5, 2)
    with pytest.raises(ValueError, match="names: no signal 'steer'"):
        d.for_model(model, names={"steer": "delta"})
    with pytest.raises(ValueError, match="units: signal 'vx' is in 'm/s'"):
        d.for_model(model, names={"vx": "delta"}, missing_outputs=("r",))
    gap = Drive.from_arrays(t, {"delta": [0, np.nan, 0, 0, 0], "vx": np.ones(5),
                                "ay": np.zeros(5)}, {"delta": "rad", "vx": "m/s", "ay": "m/s^2"})
    with pytest.raises(ValueError, match="inputs: 1 missing samples of input 'delta'"):
        gap.for_model(model, missing_outputs=("r",))
    # CSV: missing time column, missing unit, bad number, non-monotonic time
    _write_csv(tmp_path / "a.csv", ["time", "x [m]"], [t, t])
    with pytest.raises(ValueError, match="time: no column 't'"):
        Drive.from_csv(tmp_path / "a.csv")
    _write_csv(tmp_path / "b.csv", ["t", "x"], [t, t])
    with pytest.raises(ValueError, match="units: no unit for column 'x'"):
        Drive.from_csv(tmp_path / "b.csv")
    assert Drive.from_csv(tmp_path / "b.csv", units={"x": "km"}).signals["x"][1] == 100.0
    with pytest.raises(ValueError, match="columns: unknown name"):
        Drive.from_csv(tmp_path / "b.csv", units={"x": "m"}, columns=("y",))
    (tmp_path / "c.csv").write_text("t,x [m]\n0,1\n0.1,oops\n0.2,3\n")
    with pytest.raises(ValueError, match="line 3: not a number"):
        Drive.from_csv(tmp_path / "c.csv")
    (tmp_path / "d.csv").write_text("t,x [m]\n0,1\n0.2,2\n0.1,3\n")
    with pytest.raises(ValueError, match="strictly increasing"):
        Drive.from_csv(tmp_path / "d.csv")
    with pytest.raises(ValueError, match="path"):
        Drive.from_csv(tmp_path / "nothing.csv")


# -- reference channels onto reference outputs -------------------------------------------------
def test_reference_channel_feeds_a_reference_output(rav4):
    model = SingleTrack(dt=0.01, references=("vy",))
    u, y = rav4.for_model(model, names={"ref_vy": "vy"})
    u0, y0 = rav4.for_model(SingleTrack(dt=0.01))
    np.testing.assert_array_equal(u, u0)
    np.testing.assert_array_equal(y[:, :2], y0)
    np.testing.assert_array_equal(y[:, 2], rav4.reference["ref_vy"])
    assert np.isfinite(y[:, 2]).mean() > 0.9
    # a drive without it: the column is NaN when asked, else an error naming the option
    _, y_missing = rav4.for_model(model, missing_outputs=("vy",))
    np.testing.assert_array_equal(y_missing[:, :2], y0)
    assert np.all(np.isnan(y_missing[:, 2]))
    with pytest.raises(ValueError, match="output 'vy' has no signal.*missing_outputs"):
        rav4.for_model(model)
    # never by its name alone, never onto an input
    d = Drive.from_arrays(rav4.t, {"delta": rav4.signals["delta"], "vx": rav4.signals["vx"],
                                   "ay": rav4.signals["ay"], "r": rav4.signals["r"],
                                   "vy": rav4.reference["ref_vy"]},
                          {"delta": "rad", "vx": "m/s", "ay": "m/s^2", "r": "rad/s",
                           "vy": "m/s"}, reference=("vy",))
    with pytest.raises(ValueError, match="reference channels, for outputs: \\['vy'\\]"):
        d.for_model(model)
    np.testing.assert_array_equal(d.for_model(model, names={"vy": "vy"})[1][:, 2],
                                  rav4.reference["ref_vy"])
    with pytest.raises(ValueError, match="reference channel 'ref_vy' can feed a model output"):
        rav4.for_model(model, names={"ref_vy": "vx"})
    with pytest.raises(ValueError, match="units: signal 'ref_yaw_rate' is in 'rad/s'"):
        rav4.for_model(model, names={"ref_yaw_rate": "vy"})


def test_resample_keeps_the_last_sample_of_stamps_since_the_epoch():
    """Nanosecond stamps since the epoch (ROS, BLF) at 100 Hz: t[-1] - t[0] falls a float64
    rounding under (T - 1) dt; the grid still ends on the last sample, not one short."""
    T = 333
    t = (np.int64(1_700_000_000 * 10**9) + np.arange(T, dtype=np.int64) * 10_000_000) / 1e9
    assert (t[-1] - t[0]) / 0.01 < T - 1  # the rounding this is about
    y = np.sin(0.1 * np.arange(T))
    r = Drive.from_arrays(t, {"a": y}, {"a": "-"}).resample(0.01)
    assert len(r.t) == T and r.t[-1] == t[-1]
    np.testing.assert_allclose(r.signals["a"], y, rtol=0, atol=1e-5)  # stamps off by ~1e-7 s


def test_two_columns_onto_one_model_name_are_refused_naming_both():
    t = np.arange(50) * 0.01
    d = Drive.from_arrays(t, {"steer": 0.01 * np.sin(t), "steer2": 0.02 * np.sin(t),
                              "vx": np.full(50, 20.0), "ay": np.zeros(50), "r": np.zeros(50)},
                          {"steer": "rad", "steer2": "rad", "vx": "m/s", "ay": "m/s^2",
                           "r": "rad/s"})
    with pytest.raises(ValueError, match="^names: columns 'steer' and 'steer2' both map onto "
                                         "'delta'"):
        d.for_model(SingleTrack(dt=0.01), names={"steer": "delta", "steer2": "delta"})
    u, _ = d.for_model(SingleTrack(dt=0.01), names={"steer2": "delta"})  # one each: fine
    np.testing.assert_array_equal(u[:, 0], d.signals["steer2"])


@pytest.mark.parametrize("call", ["resample", "for_model"])
def test_a_max_gap_shorter_than_the_sample_interval_is_refused_naming_it(call):
    """Every sample would be a gap (all NaN): refused, naming max_gap and the interval; an
    interval of exactly max_gap (rounding makes some intervals longer) too; one a little
    longer is bridged (numpy.interp)."""
    t = np.arange(100) * 0.02
    d = Drive.from_arrays(t, {"delta": np.sin(t), "vx": np.full(100, 20.0), "ay": np.cos(t),
                              "r": np.zeros(100)},
                          {"delta": "rad", "vx": "m/s", "ay": "m/s^2", "r": "rad/s"})
    for gap in (0.005, 0.02):
        with pytest.raises(ValueError, match=rf"^max_gap: {gap} s is not longer than the drive's "
                                             r"sample interval \(0.02 s"):
            if call == "resample":
                d.resample(0.01, max_gap=gap)
            else:
                d.for_model(SingleTrack(dt=0.01), max_gap=gap)
    r = d.resample(0.01, max_gap=0.021)
    np.testing.assert_allclose(r.signals["ay"], np.interp(r.t, t, np.cos(t)), rtol=1e-13)


def test_max_gap_is_checked_when_the_drive_is_on_the_models_grid_already():
    """A drive already at the model's dt is not resampled; a max_gap shorter than its interval
    is still refused naming it (it was ignored), and a valid one changes nothing."""
    t = np.arange(100) * 0.01
    d = Drive.from_arrays(t, {"delta": np.sin(t), "vx": np.full(100, 20.0), "ay": np.cos(t),
                              "r": np.zeros(100)},
                          {"delta": "rad", "vx": "m/s", "ay": "m/s^2", "r": "rad/s"})
    with pytest.raises(ValueError, match=r"^max_gap: 0.001 s is not longer than the drive's "
                                         r"sample interval \(0.01 s"):
        d.for_model(SingleTrack(dt=0.01), max_gap=0.001)
    for a, b in zip(d.for_model(SingleTrack(dt=0.01), max_gap=0.05),
                    d.for_model(SingleTrack(dt=0.01))):
        np.testing.assert_array_equal(a, b)
