"""vehjax.data.Drive on files as people export them: pandas' ``DataFrame.to_csv`` and the csv
module's writers in each dialect (byte-order mark, CRLF, quoted headers, blank lines, trailing
separators, tabs, semicolons with decimal commas) give the same Drive as the plain file, checked
against the DataFrame's own values and the test's own unit factors; duplicate or empty names and
non-numeric cells refused naming the column and the row; ``for_model`` with and without units
declared by the model."""

import csv
import math

import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest

import vehjax  # noqa: F401  (float64)
from vehjax.data import Drive
from vehjax.data.drive import declared_units
from vehjax.data.table import MISSING, is_missing
from vehjax.models import Model, SingleTrack

N = 40
UNIT = {"t": "ms", "steer": "deg", "speed": "km/h", "ay": "g", "r": "deg/s"}
FACTOR = {"t": 1e-3, "steer": math.pi / 180, "speed": 1 / 3.6, "ay": 9.80665,
          "r": math.pi / 180}


@pytest.fixture(scope="module")
def frame():
    """A logger's table: time in ms, signals in everyday units, some samples missing."""
    rng = np.random.default_rng(46)
    t = np.cumsum(rng.uniform(8.0, 12.0, N))
    df = pd.DataFrame({
        "t [ms]": t,
        "steer [deg]": rng.normal(0.0, 30.0, N),
        "speed [km/h]": rng.uniform(20.0, 120.0, N),
        "ay [g]": rng.normal(0.0, 0.3, N) * 10.0 ** rng.integers(-8, 2, N),
        "r [deg/s]": rng.normal(0.0, 5.0, N),
    })
    df.loc[[3, 17], "ay [g]"] = np.nan
    df.loc[25, "r [deg/s]"] = np.nan
    return df


def _check_against_frame(d, df):
    """The drive holds the frame's values times the test's own SI factors, NaN where missing."""
    np.testing.assert_array_equal(d.t, df["t [ms]"].to_numpy() * FACTOR["t"])
    assert set(d.signals) == {"steer", "speed", "ay", "r"} and not d.reference
    for name in d.signals:
        want = df[f"{name} [{UNIT[name]}]"].to_numpy() * FACTOR[name]
        np.testing.assert_array_equal(d.signals[name], want)
    assert d.units == {"steer": "rad", "speed": "m/s", "ay": "m/s^2", "r": "rad/s"}


def _same(a, b):
    np.testing.assert_array_equal(a.t, b.t)
    assert a.units == b.units and a.dt == b.dt
    assert list(a.signals) == list(b.signals)
    for k in a.signals:
        np.testing.assert_array_equal(a.signals[k], b.signals[k])


@pytest.fixture(scope="module")
def plain(frame, tmp_path_factory):
    path = tmp_path_factory.mktemp("plain") / "plain.csv"
    frame.to_csv(path, index=False)
    d = Drive.from_csv(path)
    _check_against_frame(d, frame)
    return d


# -- pandas' writer ------------------------------------------------------------------------------
PANDAS = {
    "bom": dict(encoding="utf-8-sig"),                        # Excel's "CSV UTF-8"
    "crlf": dict(lineterminator="\r\n"),
    "quoted": dict(quoting=csv.QUOTE_ALL),                    # headers and numbers in quotes
    "nonnumeric": dict(quoting=csv.QUOTE_NONNUMERIC),         # quoted headers only
    "tab": dict(sep="\t"),
    "semicolon": dict(sep=";"),
    "semicolon_quoted": dict(sep=";", quoting=csv.QUOTE_ALL),
    "tab_quoted": dict(sep="\t", quoting=csv.QUOTE_ALL, lineterminator="\r\n"),
    "pipe": dict(sep="|"),
    "na_rep_NA": dict(na_rep="NA"),
    "na_rep_nan": dict(na_rep="nan"),
    "na_rep_NaN": dict(na_rep="NaN"),
    "utf16": dict(encoding="utf-16", sep="\t"),               # Excel's "Unicode Text"
    "excel_like": dict(encoding="utf-8-sig", lineterminator="\r\n", quoting=csv.QUOTE_ALL),
}


@pytest.mark.parametrize("kind", sorted(PANDAS))
def test_pandas_dialects_give_the_plain_drive(kind, frame, plain, tmp_path):
    path = tmp_path / "x.csv"
    frame.to_csv(path, index=False, **PANDAS[kind])
    d = Drive.from_csv(path)
    _same(d, plain)
    _check_against_frame(d, frame)
    encoding = PANDAS[kind].get("encoding")
    if encoding:                                              # the same, named
        _same(Drive.from_csv(path, encoding=encoding.replace("-sig", "")), plain)


def test_pandas_trailing_separator_column(frame, plain, tmp_path):
    """A frame with an empty-named last column of empty cells: every line ends with ','."""
    path = tmp_path / "x.csv"
    frame.assign(**{"": ""}).to_csv(path, index=False)
    assert all(line.endswith(",") for line in path.read_text().splitlines())
    _same(Drive.from_csv(path), plain)


def test_semicolons_with_decimal_commas(frame, plain, tmp_path):
    path = tmp_path / "x.csv"
    frame.to_csv(path, index=False, sep=";", decimal=",")
    assert "," in path.read_text()
    with pytest.raises(ValueError, match=r"separated by ';'.*decimal comma: pass decimal=','"):
        Drive.from_csv(path)
    _same(Drive.from_csv(path, decimal=","), plain)
    frame.to_csv(path, index=False, sep=";", decimal=",", quoting=csv.QUOTE_ALL,
                 encoding="utf-8-sig", lineterminator="\r\n")
    _same(Drive.from_csv(path, decimal=","), plain)
    # a point as well as a comma (a thousands separator) is not read
    path.write_text("t [s];x [m]\n0;1\n0,1;1.234,5\n0,2;3\n")
    with pytest.raises(ValueError, match=r"data row 2, line 3: not a number in column 'x'"):
        Drive.from_csv(path, decimal=",")


# -- the csv module's writers, and text edited by hand ------------------------------------------
def _rows(frame, missing=""):
    yield list(frame.columns)
    for row in frame.itertuples(index=False):
        yield [missing if np.isnan(v) else repr(float(v)) for v in row]


@pytest.mark.parametrize("dialect", ["excel", "excel-tab", "unix"])
def test_csv_module_dialects(dialect, frame, plain, tmp_path):
    path = tmp_path / "x.csv"
    with open(path, "w", newline="") as fh:
        csv.writer(fh, dialect=dialect).writerows(_rows(frame))
    _same(Drive.from_csv(path), plain)
    _same(Drive.from_csv(path, delimiter=csv.get_dialect(dialect).delimiter), plain)


@pytest.mark.parametrize("end", ["\n", "\r\n", "\r"])
@pytest.mark.parametrize("edit", ["trailing", "blank_lines", "row_of_separators", "spaces",
                                  "short_header_trailing", "all"])
def test_hand_edited_layouts(edit, end, frame, plain, tmp_path):
    lines = [",".join(r) for r in _rows(frame)]
    if edit in ("spaces", "all"):
        lines = [ln.replace(",", ", ") for ln in lines]
        lines[0] = ", ".join(f'"{h}"' for h in frame.columns)   # quoted header
    if edit in ("trailing", "all"):                           # a logger ends lines with ','
        lines = [ln + "," for ln in lines]
    if edit == "short_header_trailing":                       # only the rows carry it
        lines = lines[:1] + [ln + ",," for ln in lines[1:]]
    if edit in ("blank_lines", "all"):
        lines = ["", ""] + lines[:1] + [""] + lines[1:10] + ["", "  "] + lines[10:] + ["", ""]
    if edit in ("row_of_separators", "all"):                  # a spreadsheet's empty row
        lines = lines[:5] + [",,,,,"] + lines[5:]
    path = tmp_path / "x.csv"
    path.write_bytes(("\ufeff" if edit == "all" else "").encode() +
                     end.join(lines).encode() + end.encode())
    _same(Drive.from_csv(path), plain)


# -- names ---------------------------------------------------------------------------------------
def test_duplicate_and_empty_names_refused(frame, tmp_path):
    path = tmp_path / "x.csv"
    path.write_text("t [s],x [m],y [m],x [m]\n0,1,2,3\n0.1,1,2,3\n")
    with pytest.raises(ValueError, match=r"names 'x \[m\]' twice \(columns 2 and 4\)"):
        Drive.from_csv(path)
    path.write_text("t [s],x [m],x [cm]\n0,1,2\n0.1,1,2\n")      # one name, two units
    with pytest.raises(ValueError, match=r"names 'x' twice \(columns 2 and 3"):
        Drive.from_csv(path)
    frame.to_csv(path)                                          # pandas' index: no name
    with pytest.raises(ValueError, match=r"column 1 of the header has no name.*index=False"):
        Drive.from_csv(path)
    path.write_text("t [s],,x [m]\n0,1,2\n0.1,1,2\n")
    with pytest.raises(ValueError, match="column 2 of the header has no name"):
        Drive.from_csv(path)
    path.write_text("t [s], [m]\n0,1\n0.1,1\n")                 # a unit without a name
    with pytest.raises(ValueError, match=r"column 2 \('\[m\]'\) has no name"):
        Drive.from_csv(path)
    path.write_text("t [s],x [m],\n0,1,\n0.1,1,7\n")            # a value without a column
    with pytest.raises(ValueError, match=r"line 3: 3 fields but the header names 2 columns "
                                         r"\('7' has no column name"):
        Drive.from_csv(path)
    path.write_text("t;x [m]\n0;1\n0.1;2\n")
    with pytest.raises(ValueError, match=r"separated by ';': pass delimiter=';'"):
        Drive.from_csv(path, delimiter=",")


# -- cells ---------------------------------------------------------------------------------------
def test_missing_cells_are_a_small_documented_set(tmp_path):
    assert MISSING == ("", "nan", "NA")
    for cell in ("", "  ", "nan", "NaN", "NAN", " nan ", "NA"):
        assert is_missing(cell)
    for cell in ("n/a", "N/A", "na", "-", "null", "None", "#N/A", "0"):
        assert not is_missing(cell)
    path = tmp_path / "x.csv"
    path.write_text("t [s],x [m]\n0,1\n0.1,\n0.2,nan\n0.3,NaN\n0.4, NA \n0.5,6\n")
    x = Drive.from_csv(path).signals["x"]
    np.testing.assert_array_equal(np.isnan(x), [0, 1, 1, 1, 1, 0])
    for bad in ("n/a", "-", "null", "1.2.3", "#N/A"):
        path.write_text(f"t [s],x [m],y [m]\n\n0,1,2\n\n0.1,2,3\n0.2,3,{bad}\n")
        # data row 3 is on line 6 (two blank lines above it)
        with pytest.raises(ValueError, match=rf"data row 3, line 6: not a number in column 'y': "
                                             rf"'{bad}'"):
            Drive.from_csv(path)


def test_time_cells(tmp_path):
    path = tmp_path / "x.csv"
    path.write_text("t [s],x [m]\n0,1\n\nNA,2\n0.2,3\n")
    with pytest.raises(ValueError, match=r"data row 2, line 4: time column 't' has no time stamp"):
        Drive.from_csv(path)
    path.write_text("t,x [m]\n2024-05-01 12:00:00.00,1\n2024-05-01 12:00:00.01,2\n")
    with pytest.raises(ValueError, match=r"data row 1, line 2: not a number in column 't'.*"
                                         r"convert date-times to seconds first"):
        Drive.from_csv(path)
    path.write_text("t [s],x [m]\n0,1\n0.2,2\n0.1,3\n")
    with pytest.raises(ValueError, match=r"data row 3, line 4: time stamps must be strictly "
                                         r"increasing"):
        Drive.from_csv(path)


def test_from_arrays_text_cells():
    t = np.arange(5) * 0.1
    with pytest.raises(ValueError, match=r"values: row 3 \(index 2\): not a number in column "
                                         r"'speed': 'n/a'"):
        Drive.from_arrays(t, {"x": np.ones(5), "speed": ["1", "2", "n/a", "4", "5"]},
                          {"x": "m", "speed": "km/h"})
    with pytest.raises(ValueError, match=r"row 2 \(index 1\): not a number in column 'x': "
                                         r"\{'a': 1\}"):
        Drive.from_arrays(t, {"x": [1.0, {"a": 1}, 2.0, 3.0, 4.0]}, {"x": "m"})
    with pytest.raises(ValueError, match=r"'x' has infinite values, the first inf at row 4"):
        Drive.from_arrays(t, {"x": [1.0, 2.0, 3.0, np.inf, 4.0]}, {"x": "m"})
    d = Drive.from_arrays(t, {"x": ["3.6", None, "", "nan", "NA"],
                              "y": pd.Series([1.0, None, 2.0, 3.0, 4.0], dtype=object)},
                          {"x": "km/h", "y": "m"})
    np.testing.assert_array_equal(d.signals["x"], [1.0, np.nan, np.nan, np.nan, np.nan])
    np.testing.assert_array_equal(d.signals["y"], [1.0, np.nan, 2.0, 3.0, 4.0])


# -- units declared by the model -----------------------------------------------------------------
def _linear_model(**kw):
    return Model(transition=lambda x, u, th: jnp.array([0.9 * x[0] + u[0] * u[1]]),
                 observe=lambda x, u, th: jnp.array([x[0], 2.0 * x[0]]), dt=0.01,
                 state_names=("v",), input_names=("delta", "vx"), output_names=("ay", "r"),
                 **kw)


@pytest.fixture(scope="module")
def drive():
    t = np.arange(50) * 0.01
    rng = np.random.default_rng(7)
    vals = {"steer": rng.normal(0, 20, 50), "speed": rng.uniform(30, 90, 50),
            "ay": rng.normal(0, 1, 50), "r": rng.normal(0, 5, 50)}
    return Drive.from_arrays(t, vals, {"steer": "deg", "speed": "km/h", "ay": "m/s^2",
                                       "r": "deg/s"}), vals


NAMES = {"steer": "delta", "speed": "vx"}


def test_for_model_without_declared_units(drive):
    d, vals = drive
    model = _linear_model()
    assert model.input_units == ("-", "-")                      # what it reads, not declared
    assert declared_units(model, "input") == (None, None)
    u, y = d.for_model(model, NAMES)                            # unchecked, in SI
    np.testing.assert_allclose(u, np.stack([np.radians(vals["steer"]), vals["speed"] / 3.6], 1),
                               rtol=1e-15)
    np.testing.assert_allclose(y, np.stack([vals["ay"], np.radians(vals["r"])], 1), rtol=1e-15)
    # a built-in model declares its units and keeps checking them
    assert declared_units(SingleTrack(dt=0.01), "input") == ("rad", "m/s")
    with pytest.raises(ValueError, match="units: signal 'speed' is in 'm/s' but the model's "
                                         "input 'delta' is in 'rad'"):
        d.for_model(SingleTrack(dt=0.01), {"speed": "delta", "steer": "vx"})


def test_for_model_with_declared_units(drive):
    d, vals = drive
    model = _linear_model(units={"delta": "deg", "vx": "m/s", "r": "rad/s"})
    assert declared_units(model, "input") == ("deg", "m/s")
    assert declared_units(model, "output") == (None, "rad/s")   # ay left out: not checked
    u, y = d.for_model(model, NAMES)
    np.testing.assert_allclose(u[:, 0], vals["steer"], rtol=1e-14)   # back to the model's deg
    np.testing.assert_allclose(u[:, 1], vals["speed"] / 3.6, rtol=1e-15)
    np.testing.assert_allclose(y[:, 1], np.radians(vals["r"]), rtol=1e-15)
    swapped = {"steer": "vx", "speed": "delta"}
    with pytest.raises(ValueError) as err:
        d.for_model(model, swapped)
    msg = str(err.value)
    assert "units: signal 'speed' is in 'm/s' but the model's input 'delta' is in 'deg'" in msg
    assert "Model(..., units={'delta': 'm/s'})" in msg           # the keyword, an example
    bad = _linear_model(units={"delta": "degrees"})
    with pytest.raises(ValueError, match=r"input 'delta' declares the unit 'degrees'.*units="):
        d.for_model(bad, NAMES)


# -- to_csv's promise: from_csv reads it back, whatever the names -------------------------------
ODD = ["a,b", 'say "hi"', "a[1]", "x;y", "tab\there", "Lenkwinkel δ", "g [x]y"]


def test_to_csv_round_trip_with_odd_names(tmp_path):
    t = np.arange(6) * 0.05
    rng = np.random.default_rng(1)
    vals = {n: rng.normal(size=6) for n in ODD}
    vals[ODD[0]][2] = np.nan
    d = Drive.from_arrays(t, vals, dict.fromkeys(ODD, "deg"), reference=(ODD[1],))
    d.to_csv(tmp_path / "x.csv")
    back = Drive.from_csv(tmp_path / "x.csv", reference=(ODD[1],))
    _same(back, d)
    np.testing.assert_array_equal(back.reference[ODD[1]], d.reference[ODD[1]])
    # pandas writes the same header: the same drive
    both = {**d.signals, **d.reference}
    df = pd.DataFrame({"t [s]": t, **{f"{n} [rad]": both[n] for n in ODD}})
    df.to_csv(tmp_path / "p.csv", index=False)
    _same(Drive.from_csv(tmp_path / "p.csv", reference=(ODD[1],)), d)


def test_names_a_file_cannot_keep_are_refused(tmp_path):
    t = np.arange(3) * 0.1
    for bad in ("", " x", "x ", 1):
        with pytest.raises(ValueError, match="values: names must be non-empty strings"):
            Drive.from_arrays(t, {bad: np.ones(3)}, {bad: "m"})
    d = Drive.from_arrays(t, {"t": np.ones(3)}, {"t": "m"})
    with pytest.raises(ValueError, match="a signal is named 't' too"):
        d.to_csv(tmp_path / "x.csv")
    (tmp_path / "y.csv").write_text("t,steer [deg]\n0,1\n0.1,2\n")
    with pytest.raises(ValueError, match=r"units: no column 'stear'"):    # a typo is not ignored
        Drive.from_csv(tmp_path / "y.csv", units={"stear": "rad"})
    assert Drive.from_csv(tmp_path / "y.csv", units={"steer": "rad"}).signals["steer"][1] == 2.0


def test_files_that_are_not_utf8_text(frame, plain, tmp_path):
    path = tmp_path / "x.csv"
    frame.rename(columns={"ay [g]": "ay° [g]"}).to_csv(path, index=False, encoding="cp1252")
    with pytest.raises(ValueError, match=r"is not UTF-8 text \(byte \d+: b'\\xb0'\).*encoding="):
        Drive.from_csv(path)
    d = Drive.from_csv(path, encoding="cp1252")
    np.testing.assert_array_equal(d.signals["ay°"], plain.signals["ay"])
    path.write_bytes(b"PK\x03\x04" + bytes(100))
    with pytest.raises(ValueError, match="zip archive"):
        Drive.from_csv(path)
    for text in ("", "\n\n", "t [s],x [m]\n", "t [s],x [m]\n0,1\n"):
        path.write_text(text)
        with pytest.raises(ValueError, match="no header row|fewer than 2 rows of data"):
            Drive.from_csv(path)
