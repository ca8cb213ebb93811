"""vehjax.models.with_output_biases: constant bias states added to outputs."""

import jax
import numpy as np
import pytest

import vehjax as vj
from vehjax.models import Dynamic3DOF, Model, SingleTrackBank, with_output_biases

jax.config.update("jax_enable_x64", True)


def test_states_transition_observe_and_bank_gain():
    base = SingleTrackBank(dt=0.01)
    m = with_output_biases(base, ("ay", "r", "roll_rate"))
    assert m.state_names == base.state_names + ("ay_bias", "r_bias", "roll_rate_bias")
    assert m.state_units[5:] == tuple(base.output_units[base.output_names.index(n)]
                                      for n in ("ay", "r", "roll_rate"))
    assert m.output_names == base.output_names and m.dt == base.dt
    rng = np.random.default_rng(0)
    x, u = rng.normal(size=8) * 0.1, np.array([20.0, 0.01])
    np.testing.assert_allclose(m.transition(x, u, m.theta)[:5], base.transition(x[:5], u, m.theta))
    np.testing.assert_array_equal(m.transition(x, u, m.theta)[5:], x[5:])
    y, y0 = np.asarray(m.observe(x, u, m.theta)), np.asarray(base.observe(x[:5], u, m.theta))
    for j, name in enumerate(("ay", "r", "roll_rate")):
        k = base.output_names.index(name)
        np.testing.assert_allclose(y[k], y0[k] + x[5 + j])
    others = [k for k, n in enumerate(base.output_names) if n not in ("ay", "r", "roll_rate")]
    np.testing.assert_array_equal(y[others], y0[others])
    np.testing.assert_array_equal(m.bank_noise_gain(), np.r_[base.bank_noise_gain(), 0, 0, 0])
    # a model without a bank gain gets none
    assert not hasattr(with_output_biases(Dynamic3DOF(dt=0.01), "vy"), "bank_noise_gain")


@pytest.mark.parametrize("outputs", [(), ("vy", "vy"), ("ay",), "nope"])
def test_bad_outputs_are_refused(outputs):
    with pytest.raises(ValueError, match="outputs"):
        with_output_biases(Dynamic3DOF(dt=0.01), outputs)


def test_ekf_with_a_bias_state_is_the_kalman_filter_of_the_augmented_system():
    """On a linear model the EKF of the biased model is the Kalman recursion on the augmented
    matrices (written here in numpy), and it learns a constant sensor bias."""
    F, Bu, H = np.array([[0.95, 0.1], [0.0, 0.9]]), np.array([[0.0], [0.1]]), np.eye(2)
    model = Model(transition=lambda x, u, th: F @ x + Bu @ u, observe=lambda x, u, th: H @ x,
                  dt=0.1, state_names=("p", "v"), input_names=("a",), output_names=("p_m", "v_m"))
    m = with_output_biases(model, "v_m")
    Q, R = np.diag([1e-4, 1e-3]), np.diag([0.05, 0.02]) ** 2
    Qa, Fa = np.zeros((3, 3)), np.eye(3)
    Qa[:2, :2], Fa[:2, :2] = Q, F
    Ha = np.c_[H, [0.0, 1.0]]
    rng = np.random.default_rng(1)
    T, bias = 300, 0.3
    us = np.sin(0.05 * np.arange(T))[:, None]
    x, ys = np.zeros(2), []
    for t in range(T):
        x = F @ x + Bu @ us[t] + rng.multivariate_normal(np.zeros(2), Q)
        ys.append(H @ x + [0.0, bias] + rng.multivariate_normal(np.zeros(2), R))
    ys = np.array(ys)
    x0, P0 = np.zeros(3), np.diag([0.1, 0.1, 1.0])
    out = vj.filter(vj.filters.ekf(m, Qa, R), ys, us, x0=x0, P0=P0)
    xa, P = x0.copy(), P0.copy()
    for t in range(T):
        xa = Fa @ xa + np.r_[Bu @ us[t], 0.0]
        P = Fa @ P @ Fa.T + Qa
        S = Ha @ P @ Ha.T + R
        K = np.linalg.solve(S, Ha @ P).T
        xa = xa + K @ (ys[t] - Ha @ xa)
        P = (np.eye(3) - K @ Ha) @ P
        np.testing.assert_allclose(np.asarray(out.states)[t], xa, rtol=1e-8, atol=1e-10)
    assert abs(xa[2] - bias) < 3 * np.sqrt(P[2, 2])
