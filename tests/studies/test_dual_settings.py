"""The settings of Dutta et al. (2019)'s problem (vehjax.studies.dual_settings): the matched ones are
the simulation's noise."""

import numpy as np

import vehjax as vj
from vehjax.studies import dual_settings


def test_matched_settings_are_the_simulation_noise():
    kin = vj.models.KinematicBicycle(dt=0.02)
    cfg = dual_settings.matched_settings(dual_settings.KINEMATIC_SETTINGS, kin,
                                         np.array([1.5, 1.5]), [(0.5, 2.5), (0.5, 2.5)])
    np.testing.assert_allclose(cfg["Q"], 0.1**2 * 0.02)  # 0.1 per sqrt(s), per step of 0.02 s
    np.testing.assert_allclose(cfg["R"], 0.1**2)
    np.testing.assert_allclose(cfg["P_theta0"], 2.0**2 / 12)  # variance of U(0.5, 2.5)
    np.testing.assert_allclose(cfg["Q_theta"], (1.5e-3) ** 2)
