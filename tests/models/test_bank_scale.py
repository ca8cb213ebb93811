"""vehjax.models.bank_scale: SingleTrackBank with the virtual yaw rate's scale (eps)."""

import numpy as np
import pytest

from vehjax.models import bank_scale


def test_virtual_scale_model_and_augmented_ekf_model():
    """VirtualScaleBank and the augmented EKF's model against SingleTrackBank and eq. 10 with
    a rolling-radius mismatch, written out here."""
    import jax.numpy as jnp

    from vehjax.models import SingleTrackBank

    base = SingleTrackBank()
    m = bank_scale.VirtualScaleBank()
    assert m.state_names[-1] == "eps" and m.nx == 6
    x = jnp.array([0.3, 0.05, 0.01, 0.002, -0.001, -4e-4])
    u = jnp.array([15.0, 0.01])
    th = jnp.asarray(m.theta)
    xn = np.asarray(m.transition(x, u, th))
    np.testing.assert_allclose(xn[:5], base.transition(x[:5], u, th), rtol=1e-12, atol=1e-15)
    assert xn[5] == -4e-4                                         # a constant
    y = np.asarray(m.observe(x, u, th))
    # (v_rr - v_rl) / l_T with v_rr = (1 + eps) v_right, v_right - v_left = r l_T, to first order
    v_left = 15.0 - 0.05 * bank_scale.TRACK / 2
    v_right = 15.0 + 0.05 * bank_scale.TRACK / 2
    exact = ((1 - 4e-4) * v_right - v_left) / bank_scale.TRACK
    assert y[4] == pytest.approx(exact, abs=4e-4 * 0.05)
    np.testing.assert_allclose(y[:4], np.asarray(base.observe(x[:5], u, th))[:4], rtol=1e-12)
    B = np.asarray(m.bank_noise_gain())
    assert B.shape == (6,) and B[5] == 0.0
    for bank in (False, True):
        am = bank_scale.augmented_model(base, bank=bank)
        xa = np.zeros(am.nx)
        xa[:6] = [0.3, 0.05, 0.002, 0.1, 0.001, -4e-4]
        ya = np.asarray(am.observe(jnp.asarray(xa), u, th))
        full = jnp.array([0.3, 0.05, 0.0, 0.0, 0.0])
        yb = np.asarray(base.observe(full, u.at[1].add(0.002), th))
        assert ya[0] == pytest.approx(yb[0] + 0.1) and ya[1] == pytest.approx(0.05 + 0.001)
        assert ya[2] == pytest.approx(0.05 - 4e-4 * 15.0 / bank_scale.TRACK)
        assert am.nx == (10 if bank else 6) and am.ny == (4 if bank else 3)
