"""simulate: shapes, names, determinism, noise statistics, perturbations, bad input."""

import jax
import numpy as np
import pytest

import vehjax as vj
from vehjax.models import Dynamic3DOF, KinematicBicycle


@pytest.fixture(scope="module")
def setup():
    model = Dynamic3DOF()
    scn = vj.scenarios.sine_steer(model, duration=3.0)
    return model, scn


def test_shapes_names_and_determinism(setup):
    model, scn = setup
    a = vj.simulate(model, scn, runs=4, key=jax.random.key(3), process_std=0.01, meas_std=0.1)
    b = vj.simulate(model, scn, runs=4, key=jax.random.key(3), process_std=0.01, meas_std=0.1)
    c = vj.simulate(model, scn, runs=4, key=jax.random.key(4), process_std=0.01, meas_std=0.1)
    T = len(scn.t)
    assert a.states.shape == (4, T, 3) and a.measurements.shape == (4, T, 3)
    assert a.inputs.shape == (T, 5) and a.theta.shape == (4, 7)
    assert a.state_names == model.state_names and a.output_names == model.output_names
    np.testing.assert_array_equal(a.measurements, b.measurements)
    assert not np.allclose(a.measurements, c.measurements)
    assert not np.allclose(a.states[0], a.states[1])  # runs differ


def test_noise_free_truth_replays_the_scenario(setup):
    model, scn = setup
    sim = vj.simulate(model, scn, runs=2)
    x = scn.x0
    for k in range(50):
        x = model.transition(x, scn.inputs[k], model.theta)
    np.testing.assert_allclose(sim.states[1, 49], x, rtol=1e-13)
    np.testing.assert_allclose(sim.measurements, sim.states, rtol=1e-13)


def test_noise_statistics(setup):
    model, scn = setup
    r_std = np.array([0.2, 0.05, 0.01])
    q_std = np.array([0.02, 0.01, 0.003])
    sim = vj.simulate(model, scn, runs=40, key=jax.random.key(0), process_std=q_std, meas_std=r_std)
    resid = np.asarray(sim.measurements - sim.states).reshape(-1, 3)
    n = resid.shape[0]
    # sample std of n Gaussian draws is within 5/sqrt(2n) relative of the truth with overwhelming odds
    np.testing.assert_allclose(resid.std(axis=0), r_std, rtol=5 / np.sqrt(2 * n))
    assert np.all(np.abs(resid.mean(axis=0)) < 5 * r_std / np.sqrt(n))
    prev = np.concatenate([np.broadcast_to(sim.x0[:, None], (40, 1, 3)), sim.states[:, :-1]], axis=1)
    pred = jax.jit(jax.vmap(jax.vmap(lambda x, u, th: model.transition(x, u, th), (0, 0, None)),
                            (0, None, 0)))(prev, sim.inputs, sim.theta)  # one compile
    w = np.asarray(sim.states - pred).reshape(-1, 3)
    np.testing.assert_allclose(w.std(axis=0), q_std, rtol=5 / np.sqrt(2 * n))


def test_time_varying_scale_biases_offset_and_parameters(setup):
    model, scn = setup
    T = len(scn.t)
    scale = np.where(scn.t < 1.0, 0.0, 1.0)
    sim = vj.simulate(model, scn, runs=30, key=jax.random.key(1), meas_std=0.1, meas_scale=scale,
                      param_std=0.1, bias_walk_std=[0.0, 0.01, 0.0], bias0=[0.5, 0.0, 0.0],
                      steering_offset=0.01)
    resid = np.asarray(sim.measurements - sim.states - sim.biases)
    assert np.max(np.abs(resid[:, scn.t < 1.0])) < 1e-12 and np.std(resid[:, scn.t >= 1.0]) > 0.05
    np.testing.assert_allclose(sim.biases[:, :, 0], 0.5)
    steps = np.diff(np.asarray(sim.biases[:, :, 1]), axis=1).ravel()
    np.testing.assert_allclose(steps.std(), 0.01, rtol=5 / np.sqrt(2 * steps.size))
    rel = np.asarray(sim.theta) / np.asarray(model.theta) - 1.0
    np.testing.assert_allclose(rel.std(), 0.1, rtol=0.2)
    np.testing.assert_array_equal(sim.inputs, scn.inputs)  # the filter sees measured inputs
    # with the offset the truth steers more than the measured input: the yaw rate grows
    clean = vj.simulate(model, scn, runs=1, theta=model.theta)
    same = vj.simulate(model, scn, runs=1, theta=model.theta, steering_offset=0.01)
    assert float(np.mean(same.states[0, :, 2] - clean.states[0, :, 2])) > 0.01


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(runs=0), "runs"),
        (dict(runs=2.5), "runs"),
        (dict(meas_std=-0.1), "meas_std"),
        (dict(process_std=[0.1, 0.1]), "process_std"),
        (dict(meas_std=float("inf")), "meas_std"),
        (dict(meas_scale=np.ones(3)), "meas_scale"),
        (dict(theta=np.ones(3)), "theta"),
        (dict(steering_offset=float("nan")), "steering_offset"),
    ],
)
def test_bad_input_raises_before_tracing(setup, kwargs, match):
    model, scn = setup
    with pytest.raises(ValueError, match=match):
        vj.simulate(model, scn, **kwargs)


def test_scenario_for_another_model_is_rejected(setup):
    model, scn = setup
    with pytest.raises(ValueError, match="scenario"):
        vj.simulate(KinematicBicycle(), scn)
