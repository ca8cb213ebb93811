"""``vehjax fit`` and ``vehjax estimate`` on drive files end to end (in process, through
``vehjax.cli.main``).

The drives are a linear single-track car with known cornering stiffnesses, integrated exactly
between samples (zero-order hold through scipy's matrix exponential of the textbook linear
equations, written here: not the filter's RK4 step), measured with white noise, written as a
logger would (steering in deg, speed in km/h, ay in g, the yaw rate in deg/s, time in ms, the
true sideslip as a reference column).
"""

import json
import math

import numpy as np
import pytest
from scipy.linalg import expm

import vehjax
from vehjax import cli
from vehjax.commands import config as drive_config
from vehjax.data import Drive

SPEC = {"m": 1500.0, "iz": 2700.0, "lf": 1.2, "lr": 1.5}
TRUE = {"cf": 9.0e4, "cr": 1.1e5}
DT = 0.01
NOISE = (0.2, 0.005)  # ay [m/s^2], r [rad/s]
STEPS = 1500

CONFIG = """
[drive]
time = "time"
reference = ["beta_true"]
names = { steer = "delta", speed = "vx", acc_y = "ay", yaw_rate = "r" }

[model]
name = "SingleTrack"
dt = 0.01
theta = { m = 1500.0, iz = 2700.0, lf = 1.2, lr = 1.5, cf = 1.2e5, cr = 1.4e5 }

[fit]
params = ["cf", "cr"]
noise = ["R"]
filter = "ekf"
process_std = [1e-3, 3e-4]
meas_std = [0.3, 0.01]
P0_std = [0.1, 0.01]
"""


def _matrices(vx):
    """The linear single-track equations (small angles): x' = A x + B delta, ay = C x + D delta
    for x = (vy, r), at the speed vx [m/s]."""
    m, iz, lf, lr = SPEC["m"], SPEC["iz"], SPEC["lf"], SPEC["lr"]
    cf, cr = TRUE["cf"], TRUE["cr"]
    A = np.array([[-(cf + cr) / (m * vx), (lr * cr - lf * cf) / (m * vx) - vx],
                  [(lr * cr - lf * cf) / (iz * vx), -(lf**2 * cf + lr**2 * cr) / (iz * vx)]])
    B = np.array([cf / m, lf * cf / iz])
    C = A[0] + np.array([0.0, vx])  # ay = vy' + vx r
    return A, B, C, B[0]


def truth(seed: int, steps: int = STEPS):
    """(t (T,) [s], delta [rad], vx [m/s], states (T, 2), measurements (T, 2)): the input
    held over (t_{k-1}, t_k], the state at t_k integrated exactly from the one at t_{k-1}."""
    rng = np.random.default_rng(seed)
    t = DT * np.arange(1, steps + 1)
    ph = rng.uniform(0.0, 2 * np.pi, 4)
    delta = np.deg2rad(1.5) * sum(np.sin(2 * np.pi * f * t + p)
                                  for f, p in zip((0.25, 0.6, 1.3), ph))
    vx = 20.0 + 3.0 * np.sin(2 * np.pi * 0.05 * t + ph[3])
    x, xs, ys = np.zeros(2), [], []
    for k in range(steps):
        A, B, C, D = _matrices(vx[k])
        M = np.zeros((3, 3))
        M[:2, :2], M[:2, 2] = A * DT, B * DT
        E = expm(M)
        x = E[:2, :2] @ x + E[:2, 2] * delta[k]
        xs.append(x)
        ys.append([C @ x + D * delta[k], x[1]])
    ys = np.array(ys) + rng.normal(size=(steps, 2)) * np.array(NOISE)
    return t, delta, vx, np.array(xs), ys


def write_drive(path, seed: int, steps: int = STEPS):
    """A drive CSV in a logger's units; returns the truth of :func:`truth`."""
    t, delta, vx, xs, ys = truth(seed, steps)
    cols = {"time [ms]": 1e3 * t, "steer [deg]": np.degrees(delta), "speed [km/h]": 3.6 * vx,
            "acc_y [g]": ys[:, 0] / 9.80665, "yaw_rate [deg/s]": np.degrees(ys[:, 1]),
            "beta_true [rad]": np.arctan(xs[:, 0] / vx)}
    with open(path, "w") as fh:
        fh.write(",".join(cols) + "\n")
        for row in np.stack(list(cols.values()), axis=1):
            fh.write(",".join(repr(float(v)) for v in row) + "\n")
    return t, delta, vx, xs, ys


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """`vehjax fit` on drive 1: (folder, the fit.json content)."""
    d = tmp_path_factory.mktemp("drive_fit")
    write_drive(d / "drive1.csv", seed=1)
    return d, fit_in(d, "drive1.csv", CONFIG)


def fit_in(d, drive: str, config: str) -> dict:
    """`vehjax fit` of the drive file ``d / drive`` with ``config`` (car.toml) into d / "fit":
    the fit.json content."""
    (d / "car.toml").write_text(config)
    code = cli.main(["fit", str(d / drive), "--config", str(d / "car.toml"),
                     "--out", str(d / "fit"), "--no-progress"])
    assert code == 0
    return json.loads((d / "fit" / "fit.json").read_text())


def check_stiffnesses(content: dict) -> None:
    """cf, cr recovered within 3 of their standard errors (each under 5 % of the value), R
    near the measurement noise's variances."""
    res = content["result"]
    for k, v in TRUE.items():
        se = res["std_errors"][k]
        assert 0 < se < 0.05 * v, (k, se)
        assert abs(res["values"][k] - v) < 3 * se, (k, res["values"][k], se)
    np.testing.assert_allclose(np.diag(content["filter"]["R"]), np.square(NOISE), rtol=0.15)


def test_fit_recovers_the_stiffnesses_within_their_standard_errors(fitted):
    d, content = fitted
    check_stiffnesses(content)
    report = (d / "fit" / "report.txt").read_text()
    assert "cf" in report and "+-" in report and "filter: ekf" in report
    for png in ("fitted.png", "innovations.png"):
        assert (d / "fit" / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # the spec values and the fitted ones, every parameter by name
    assert content["model"]["theta"]["m"] == SPEC["m"]
    assert content["model"]["theta"]["cf"] == content["result"]["values"]["cf"]


def test_estimate_equals_vehjax_filter_and_tracks_the_sideslip(fitted, tmp_path):
    d, content = fitted
    t, delta, vx, xs, ys = write_drive(tmp_path / "drive2.csv", seed=2)
    code = cli.main(["estimate", str(tmp_path / "drive2.csv"), "--fit", str(d / "fit" / "fit.json"),
                     "--out", str(tmp_path / "est")])
    assert code == 0
    est = Drive.from_csv(tmp_path / "est" / "estimates.csv")
    np.testing.assert_allclose(est.t, t, rtol=0, atol=1e-12)
    assert est.units["vy"] == "m/s" and est.units["r_std"] == "rad/s"
    # the same filter built in Python from the fitted values
    theta = [content["model"]["theta"][k] for k in ("m", "iz", "lf", "lr", "cf", "cr")]
    model = vehjax.models.SingleTrack(dt=DT, theta=theta)
    ekf = vehjax.filters.ekf(model, np.array(content["filter"]["Q"]),
                             np.array(content["filter"]["R"]))
    us = np.stack([delta, vx], axis=1)
    ref = vehjax.filter(ekf, ys, us, x0=np.zeros(2), P0=np.array([0.1, 0.01]) ** 2)
    for i, n in enumerate(("vy", "r")):
        np.testing.assert_allclose(est.signals[n], np.asarray(ref.states)[:, i], rtol=1e-9,
                                   atol=1e-12)
        np.testing.assert_allclose(est.signals[f"{n}_std"],
                                   np.sqrt(np.asarray(ref.covariances)[:, i, i]), rtol=1e-9)
    beta = np.arctan(est.signals["vy"] / vx)
    rms = math.sqrt(np.mean((beta - np.arctan(xs[:, 0] / vx)) ** 2))
    assert rms < np.deg2rad(0.02), np.degrees(rms)  # 0.006 deg; beta = 0: 0.5 deg
    assert rms < 0.1 * np.std(np.arctan(xs[:, 0] / vx))
    assert (tmp_path / "est" / "estimates.png").stat().st_size > 10_000


def _other_layout(path, steps):
    """A drive whose accelerometer column is named otherwise, and a configuration for it."""
    write_drive(path, seed=3, steps=steps)
    text = path.read_text()
    path.write_text(text.replace("acc_y [g]", "ay_g [g]", 1))
    toml = path.with_suffix(".toml")
    toml.write_text(CONFIG.split("[model]")[0].replace("acc_y", "ay_g")
                    + "[estimate]\nsmooth = true\n")
    return path, toml


def test_estimate_with_another_layout_smoothed_writes_parquet_or_says_why_not(fitted, tmp_path,
                                                                             capsys):
    """--config's [drive] and [estimate] replace the fit's; Parquet holds the CSV's columns
    (read back by pyarrow), or a one-line note says why there is none."""
    d, _ = fitted
    drive, toml = _other_layout(tmp_path / "other.csv", steps=200)
    assert cli.main(["estimate", str(drive), "--fit", str(d / "fit" / "fit.json"),
                     "--config", str(toml), "--out", str(tmp_path / "est")]) == 0
    err = capsys.readouterr().err
    assert "EKF smoother" in err
    csv = Drive.from_csv(tmp_path / "est" / "estimates.csv")
    assert len(csv.t) == 200 and np.all(np.isfinite(csv.signals["vy"]))
    try:
        import pyarrow.parquet as pq
    except ImportError:
        assert [line for line in err.splitlines() if "pyarrow" in line] == [
            "vehjax estimate: note: pyarrow is not installed, so no estimates.parquet "
            "(pip install 'vehjax[export]')"]
        assert not (tmp_path / "est" / "estimates.parquet").exists()
        return
    table = pq.read_table(tmp_path / "est" / "estimates.parquet")
    assert table.column_names == ["t [s]", "vy [m/s]", "vy_std [m/s]", "r [rad/s]",
                                  "r_std [rad/s]"]
    assert table.schema.field("vy [m/s]").metadata == {b"unit": b"m/s"}
    np.testing.assert_array_equal(table.column("t [s]").to_numpy(), csv.t)
    np.testing.assert_array_equal(table.column("vy [m/s]").to_numpy(), csv.signals["vy"])
    np.testing.assert_array_equal(table.column("r_std [rad/s]").to_numpy(),
                                  csv.signals["r_std"])


# ---- bad input: one line on stderr, exit code 2, no traceback, nothing written -------------

BAD_CONFIGS = [
    (CONFIG.replace("params =", "parms ="), ["car.toml [fit] parms", "unknown key"]),
    (CONFIG + "\n[fitt]\n", ["car.toml", "unknown section [fitt]"]),
    (CONFIG.replace('steer = "delta"', 'steerr = "delta"'), ["[drive] names", "steerr"]),
    (CONFIG.replace('time = "time"', 'time = "tme"'), ["[drive] time", "tme"]),
    (CONFIG.replace('"SingleTrack"', '"SingleTrak"'), ["[model] name", "SingleTrak"]),
    (CONFIG.replace('"SingleTrack"', '"no_such_package.cars:make"'),
     ["[model] name", "no_such_package"]),
    (CONFIG.replace("cf = 1.2e5", "cff = 1.2e5"), ["[model] theta", "cff"]),
    (CONFIG.replace("cf = 1.2e5", "cf = -1.2e5"), ["[model] theta", "cf"]),
    (CONFIG.replace("meas_std = [0.3, 0.01]", "meas_std = [0.3, 0.01, 1.0]"),
     ["[fit] meas_std", "one per ay, r"]),
    (CONFIG.replace("meas_std = [0.3, 0.01]", "meas_std = [0.3, 0.0]"),
     ["[fit] meas_std[1]", "> 0"]),
    (CONFIG.replace('params = ["cf", "cr"]', 'params = ["cf", "cx"]'), ["[fit] params", "cx"]),
    (CONFIG.replace('filter = "ekf"', 'filter = "pf"'), ["[fit] filter", "ekf, ukf, ckf"]),
    (CONFIG.replace('filter = "ekf"', "steps = 0"), ["[fit] steps", ">= 1"]),
    (CONFIG.replace("P0_std = [0.1, 0.01]", ""), ["[fit] P0_std", "missing"]),
    (CONFIG.replace('noise = ["R"]', 'noise = ["R", "S"]'), ["[fit] noise", "'S'"]),
    (CONFIG + "\n[estimate]\nsmooth = 1\n", ["[estimate] smooth", "true or false"]),
    (CONFIG.replace("[fit]", "[fit]\ninput_noise = { steer = 0.001 }"),
     ["[fit] input_noise", "steer"]),
    (CONFIG.replace("filter =", "bounds = { cf = [1e3, 5e4] }\nfilter ="),
     ["[fit] bounds", "cf starts at 120000", "[1000, 50000]"]),
    (CONFIG.replace("filter =", "bounds = { m = [1e3, 5e4] }\nfilter ="),
     ["[fit] bounds", "'m' is not among the fitted params"]),
    (CONFIG.replace("filter =", "bounds = { cf = [5e4, 1e3] }\nfilter ="),
     ["[fit] bounds.cf", "low < high"]),
    (CONFIG.replace("names = {", "names = [").replace('r" }', 'r" ]'), ["car.toml", "TOML"]),
]


def _refused(capsys, argv, words, out_dir):
    code = cli.main(argv)
    io = capsys.readouterr()
    lines = io.err.splitlines()
    assert code == 2, io.err
    assert len(lines) == 1 and "Traceback" not in io.err, io.err
    for w in words:
        assert w in lines[0], (w, lines[0])
    assert io.out == "" and not out_dir.exists()


@pytest.fixture(scope="module")
def small_drive(tmp_path_factory):
    path = tmp_path_factory.mktemp("small") / "drive.csv"
    write_drive(path, seed=4, steps=50)
    return path


@pytest.mark.parametrize("text, words", BAD_CONFIGS)
def test_fit_refuses_a_bad_configuration_in_one_line(small_drive, tmp_path, capsys, text, words):
    (tmp_path / "car.toml").write_text(text)
    _refused(capsys, ["fit", str(small_drive), "--config", str(tmp_path / "car.toml"), "--out",
                      str(tmp_path / "out")], words, tmp_path / "out")


@pytest.mark.parametrize("extra, words", [
    (["--model", "NoSuchModel"], ["--model: [model] name", "NoSuchModel"]),
    (["--params", "cf,cx"], ["[fit] params", "cx"]),
    (["--params", "cf,cf"], ["--params", "unique"]),
    (["--filter", "pf"], ["--filter", "pf"]),
])
def test_fit_refuses_bad_options_in_one_line(small_drive, tmp_path, capsys, extra, words):
    (tmp_path / "car.toml").write_text(CONFIG)
    _refused(capsys, ["fit", str(small_drive), "--config", str(tmp_path / "car.toml"), "--out",
                      str(tmp_path / "out"), *extra], words, tmp_path / "out")


def test_a_bad_configuration_as_a_program_is_one_line_exit_2(small_drive, tmp_path):
    import subprocess
    import sys

    (tmp_path / "car.toml").write_text(CONFIG.replace('"SingleTrack"', '"SingleTrak"'))
    out = subprocess.run([sys.executable, "-m", "vehjax.cli", "fit", str(small_drive),
                          "--config", str(tmp_path / "car.toml"), "--out", str(tmp_path / "o")],
                         capture_output=True, text=True)
    assert out.returncode == 2 and out.stdout == "", out.stderr
    assert out.stderr.splitlines() == [out.stderr.strip()] and "SingleTrak" in out.stderr


def test_missing_files_are_one_line(small_drive, tmp_path, capsys):
    (tmp_path / "car.toml").write_text(CONFIG)
    out = tmp_path / "out"
    _refused(capsys, ["fit", str(tmp_path / "nope.csv"), "--config", str(tmp_path / "car.toml"),
                      "--out", str(out)], ["DRIVE", "nope.csv", "not a file"], out)
    _refused(capsys, ["fit", str(small_drive), "--config", str(tmp_path / "nope.toml"),
                      "--out", str(out)], ["--config", "nope.toml"], out)
    _refused(capsys, ["estimate", str(small_drive), "--fit", str(tmp_path / "fit.json"),
                      "--out", str(out)], ["--fit", "not a file"], out)
    (tmp_path / "fit.json").write_text('{"format": "other"}')
    _refused(capsys, ["estimate", str(small_drive), "--fit", str(tmp_path / "fit.json"),
                      "--out", str(out)], ["--fit", "vehjax-fit/1"], out)


def test_estimate_refuses_a_drive_laid_out_otherwise(fitted, tmp_path, capsys):
    d, _ = fitted
    drive, _ = _other_layout(tmp_path / "other.csv", steps=50)
    _refused(capsys, ["estimate", str(drive), "--fit", str(d / "fit" / "fit.json"), "--out",
                      str(tmp_path / "out")], ["fit.json [drive] names", "acc_y"], tmp_path / "out")
    (tmp_path / "bad.toml").write_text(CONFIG.replace("max_gap", "max_gapp")
                                       .replace("[drive]", "[drive]\nmax_gapp = 0.1"))
    _refused(capsys, ["estimate", str(drive), "--fit", str(d / "fit" / "fit.json"), "--config",
                      str(tmp_path / "bad.toml"), "--out", str(tmp_path / "out")],
             ["bad.toml [drive] max_gapp", "unknown key"], tmp_path / "out")
    # a key the configuration's [drive] maps wrongly names that file, not the fit
    (tmp_path / "bad.toml").write_text(CONFIG.replace("acc_y", "acc_z"))
    _refused(capsys, ["estimate", str(drive), "--fit", str(d / "fit" / "fit.json"), "--config",
                      str(tmp_path / "bad.toml"), "--out", str(tmp_path / "out")],
             ["bad.toml [drive] names", "acc_z"], tmp_path / "out")


def test_a_users_model_by_module_path(tmp_path, monkeypatch):
    """'package.module:factory' is called with dt and [model] options, then theta applied."""
    from vehjax.commands import setup

    (tmp_path / "my_cars.py").write_text(
        "import vehjax\n"
        "def lagged(dt, substeps=2):\n"
        "    return vehjax.models.SingleTrackLag(dt=dt, substeps=substeps)\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    model = setup.build_model({"name": "my_cars:lagged", "options": {"substeps": 3},
                               "theta": {"m": 1600.0}}, 0.02)
    assert type(model).__name__ == "SingleTrackLag" and model.dt == 0.02
    assert model.substeps == 3 and float(model.theta[0]) == 1600.0
    with pytest.raises(ValueError, match=r"\[model\] options: .*wheels"):
        setup.build_model({"name": "my_cars:lagged", "options": {"wheels": 4}}, 0.02)
    with pytest.raises(ValueError, match=r"\[model\] name: 'my_cars' has no function 'nope'"):
        setup.build_model({"name": "my_cars:nope"}, 0.02)


def test_the_configurations_names_are_vehjaxs():
    from vehjax.commands import setup
    from vehjax.tune import likelihood, options, staged

    assert drive_config.NOISE_KINDS == likelihood.NOISE_KINDS
    assert drive_config.OPTIMIZERS == tuple(options.OPTIMIZERS)
    assert drive_config.STARTS == staged.STARTS
    assert drive_config.FILTERS == tuple(setup.BUILDERS)


@pytest.mark.slow  # a second fit (UKF): `pytest -m slow`
def test_ukf_fit_with_biases_input_noise_and_x0_rebuilds_exactly(tmp_path):
    """[model] output_biases, [fit] input_noise fitted and fit_x0 with the UKF: fit.json holds
    them, and `vehjax estimate` equals vehjax.filter with the rebuilt UKF."""
    write_drive(tmp_path / "d1.csv", seed=5, steps=400)
    t, delta, vx, xs, ys = write_drive(tmp_path / "d2.csv", seed=6, steps=300)
    text = (CONFIG.replace("dt = 0.01", 'dt = 0.01\noutput_biases = ["ay"]')
            .replace('noise = ["R"]', 'noise = ["R", "input"]\nfit_x0 = true\nsteps = 20\n'
                     'input_noise = { delta = 5e-4 }')
            .replace("process_std = [1e-3, 3e-4]", "process_std = [1e-3, 3e-4, 1e-5]")
            .replace("P0_std = [0.1, 0.01]", "P0_std = [0.1, 0.01, 0.1]"))
    (tmp_path / "car.toml").write_text(text)
    assert cli.main(["fit", str(tmp_path / "d1.csv"), "--config", str(tmp_path / "car.toml"),
                     "--out", str(tmp_path / "fit"), "--filter", "ukf", "--no-progress"]) == 0
    content = json.loads((tmp_path / "fit" / "fit.json").read_text())
    assert content["filter"]["family"] == "ukf" and len(content["x0_fitted"]) == 3
    assert content["x0"] == [0.0, 0.0, 0.0]  # a new drive starts from the configuration's prior
    assert set(content["filter"]["input_noise"]) == {"delta"}
    assert cli.main(["estimate", str(tmp_path / "d2.csv"), "--fit",
                     str(tmp_path / "fit" / "fit.json"), "--out", str(tmp_path / "est")]) == 0
    est = Drive.from_csv(tmp_path / "est" / "estimates.csv")
    theta = [content["model"]["theta"][k] for k in ("m", "iz", "lf", "lr", "cf", "cr")]
    model = vehjax.models.with_output_biases(vehjax.models.SingleTrack(dt=DT, theta=theta),
                                             ("ay",))
    ukf = vehjax.filters.ukf(model, np.array(content["filter"]["Q"]),
                             np.array(content["filter"]["R"]),
                             input_noise=content["filter"]["input_noise"])
    ref = vehjax.filter(ukf, ys, np.stack([delta, vx], axis=1), x0=np.zeros(3),
                        P0=np.array([0.1, 0.01, 0.1]) ** 2)
    for i, n in enumerate(("vy", "r", "ay_bias")):
        np.testing.assert_allclose(est.signals[n], np.asarray(ref.states)[:, i], rtol=1e-9,
                                   atol=1e-12)
