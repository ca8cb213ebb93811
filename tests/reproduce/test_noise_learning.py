"""`vehjax reproduce noise-learning` (issue #33, item 3): registration, option checks, the
verdict rules on hand-made numbers, and a tiny run (slow: it compiles twelve filters) whose
report holds every method's row in both tables."""

import contextlib
import io

import pytest

from vehjax.reproduce import load, noise_learning as nl

DEG = nl.DEG


def test_registered_with_its_defaults():
    assert load("noise-learning") is nl
    p = nl.parser()
    assert p.get_default("runs") == 100
    assert p.get_default("duration") == 180.0
    assert p.get_default("methods").split(",") == list(nl.METHODS)


@pytest.mark.parametrize("argv, name", [
    (["--methods", "EKF,VB-R (CKF)"], "--methods"),
    (["--forgetting", "1.5"], "--forgetting"),
])
def test_bad_options_name_themselves(argv, name, tmp_path):
    with pytest.raises(ValueError, match=name):
        nl.main(argv + ["--out", str(tmp_path)])


def _metrics(**over):
    m = dict(method="x", diverged=0, ms=0.1, offset_mean=0.01, offset_rms=0.05,
             ay_bias=0.01, r_bias=0.02, roll_rate_bias=0.02, ay_std=0.02, r_std=-0.05,
             roll_rate_std=0.0, coverage={"delta_offset": 0.95, "ay_bias": 0.93, "ay_std": 0.9},
             nees_in=0.93, nees_dof=1.0, nis_in=0.95, nis_dof=1.0)
    m.update(over)
    return m


def test_verdict_rules():
    assert nl.verdict(_metrics()) == ("learns the offset; biases tracked; stds within 10 %; "
                                      "honest (NEES, coverage)")
    v = nl.verdict(_metrics(offset_mean=0.06))
    assert v.startswith("misses the offset")
    # a quarter of the gyro's 0.3 deg/s noise std is the limit of "tracked"
    assert "off on r" in nl.verdict(_metrics(r_bias=0.076))
    assert "biases tracked" in nl.verdict(_metrics(r_bias=0.074))
    assert "off on roll_rate" in nl.verdict(_metrics(roll_rate_std=-0.11))
    v = nl.verdict(_metrics(nees_in=0.5, nees_dof=3.0))
    assert "over-confident" in v and "not honest" in v
    v = nl.verdict(_metrics(nees_in=0.5, nees_dof=0.85))
    assert "under-confident" in v and "not honest" in v
    v = nl.verdict(_metrics(nees_in=0.86, nees_dof=1.01))  # near 1: no lean claimed
    assert "NEES in band 0.86, 1.01 per dof" in v and "confident" not in v
    v = nl.verdict(_metrics(coverage={"delta_offset": 0.95, "ay_std": 0.6}))
    assert "ay_std interval holds in 0.60 of runs" in v
    m = _metrics()
    for k in ("offset_mean", "offset_rms", "ay_bias", "r_bias", "roll_rate_bias"):
        del m[k]
    assert nl.verdict(m).startswith("no offset; no biases")


@pytest.mark.slow
def test_tiny_study_writes_every_methods_row(tmp_path):
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = nl.main(["--runs", "2", "--duration", "3", "--particles", "10",
                      "--drive-executions", "2", "--drive-particles", "10", "--iterations", "2",
                      "--out", str(tmp_path)])
    assert rc == 0
    report = (tmp_path / "report.md").read_text()
    assert (tmp_path / "noise_learning.png").stat().st_size > 10_000
    sim, drive = report.split("## RAV4 drive")
    for meth in nl.METHODS:
        assert sum(line.startswith(f"| {meth} |") for line in sim.splitlines()) == 1, meth
        assert sum(line.startswith(f"| {meth} |") for line in drive.splitlines()) == 1, meth
    # the numbers are numbers: the VB and MPF rows report an offset, the ACKF none
    row = {line.split(" | ")[0][2:]: line.split(" | ") for line in sim.splitlines()
           if line.startswith("| ")}
    assert row["Sage-Husa ACKF"][1] == "-"
    for meth in ("VB-R (CKF)", "VB-PR (CKF)", "MPF (paper)", "MPF (consistent)",
                 "augmented EKF"):
        mean, rms = (float(v) for v in row[meth][1].split(" / "))
        assert abs(mean) < 1.0 and 0 <= rms < 1.0
