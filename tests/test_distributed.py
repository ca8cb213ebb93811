"""vehjax.run under multi-controller JAX (jax.distributed): two local CPU processes, each calling
run with the same arguments, both return what one process returns (issue #16, "past one machine").

The test spawns two worker processes (this file run as a script) that initialise jax.distributed
on a free localhost port (gloo CPU collectives), process 0 with two CPU devices and process 1 with
one, load the same data, run the same studies and write their results to npz files; meanwhile
the parent runs the studies in one process on one device, then compares. About 30 s on two
cores, most of it XLA compiling the same programs in three processes.

What is compared how. The two workers hold the same gathered arrays: bit for bit. Against one
process the programs differ (sharded over three devices against one), so the results agree to
a tolerance: the UKF's to 1e-10 (float64 rounding through 50 steps of small, well-conditioned
algebra). The particle filters draw float32 normals, which two programs may round differently
in the last float32 bit (tests/_contract.py's DRAW_RTOL), and a resampling decision can turn on
that bit; so the particle studies run a program without resampling decisions (``ess_threshold=0``:
the filter never resamples) and agree to DRAW_RTOL. The workers compile with this process's XLA
code-generation options (tests/conftest.py's), so the comparison is between shardings, not
between code generators.
"""

import os
import socket
import subprocess
import sys
import time

import jax
import numpy as np
import pytest

import vehjax  # noqa: F401  (float64)
from _contract import DRAW_RTOL

WORKER_TIMEOUT = 150  # s, for the pair; a hung worker fails the test instead of CI
UKF_RUNS, UKF_STEPS = 7, 50
PF_RUNS, PF_STEPS, PF_PARTICLES = 4, 30, 64
STUDIES = ("ukf", "pf", "pf_compiled")
FIELDS = ("states", "covariances", "params", "params_cov", "loglik", "nis", "n_obs",
          "diverged", "diverged_at", "at_bound")
# a linear model (constant acceleration input), cheap to compile
A = np.array([[1.0, 0.1], [0.0, 1.0]])
B = np.array([[0.005], [0.1]])
H = np.array([[1.0, 0.0], [0.3, 1.0]])
Q, RN = [0.01, 0.02], [0.5, 0.2]
P0 = np.array([[2.0, 0.3], [0.3, 1.0]])


def _estimators():
    import jax.numpy as jnp

    model = vehjax.models.Model(
        lambda x, u, th: jnp.asarray(A) @ x + jnp.asarray(B) @ u,
        lambda x, u, th: jnp.asarray(H) @ x,
        dt=0.1, state_names=("p", "v"), input_names=("a",), output_names=("y1", "y2"),
    )
    ukf = vehjax.filters.ukf(model, Q, RN)
    assert ukf.batch is not None  # the runs-last path of vehjax.run; the PF is vmapped
    # ess_threshold=0: never resamples, so no decision turns on a draw's last float32 bit
    return ukf, vehjax.filters.bootstrap_pf(model, Q, RN, n_particles=PF_PARTICLES,
                                            resampling=vehjax.filters.Resampling(ess_threshold=0.0))


def _make_data(path):
    rng = np.random.default_rng(0)
    ys = rng.normal(size=(UKF_RUNS, UKF_STEPS, 2)) + np.linspace(0, 3, UKF_STEPS)[None, :, None]
    ys[1, 4, 1] = np.nan  # a missing component
    ys[4, 20, 0] = 1e300  # run 4 diverges
    x0s = np.array([0.5, -1.0]) + np.linspace(-0.2, 0.2, UKF_RUNS)[:, None]  # one per run
    np.savez(path, ys=ys, us=rng.normal(size=(UKF_STEPS, 1)), x0s=x0s)


def _ukf_study(ukf, d, **placement):
    """The runs-last UKF path; 3 runs a chunk (a multiple of 1 or 3 devices): 3 chunks of the
    7 runs, the last padded. ``placement``: further fields of its vehjax.Execution."""
    return vehjax.run(ukf, d["ys"], d["us"], x0=d["x0s"], P0=P0, return_covariances=True,
                      execution=vehjax.Execution(chunk_size=3, **placement), progress=False)


def _studies(data_path, pf_progress=False, **placement):
    """The studies as RunResults; the same calls in every process (SPMD). The PF (vmapped path,
    per-run keys) is compiled by compile_run; 4 runs in one chunk, padded to the device count."""
    d = np.load(data_path)
    ukf, pf = _estimators()
    pf_ys = d["ys"][:PF_RUNS, :PF_STEPS].copy()
    pf_ys[pf_ys > 1e3] = np.nan
    pf_args = (pf, pf_ys, d["us"][:PF_STEPS])
    pf_kw = dict(x0=d["x0s"][0], P0=P0, key=jax.random.key(11), progress=False,
                 execution=vehjax.Execution(**placement))
    prepared = vehjax.compile_run(*pf_args, **pf_kw)
    return {
        "ukf": _ukf_study(ukf, d, **placement),
        "pf_compiled": prepared(),
        # the executable compile_run made; a progress bar on process 0 only
        "pf": vehjax.run(*pf_args, **{**pf_kw, "progress": pf_progress}),
    }


def _save(path, results):
    np.savez(path, **{f"{name}.{f}": getattr(res, f) for name, res in results.items()
                      for f in FIELDS if getattr(res, f) is not None})


def _worker(pid, port, n_local, data_path, out_path):
    """One of the two processes: initialise jax.distributed, run the studies, save them."""
    t0 = time.perf_counter()
    jax.config.update("jax_num_cpu_devices", n_local)
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(coordinator_address=f"127.0.0.1:{port}", num_processes=2,
                               process_id=pid, initialization_timeout=60)
    assert jax.process_count() == 2 and len(jax.local_devices()) == n_local
    t1 = time.perf_counter()
    results = _studies(data_path, pf_progress=True)
    t2 = time.perf_counter()
    # devices=False: each process runs the whole study on its own first device, no communication
    d = np.load(data_path)
    results["local"] = _ukf_study(_estimators()[0], d, devices=False)
    t3 = time.perf_counter()
    # arguments that differ between processes are refused in every process, nothing hangs
    ys = d["ys"].copy()
    ys[0, 0, 0] += jax.process_index()
    try:
        vehjax.run(_estimators()[0], ys, d["us"], x0=d["x0s"], P0=P0, progress=False)
        refused = "no"
    except ValueError as e:
        refused = "yes" if "same arguments" in str(e) else repr(e)
    _save(out_path, results)
    print(f"worker {pid}: {len(jax.devices())} global devices, init {t1 - t0:.1f} s, studies "
          f"{t2 - t1:.1f} s, local {t3 - t2:.1f} s, refused={refused}, ok", flush=True)
    jax.distributed.shutdown()


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _no_gloo():
    """True when this jaxlib has no gloo CPU collectives (built without them)."""
    try:
        from jax._src.lib import _jax
    except ImportError:
        return False  # cannot tell: run the test
    return not hasattr(_jax, "make_gloo_tcp_collectives")


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    path = tmp_path_factory.mktemp("dist") / "data.npz"
    _make_data(path)
    return path


def _start(local_devices, data, tmp_path):
    env = dict(os.environ, JAX_PLATFORMS="cpu", JAX_ENABLE_X64="1")
    # the workers set their own device counts; they keep this process's code generation
    # (tests/conftest.py's LLVM level and fusion emitters), which changes the last bits
    keep = [f for f in os.environ.get("XLA_FLAGS", "").split()
            if not f.startswith("--xla_force_host_platform_device_count")]
    env["XLA_FLAGS"] = " ".join(keep)
    port = _free_port()
    outs = [tmp_path / f"out{i}.npz" for i in range(2)]
    procs = [
        subprocess.Popen(
            [sys.executable, __file__, str(i), str(port), str(n), str(data), str(outs[i])],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env,
            cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
        )
        for i, n in enumerate(local_devices)
    ]
    return procs, outs, time.monotonic() + WORKER_TIMEOUT


def _finish(procs, outs, deadline):
    logs = []
    try:
        for p in procs:
            logs.append(p.communicate(timeout=max(1.0, deadline - time.monotonic()))[0])
    except subprocess.TimeoutExpired:
        for p in procs:
            p.kill()
        logs = [p.communicate()[0] for p in procs]
        pytest.fail(f"workers hung past {WORKER_TIMEOUT} s:\n" + "\n---\n".join(
            log[-2000:] for log in logs))
    for i, (p, log) in enumerate(zip(procs, logs)):
        assert p.returncode == 0, f"worker {i} failed:\n{log[-4000:]}"
        assert "refused=yes, ok" in log, log[-2000:]
        print(log.strip().splitlines()[-1])
    return [dict(np.load(o)) for o in outs], logs


def _compare(got, want, name, exact, rtol=1e-10):
    """Every field of study ``name`` from a worker (``got``) against one process's: bit for bit
    (``exact``), or to ``rtol`` with the absolute tolerance ``rtol`` times the field's largest
    entry (an off-diagonal covariance near zero carries the error of the largest ones)."""
    for f in FIELDS:
        a, b = got.get(f"{name}.{f}"), getattr(want, f)
        if b is None:
            assert a is None, (name, f)
            continue
        assert a is not None and a.shape == b.shape, (name, f)
        if exact or a.dtype.kind in "biu":
            np.testing.assert_array_equal(a, b, err_msg=f"{name}.{f}")
        else:
            atol = max(1e-12, rtol * float(np.max(np.abs(b[np.isfinite(b)]), initial=0.0)))
            np.testing.assert_allclose(a, b, rtol=rtol, atol=atol, err_msg=f"{name}.{f}")


@pytest.mark.slow  # two fresh processes compiling the study: `pytest -m slow` (README)
@pytest.mark.skipif(_no_gloo(), reason="this jaxlib has no gloo CPU collectives, so CPU "
                    "processes cannot exchange data under jax.distributed")
def test_two_processes_equal_one_process(data, tmp_path):
    """Process 0 with two CPU devices, process 1 with one: three devices in the global mesh."""
    procs = _start((2, 1), data, tmp_path)
    try:
        # one process, one device, meanwhile
        one = _studies(data, devices=False)
    finally:
        outs, logs = _finish(*procs)
    assert "vehjax.run" in logs[0] and "vehjax.run" not in logs[1]  # the progress bar
    # both processes hold the whole result, bit for bit
    assert outs[0].keys() == outs[1].keys()
    for k in outs[0]:
        np.testing.assert_array_equal(outs[0][k], outs[1][k], err_msg=k)
    for name in STUDIES:
        _compare(outs[0], one[name], name, exact=False,
                 rtol=1e-10 if name == "ukf" else DRAW_RTOL)
    assert outs[0]["ukf.diverged"].tolist() == [False] * 4 + [True, False, False]
    # devices=False: each process ran the whole study alone, as one process does
    _compare(outs[0], one["ukf"], "local", exact=True)


def test_digest_tells_different_arguments_apart(data):
    """What the processes compare before they run (one process suffices to test it)."""
    import importlib

    plan_module = importlib.import_module("vehjax.runner.plan")
    shard = importlib.import_module("vehjax.runner.shard")
    d = np.load(data)
    ukf, pf = _estimators()

    def digest(est=ukf, ys=d["ys"], key=None, **kw):
        args = dict(x0=d["x0s"], P0=P0, theta0=None, P_theta0=None, key=key,
                    return_covariances=False, progress=None, execution=None)
        args.update(kw)
        plan = plan_module.plan(est, ys, d["us"], **args)
        assert not plan.spans_processes  # one process: the plain path
        return shard.digest(plan)

    base = digest()
    assert base.dtype == np.uint32 and base.shape == (8,)
    np.testing.assert_array_equal(digest(), base)
    ys = d["ys"].copy()
    ys[0, 0, 0] = np.nextafter(ys[0, 0, 0], np.inf)
    for other in (digest(ys=ys), digest(execution=vehjax.Execution(chunk_size=2)),
                  digest(return_covariances=True),
                  digest(x0=d["x0s"][0]), digest(est=ukf._replace(name="other"))):
        assert not np.array_equal(other, base)
    keyed = digest(est=pf, key=jax.random.key(0))
    assert not np.array_equal(digest(est=pf, key=jax.random.key(1)), keyed)


if __name__ == "__main__":
    _worker(int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), sys.argv[4], sys.argv[5])
