"""Test-session setup.

One JAX persistent compilation cache per test session, in a fresh temporary folder that the
pytest-xdist workers and the notebook kernels inherit (the environment is set here, in the
controlling process, before jax is imported): the same study compiled by a test, a CLI test and
a notebook is compiled once. The folder is removed when the session ends. A cache the caller
configured (JAX_COMPILATION_CACHE_DIR set) is left alone.
"""

import os
import shutil
import tempfile

if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
    os.environ["JAX_COMPILATION_CACHE_DIR"] = tempfile.mkdtemp(prefix="vehjax-tests-jaxcache-")
    os.environ["VEHJAX_TEST_OWNS_CACHE"] = str(os.getpid())
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.5")

import vehjax  # noqa: E402,F401  (turns on float64 before any test builds arrays)


def pytest_unconfigure(config):
    if os.environ.get("VEHJAX_TEST_OWNS_CACHE") == str(os.getpid()):
        shutil.rmtree(os.environ["JAX_COMPILATION_CACHE_DIR"], ignore_errors=True)
