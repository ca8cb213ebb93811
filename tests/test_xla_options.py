"""The exactness checks under the XLA options users run, not only the suite's own.

The suite compiles with LLVM at optimisation level 0 and XLA's CPU fusion emitters off
(tests/conftest.py), for speed. Those options change the machine code, so the last bits of
floating-point results, and a claim of equality checked only under them would hold for a program
users do not run: ``vehjax.run`` compiles small dense studies with the fusion emitters off at
level 3 (vehjax.execution), everything else with XLA's defaults (level 3, emitters on). Here the
checks that compare two programs or a program with an independent reference (the Gaussian and
particle filters' batched form against their step run by run, the studies' chunking, blocking and
keys, the RTS and parallel smoothers against numpy's recursions, the marginalized PF's smoother
path) run again in a fresh process under each of the other three combinations; each must pass
with the tolerances it states (derived beside each test, tests/_contract.py for the filters).
"""

import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

CHECKS = [
    "tests/filters/test_gaussian.py::test_many_runs_form_equals_the_step_run_by_run",
    "tests/filters/test_gaussian.py::test_many_runs_form_with_each_runs_theta0",
    "tests/filters/test_particle.py::test_many_runs_form_equals_the_step_run_by_run",
    "tests/filters/marginalized/test_paper.py::test_many_runs_form_equals_the_step_run_by_run",
    "tests/filters/test_runs_last.py::test_runs_last_equals_vmapped_step",
    "tests/filters/test_runs_last.py::test_runs_last_chunked_equals_one_chunk",
    "tests/test_run.py::test_matches_numpy_kalman_filter_run_by_run",
    "tests/test_run.py::test_chunked_equals_unchunked_and_progress",
    "tests/test_run.py::test_runs_in_blocks_equal_runs_side_by_side",
    "tests/test_run.py::test_keys_are_split_per_run_independent_of_chunking",
    "tests/test_smoothing.py::test_rts_equals_numpy_textbook_rts",
    "tests/test_smoothing.py::test_parallel_rts_equals_numpy_textbook_rts",
    "tests/smoothers/test_smoothing_parallel.py::"
    "test_parallel_and_sequential_kalman_equal_numpy_with_missing_components",
    "tests/smoothers/test_smoothing_mpf.py::"
    "test_linear_one_path_of_the_filter_is_the_exact_conditional",
]

# (LLVM optimisation level, CPU fusion emitters): the suite's own is (0, off)
OPTIONS = {
    "xla-defaults": None,
    "level0-emitters-on": "--xla_backend_optimization_level=0 --xla_cpu_use_fusion_emitters=true",
    "level3-emitters-off": "--xla_backend_optimization_level=3 --xla_cpu_use_fusion_emitters=false",
}


@pytest.mark.slow  # three fresh processes compiling about 30 programs each: `pytest -m slow`
@pytest.mark.parametrize("name", list(OPTIONS))
def test_exactness_checks_hold_under_other_xla_options(name):
    env = dict(os.environ)
    env.pop("XLA_FLAGS", None)
    env.pop("JAX_COMPILATION_CACHE_DIR", None)  # a cache keyed on the options: keep them apart
    env.pop("VEHJAX_TEST_OWNS_CACHE", None)
    if OPTIONS[name] is None:
        env["VEHJAX_TEST_XLA_DEFAULTS"] = "1"
    else:
        env["XLA_FLAGS"] = OPTIONS[name]
    # the project's addopts (two workers, "not slow") replaced: one process, every check; the
    # tests imported by their path as the suite does (pyproject.toml)
    cmd = [sys.executable, "-m", "pytest", "-o", "addopts=", "-q", "-p", "no:cacheprovider",
           "--import-mode=importlib", "-m", "slow or not slow", *CHECKS]
    res = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=1200)
    assert res.returncode == 0, f"under {name}:\n{res.stdout[-4000:]}\n{res.stderr[-2000:]}"
    last = res.stdout.strip().splitlines()[-1]
    assert " passed" in last and "failed" not in last and "skipped" not in last, last
