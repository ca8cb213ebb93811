"""simulate: shapes, names, determinism, noise statistics, perturbations, bad input, sizes that
cannot fit, the progress bar of a long study, NaN measurements of finite states."""

import importlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import vehjax as vj
from vehjax.models import Dynamic3DOF, KinematicBicycle

sim_mod = importlib.import_module("vehjax.simulate")  # the module (vj.simulate is the function)


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
    sim = vj.simulate(model, scn, runs=30, key=jax.random.key(1), meas_std=0.1,
                      noise_scale=vj.NoiseScale(meas=scale), params=vj.ParamDraw(std=0.1),
                      bias=vj.BiasWalk(std=[0.0, 0.01, 0.0], initial=[0.5, 0.0, 0.0]),
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
    clean = vj.simulate(model, scn, runs=1, params=vj.ParamDraw(theta=model.theta))
    same = vj.simulate(model, scn, runs=1, params=vj.ParamDraw(theta=model.theta),
                       steering_offset=0.01)
    assert float(np.mean(same.states[0, :, 2] - clean.states[0, :, 2])) > 0.01


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(runs=0), "runs"),
        (dict(runs=2.5), "runs"),
        (dict(meas_std=-0.1), "meas_std"),
        (dict(process_std=[0.1, 0.1]), "process_std"),
        (dict(meas_std=float("inf")), "meas_std"),
        (dict(noise_scale=vj.NoiseScale(meas=np.ones(3))), "noise_scale.meas"),
        (dict(params=vj.ParamDraw(theta=np.ones(3))), "params.theta"),
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


# ---- sizes nobody can run, progress of a long study, measurements the model made NaN -----------

def test_a_study_too_large_for_memory_is_refused_before_any_tracing(setup, monkeypatch):
    """runs x steps whose arrays exceed the device's memory: one ValueError line naming runs and
    the scenario's steps, with the estimate and the limit, before jax traces anything."""
    model, scn = setup
    traced = []
    monkeypatch.setattr(sim_mod, "_simulate_jit", lambda *a: traced.append(a))
    with pytest.raises(ValueError) as err:
        vj.simulate(model, scn, runs=100_000_000)
    text = str(err.value)
    assert text.startswith("runs, scenario: 100000000 runs x 300 steps of Dynamic3DOF need about")
    assert "TiB of memory" in text and "cpu device 0 has" in text and "\n" not in text
    assert "fewer runs or fewer steps" in text and not traced
    # the same size check, with the caller's names, and its limit moves with the device memory
    need = sim_mod.study_bytes(model, 100, 300)
    monkeypatch.setattr(vj.execution, "memory_limit", lambda device: need - 1)
    with pytest.raises(ValueError, match="^--runs, --dt: 100 runs x 300 steps"):
        sim_mod.check_size(model, 100, 300, names="--runs, --dt")
    monkeypatch.setattr(vj.execution, "memory_limit", lambda device: need)
    sim_mod.check_size(model, 100, 300)  # exactly fits: no error


def test_study_bytes_counts_runs_steps_and_sizes():
    model = Dynamic3DOF()  # nx = ny = 3, nu = 5
    b = sim_mod.study_bytes
    assert b(model, 10, 100) == 10 * 100 * (4 * 9 * 8 + 2) + 100 * 2 * 11 * 8
    assert b(model, 20, 100) - b(model, 10, 100) == 10 * 100 * 290
    assert b(model, 10, 100, itemsize=4) < b(model, 10, 100)


def test_progress_shows_for_a_long_study_only(setup, capsys, monkeypatch):
    """progress=True: a bar over the steps on stderr ending at every step; the default shows
    none for a short study and one from PROGRESS_RUN_STEPS runs x steps on; the results are
    the same with and without the bar."""
    model, scn = setup
    T = len(scn.t)
    quiet = vj.simulate(model, scn, runs=2, key=jax.random.key(5), meas_std=0.1)
    assert capsys.readouterr().err == ""
    shown = vj.simulate(model, scn, runs=2, key=jax.random.key(5), meas_std=0.1, progress=True)
    err = capsys.readouterr().err
    assert "vehjax.simulate" in err and f"{T}/{T}" in err
    # another program (the callback): the same draws, to rounding
    np.testing.assert_allclose(shown.measurements, quiet.measurements, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(shown.states, quiet.states, rtol=1e-12, atol=1e-15)
    monkeypatch.setattr(sim_mod, "PROGRESS_RUN_STEPS", 2 * T)
    vj.simulate(model, scn, runs=2, key=jax.random.key(5), meas_std=0.1)
    assert f"{T}/{T}" in capsys.readouterr().err  # 2 runs x T steps: long enough now
    vj.simulate(model, scn, runs=2, key=jax.random.key(5), meas_std=0.1, progress=False)
    assert capsys.readouterr().err == ""
    with pytest.raises(ValueError, match="^progress: expected None, True or False, got 'no'"):
        vj.simulate(model, scn, progress="no")


def _sqrt_model():
    """y = sqrt(x): NaN once the random walk x goes negative, the state itself finite."""
    return vj.models.Model(lambda x, u, th: x, lambda x, u, th: jnp.sqrt(x), dt=0.1,
                           state_names=("x",), output_names=("y",))


def test_nan_measurements_of_finite_states_are_flagged_and_warned():
    model = _sqrt_model()
    scn = vj.scenarios.from_inputs(model, np.zeros((40, 0)), [0.3])
    with pytest.warns(RuntimeWarning, match=r"NaN or \+-inf measurements .* in (\d+) of 64 runs"):
        sim = vj.simulate(model, scn, runs=64, key=jax.random.key(0), process_std=0.1)
    states, ys = np.asarray(sim.states), np.asarray(sim.measurements)
    want = np.any(states < 0, axis=1)[:, 0]  # a negative state: sqrt is NaN
    assert 0 < want.sum() < 64 and np.all(np.isfinite(states))
    np.testing.assert_array_equal(np.asarray(sim.nonfinite_measurements), want)
    np.testing.assert_array_equal(np.any(np.isnan(ys), axis=(1, 2)), want)
    assert not np.any(np.asarray(sim.diverged))  # the states are fine: nothing frozen
    assert sim.to_dict()["nonfinite_measurements"].tolist() == want.tolist()


def test_finite_measurements_raise_no_warning(setup, recwarn):
    model, scn = setup
    sim = vj.simulate(model, scn, runs=2, meas_std=0.1)
    assert not np.any(np.asarray(sim.nonfinite_measurements))
    assert not [w for w in recwarn if issubclass(w.category, RuntimeWarning)]
