"""`vehjax reproduce dutta2019` at a reduced size: runs end to end, tables and figures written."""

import jax
import numpy as np
import pytest

import vehjax as vj
from vehjax import cli
from vehjax.reproduce import dutta2019


def test_reduced_study_writes_tables_and_figures(tmp_path, capsys):
    rc = cli.main([
        "reproduce", "dutta2019", "--runs", "3", "--particles", "64", "--settings", "matched",
        "--filters", "Dual EKF,Dual UKF,Particle+UKF",
        "--kinematic-duration", "4", "--dynamic-duration", "3", "--out", str(tmp_path),
    ])
    assert rc == 0
    report = (tmp_path / "report.md").read_text()
    for heading in ("Table I", "Table II", "Table III", "Fig. 6"):
        assert f"### {heading}" in report
    for name in ("Dual EKF", "Dual UKF", "Particle+UKF"):
        assert f"| {name} (vehjax) |" in report
    assert "| Joint EKF (vehjax) |" not in report
    assert "| Dual UKF (paper) | 1.580 | 1.390 |" in report
    assert "| Particle+UKF (paper) | 0.1727 | 0.1566 | 0.0630 |" in report
    assert "nan" not in report.lower()
    for png in ("fig4_5_kinematic_lf_lr", "fig6_input_frequency", "fig7_9_dynamic_states",
                "fig10_12_dynamic_m_cx_cy"):
        assert (tmp_path / f"{png}_matched.png").stat().st_size > 10_000
    assert "Table III" in capsys.readouterr().out


def test_matched_settings_are_the_simulation_noise():
    kin = vj.models.KinematicBicycle(dt=0.02)
    cfg = dutta2019.matched_settings(dutta2019.KINEMATIC_SETTINGS, kin, np.array([1.5, 1.5]),
                                     [(0.5, 2.5), (0.5, 2.5)])
    np.testing.assert_allclose(cfg["Q"], 0.1**2 * 0.02)  # 0.1 per sqrt(s), per step of 0.02 s
    np.testing.assert_allclose(cfg["R"], 0.1**2)
    np.testing.assert_allclose(cfg["P_theta0"], 2.0**2 / 12)  # variance of U(0.5, 2.5)
    np.testing.assert_allclose(cfg["Q_theta"], (1.5e-3) ** 2)


def test_dynamic_excitation_is_of_the_vehicledata_kind():
    dyn = vj.models.Dynamic3DOF(dt=0.02)
    scn = dutta2019.dynamic_scenario(dyn, duration=40.0)
    sim = vj.simulate(dyn, scn, runs=1, key=jax.random.key(0))
    vx, vy, r = np.asarray(sim.states)[0].T
    assert 12.0 < vx.min() < 17.0 and 21.0 < vx.max() < 25.0  # speed swinging around 20 m/s
    assert 0.2 < np.abs(vy).max() < 2.0 and 0.2 < np.abs(r).max() < 0.6  # lateral excitation
    assert np.all(np.asarray(scn.inputs)[:, 2:4] == 0.0)  # front-wheel drive


def test_bad_options_are_refused():
    with pytest.raises(ValueError, match="--filters"):
        dutta2019.main(["--filters", "Dual KF"])
    with pytest.raises(ValueError, match="--settings"):
        dutta2019.main(["--settings", "tuned"])
    with pytest.raises(ValueError, match="--runs"):
        dutta2019.main(["--runs", "1"])
