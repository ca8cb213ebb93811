"""`vehjax reproduce consistency` at a reduced size: NEES / NIS of filters with matched noise
(issue 17, item 4). The full study (every filter on every built-in model, 100 runs x 3 s) is
the command's default; here 100 runs x 1 s on the 3-DOF model and the bank model."""

import contextlib
import io

import numpy as np
import pytest

from vehjax.reproduce import consistency, load


def test_registered_with_its_defaults():
    assert load("consistency") is consistency
    p = consistency.parser()
    assert p.get_default("runs") == 100
    assert p.get_default("models").split(",") == list(consistency.MODELS)
    assert p.get_default("filters").split(",") == list(consistency.FILTERS)
    assert p.get_default("particles") is None  # per model: consistency.PARTICLES
    assert consistency.PARTICLES == {"KinematicBicycle": 20000, "SingleTrackBank": 20000}


@pytest.mark.parametrize("argv, name", [
    (["--models", "Dynamic3DOF,Unicycle"], "--models"),
    (["--filters", "EKF,KF"], "--filters"),
    (["--runs", "1"], "--runs"),
    (["--particles", "1"], "--particles"),
    (["--filters", "MPF", "--models", "Dynamic3DOF"], "--filters"),
])
def test_bad_options_name_the_option(argv, name, tmp_path):
    with pytest.raises(ValueError, match=name):
        consistency.main(argv + ["--out", str(tmp_path)])


def _study(tmp_path, models, filters, particles):
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = consistency.main(["--models", models, "--filters", filters, "--runs", "100",
                               "--duration", "1", "--particles", str(particles),
                               "--out", str(tmp_path)])
    assert rc == 0
    rows = {(r["model"], r["filter"]): r for r in _csv(tmp_path / "consistency.csv")}
    for key, r in rows.items():
        assert r["runs"] == 100 and r["steps"] == 100 and r["diverged"] == 0, key
        assert r["particles"] == (particles if "PF" in key[1] else None), key
    return rows, (tmp_path / "report.md").read_text()


def test_matched_filters_are_consistent_and_the_paper_ackf_is_not(tmp_path, monkeypatch):
    """With the noise matched, the EKF and the bootstrap PF (3000 particles: on this 1 s data
    the PF's own Monte-Carlo error shows at 1000, 0.890 of the steps in the band and NEES 1.04
    per dof against 0.950 and 1.02 with 3000, measured when the data's seed moved) keep the
    run-averaged NEES and NIS inside the 95 % band on at least 90 % of the steps; the Sage-Husa
    ACKF as the paper prints it (d_1 = 1: the first innovation replaces the correct prior) is
    over-confident, and the report says so."""
    # the PF at LLVM level 3 (tests compile at 0, tests/conftest.py): 3 x 10^7 particle-steps
    # run about 15x slower at level 0 than the longer compile costs
    monkeypatch.setitem(consistency.COMPILER_OPTIONS, ("Dynamic3DOF", "bootstrap PF"),
                        {"xla_backend_optimization_level": 3})
    rows, report = _study(tmp_path, "Dynamic3DOF", "EKF,ACKF (paper),bootstrap PF", 3000)
    assert set(rows) == {("Dynamic3DOF", f) for f in ("EKF", "ACKF (paper)", "bootstrap PF")}
    for key, r in rows.items():
        if key[1] == "ACKF (paper)":
            assert r["nees_in"] < 0.5 and r["nees_per_dof"] > 2.0, (key, r)
        else:
            assert r["nees_in"] >= 0.9 and r["nis_in"] >= 0.9, (key, r)
            assert 0.8 < r["nees_per_dof"] < 1.25 and 0.8 < r["nis_per_dof"] < 1.25, (key, r)
    assert "| Dynamic3DOF | ACKF (paper) | 100 x 100 |" in report
    assert report.count("**not consistent** (over-confident)") == 1
    assert "2 of 3 filter-model pairs run" in report
    assert "not ACKF (paper) on Dynamic3DOF." in report


def test_mpf_with_known_statistics_is_near_consistent(tmp_path):  # and the Kalman-bias row
    """The MPF with its noise statistics as good as known, on data from its own noise model
    (paper 004 eq. 3-10): the NIS stays in the band and the NEES averages within 20 % of its
    degrees of freedom. (Its NEES leaves the band early in the run, under-confident on the
    bank states: the full study's report gives the numbers.)"""
    rows, report = _study(tmp_path, "SingleTrackBank",
                          "MPF (known noise),MPF (covariances known; biases as Kalman states)", 300)
    r = rows[("SingleTrackBank", "MPF (known noise)")]
    assert r["nis_in"] >= 0.9 and 0.8 < r["nis_per_dof"] < 1.25, r
    assert 0.8 < r["nees_per_dof"] < 1.2, r
    assert "| SingleTrackBank | MPF (known noise) | 100 x 100 |" in report
    # the parameter table: with the statistics as good as known every final estimate sits on
    # its true value, inside its interval in every run, with no spread over runs
    line = next(ln for ln in report.splitlines()
                if ln.startswith("| SingleTrackBank | MPF (known noise) |") and " / " in ln)
    cells = [c.strip().split(" / ") for c in line.strip("| ").split(" | ")[2:]]
    assert len(cells) == 8, line  # offset, std, then bias and std of each of the 3 sensors
    for cover, spread in cells:
        assert float(cover) == 1.0 and float(spread) < 0.05, line
    # with the biases as Kalman states (the NiW's confounded bias estimate taken out), the bias
    # intervals are honest: each holds the truth in most runs, the spread near the reported std
    r = rows[("SingleTrackBank", "MPF (covariances known; biases as Kalman states)")]
    assert 0.8 < r["nees_per_dof"] < 1.2 and r["nis_in"] >= 0.9, r
    line = next(ln for ln in report.splitlines()
                if ln.startswith("| SingleTrackBank | MPF (covariances known; biases as Kalman")
                and " / " in ln)
    cells = [c.strip().split(" / ") for c in line.strip("| ").split(" | ")[2:]]
    for cover, spread in cells[2:5]:  # ay, r, roll-rate bias
        assert float(cover) >= 0.85 and 0.7 < float(spread) < 1.2, line


def _csv(path):
    lines = path.read_text().splitlines()
    keys = lines[0].split(",")
    out = []
    for ln in lines[1:]:
        vals = dict(zip(keys, ln.split(",")))
        out.append({k: v if k in ("model", "filter") else
                    (int(v) if k in ("runs", "steps", "diverged") else
                     (int(v) if v else None) if k == "particles" else float(v))
                    for k, v in vals.items()})
    assert all(np.isfinite(r["seconds"]) for r in out)
    return out
