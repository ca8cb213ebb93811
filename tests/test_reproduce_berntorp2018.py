"""`vehjax reproduce berntorp2018` (paper 004) at a reduced size, and a smoke test of
`vehjax bench marginalized`. The marginalized PF takes tens of seconds to compile on CPU, so
each test compiles it as few times as it can."""

import contextlib
import io
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
    for label in ("raw gyro", "gyro - MPF bias", "gyro - EKF bias"):
        rms, mx, share = (float(v) for v in _row(text, label))
        assert 0 < rms < 1.0 and mx < 3.0 and 0 <= share <= 1, label


def test_bench_marginalized_smoke(capsys):
    from vehjax.cli import load_benchmark

    bench = load_benchmark("marginalized")
    assert bench.parser().get_default("runs") == 100
    assert bench.main(["--particles", "20,40", "--steps", "20", "--runs", "1", "--repeat", "1"]) == 0
    out = capsys.readouterr().out
    assert "target: 1 run" in out and "linearity" in out
    assert "operations and bytes accessed per particle-step" in out and "GFLOP/s" in out
    assert "compiled with XLA's defaults" in out
