"""Test-session setup.

XLA's backend (LLVM) optimisation level 0 and its CPU fusion emitters off, unless XLA_FLAGS
names them or VEHJAX_TEST_XLA_DEFAULTS=1 asks for XLA's own options: see below. These speed
options change the last bits of floating-point results, not the programs' meaning; the
exactness checks also run under XLA's defaults and the other combinations
(tests/test_xla_options.py, ``pytest -m slow``).

One JAX persistent compilation cache per test session, in a fresh temporary folder that the
pytest-xdist workers and the notebook kernels inherit (the environment is set here, in the
controlling process, before jax is imported): the same study compiled by a test, a CLI test and
a notebook is compiled once. The folder is removed when the session ends. A cache the caller
configured (JAX_COMPILATION_CACHE_DIR set) is left alone.
"""

import os
import shutil
import tempfile

# VEHJAX_TEST_XLA_DEFAULTS=1: XLA's own options, as users run (tests/test_xla_options.py)
_DEFAULTS = os.environ.get("VEHJAX_TEST_XLA_DEFAULTS") == "1"
if not _DEFAULTS and "--xla_backend_optimization_level" not in os.environ.get("XLA_FLAGS", ""):
    # The suite is compile-bound (small studies, many programs): LLVM at level 0 compiles
    # about a fifth faster (full suite on 2 cores: 14:00 before, 11:28 after with 80 s of new
    # tests). The programs (HLO, fusion) are the same; the machine code is less optimised (the
    # few run-heavy tests feel it) and the last bits of floating-point results can differ from
    # level 3 (e.g. which multiply-adds are contracted), so a test comparing across processes
    # gives its workers the same flag (tests/test_distributed.py).
    # LLVM's expensive passes off as well: tests/models/test_sevendof.py 165 -> 149 s of CPU (loaded
    # machine, one process each)
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "")
                               + " --xla_backend_optimization_level=0"
                               + " --xla_llvm_disable_expensive_passes=true").strip()
if not _DEFAULTS and "--xla_cpu_use_fusion_emitters" not in os.environ.get("XLA_FLAGS", ""):
    # XLA's CPU fusion emitters off: a bootstrap PF's program compiles in about half the CPU
    # time (1.4 against 2.7-3.5 s, measured on 2 cores). vehjax.run already compiles its
    # small dense studies so on the CPU (vehjax.execution.compiler_options); here every program
    # of the suite is, so a test comparing two programs compares the same code generation.
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "")
                               + " --xla_cpu_use_fusion_emitters=false").strip()

if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
    os.environ["JAX_COMPILATION_CACHE_DIR"] = tempfile.mkdtemp(prefix="vehjax-tests-jaxcache-")
    os.environ["VEHJAX_TEST_OWNS_CACHE"] = str(os.getpid())
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.5")

import vehjax  # noqa: E402,F401  (turns on float64 before any test builds arrays)


def pytest_unconfigure(config):
    if os.environ.get("VEHJAX_TEST_OWNS_CACHE") == str(os.getpid()):
        shutil.rmtree(os.environ["JAX_COMPILATION_CACHE_DIR"], ignore_errors=True)
