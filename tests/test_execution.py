"""The execution seam (vehjax.execution): each platform's strategy, the GPU strategy forced on the
CPU giving the CPU strategy's results for every family, no platform rule outside the seam, the
memory guards, compile_run's own copy, and `vehjax bench device --quick`."""

import os
import re
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import vehjax as vj
from vehjax import execution

from _contract import DRAW_RTOL

ROOT = Path(__file__).resolve().parents[1]


def _f(x, u, th):  # a user's model written with trigonometry (substitutes apply on CPU)
    return jnp.array([x[0] + 0.1 * x[1], x[1] + 0.1 * (-th[0] * jnp.sin(x[0]) - th[1] * x[1]
                                                        + u[0])])


def _h(x, u, th):
    return jnp.array([jnp.sin(x[0]) + 0.2 * x[1], x[1]])


MODEL = vj.models.Model(_f, _h, dt=0.1, state_names=("a", "w"), param_names=("g", "c"),
                        input_names=("u",), output_names=("s", "w"), theta=[2.0, 0.3])
Q = np.diag([1e-3, 4e-3])
R = np.diag([0.02, 0.03])
X0 = np.array([0.3, 0.0])
P0 = np.diag([0.05, 0.05])


def _data(runs=3, steps=12, seed=0):
    rng = np.random.default_rng(seed)
    us = 0.3 * np.sin(0.4 * np.arange(steps))[:, None]
    xs = np.zeros((runs, steps, 2))
    x = np.tile(X0, (runs, 1))
    for t in range(steps):
        x = np.array([np.asarray(_f(xi, us[t], MODEL.theta)) for xi in x])
        x += rng.normal(size=x.shape) * np.sqrt(np.diag(Q))
        xs[:, t] = x
    ys = np.array([[np.asarray(_h(xs[r, t], us[t], MODEL.theta)) for t in range(steps)]
                   for r in range(runs)]) + rng.normal(size=(runs, steps, 2)) * np.sqrt(np.diag(R))
    ys[1, 4, 0] = np.nan  # a missing component
    return ys, us


def _families():
    th = MODEL.theta
    return {
        "ekf": (vj.filters.ekf(MODEL, Q, R), {}),
        "ukf": (vj.filters.ukf(MODEL, Q, R), {}),
        "ackf": (vj.filters.ackf(MODEL, Q, R), {}),
        "dual_ekf": (vj.filters.dual_ekf(MODEL, Q, R, Q_theta=np.diag([1e-6]), estimate=("g",)),
                     dict(theta0=th[:1] * 1.1, P_theta0=np.diag([0.04]))),
        "joint_ukf": (vj.filters.joint_ukf(MODEL, Q, R, Q_theta=np.diag([1e-6]),
                                           estimate=("g",)),
                      dict(theta0=th[:1] * 1.1, P_theta0=np.diag([0.04]))),
        "bootstrap_pf": (vj.filters.bootstrap_pf(MODEL, Q, R, n_particles=64), dict(key=jax.random.key(1))),
        "liu_west": (vj.filters.liu_west_ukf(MODEL, Q, R, n_particles=32, estimate=("g",),
                                             theta_low=[1.0], theta_high=[3.0]),
                     dict(key=jax.random.key(2))),
    }


FAMILIES = _families()


def test_each_platform_has_its_rules():
    cpu, gpu, tpu = (execution.for_platform(p) for p in ("cpu", "gpu", "tpu"))
    assert cpu.block_numbers and cpu.chunk_work and cpu.elemental_emitter
    assert cpu.substitute_elementary and cpu.runs_last and cpu.prefetch_inputs
    for s in (gpu, tpu):
        assert s.block_numbers is None and s.chunk_work is None
        assert not s.elemental_emitter and not s.substitute_elementary and s.runs_last
        assert not s.prefetch_inputs
    assert execution.for_platform("cuda") == gpu
    assert execution.for_platform("gpu", device_memory=80 * 2**30).chunk_bytes == 20 * 2**30
    dev = jax.devices()[0]
    if dev.platform == "cpu":  # this machine (CI); on a GPU the device's memory sets the chunk
        assert execution.for_device(dev) == cpu
        assert execution.resolve(None, dev) == cpu
    else:
        mine = execution.for_device(dev)
        assert mine.platform == dev.platform and mine.block_numbers is None
        assert execution.resolve(None, dev) == mine
    assert execution.resolve("gpu", jax.devices()[0]) == gpu
    assert execution.block_size(cpu, 5000) == 13 and execution.block_size(gpu, 5000) is None
    for est, _ in FAMILIES.values():  # no CPU-only option reaches another platform
        assert execution.compiler_options(gpu, est.workload) is None
        assert execution.compiler_options(tpu, est.workload, {"xla_x": 1}) == {"xla_x": 1}
    assert execution.compiler_options(cpu, FAMILIES["ekf"][0].workload) == {
        "xla_cpu_use_fusion_emitters": False}
    assert execution.compiler_options(cpu, FAMILIES["bootstrap_pf"][0].workload) is None
    ys, us = _data()
    assert cpu.side_by_side == (os.cpu_count() or 1) and gpu.side_by_side == 1
    for bad in ("fpga", 3, cpu._replace(block_numbers=0), cpu._replace(runs_last="yes"),
                cpu._replace(chunk_bytes=-1.0), cpu._replace(side_by_side=0)):
        with pytest.raises(ValueError, match="strategy"):
            vj.run(FAMILIES["ekf"][0], ys, us, x0=X0, P0=P0, execution=vj.Execution(strategy=bad))


@pytest.mark.parametrize("family", [
    # the particle filters (Liu-West about 17 s of compiling on 2 cores, the bootstrap PF 13 s)
    # and the dual EKF (the joint UKF stands for the parameter filters): `pytest -m slow`
    pytest.param(f, marks=pytest.mark.slow) if f in ("liu_west", "bootstrap_pf", "dual_ekf")
    else f
    for f in sorted(FAMILIES)])
def test_gpu_strategy_on_the_cpu_gives_the_cpu_results(family, monkeypatch):
    """No blocking, no CPU XLA options, no trigonometric substitutes, chunks from a device
    budget: the same estimates to 1e-12 (the strategies change execution, not results), or,
    for a filter whose estimates move more than that when the data move by one ulp (measured
    here under the CPU strategy: the Sage-Husa ACKF on run 1 moves by about 3e-4), to within
    that sensitivity; and the GPU strategy's study is compiled with no CPU option. (The CKF is
    the UKF's code with another rule; the marginalized PF is left out for its compile time.)
    A filter that draws random numbers agrees to its float32 draws' rounding (DRAW_RTOL)."""
    est, kw = FAMILIES[family]
    ys, us = _data(runs=5)
    cpu = execution.for_platform("cpu")._replace(block_numbers=1)  # blocks of 4 runs, padded
    seen = []
    real = execution.compiler_options

    def spy(strategy, workload, user=None):
        out = real(strategy, workload, user)
        seen.append((strategy.platform, out))
        return out

    monkeypatch.setattr(execution, "compiler_options", spy)
    a = vj.run(est, ys, us, x0=X0, P0=P0, return_covariances=True,
               execution=vj.Execution(strategy=cpu), **kw)
    b = vj.run(est, ys, us, x0=X0, P0=P0, return_covariances=True,
               execution=vj.Execution(strategy="gpu"), **kw)
    assert [p for p, _ in seen] == ["cpu", "gpu"]
    assert seen[1][1] is None or not any(k.startswith("xla_cpu") for k in seen[1][1])
    ulp = vj.run(est, ys * (1 + np.finfo(float).eps), us, x0=X0, P0=P0, return_covariances=True,
                 execution=vj.Execution(strategy=cpu), **kw)  # the same compiled study, data one ulp away
    for name in ("states", "covariances", "params", "loglik", "nis"):
        ref, got, moved = (np.asarray(getattr(r, name)) for r in (a, b, ulp))
        sensitivity = float(np.nanmax(np.abs(moved - ref), initial=0.0))
        # a filter that draws random numbers: two programs round its float32 draws apart
        # (tests/_contract.py), which moving the data by one ulp does not show
        rel = DRAW_RTOL if est.needs_key else 1e-12
        tol = max(rel * max(1.0, float(np.nanmax(np.abs(ref), initial=0.0))), sensitivity)
        assert float(np.nanmax(np.abs(got - ref), initial=0.0)) <= tol, f"{family}: {name}"
    np.testing.assert_array_equal(b.diverged, a.diverged)
    assert not a.diverged.any()


def test_gpu_strategy_drops_the_substitutes():
    """Under the GPU strategy a fast_math model is traced with jnp's own sin (no substitute);
    under the CPU strategy with vehjax's."""
    x, u = jnp.array([0.3, 0.1]), jnp.array([0.0])

    def prims(strategy):
        with execution.using(strategy):
            jaxpr = jax.make_jaxpr(MODEL.observe)(x, u, jnp.asarray(MODEL.theta))
        return {e.primitive.name for e in jaxpr.jaxpr.eqns}

    assert "sin" in prims(execution.for_platform("gpu"))
    assert "sin" not in prims(execution.for_platform("cpu"))


def test_results_can_stay_on_the_device():
    est, _ = FAMILIES["ekf"]
    ys, us = _data(runs=5)
    host = vj.run(est, ys, us, x0=X0, P0=P0, execution=vj.Execution(chunk_size=2))
    dev = vj.run(est, ys, us, x0=X0, P0=P0, execution=vj.Execution(
        chunk_size=2, strategy=execution.for_platform("cpu")._replace(results_to_host=False)))
    assert isinstance(dev.states, jax.Array) and isinstance(host.states, np.ndarray)
    np.testing.assert_allclose(np.asarray(dev.states), host.states, rtol=1e-13, atol=0)


def test_memory_guards_refuse_a_study_that_cannot_fit():
    ys, us = _data(runs=2)
    huge_pf = vj.filters.bootstrap_pf(MODEL, Q, R, n_particles=2**30)  # 16 x 8 x 2^30 x 2 bytes a run
    with pytest.raises(ValueError, match=r"one run needs about .* GiB.* device has .* GiB"):
        vj.run(huge_pf, ys, us, x0=X0, P0=P0, key=jax.random.key(0))
    # results: 300 states with covariances over 4000 runs x 2000 steps = 5.8 TB on the host
    n = 300
    big = vj.models.Model(lambda x, u, th: 0.9 * x, lambda x, u, th: x[:1], dt=0.1,
                          state_names=tuple(f"x{i}" for i in range(n)), output_names=("y",))
    est = vj.filters.ekf(big, np.eye(n), np.eye(1))
    with pytest.raises(ValueError, match=r"results need about .* GiB of host memory"):
        vj.compile_run(est, np.zeros((4000, 2000, 1)), None, x0=np.zeros(n), P0=np.eye(n),
                       return_covariances=True)


def test_compile_run_keeps_its_own_copy_of_the_data():
    est, _ = FAMILIES["ekf"]
    ys, us = _data()
    prepared = vj.compile_run(est, ys, us, x0=X0, P0=P0)
    first = prepared()
    ys[:] = 0.0
    us[:] = 5.0
    np.testing.assert_array_equal(prepared().states, first.states)


_PLATFORM = re.compile(r"\.platform\b|default_backend|memory_stats|xla_cpu_|device_kind")


def test_no_module_outside_the_seam_reads_the_platform():
    """Only vehjax/execution.py reads the platform or names a CPU XLA option (and the package's
    __init__ the one XLA flag that must be set before JAX starts, docs/execution.md); benchmarks
    may print the platform but take their XLA options from the seam."""
    offenders = []
    for path in sorted((ROOT / "vehjax").rglob("*.py")):
        if path.name == "execution.py" or path == ROOT / "vehjax" / "__init__.py":
            continue
        for i, line in enumerate(path.read_text().splitlines(), 1):
            if _PLATFORM.search(line):
                offenders.append(f"{path.relative_to(ROOT)}:{i}: {line.strip()}")
    for path in sorted((ROOT / "benchmarks").glob("*.py")):
        for i, line in enumerate(path.read_text().splitlines(), 1):
            if "xla_cpu_" in line:
                offenders.append(f"{path.relative_to(ROOT)}:{i}: {line.strip()}")
    assert not offenders, "\n".join(offenders)


@pytest.mark.slow  # a benchmark smoke run: `pytest -m slow` (README)
def test_bench_device_quick_runs(capsys):
    from vehjax import cli

    bench = cli.load_benchmark("device")
    assert bench.main(["--quick", "--repeat", "1", "--parts", "scale,float32",
                       "--families", "EKF"]) == 0
    out = capsys.readouterr().out
    assert "Device benchmark on" in out and "particle-steps per second" in out
    assert re.search(r"EKF\s+[\d.]+\s+[\d.]+", out) and "targets" in out


def test_one_run_goes_by_the_per_run_step(monkeypatch):
    """A chunk of one run takes the per-run step (the one vehjax.filter runs), a chunk of more
    the runs-last step, under the CPU's strategy (execution.runs_last_for)."""
    import importlib

    batch = importlib.import_module("vehjax.runner.batch")

    cpu = execution.for_platform("cpu")
    assert not execution.runs_last_for(cpu, 1) and execution.runs_last_for(cpu, 2)
    assert not execution.runs_last_for(cpu._replace(runs_last=False), 5)
    taken = []
    real = batch.runs_last_study
    monkeypatch.setattr(batch, "runs_last_study",
                        lambda *a, **k: taken.append(a[3][0]) or real(*a, **k))
    est = FAMILIES["ekf"][0]
    ys, us = _data(runs=2, steps=7, seed=5)  # shapes no other test traces (no cached study)
    one = vj.run(est, ys[:1], us, x0=X0, P0=P0, execution=vj.Execution(strategy=cpu))
    assert taken == []
    ref = vj.filter(est, ys[0], us, x0=X0, P0=P0)
    np.testing.assert_allclose(one.states[0], ref.states, rtol=1e-12, atol=1e-12)
    vj.run(est, ys[:2], us, x0=X0, P0=P0, execution=vj.Execution(strategy=cpu))
    assert taken == [True]


@pytest.mark.parametrize("bad", ["cpu", b"cpu", 3, [], ["cpu"]])
def test_devices_that_are_not_devices_are_refused_naming_devices(bad):
    """A string is not read as the sequence of its characters."""
    with pytest.raises(ValueError, match="^devices: expected") as err:
        execution.resolve_devices(bad)
    assert repr(bad) in str(err.value)
    assert execution.resolve_devices([jax.devices()[0]]) == [jax.devices()[0]]
