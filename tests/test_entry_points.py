"""Every public entry point checks its arguments by the same rules (vehjax.validation): the same
bad or edge input is accepted by all of filter, run, compile_run, simulate and tune.objective
with equal results, or refused by all with a ValueError naming the argument.

The model is a 1-state linear model written here (x' = a x + u, y = x), small enough that the
hypothesis part compiles each entry point once per dtype and shape and stays near a minute on
one core. The reference results of the agreement test are vehjax.run's on the valid data, and
a Kalman filter in numpy (written here, not vehjax's) for the valid data itself.
"""

import ast
import functools
import re
import shutil
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import vehjax as vj
from vehjax import validation
from vehjax import filters as F
from vehjax import tune

A_TRUE = 0.9
MODEL = vj.models.Model(lambda x, u, th: th[0] * x + u, lambda x, u, th: x, dt=0.1,
                        state_names=("x",), input_names=("u",), output_names=("y",),
                        param_names=("a",), theta=[A_TRUE])
Q, R = np.array([[0.04]]), np.array([[0.25]])
RUNS, T = 2, 5
X0, P0 = np.array([0.5]), np.array([[2.0]])


def _data(seed=0):
    """Measurements (RUNS, T, 1) and shared inputs (T, 1) drawn from the model in numpy."""
    rng = np.random.default_rng(seed)
    us = rng.normal(size=(T, 1))
    ys = np.empty((RUNS, T, 1))
    for r in range(RUNS):
        x = X0[0] + rng.normal() * np.sqrt(P0[0, 0])
        for t in range(T):
            x = A_TRUE * x + us[t, 0] + rng.normal() * np.sqrt(Q[0, 0])
            ys[r, t, 0] = x + rng.normal() * np.sqrt(R[0, 0])
    return ys, us


YS, US = _data()
EKF = F.ekf(MODEL, Q, R)


def numpy_kf(y, u, x0, P0, a=A_TRUE):
    """Scalar Kalman filter (predict with u_t, update with y_t; NaN skipped): means (T,) and
    log-likelihood."""
    x, P, ll, means = float(x0[0]), float(P0[0, 0]), 0.0, []
    for t in range(len(y)):
        x, P = a * x + u[t, 0], a * a * P + Q[0, 0]
        if np.isfinite(y[t, 0]):
            S = P + R[0, 0]
            e = y[t, 0] - x
            ll += -0.5 * (np.log(2 * np.pi * S) + e * e / S)
            K = P / S
            x, P = x + K * e, (1 - K) * P
        means.append(x)
    return np.array(means), ll


def test_the_reference_kalman_filter_agrees_with_run():
    out = vj.run(EKF, YS, US, x0=X0, P0=P0, progress=False)
    for r in range(RUNS):
        m, ll = numpy_kf(YS[r], US, X0, P0)
        np.testing.assert_allclose(out.states[r, :, 0], m, rtol=1e-10)
        np.testing.assert_allclose(out.loglik[r], ll, rtol=1e-10)


# ---- the entry points, each given the same (possibly bad) arguments ----------------------------

def _named(err: ValueError, arg: str) -> bool:
    """The message names ``arg`` first (``P0:``, ``P0[1]:``; simulate's ``scenario.x0:``)."""
    return re.match(rf"^(scenario\.)?{re.escape(arg)}(\[\d+\])?:", str(err)) is not None


def _call(fn):
    """('ok', result) or ('refused', ValueError); anything else propagates (a failure)."""
    try:
        return "ok", fn()
    except ValueError as err:
        return "refused", err


def _entry_points(ys, us, x0, P0, which):
    """The calls of every entry point that takes the arguments in ``which``. ``ys`` are the
    study's (RUNS, T, 1) measurements (filter gets run 0's), ``us`` the shared inputs."""
    first = ys[0] if isinstance(ys, list) else (ys[0] if np.ndim(ys) == 3 else ys)
    calls = {
        "filter": lambda: vj.filter(EKF, first, us, x0=x0, P0=P0),
        "run": lambda: vj.run(EKF, ys, us, x0=x0, P0=P0, progress=False),
        "compile_run": lambda: vj.compile_run(EKF, ys, us, x0=x0, P0=P0, progress=False)(),
        "tune.objective": lambda: tune.objective(F.ekf, MODEL, Q, R, ys, us, x0=x0, P0=P0,
                                                 params=tune.Fitted(noise=("R",))),
    }
    if which in ("inputs", "x0"):
        scn = vj.scenarios.Scenario("test", np.arange(T) * 0.1, us, x0, ("u",), None)
        calls["simulate"] = lambda: vj.simulate(MODEL, scn, runs=RUNS, key=jax.random.key(0))
    return calls


def _mutate(kind: str, a: np.ndarray, where: int):
    """``a`` changed by ``kind`` at flat position ``where`` (for the value kinds)."""
    a = np.array(a, dtype=float)
    if kind in ("nan", "inf", "-inf"):
        a.flat[where % a.size] = {"nan": np.nan, "inf": np.inf, "-inf": -np.inf}[kind]
        return a
    return {
        "complex": lambda: a.astype(complex),
        "float32": lambda: a.astype(np.float32),
        "int": lambda: np.round(a).astype(np.int64),
        "bool": lambda: a > 0,
        "list": lambda: a.tolist(),
        "empty": lambda: a[..., :0] if a.ndim and a.shape[-1] else a[:0],
        "extra_column": lambda: np.concatenate([a, a[..., :1]], axis=-1),
        "extra_axis": lambda: a[None],
        "text": lambda: a.astype(str),
    }[kind]()


def _expected_refused(arg: str, kind: str) -> bool:
    """The documented rules (vehjax.validation): whether ``arg`` changed by ``kind`` is refused."""
    if kind in ("float32", "int", "list"):
        return False  # real numbers in another precision or container: accepted
    if kind == "nan":
        return arg != "measurements"  # a NaN measurement component is missing
    return True  # +-inf, complex, bool, text, empty, wrong shapes


def _agree(arg: str, kind: str, args: dict):
    """Call every entry point with ``args``; all must accept or all refuse (as the rules say),
    refusals naming ``arg``, acceptances giving equal results, those of the numpy filter."""
    outcomes = {name: _call(fn) for name, fn in
                _entry_points(args["measurements"], args["inputs"], args["x0"], args["P0"],
                              arg).items()}
    states = {name: status for name, (status, _) in outcomes.items()}
    assert len(set(states.values())) == 1, (arg, kind, outcomes)
    status = next(iter(states.values()))
    assert status == ("refused" if _expected_refused(arg, kind) else "ok"), (arg, kind, outcomes)
    if status == "refused":
        for name, (_, err) in outcomes.items():
            assert _named(err, arg), (name, arg, kind, str(err))
        return
    # accepted by all: equal results (filter = run's run 0 = compile_run's; tune's loss is
    # minus run's log-likelihood per step)
    run_out = outcomes["run"][1]
    np.testing.assert_array_equal(run_out.states, outcomes["compile_run"][1].states)
    one = outcomes["filter"][1]
    np.testing.assert_allclose(np.asarray(one.states), run_out.states[0], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(float(one.loglik.sum()), run_out.loglik[0], rtol=1e-9)
    obj = outcomes["tune.objective"][1]
    loss = float(obj.loss(obj.z0, obj.data)[0])
    np.testing.assert_allclose(loss, -run_out.loglik.sum() / (RUNS * T), rtol=1e-9)
    assert not run_out.diverged.any()
    if "simulate" in outcomes:
        assert np.isfinite(outcomes["simulate"][1].states).all()
    # the numbers of the numpy reference on the same data
    ys, us, x0, p0 = (np.asarray(args[k], dtype=float) for k in
                      ("measurements", "inputs", "x0", "P0"))
    for r in range(RUNS):
        m, ll = numpy_kf(ys[r], us, x0, p0)
        np.testing.assert_allclose(run_out.states[r, :, 0], m, rtol=1e-6)
        np.testing.assert_allclose(run_out.loglik[r], ll, rtol=1e-6)


_ARGS = ("measurements", "inputs", "x0", "P0")


@pytest.mark.parametrize("arg", _ARGS)
@pytest.mark.parametrize("kind", ["nan", "inf", "-inf"])
@settings(max_examples=3, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(where=st.integers(0, 2 * T - 1))
def test_non_finite_values_one_rule_everywhere(arg, kind, where):
    """NaN in measurements is missing (accepted by all, equal results); NaN elsewhere and +-inf
    anywhere are refused by all, naming the argument."""
    args = dict(measurements=YS, inputs=US, x0=X0, P0=P0)
    if arg == "measurements":
        bad = np.array(YS)
        bad[0].flat[where % T] = {"nan": np.nan, "inf": np.inf, "-inf": -np.inf}[kind]
        args[arg] = bad  # in run 0, the run filter is given
    else:
        args[arg] = _mutate(kind, args[arg], where)
    _agree(arg, kind, args)


@pytest.mark.parametrize("arg", _ARGS)
@pytest.mark.parametrize("kind", ["complex", "float32", "int", "bool", "list", "empty",
                                  "extra_column", "extra_axis", "text"])
def test_dtypes_containers_and_shapes_alike_everywhere(arg, kind):
    """Complex, bool and text arrays, empty arrays and wrong shapes are refused by all;
    float32, integer arrays and lists accepted by all with the same results."""
    args = dict(measurements=YS, inputs=US, x0=X0, P0=P0)
    if arg == "measurements" and kind == "empty":
        args[arg] = YS[:, :0]  # no steps
    else:
        args[arg] = _mutate(kind, args[arg], 0)
    _agree(arg, kind, args)


# ---- the rules themselves, and the cases of issue 31 -----------------------------------------

def test_validate_imports_nothing_of_vehjax():
    """The import circle with models/base is gone: vehjax.validation is a leaf module."""
    tree = ast.parse(Path(validation.__file__).read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            assert node.level == 0 and not (node.module or "").startswith("vehjax"), node.module
        if isinstance(node, ast.Import):
            assert not any(a.name.startswith("vehjax") for a in node.names)


def test_array_rule_names_the_first_bad_index():
    a = np.zeros((3, 2))
    a[1, 1], a[2, 0] = np.nan, np.inf
    with pytest.raises(ValueError, match=r"^u: expected finite values, found nan at index \(1, 1\)"):
        validation.array("u", a)
    with pytest.raises(ValueError, match=r"^y: expected no \+-inf, found inf at index \(2, 0\)"):
        validation.array("y", a, missing=True)
    a[2, 0] = 0.0
    assert np.isnan(validation.array("y", a, missing=True)[1, 1])  # NaN: missing
    assert validation.array("y", [[1, 2]]).dtype == np.float64
    assert validation.array("y", np.ones(2, np.float32)).dtype == np.float32
    for bad, what in ((np.ones(2, complex), "complex"), (np.ones(2, bool), "bool"),
                      (["a"], "<U1"), ([[1.0], [1.0, 2.0]], "numeric array")):
        with pytest.raises(ValueError, match=f"^v: expected a .*{re.escape(what)}"):
            validation.array("v", bad)


def test_one_prior_check_the_same_message_everywhere():
    """x0/P0 are checked by one function: every entry point and the filters' init say the same."""
    for x0, p0 in ((np.array([np.nan]), P0), (X0, np.array([[-1.0]])), (X0, np.eye(2)),
                   (X0, np.array([[1j]])), (np.zeros(3), P0)):
        msgs = []
        for fn in (lambda: vj.filter(EKF, YS[0], US, x0=x0, P0=p0),
                   lambda: vj.run(EKF, YS, US, x0=x0, P0=p0),
                   lambda: tune.objective(F.ekf, MODEL, Q, R, YS, US, x0=x0, P0=p0),
                   lambda: EKF.init(x0, p0),
                   lambda: F.bootstrap_pf(MODEL, Q, R, n_particles=4).init(
                       x0, p0, key=jax.random.key(0))):
            with pytest.raises(ValueError) as err:
                fn()
            msgs.append(str(err.value).split(" or (")[0].split(" for nx")[0])
        assert msgs[0].startswith(("x0:", "P0:")) and len(set(msgs)) == 1, msgs


def test_per_run_variances_when_runs_equal_states():
    """P0 of per-run variances (R, nx) reads as one (nx, nx) matrix when R == nx: the message
    says so, and how to pass them; with R != nx the shape is refused with the same hint."""
    m2 = vj.models.Model(lambda x, u, th: x + u[0], lambda x, u, th: x, dt=0.1,
                         state_names=("a", "b"), input_names=("u",))
    est = F.ekf(m2, np.eye(2) * 0.01, np.eye(2) * 0.1)
    ys, us = np.zeros((2, T, 2)), np.zeros((T, 1))
    variances = np.array([[1.0, 2.0], [3.0, 4.0]])  # run 0: (1, 2), run 1: (3, 4)
    with pytest.raises(ValueError, match=r"^P0: expected a symmetric .*per-run variances"):
        vj.run(est, ys, us, x0=np.zeros(2), P0=variances)
    with pytest.raises(ValueError, match=r"^P0: expected shape .*per-run variances"):
        vj.run(est, np.zeros((3, T, 2)), us, x0=np.zeros(2), P0=np.ones((3, 2)))
    # what the message says to do works, and is what each run's own diagonal gives
    out = vj.run(est, ys, us, x0=np.zeros(2), P0=variances[:, :, None] * np.eye(2),
                 return_covariances=True, progress=False)
    one = vj.filter(est, ys[1], us, x0=np.zeros(2), P0=np.diag(variances[1]))
    np.testing.assert_allclose(out.covariances[1], one.covariances, rtol=1e-9)


@pytest.mark.parametrize("builder", [F.ekf, F.ukf, F.ckf, F.ackf])
def test_filter_theta0_replaces_the_model_parameters_of_a_state_only_filter(builder):
    est = builder(MODEL, Q, R)
    a = vj.filter(est, YS[0], US, x0=X0, P0=P0, theta0=[0.5])
    b = vj.filter(builder(MODEL.with_theta(a=0.5), Q, R), YS[0], US, x0=X0, P0=P0)
    np.testing.assert_array_equal(a.states, b.states)
    assert a.params.shape == (T, 0) and not bool(a.diverged)
    if builder is F.ekf:  # and it is the Kalman filter at a = 0.5 (numpy reference)
        np.testing.assert_allclose(a.states[:, 0], numpy_kf(YS[0], US, X0, P0, a=0.5)[0],
                                   rtol=1e-10)
    with pytest.raises(ValueError, match=r"^theta0: expected shape \(1,\)"):
        vj.filter(est, YS[0], US, x0=X0, P0=P0, theta0=[0.5, 1.0])
    with pytest.raises(ValueError, match=r"^theta0: expected finite"):
        vj.filter(est, YS[0], US, x0=X0, P0=P0, theta0=[np.nan])
    with pytest.raises(ValueError, match=r"^P_theta0: .*estimates no parameters"):
        vj.filter(est, YS[0], US, x0=X0, P0=P0, theta0=[0.5], P_theta0=[[1.0]])
    # run takes it alike, shared or one per run, and checks its length before tracing
    out = vj.run(est, YS, US, x0=X0, P0=P0, theta0=[0.5])
    np.testing.assert_allclose(out.states[0], a.states, rtol=1e-12, atol=1e-12)
    per_run = vj.run(est, YS, US, x0=X0, P0=P0, theta0=np.full((len(YS), 1), 0.5))
    np.testing.assert_allclose(per_run.states, out.states, rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match=r"^theta0: expected the model's 1 parameters"):
        vj.run(est, YS, US, x0=X0, P0=P0, theta0=[0.5, 1.0])
    # an estimator that does not say its model's parameter count takes none in run
    with pytest.raises(ValueError, match=r"^theta0: .*with_theta"):
        vj.run(est._replace(dims=est.dims._replace(n_theta=None)), YS, US, x0=X0, P0=P0, theta0=[0.5])


def test_particle_filter_theta0_replaces_the_model_parameters():
    key = jax.random.key(3)
    est = F.bootstrap_pf(MODEL, Q, R, n_particles=16)
    a = vj.filter(est, YS[0], US, x0=X0, P0=P0, theta0=[0.5], key=key)
    b = vj.filter(F.bootstrap_pf(MODEL.with_theta(a=0.5), Q, R, n_particles=16), YS[0], US,
                  x0=X0, P0=P0, key=key)
    np.testing.assert_array_equal(a.states, b.states)


def test_models_returning_complex_or_with_complex_theta_are_refused():
    kw = dict(dt=0.1, state_names=("x",), input_names=("u",), param_names=("a",), theta=[0.9])
    with pytest.raises(ValueError, match=r"^transition: .*real floating.*complex"):
        vj.models.Model(lambda x, u, th: (1 + 0j) * x, lambda x, u, th: x, **kw)
    with pytest.raises(ValueError, match=r"^observe: .*real floating.*complex"):
        vj.models.Model(lambda x, u, th: x, lambda x, u, th: x * 1j, **kw)
    with pytest.raises(ValueError, match=r"^observe: .*real floating.*int"):
        vj.models.Model(lambda x, u, th: x, lambda x, u, th: jnp.ones(1, jnp.int32), **kw)
    with pytest.raises(ValueError, match=r"^theta: expected a real .*complex"):
        vj.models.Model(lambda x, u, th: x, lambda x, u, th: x, **{**kw, "theta": [0.9j]})


def test_simulate_rechecks_a_scenario_built_directly():
    us = np.array(US)
    us[2, 0] = np.nan
    scn = vj.scenarios.Scenario("mine", np.arange(T) * 0.1, us, X0, ("u",), None)
    with pytest.raises(ValueError, match=r"^scenario\.inputs: expected finite.*\(2, 0\)"):
        vj.simulate(MODEL, scn)
    scn = scn._replace(inputs=US, x0=np.array([np.inf]))
    with pytest.raises(ValueError, match=r"^scenario\.x0: expected finite.*\(0,\)"):
        vj.simulate(MODEL, scn)
    with pytest.raises(ValueError, match=r"^scenario\.inputs: expected shape"):
        vj.simulate(MODEL, scn._replace(inputs=US[:, 0], x0=X0))
    with pytest.raises(ValueError, match=r"^inputs: expected finite"):
        vj.scenarios.from_inputs(MODEL, us, X0)


def _copy_drive(tmp_path):
    from vehjax.data import comma2k19

    folder = tmp_path / "drive"
    shutil.copytree(comma2k19._PACKAGED, folder)
    return folder


def _rewrite(path: Path, change):
    a = np.load(path, allow_pickle=False)
    a = change(a)
    with open(path, "wb") as f:  # np.save(path) would add a .npy suffix
        np.save(f, a)


@pytest.mark.parametrize("rel, bad, sample, column", [
    ("processed_log/CAN/speed/value", np.nan, 17, 0),
    ("processed_log/IMU/gyro/value", -np.inf, 5, 2),
    ("global_pose/frame_velocities", np.inf, 0, 1),
])
def test_loader_names_the_file_and_the_first_bad_sample(tmp_path, rel, bad, sample, column):
    from vehjax.data import load_comma2k19

    folder = _copy_drive(tmp_path)
    assert np.isfinite(load_comma2k19(folder).signals["speed_can"]).all()  # the copy loads

    def put(a):
        a = np.array(a, dtype=float)
        a.reshape(len(a), -1)[sample, column] = bad
        a.reshape(len(a), -1)[sample + 3, column] = bad  # a later one is not the first
        return a

    _rewrite(folder / rel, put)
    with pytest.raises(ValueError, match=rf"^{re.escape(str(folder / rel))}: expected finite "
                                         rf"values, found .*at sample {sample} \(column {column}\)"):
        load_comma2k19(folder)


def test_loader_refuses_complex_and_non_finite_times(tmp_path):
    from vehjax.data import load_comma2k19

    folder = _copy_drive(tmp_path)
    rel = folder / "processed_log/CAN/steering_angle/value"
    _rewrite(rel, lambda a: a.astype(complex))
    with pytest.raises(ValueError, match=rf"^{re.escape(str(rel))}: expected a real .*complex"):
        load_comma2k19(folder)
    folder = _copy_drive(tmp_path / "2")
    rel = folder / "processed_log/CAN/speed/t"
    _rewrite(rel, lambda a: np.where(np.arange(len(a)) == 4, np.nan, a))
    with pytest.raises(ValueError, match=rf"^{re.escape(str(rel))}: non-finite .*sample 4"):
        load_comma2k19(folder)


def test_tune_fit_refuses_a_dual_filter_naming_the_builder():
    for builder in (F.dual_ekf, functools.partial(F.dual_ekf, Q_theta=[1e-4], estimate="a")):
        with pytest.raises(ValueError, match="^builder:"):
            tune.fit(builder, MODEL, Q, R, YS, US, x0=X0, P0=P0,
                     options=tune.Options(optimizer=tune.Scoring(steps=1)))


def test_run_refuses_repeated_devices():
    d = jax.devices()[0]
    with pytest.raises(ValueError, match="^execution.devices: expected each device at most once"):
        vj.run(EKF, YS, US, x0=X0, P0=P0, execution=vj.Execution(devices=[d, d]))


@pytest.mark.parametrize("call, arg", [
    (lambda: F.ukf(MODEL, Q, R, points=F.SigmaPoints(alpha="x")), "alpha"),
    (lambda: F.ukf(MODEL, Q, R, points=F.SigmaPoints(kappa=1j)), "kappa"),
    (lambda: F.ekf(MODEL, [[1j]], R), "Q"),
    (lambda: F.ekf(MODEL, Q, R, input_noise={"u": 1j}), "input_noise"),
    (lambda: F.dual_ekf(MODEL, Q, R, Q_theta=["x"], estimate="a"), "Q_theta"),
    (lambda: vj.filter(F.bootstrap_pf(MODEL, Q, R, n_particles=4), YS[0], US, x0=X0, P0=P0,
                       key=0), "key"),
    (lambda: vj.filter(EKF, YS[0], US, x0="x", P0=P0), "x0"),
    (lambda: vj.simulate(MODEL, vj.scenarios.from_inputs(MODEL, US, X0), meas_std=1j),
     "meas_std"),
    (lambda: vj.simulate(MODEL, vj.scenarios.from_inputs(MODEL, US, X0),
                         bias=vj.BiasWalk(initial="x")), "bias.initial"),
    (lambda: vj.simulate(MODEL, "not a scenario"), "scenario"),
    (lambda: vj.run(EKF, YS, US, x0=X0, P0=P0, execution=vj.Execution(chunk_size="2")),
     "execution.chunk_size"),
])
def test_wrong_argument_types_are_value_errors_naming_the_argument(call, arg):
    """Not a TypeError or an error from inside JAX: a ValueError naming the argument."""
    with pytest.raises(ValueError, match=rf"^{arg}:"):
        call()


def test_importing_vehjax_starts_no_jax_backend():
    """After ``import vehjax`` the JAX options that must precede any JAX operation (the CPU
    device count, jax.distributed) can still be set: importing runs no JAX computation."""
    import subprocess
    import sys

    code = ("import jax, vehjax, vehjax.cli\n"
            "jax.config.update('jax_num_cpu_devices', 3)\n"
            "assert len(jax.devices()) == 3, jax.devices()\n"
            "print('ok')\n")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=300, env={**__import__("os").environ, "JAX_PLATFORMS": "cpu"})
    assert res.returncode == 0 and "ok" in res.stdout, res.stderr[-2000:]
