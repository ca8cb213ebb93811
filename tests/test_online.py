"""vehjax.Online: a filter sample by sample equals vehjax.filter over the same samples (EKF, UKF,
a bootstrap PF with the same key), compiled once; stamps at 2 dt equal the filter with NaN rows
inserted; refusals name their argument and leave the filter unchanged; save/load continues
identically; the exported step runs in a process without vehjax; the step runs in the calling
thread under JAX's default asynchronous CPU dispatch."""

import json
import os
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import vehjax as vj
from vehjax import execution
from vehjax import online as O

MODEL = vj.models.SingleTrack(dt=0.01)
DT = MODEL.dt
Q = np.diag([0.02, 0.005]) ** 2
R = np.diag([0.2, 0.005]) ** 2
X0 = np.zeros(2)
P0 = np.diag([0.1, 0.01])
T = 60
TOL = dict(rtol=1e-9, atol=1e-12)


def _data():
    scn = vj.scenarios.double_lane_change(MODEL, speed=20.0)
    sim = vj.simulate(MODEL, scn, runs=1, key=jax.random.key(0), process_std=[0.02, 0.005],
                      meas_std=[0.2, 0.005])
    ys, us = np.array(sim.measurements[0][100:100 + T]), np.array(sim.inputs[100:100 + T])
    ys[5, 0] = np.nan      # one missing component
    ys[11:14, 1] = np.nan  # a few more
    ys[20] = np.nan        # an all-missing sample
    return ys, us


YS, US = _data()
BUILD = {
    "ekf": lambda: vj.filters.ekf(MODEL, Q, R),
    "ukf": lambda: vj.filters.ukf(MODEL, Q, R),
    "bootstrap_pf": lambda: vj.filters.bootstrap_pf(MODEL, Q, R, n_particles=64),
}

# the particle filter's cases: about 10 s each on 2 cores, so in the slow run (pytest -m slow)
PF_SLOW = pytest.param("bootstrap_pf", marks=pytest.mark.slow)


def _counted(est):
    """``est`` whose step counts its traces in ``calls``."""
    calls = []

    def step(state, y, u):
        calls.append(1)
        return est.step(state, y, u)

    return est._replace(step=step, runtime=est.runtime._replace(batch=None)), calls


def _key(est):
    return jax.random.key(3) if est.needs_key else None


def _feed(live, ys, us):
    """Update with every row (an all-NaN row as y=None); the estimates stacked."""
    outs = [live.update(None if np.isnan(y).all() else y, u) for y, u in zip(ys, us)]
    return {f: np.stack([getattr(o, f) for o in outs]) for f in
            ("mean", "cov", "loglik", "nis", "n_obs", "diverged")}


@pytest.mark.parametrize("name", ["ekf", "ukf", PF_SLOW])
def test_online_equals_filter_and_compiles_once(name):
    """Sample by sample equals vehjax.filter (estimates and the final filter state), compiled
    once."""
    est, calls = _counted(BUILD[name]())
    live = vj.Online(est, X0, P0, key=_key(est))
    traced = len(calls)
    got = _feed(live, YS, US)
    assert len(calls) == traced  # the step was traced before the first sample, never again
    ref = vj.filter(est, YS, US, x0=X0, P0=P0, key=_key(est))
    np.testing.assert_allclose(got["mean"], ref.states, **TOL)
    np.testing.assert_allclose(got["cov"], ref.covariances, **TOL)
    np.testing.assert_allclose(got["loglik"], ref.loglik, **TOL)
    np.testing.assert_allclose(got["nis"], ref.nis, **TOL)
    np.testing.assert_array_equal(got["n_obs"], ref.n_obs)
    assert got["n_obs"][20] == 0 and got["loglik"][20] == 0.0
    assert not got["diverged"].any() and not bool(ref.diverged)
    assert live.steps == T and live.t is None
    # the whole filter state (a PF's particles and key included) is vehjax.filter's last one
    state = live.state
    assert isinstance(state, O.OnlineState) and not bool(state.bad)
    assert jax.tree.structure(state.filter) == jax.tree.structure(ref.state)
    for a, b in zip(jax.tree.leaves(state.filter), jax.tree.leaves(ref.state)):
        if jax.dtypes.issubdtype(a.dtype, jax.dtypes.prng_key):
            a, b = jax.random.key_data(a), jax.random.key_data(b)
        np.testing.assert_allclose(a, b, **TOL)


def test_stamps_at_two_steps_are_prediction_steps():
    est, calls = _counted(BUILD["ekf"]())
    live = vj.Online(est, X0, P0, dt=DT, t0=1.0)
    traced = len(calls)
    n = 20
    rng = np.random.default_rng(0)
    stamps = 1.0 + 2 * DT * np.arange(1, n + 1) + rng.uniform(-0.3, 0.3, n) * DT  # jitter
    stamps[10:] += DT  # one gap of 3 steps
    outs = [live.update(YS[i], US[i], t=stamps[i]) for i in range(n)]
    assert len(calls) == traced + 1  # the gaps' loop, compiled on the first gap, once
    steps = [2] * n
    steps[10] = 3
    rows_y, rows_u, at = [], [], []
    for i, k in enumerate(steps):
        rows_y += [np.full(2, np.nan)] * (k - 1) + [YS[i]]
        rows_u += [US[i]] * k
        at.append(len(rows_y) - 1)
    ref = vj.filter(est, np.array(rows_y), np.array(rows_u), x0=X0, P0=P0)
    np.testing.assert_allclose(np.stack([o.mean for o in outs]), ref.states[np.array(at)], **TOL)
    np.testing.assert_allclose(np.stack([o.cov for o in outs]), ref.covariances[np.array(at)],
                               **TOL)
    np.testing.assert_allclose([o.loglik for o in outs], ref.loglik[np.array(at)], **TOL)
    assert live.steps == sum(steps) and [o.steps for o in outs] == list(np.cumsum(steps))
    assert live.t == pytest.approx(1.0 + sum(steps) * DT)  # on the grid, jitter absorbed
    # without t0 the first stamp is one step after the prior; an unstamped sample is one step
    other = vj.Online(est, X0, P0, dt=DT)
    assert other.update(YS[0], US[0], t=5.0).t == 5.0
    assert other.update(YS[1], US[1]).t == pytest.approx(5.0 + DT)


def test_refusals_name_their_argument_and_change_nothing():
    est, calls = _counted(BUILD["ekf"]())
    live = vj.Online(est, X0, P0, dt=DT, max_gap=0.5)
    live.update(YS[0], US[0], t=2.0)
    traced = len(calls)
    bad = [
        (dict(y=YS[1], u=US[1], t=2.0), "^t: .*repeats"),            # repeats
        (dict(y=YS[1], u=US[1], t=2.0 + 0.4 * DT), "^t: "),          # less than half a step
        (dict(y=YS[1], u=US[1], t=1.9), "^t: .*goes back"),           # back
        (dict(y=YS[1], u=US[1], t=3.0), "^t: .*max_gap"),             # too long a gap
        (dict(y=YS[1], u=US[1], t=float("nan")), "^t: "),
        (dict(y=YS[1], u=US[1], t="soon"), "^t: "),
        (dict(y=YS[1][:1], u=US[1]), r"^y: expected shape \(2,\)"),
        (dict(y=np.ones(3), u=US[1]), r"^y: expected shape \(2,\)"),
        (dict(y=[1.0, np.inf], u=US[1]), "^y: .*inf"),
        (dict(y=YS[1], u=US[1][:1]), r"^u: expected shape \(2,\)"),
        (dict(y=YS[1], u=[0.0, np.nan]), "^u: "),
        (dict(y=YS[1]), "^u: required"),
        (dict(y=np.array([1.0, 2.0j]), u=US[1]), "^y: "),
    ]
    for kw, match in bad:
        with pytest.raises(ValueError, match=match):
            live.update(**kw)
    assert len(calls) == traced and live.steps == 1 and live.t == 2.0
    fresh = vj.Online(est, X0, P0, dt=DT)
    fresh.update(YS[0], US[0], t=2.0)
    a, b = live.update(YS[1], US[1], t=2.0 + DT), fresh.update(YS[1], US[1], t=2.0 + DT)
    np.testing.assert_array_equal(a.mean, b.mean)
    with pytest.raises(ValueError, match="^t: time stamps need"):
        vj.Online(est, X0, P0).update(YS[0], US[0], t=0.0)
    with pytest.raises(ValueError, match="^key"):
        vj.Online(BUILD["bootstrap_pf"](), X0, P0)
    with pytest.raises(ValueError, match="^P0"):
        vj.Online(est, X0, np.eye(3))
    with pytest.raises(ValueError, match="^dt"):
        vj.Online(est, X0, P0, dt=0.0)
    with pytest.raises(ValueError, match="^max_gap"):
        vj.Online(est, X0, P0, dt=DT, max_gap=-1.0)
    with pytest.raises(ValueError, match="^estimator"):
        vj.Online(est._replace(dims=est.dims._replace(ny=None)), X0, P0)
    with pytest.raises(ValueError, match="^estimator"):
        vj.Online("ekf", X0, P0)


@pytest.mark.parametrize("name", ["ekf", PF_SLOW])
def test_save_and_load_continue_identically(name, tmp_path):
    est = BUILD[name]()
    whole = vj.Online(est, X0, P0, key=_key(est), dt=DT)
    part = vj.Online(est, X0, P0, key=_key(est), dt=DT)
    stamps = 0.5 + DT * np.arange(T)
    for i in range(30):
        whole.update(YS[i], US[i], t=stamps[i])
        part.update(YS[i], US[i], t=stamps[i])
    part.save(tmp_path / "car.npz")
    back = vj.Online.load(tmp_path / "car.npz", est)
    assert back.steps == 30 and back.t == part.t
    for i in range(30, T):
        a, b = whole.update(YS[i], US[i], t=stamps[i]), back.update(YS[i], US[i], t=stamps[i])
        np.testing.assert_array_equal(a.mean, b.mean)
        np.testing.assert_array_equal(a.cov, b.cov)
    other = vj.filters.bootstrap_pf(MODEL, Q, R, n_particles=32)  # another state's layout
    with pytest.raises(ValueError, match="^path: .*" + ("expects" if est.needs_key else
                                                           "not of 'bootstrap_pf'")):
        vj.Online.load(tmp_path / "car.npz", other)
    with pytest.raises(ValueError, match="^estimator"):
        vj.Online.load(tmp_path / "car.npz", "ekf")
    np.savez(tmp_path / "other.npz", a=np.zeros(2))
    with pytest.raises(ValueError, match="^path: .*not a saved Online"):
        vj.Online.load(tmp_path / "other.npz", est)


def test_pack_round_trip_with_a_typed_key():
    tree = {"k": jax.random.key(5), "x": jnp.arange(3.0), "P": jnp.eye(2),
            "n": jnp.asarray(4, jnp.int32), "flag": jnp.asarray(True)}
    layout = O.layout_of(tree)
    buffers = O.pack(tree, layout)
    assert len(buffers) == 3  # uint32 (the key data), float64 (and the bool), int32
    back = O.unpack(buffers, layout)
    np.testing.assert_array_equal(jax.random.key_data(back["k"]), jax.random.key_data(tree["k"]))
    for f in ("x", "P", "n", "flag"):
        np.testing.assert_array_equal(back[f], tree[f])


# run as ``python -I -S``: no PYTHONPATH, no working directory and no .pth files (so not the
# editable install's finder) on sys.path; the packages' folder of jax alone is added
_LOADER = """
import importlib.util, json, os, sys
sys.path.append(sys.argv[1])
import jax, numpy as np
source = [p for p in sys.path if os.path.exists(os.path.join(p or ".", "vehjax"))]
try:
    import vehjax
    importable = True
except ModuleNotFoundError:
    importable = False
jax.config.update("jax_enable_x64", True)
step = jax.jit(jax.export.deserialize(open("step.jax", "rb").read()).call)
saved = np.load("car.npz")
cpu = jax.devices("cpu")[0]  # committed like the step's outputs: one compile
state = [jax.device_put(saved[f"state_{i}"], cpu) for i in range(int(saved["n_buffers"]))]
data = np.load("data.npz")
means, logliks = [], []
for y, u in zip(data["ys"], data["us"]):
    out = step(state, y, u)
    state = out["state"]
    means.append(np.asarray(out["mean"]).tolist())
    logliks.append(float(out["loglik"]))
print(json.dumps({"means": means, "logliks": logliks, "source": source,
                  "importable": importable, "spec": importlib.util.find_spec("vehjax") is not None,
                  "loaded": sorted(m for m in sys.modules if m.startswith("vehjax"))}))
"""


@pytest.mark.parametrize("name", ["ukf", PF_SLOW])
def test_exported_step_runs_without_vehjax(name, tmp_path):
    est = BUILD[name]()
    live = vj.Online(est, X0, P0, key=_key(est))
    for i in range(10):
        live.update(YS[i], US[i])
    live.save(tmp_path / "car.npz")
    live.export(tmp_path / "step.jax")
    ys, us = YS[10:25], US[10:25]
    np.savez(tmp_path / "data.npz", ys=ys, us=us)
    want = [live.update(y, u) for y, u in zip(ys, us)]
    packages = os.path.dirname(os.path.dirname(jax.__file__))
    assert not os.path.exists(os.path.join(packages, "vehjax"))  # an editable install's finder
    env = {k: v for k, v in os.environ.items() if k in ("PATH", "HOME", "LANG", "TMPDIR")}
    done = subprocess.run([sys.executable, "-I", "-S", "-c", _LOADER, packages], cwd=tmp_path,
                          env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    got = json.loads(done.stdout.strip().splitlines()[-1])
    assert got["source"] == [] and not got["importable"] and not got["spec"]
    assert got["loaded"] == []
    np.testing.assert_allclose(got["means"], [w.mean for w in want], **TOL)
    np.testing.assert_allclose(got["logliks"], [w.loglik for w in want], **TOL)


@pytest.mark.slow  # two more compiles (the filter and vehjax.filter in float32)
def test_float32_runs_in_float32():
    est = BUILD["ekf"]()
    live = vj.Online(est, X0.astype(np.float32), P0.astype(np.float32))
    out = live.update(YS[0], US[0])
    assert out.mean.dtype == np.float32 and out.cov.dtype == np.float32
    ref = vj.filter(est, YS[:1].astype(np.float32), US[:1].astype(np.float32),
                    x0=X0.astype(np.float32), P0=P0.astype(np.float32))
    np.testing.assert_allclose(out.mean, ref.states[0], rtol=1e-5)


def _bench():
    from vehjax.cli import load_benchmark

    return load_benchmark("online")


@pytest.mark.slow  # a benchmark's smoke run (pyproject.toml's slow marker)
def test_bench_online_smoke_ekf(capsys):
    """Tiny sizes, the EKF row: checked equal to vehjax.filter and filterpy, then timed."""
    assert _bench().main(["--quick", "--rows", "ekf", "--dispatch", "async"]) == 0
    out = capsys.readouterr().out
    assert "FAILED" not in out and "target: Online.update median" in out
    assert all(f"ekf  {c}" in out for c in ("Online.update", "vehjax.filter", "vehjax.run"))


@pytest.mark.slow  # two fresh processes, each importing JAX and compiling
def test_bench_online_both_dispatches_run_in_fresh_processes(capfd):
    """The default ``--dispatch both``: a child per mode, each saying its mode, then one line
    per row with both medians (numbers, not NaN: each child reported its row)."""
    assert _bench().main(["--quick", "--rows", "ekf"]) == 0
    out = capfd.readouterr().out
    assert "dispatch sync:" in out and "dispatch async:" in out and "FAILED" not in out
    line = [ln for ln in out.splitlines() if ln.startswith("ekf  target 30 us:")]
    assert len(line) == 1 and "nan" not in line[0], out


@pytest.mark.slow  # the marginalized PF's compiles: about two minutes on 2 cores
def test_bench_online_smoke_all_rows(capsys):
    assert _bench().main(["--quick", "--dispatch", "async"]) == 0
    out = capsys.readouterr().out
    assert "FAILED" not in out and "paper 004's 1.4 ms a step: ratio" in out


def _returns_after_the_work(device) -> bool:
    """Whether a call of a compiled 0.05 s computation on ``device`` returns only once it has
    run (the calling thread) rather than at once (handed to a worker thread)."""
    def work(a):
        return jax.lax.fori_loop(0, 200, lambda i, b: jnp.tanh(b @ a), a)

    on = jax.sharding.SingleDeviceSharding(device)
    a = jax.device_put(np.eye(200) * 0.5, on)
    fn = jax.jit(work).lower(a).compile()
    fn(a).block_until_ready()
    t0 = time.perf_counter()
    out = fn(a)
    returned = time.perf_counter() - t0
    out.block_until_ready()
    return returned > 0.5 * (time.perf_counter() - t0)


@pytest.mark.skipif(jax.default_backend() != "cpu"
                    or not jax.config.read("jax_cpu_enable_async_dispatch"),
                    reason="JAX's asynchronous CPU dispatch is what the live device avoids")
def test_the_step_runs_in_the_calling_thread_under_async_dispatch():
    """Under JAX's default (asynchronous) CPU dispatch a large computation's call returns before
    it has run; on the live device it returns after. Online's state lives there, and its
    ``state`` comes back on JAX's default device, usable beside the process's other arrays."""
    device = execution.live_device()
    assert device.client is not jax.local_devices()[0].client
    assert not _returns_after_the_work(jax.local_devices()[0])
    assert _returns_after_the_work(device)
    live = vj.Online(BUILD["ukf"](), X0, P0)
    live.update(YS[0], US[0])
    assert all(b.devices() == {device} for b in live._buffers)
    state = live.state
    assert state.mean.devices() == {jax.local_devices()[0]}
    again = vj.filter(BUILD["ukf"](), YS[1:3], US[1:3], x0=state.mean, P0=state.cov)
    np.testing.assert_allclose(again.states[0], live.update(YS[1], US[1]).mean, **TOL)
