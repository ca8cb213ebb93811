"""`vehjax reproduce dutta2019` at a reduced size: runs end to end, tables and figures written."""

import numpy as np
import pytest

from vehjax import cli
from vehjax.reproduce import dutta2019


def test_reduced_study_writes_tables_and_figures(tmp_path, capsys):
    rc = cli.main([
        "reproduce", "dutta2019", "--runs", "3", "--particles", "64",
        "--kinematic-duration", "4", "--dynamic-duration", "3", "--out", str(tmp_path),
    ])
    assert rc == 0
    report = (tmp_path / "report.md").read_text()
    for heading in ("Table I", "Table II", "Table III", "Fig. 6"):
        assert heading in report
    for name in ("Dual EKF", "Dual UKF", "Particle+UKF", "Joint EKF", "Joint UKF"):
        assert f"| {name} (vehjax) |" in report
    assert "| Dual UKF (paper) | 1.580 | 1.390 |" in report
    for png in ("fig4_5_kinematic_lf_lr.png", "fig6_input_frequency.png",
                "fig7_9_dynamic_states.png", "fig10_12_dynamic_m_cx_cy.png"):
        assert (tmp_path / png).stat().st_size > 10_000
    assert "Table III" in capsys.readouterr().out


def test_dynamic_excitation_is_of_the_vehicledata_kind():
    from vehjax.models import Dynamic3DOF
    import jax
    import vehjax as vj

    dyn = Dynamic3DOF(dt=0.01)
    scn = dutta2019.dynamic_scenario(dyn, duration=20.0)
    sim = vj.simulate(dyn, scn, runs=1, key=jax.random.key(0))
    vx, vy, r = np.asarray(sim.states)[0].T
    assert 18.0 < vx.min() and vx.max() < 22.5  # speed held near 20 m/s, swinging by about 1
    assert 0.1 < np.abs(vy).max() < 1.5 and 0.1 < np.abs(r).max() < 0.5  # lateral excitation
    assert np.all(np.asarray(scn.inputs)[:, 2:4] == 0.0)  # front-wheel drive


def test_bad_options_are_refused():
    with pytest.raises(ValueError, match="--filters"):
        dutta2019.main(["--filters", "Dual KF"])
    with pytest.raises(ValueError, match="--runs"):
        dutta2019.main(["--runs", "1"])
