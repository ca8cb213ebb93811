"""Manoeuvres: shapes, the ISO 3888-1 course followed, open-loop steering profiles, bad input."""

import jax
import numpy as np
import pytest

import vehjax as vj
from vehjax import scenarios
from vehjax.models import Dynamic3DOF, KinematicBicycle, Model

# ISO 3888-1 lane widths for a 1.8 m wide car: 1.1 W + 0.25, 1.2 W + 0.25, 1.3 W + 0.25 [m].
_W = 1.8
_LANES = [((0.0, 15.0), 0.0, 1.1 * _W + 0.25), ((45.0, 70.0), 3.5, 1.2 * _W + 0.25),
          ((95.0, 110.0), 0.0, 1.3 * _W + 0.25)]


@pytest.mark.parametrize("cls", [KinematicBicycle, Dynamic3DOF])
def test_double_lane_change_keeps_the_centre_of_gravity_inside_the_lanes(cls):
    model = cls()
    scn = scenarios.double_lane_change(model, speed=20.0)
    assert scn.inputs.shape == (len(scn.t), model.nu) and scn.x0.shape == (model.nx,)
    X, Y = scn.path[:, 0], scn.path[:, 1]
    assert X[0] == -20.0 and X[-1] > 110.0
    for (x_lo, x_hi), centre, width in _LANES:
        inside = (X >= x_lo) & (X <= x_hi)
        # the simple pure-pursuit driver keeps the CoG between the cones; it does not promise
        # that a 1.8 m wide body clears them at 20 m/s (the dynamic model overshoots ~0.6 m)
        assert np.max(np.abs(Y[inside] - centre)) < width / 2, (x_lo, x_hi)


def test_centreline_has_the_iso_offsets():
    X = np.array([0.0, 15.0, 30.0, 45.0, 57.5, 70.0, 95.0, 120.0])
    np.testing.assert_allclose(scenarios.iso3888_centreline(X), [0, 0, 1.75, 3.5, 3.5, 3.5, 0, 0], atol=1e-12)


def test_open_loop_profiles():
    model = Dynamic3DOF()  # one length for all: the profiles share one compiled drive
    scn = scenarios.sine_steer(model, amplitude=0.04, frequency=0.5, duration=5.0)
    np.testing.assert_allclose(scn.inputs[:, -1], 0.04 * np.sin(np.pi * scn.t), atol=1e-12)
    step = scenarios.step_steer(model, amplitude=0.02, t_step=1.0, duration=5.0)
    assert np.all(step.inputs[step.t < 1.0, -1] == 0.0)
    np.testing.assert_allclose(step.inputs[step.t > 1.2, -1], 0.02)
    ch = scenarios.chirp(model, amplitude=0.02, f0=0.2, f1=2.0, duration=5.0)
    assert np.max(np.abs(ch.inputs[:, -1])) <= 0.02 + 1e-12
    dw = scenarios.sine_with_dwell(model, amplitude=0.05, frequency=0.7, dwell=0.5, t0=1.0, duration=5.0)
    d = np.asarray(dw.inputs[:, -1])
    hold = (dw.t > 1.0 + 0.75 / 0.7 + 0.01) & (dw.t < 1.0 + 0.75 / 0.7 + 0.49)
    np.testing.assert_allclose(d[hold], -0.05, atol=1e-9)
    assert np.all(d[dw.t > 1.0 + 1 / 0.7 + 0.5 + 0.01] == 0.0)
    # the speed controller holds speed with the model's own longitudinal inputs
    assert np.all(np.asarray(scn.inputs[:, 0]) > 0)


def test_scenarios_reject_bad_input():
    model = Dynamic3DOF()
    with pytest.raises(ValueError, match="speed"):
        scenarios.double_lane_change(model, speed=-1.0)
    with pytest.raises(ValueError, match="frequency"):
        scenarios.sine_steer(model, frequency=0.0)
    with pytest.raises(ValueError, match="duration"):
        scenarios.step_steer(model, duration=float("nan"))
    user = Model(transition=lambda x, u, th: x, observe=lambda x, u, th: x, dt=0.1, state_names=("x",))
    with pytest.raises(ValueError, match="from_inputs"):
        scenarios.double_lane_change(user)
    with pytest.raises(ValueError, match="inputs"):
        scenarios.from_inputs(model, np.zeros((10, 3)), np.zeros(3))


def test_from_inputs_feeds_simulate():
    user = Model(transition=lambda x, u, th: 0.9 * x + u, observe=lambda x, u, th: x, dt=0.1,
                 state_names=("x",), input_names=("u",))
    scn = scenarios.from_inputs(user, np.ones((30, 1)), [0.0])
    sim = vj.simulate(user, scn, runs=2)
    np.testing.assert_allclose(sim.states[0, -1, 0], (1 - 0.9**30) / 0.1, rtol=1e-12)


def test_slip_and_steer_is_of_the_vehicledata_kind():
    dyn = vj.models.Dynamic3DOF(dt=0.02)
    scn = scenarios.slip_and_steer(dyn, duration=40.0)
    sim = vj.simulate(dyn, scn, runs=1, key=jax.random.key(0))
    vx, vy, r = np.asarray(sim.states)[0].T
    assert 12.0 < vx.min() < 17.0 and 21.0 < vx.max() < 25.0  # speed swinging around 20 m/s
    assert 0.2 < np.abs(vy).max() < 2.0 and 0.2 < np.abs(r).max() < 0.6  # lateral excitation
    assert np.all(np.asarray(scn.inputs)[:, 2:4] == 0.0)  # front-wheel drive


@pytest.mark.parametrize("name", sorted(scenarios.REGISTRY))
def test_default_steps_counts_the_steps_the_builder_drives(name):
    """default_steps, found without driving, is the length of the drive each CLI manoeuvre
    makes with its default duration (the double lane change's depends on the speed)."""
    model = KinematicBicycle(dt=0.05)
    build = scenarios.REGISTRY[name]
    for speed in (15.0, 25.0):
        assert scenarios.default_steps(build, model, speed) == len(build(model, speed=speed).t)
    with pytest.raises(ValueError, match="speed"):
        scenarios.default_steps(build, model, -1.0)
