"""``import vehjax`` and ``vehjax --help`` import no JAX: the package's names load on first use
(vehjax/__init__.py), and float64 is on whenever vehjax code runs, whichever was imported first.

Each check runs in a fresh interpreter (what is imported is a property of the process). The
environment of these interpreters has no JAX_ENABLE_X64 (the test session's own ``import
vehjax`` set it): float64 must come from vehjax itself. No wall times are asserted; they are
measured in benchmarks/results.
"""

import json
import os
import subprocess
import sys
import textwrap

import pytest

import vehjax
from vehjax import cli

#: what ``import vehjax`` and ``vehjax --help`` must not import
HEAVY = ("jax", "jaxlib", "numpy", "scipy", "matplotlib", "tqdm", "equinox", "optax")


def _python(code: str, x64: str | None = None, env: dict | None = None) -> dict:
    """Run ``code`` in a fresh interpreter (JAX_ENABLE_X64 unset, or set to ``x64``; the
    variables of ``env`` set, those mapped to None unset); its last line of stdout, JSON, is
    returned."""
    changes = dict(env or {})
    env = {k: v for k, v in os.environ.items() if k != "JAX_ENABLE_X64" and k not in changes}
    env.update({k: v for k, v in changes.items() if v is not None})
    if x64 is not None:
        env["JAX_ENABLE_X64"] = x64
    out = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True,
                         text=True, env=env)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


_LOADED = f"""
import json, sys
print(json.dumps(sorted(m for m in {HEAVY!r} if m in sys.modules)))
"""


def test_import_vehjax_imports_no_jax_numpy_or_matplotlib():
    assert _python("import vehjax" + _LOADED) == []


@pytest.mark.parametrize("argv", [["--help"], ["--version"], ["simulate", "--help"],
                                  ["models", "--help"], ["simulate", "NoSuchModel", "x"],
                                  ["fit", "--help"], ["estimate", "--help"]])
def test_the_command_line_parser_imports_no_jax(argv):
    # as ``python -m vehjax.cli`` and as the ``vehjax`` entry point (vehjax.cli:main) run it
    for run in ("import runpy; runpy.run_module('vehjax.cli', run_name='__main__')",
                "from vehjax.cli import main; sys.exit(main())"):
        code = f"""
        import contextlib, io, sys
        sys.argv = ["vehjax", *{argv!r}]
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            try:
                {run}
            except SystemExit:
                pass
        """
        assert _python(textwrap.dedent(code) + _LOADED) == [], (argv, run)


def test_the_parsers_names_are_the_registries():
    assert cli.MODELS == tuple(sorted(vehjax.models.REGISTRY))
    assert cli.SCENARIOS == tuple(sorted(vehjax.scenarios.REGISTRY))


_DTYPE = """
import json, jax, jax.numpy as jnp
print(json.dumps([str(jnp.zeros(()).dtype), jax.config.jax_enable_x64]))
"""


@pytest.mark.parametrize("first, x64", [
    ("import vehjax\nvehjax.filter", None),  # vehjax first, JAX on first use
    ("import vehjax\nvehjax.filter", "0"),  # as before: importing vehjax switches JAX to float64
    ("from vehjax.filters import ekf", None),  # a submodule first: runs vehjax/__init__ first
    ("import jax, vehjax\nassert jax.config.jax_enable_x64", None),  # JAX first
    ("import jax, vehjax\nassert jax.config.jax_enable_x64", "0"),
])
def test_float64_is_on_whichever_is_imported_first(first, x64):
    assert _python(first + _DTYPE, x64) == ["float64", True]


def test_the_lazy_names_are_the_eager_ones():
    code = """
    import json, types, vehjax
    from vehjax.run import RunResult  # the submodules run and simulate load before the names
    import vehjax.studies.dual_settings  # imports vehjax.simulate
    out = {"run": type(vehjax.run).__name__, "simulate": type(vehjax.simulate).__name__,
           "all": vehjax.__all__, "dir": all(n in dir(vehjax) for n in vehjax.__all__)}
    ns = {}
    exec("from vehjax import *", ns)
    out["star"] = sorted(n for n in ns if not n.startswith("__"))
    out["kinds"] = {n: isinstance(getattr(vehjax, n), types.ModuleType) for n in vehjax.__all__}
    out["same"] = (vehjax.run is sys.modules["vehjax.run"].run
                   and vehjax.RunResult is RunResult and vehjax.filters.ekf is not None
                   and vehjax.tune.fit is sys.modules["vehjax.tune"].fit
                   and vehjax.engine is sys.modules["vehjax.engine"])
    try:
        vehjax.no_such_name
        out["missing"] = "no error"
    except AttributeError as err:
        out["missing"] = str(err)
    print(json.dumps(out))
    """
    out = _python("import sys\n" + textwrap.dedent(code))
    assert out["run"] == out["simulate"] == "function"
    assert out["all"] == vehjax.__all__ and out["dir"] and out["same"]
    assert out["star"] == sorted(vehjax.__all__)
    modules = {"filters", "models", "scenarios", "studies", "metrics", "data", "tune", "calibrate",
               "execution"}
    assert out["kinds"] == {n: n in modules for n in vehjax.__all__}
    assert out["missing"] == "module 'vehjax' has no attribute 'no_such_name'"


_CACHE = """
import json, jax, jax.numpy as jnp
f = jax.jit(lambda a: jnp.cumsum(jnp.sin(a) @ a.T, axis=0))
f(jnp.ones((64, 64))).block_until_ready()
print(json.dumps(jax.config.jax_compilation_cache_dir))
"""
_NO_CACHE = {"JAX_COMPILATION_CACHE_DIR": None, "VEHJAX_CACHE_DIR": None,
             "VEHJAX_COMPILATION_CACHE": None, "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0"}


@pytest.mark.parametrize("first", ["import vehjax\nvehjax.filter", "import jax, vehjax"])
def test_compiled_programs_are_kept_in_vehjax_cache_folder(tmp_path, first):
    """Whichever is imported first, a program compiled in one process is written to the cache
    folder (VEHJAX_CACHE_DIR here; ~/.cache/vehjax/xla by default) and read back by the next
    process, which writes nothing new."""
    env = {**_NO_CACHE, "VEHJAX_CACHE_DIR": str(tmp_path / "xla")}
    assert _python(first + _CACHE, env=env) == str(tmp_path / "xla")
    entries = sorted(p.name for p in (tmp_path / "xla").iterdir())
    assert entries  # the program, written
    assert _python(first + _CACHE, env=env) == str(tmp_path / "xla")
    assert sorted(p.name for p in (tmp_path / "xla").iterdir()) == entries  # read, not redone


def test_the_cache_defaults_to_the_user_cache_folder_and_can_be_turned_off(tmp_path):
    home = {**_NO_CACHE, "XDG_CACHE_HOME": str(tmp_path)}
    assert _python("import vehjax" + _CACHE, env=home) == str(tmp_path / "vehjax" / "xla")
    assert _python("import vehjax" + _CACHE,
                   env={**home, "VEHJAX_COMPILATION_CACHE": "Off"}) is None
    mine = str(tmp_path / "mine")  # a cache the user set is left alone
    assert _python("import vehjax" + _CACHE,
                   env={**home, "JAX_COMPILATION_CACHE_DIR": mine}) == mine
    assert _python(f"import jax\njax.config.update('jax_compilation_cache_dir', {mine!r})\n"
                   "import vehjax" + _CACHE, env=home) == mine


def test_xla_flags_raise_the_small_loop_limit_once(monkeypatch):
    """The small-while-loop limit is added to XLA_FLAGS, merged into backend extra options
    already given, and left as it is where the user set it or turned it off."""
    monkeypatch.delenv("VEHJAX_XLA_SMALL_LOOPS", raising=False)
    item = f"xla_cpu_small_while_loop_byte_threshold={vehjax.SMALL_LOOP_BYTES}"
    assert vehjax._xla_flags("") == f"--xla_backend_extra_options={item}"
    assert (vehjax._xla_flags("--xla_a=1 --xla_backend_extra_options=k=v --xla_b=2")
            == f"--xla_a=1 --xla_backend_extra_options=k=v,{item} --xla_b=2")
    mine = "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=0"
    assert vehjax._xla_flags(mine) == mine
    assert vehjax._xla_flags(vehjax._xla_flags("")) == vehjax._xla_flags("")
    monkeypatch.setenv("VEHJAX_XLA_SMALL_LOOPS", "Off")
    assert vehjax._xla_flags("--xla_a=1") == "--xla_a=1"


_SMALL_CALL = """
import json, vehjax, jax, numpy as np
from vehjax.models import SingleTrack
est = vehjax.filters.ekf(SingleTrack(tyres="linear"), np.diag([1e-4, 1e-5]), np.diag([0.1, 1e-4]))
us = np.tile([0.01, 20.0], (50, 1))
f = jax.jit(lambda y: vehjax.filter(est, y, us, x0=np.zeros(2), P0=np.eye(2)).loglik)
print(json.dumps("xla_cpu_small_call" in f.lower(np.zeros((50, 2))).compile().as_text()))
"""


@pytest.mark.parametrize("first", ["", "import jax\n"])
def test_a_filters_scan_compiles_into_one_kernel(first):
    """With vehjax imported before JAX computes anything (JAX imported first or not), XLA:CPU
    compiles a filter's scan over time into one function (its small-loop call) rather than
    running each step's kernels through its thunk executor; VEHJAX_XLA_SMALL_LOOPS=off keeps
    XLA's own limit, under which it does not."""
    flags = {"XLA_FLAGS": None, "VEHJAX_XLA_SMALL_LOOPS": None}
    assert _python(first + _SMALL_CALL, env=flags) is True
    assert _python(first + _SMALL_CALL, env={**flags, "VEHJAX_XLA_SMALL_LOOPS": "off"}) is False
