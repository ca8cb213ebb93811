"""vehjax.studies.banked_road: paper 004's simulated scenario (its bank path and looped inputs)."""

import numpy as np
import pytest

from vehjax.studies import banked_road


def test_bank_path_and_looped_inputs():
    t = np.arange(1, 12001) * 0.01
    acc, phi = banked_road.bank_profile(t, 0.01)
    assert np.degrees(np.abs(phi)).max() == pytest.approx(6.0, abs=0.05)
    assert np.degrees(phi[-1]) == pytest.approx(0.0, abs=1e-6)  # two full cycles
    U = np.arange(10.0)[:, None] * np.ones((1, 2))
    L = banked_road.looped_inputs(U, 25)
    assert L.shape == (25, 2) and np.all(np.abs(np.diff(L[:, 0])) <= 1.0)  # continuous joints
