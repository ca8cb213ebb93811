"""`vehjax reproduce berntorp2018` (paper 004) at a reduced size, and a smoke test of
`vehjax bench marginalized`. The marginalized PF takes tens of seconds to compile on CPU, so
each test compiles it as few times as it can."""

import contextlib
import io
import math
import re

import numpy as np
import pytest

from vehjax.reproduce import berntorp2018, load


def _run(argv):
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = berntorp2018.main(argv)
    return rc, buf.getvalue()


def _links_exist(out):
    report = (out / "report.md").read_text()
    links = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", report)
    for name in links:
        assert (out / name).stat().st_size > 0, name
    return report, links


def _row(text, label):
    line = next(ln for ln in text.splitlines() if ln.startswith(f"| {label}"))
    return line.split("|")[2:-1]


def test_registered_with_a_citation():
    assert load("berntorp2018") is berntorp2018
    assert "Berntorp" in berntorp2018.PAPER and "2018" in berntorp2018.PAPER
    assert berntorp2018.parser().get_default("runs") == 100


def test_citation_as_published():
    assert ("Noise-statistics learning of automotive-grade sensors using adaptive marginalized "
            "particle filtering") in berntorp2018.PAPER
    assert "Journal of Dynamic Systems, Measurement, and Control" in berntorp2018.PAPER
    assert "TR2018-181" in berntorp2018.PAPER
    assert "Noise-statistics learning" in berntorp2018.parser().description


def test_virtual_yaw_scale_from_the_sensors_alone():
    # synthetic: a yaw rate the estimate never sees, a gyro bias, a rolling-radius mismatch
    rng = np.random.default_rng(0)
    T, track, eps, bias = 6000, 1.61, -4e-4, 6e-4
    t = np.arange(T) * 0.01
    vx = 14.0 + 6.0 * np.sin(2 * np.pi * t / 40.0)
    r = 0.02 * np.sin(2 * np.pi * t / 7.0) + 0.01 * rng.standard_normal(T).cumsum() / 50
    gyro = r + bias + 0.003 * rng.standard_normal(T)
    r_virt = r + eps * vx / track + 0.008 * rng.standard_normal(T)
    r_virt[::97] = np.nan                                           # missing samples skipped
    e, b = berntorp2018.virtual_yaw_scale(gyro, r_virt, vx, track)
    # least-squares standard errors of the two coefficients, from the noise written above
    A = np.stack([np.ones(T), -vx / track], 1)
    se = np.sqrt(np.diag(np.linalg.inv(A.T @ A))) * math.hypot(0.003, 0.008)
    assert abs(b - bias) < 4 * se[0] and abs(e - eps) < 4 * se[1], (b, e, se)


def test_bank_path_and_looped_inputs():
    t = np.arange(1, 12001) * 0.01
    acc, phi = berntorp2018.bank_profile(t, 0.01)
    assert np.degrees(np.abs(phi)).max() == pytest.approx(6.0, abs=0.05)
    assert np.degrees(phi[-1]) == pytest.approx(0.0, abs=1e-6)  # two full cycles
    U = np.arange(10.0)[:, None] * np.ones((1, 2))
    L = berntorp2018.looped_inputs(U, 25)
    assert L.shape == (25, 2) and np.all(np.abs(np.diff(L[:, 0])) <= 1.0)  # continuous joints


def test_simulation_study(tmp_path):
    rc, text = _run(["--runs", "3", "--duration", "20", "--particles", "50", "--seed", "1",
                     "--out", str(tmp_path)])
    assert rc == 0
    report, links = _links_exist(tmp_path)
    assert len(links) == 5 and "Steady-state" in report
    mean, worst, _ = _row(text, "steering offset error [deg]")
    assert np.isfinite(float(mean)) and float(worst) < 0.28  # better than ignoring the offset
    for s in ("ay", "r", "roll_rate"):
        rel = float(_row(text, f"{s} std relative error")[0])
        assert -0.9 < rel < 1.0, (s, rel)  # started at +1 (twice the truth)
    assert float(_row(text, "bank phi RMS error")[0]) < 1.0  # deg; the bank reaches 6 deg
    assert float(_row(text, "r RMS error")[0]) < 0.3  # deg/s, the gyro's own noise


def test_drive_study(tmp_path):
    rc, text = _run(["--drive", "--runs", "2", "--duration", "15", "--particles", "50",
                     "--out", str(tmp_path)])
    assert rc == 0
    report, links = _links_exist(tmp_path)
    assert len(links) == 3 and "EKF" in report  # Fig. 8, 9, 10 (bank)
    roll = _row(text, "bank angle - pose roll")
    assert float(roll[0].split()[1]) < 2.0  # deg: the bank estimate follows the car's roll
    off = float(_row(text, "steering offset, road wheel")[0])
    assert abs(off) < 1.0  # deg at the road wheel
    for label in ("raw gyro", "gyro - MPF bias", "gyro - EKF bias", "MPF yaw-rate estimate",
                  "EKF yaw-rate estimate"):
        rms, mx, share = (float(v) for v in _row(text, label))
        assert 0 < rms < 1.0 and mx < 3.0 and 0 <= share <= 1, label
    eps = float(re.search(r"rolling-radius mismatch eps = ([-+0-9.e]+)", text)[1])
    assert -8e-4 < eps < -1e-4                       # 15 s of it; -4.0e-4 from the whole segment
    for label in ("MPF vy estimate", "EKF vy estimate", "vy = 0"):
        rms, mx = (float(v) for v in _row(text, label))
        assert 0 < rms < 0.5 and mx < 1.0, label
    assert "Virtual yaw rate's scale" in report


@pytest.mark.slow  # a study: `pytest -m slow` (README)
def test_bench_marginalized_smoke(capsys):
    from vehjax.cli import load_benchmark

    bench = load_benchmark("marginalized")
    assert bench.parser().get_default("runs") == 100
    assert bench.main(["--particles", "20,40", "--steps", "20", "--runs", "1", "--repeat", "1"]) == 0
    out = capsys.readouterr().out
    assert "target: 1 run" in out and "linearity" in out
    assert "operations and bytes accessed per particle-step" in out and "GFLOP/s" in out
    assert "compiled with XLA's defaults" in out
