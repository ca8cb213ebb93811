"""vehjax: batched, jitted state and parameter estimation for road vehicles.

Importing vehjax switches JAX to float64 (``jax_enable_x64``): estimation accuracy needs it.
Pass float32 arrays to run in single precision.

``import vehjax`` itself is light: it imports neither JAX nor numpy. The submodules and the
names of ``__all__`` load when first used (``vehjax.filter``, ``vehjax.tune.fit``, ``from vehjax
import run``, ``import vehjax.models``), so that ``vehjax --help`` answers at once. float64 is on
before any vehjax module runs: when JAX is not imported yet, importing vehjax sets
``JAX_ENABLE_X64=1`` in the environment, which JAX reads when it is imported (child processes
inherit it); when JAX was imported first, importing vehjax calls
``jax.config.update("jax_enable_x64", True)``.

Compiled programs are kept on disk between processes (JAX's persistent compilation cache, in
``~/.cache/vehjax/xla``; ``VEHJAX_CACHE_DIR`` names another folder): the second fit or study of
the same structure, in a new process, skips most of its compile (the brush fit of
``benchmarks/bench_fit_limit.py``: about a fifth less wall time the second time). Entries are small (a few MB for a fit's programs) and are never evicted:
delete the folder to clear it. ``VEHJAX_COMPILATION_CACHE=off`` turns it off; a cache already
set (``JAX_COMPILATION_CACHE_DIR``, or ``jax.config`` before importing vehjax) is left alone.

On the CPU, importing vehjax also lets XLA compile each filter's scan over time into one
function (``XLA_FLAGS``, :data:`SMALL_LOOP_BYTES`): one run goes several times faster. It acts
when vehjax is imported before JAX computes anything; ``VEHJAX_XLA_SMALL_LOOPS=off`` turns it
off (docs/execution.md, "One kernel per scan").
"""

import importlib
import importlib.util
import os
import sys
import types
from typing import TYPE_CHECKING



def _turned_off(variable: str) -> bool:
    """Whether the environment variable says ``0``/``off``/``false``/``no`` (any case)."""
    return os.environ.get(variable, "").strip().lower() in ("0", "off", "false", "no")


def _cache_dir() -> str | None:
    """The folder of the persistent compilation cache vehjax asks JAX for: ``VEHJAX_CACHE_DIR``,
    else ``$XDG_CACHE_HOME/vehjax/xla`` (``~/.cache/vehjax/xla``); None when
    ``VEHJAX_COMPILATION_CACHE`` is ``0``/``off``/``false``/``no``, or when a cache is set
    already (``JAX_COMPILATION_CACHE_DIR``, or ``jax.config`` of an imported JAX)."""
    if _turned_off("VEHJAX_COMPILATION_CACHE"):
        return None
    if os.environ.get("JAX_COMPILATION_CACHE_DIR"):
        return None
    if "jax" in sys.modules and sys.modules["jax"].config.jax_compilation_cache_dir:
        return None
    if os.environ.get("VEHJAX_CACHE_DIR"):
        return os.environ["VEHJAX_CACHE_DIR"]
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "vehjax", "xla")


#: XLA:CPU compiles a while loop that accesses at most this many bytes into one function
#: (its small-while-loop pass; XLA's own limit is 1 kB), instead of running each step's kernels
#: one by one through its thunk executor: a filter's ``lax.scan`` over a drive then runs at
#: the speed of compiled scalar code (``benchmarks/bench_floor.py``)
SMALL_LOOP_BYTES = 1 << 30
_SMALL_LOOP_OPTION = "xla_cpu_small_while_loop_byte_threshold"


def _xla_flags(flags: str) -> str:
    """``XLA_FLAGS`` with XLA:CPU's small-while-loop limit raised to :data:`SMALL_LOOP_BYTES`
    (a backend extra option, merged into a ``--xla_backend_extra_options`` already given);
    unchanged when the flags set that limit already or ``VEHJAX_XLA_SMALL_LOOPS`` is
    ``0``/``off``/``false``/``no``."""
    if _SMALL_LOOP_OPTION in flags or _turned_off("VEHJAX_XLA_SMALL_LOOPS"):
        return flags
    item = f"{_SMALL_LOOP_OPTION}={SMALL_LOOP_BYTES}"
    words = flags.split()
    for i, w in enumerate(words):
        if w.startswith("--xla_backend_extra_options="):
            words[i] = w + ("," if not w.endswith("=") else "") + item
            return " ".join(words)
    return " ".join(words + [f"--xla_backend_extra_options={item}"])


def _configure_jax() -> None:
    """float64 on, and the persistent compilation cache (:func:`_cache_dir`), through the
    environment when JAX is not imported yet (it reads it when imported; child processes
    inherit it), through ``jax.config`` when it is. XLA's flags (:func:`_xla_flags`) are read
    when JAX starts its first backend: set here in every case, they act unless JAX has
    computed something before vehjax was imported."""
    flags = os.environ.get("XLA_FLAGS", "")
    ours = _xla_flags(flags)
    if ours != flags:
        os.environ["XLA_FLAGS"] = ours
    cache = _cache_dir()
    if "jax" in sys.modules:
        config = sys.modules["jax"].config
        config.update("jax_enable_x64", True)
        if cache is not None:
            config.update("jax_compilation_cache_dir", cache)
    else:
        os.environ["JAX_ENABLE_X64"] = "1"
        if cache is not None:
            os.environ["JAX_COMPILATION_CACHE_DIR"] = cache


_configure_jax()

if TYPE_CHECKING:  # what static analysers and IDEs see; at run time each loads on first use
    from . import calibrate, data, execution, filters, metrics, models, scenarios, studies, tune
    from .filtering import FilterResult, filter
    from .online import Online
    from .execution import Execution
    from .run import CompiledRun, RunResult, compile_run, run
    from .simulate import BiasWalk, NoiseScale, ParamDraw, Simulation, simulate
    from .smoothing import SmoothResult, smooth

__version__ = "0.1.0"

__all__ = [
    "filters", "models", "scenarios", "studies", "metrics", "data", "tune", "calibrate",
    "execution", "simulate",
    "Simulation", "ParamDraw", "NoiseScale", "BiasWalk",
    "filter", "FilterResult", "smooth", "SmoothResult", "run", "compile_run", "RunResult", "CompiledRun",
    "Execution", "Online",
]

#: the names of ``__all__`` that are not submodules -> the submodule that defines each
_DEFINED_IN = {
    "filter": "filtering", "FilterResult": "filtering", "smooth": "smoothing", "SmoothResult": "smoothing",
    "run": "run", "compile_run": "run", "RunResult": "run", "CompiledRun": "run",
    "Execution": "execution",
    "simulate": "simulate", "Simulation": "simulate", "ParamDraw": "simulate",
    "NoiseScale": "simulate", "BiasWalk": "simulate",
    "Online": "online",
}


def __getattr__(name: str):
    """A name of ``__all__`` or a submodule, imported on first use (PEP 562) and kept."""
    if name in _DEFINED_IN:
        value = getattr(importlib.import_module(f"{__name__}.{_DEFINED_IN[name]}"), name)
    elif name.isidentifier() and not name.startswith("__") \
            and importlib.util.find_spec(f"{__name__}.{name}") is not None:
        value = importlib.import_module(f"{__name__}.{name}")
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))


class _Package(types.ModuleType):
    """vehjax's module type: ``vehjax.run`` and ``vehjax.simulate`` stay the functions.

    The import system binds a submodule to its package's attribute when the submodule first
    loads (``from vehjax.run import RunResult`` anywhere would make ``vehjax.run`` the module);
    those two names keep the function of that name, the module stays in ``sys.modules``."""

    def __setattr__(self, name, value):
        if name in _DEFINED_IN and isinstance(value, types.ModuleType) \
                and value.__name__ == f"{__name__}.{name}":
            value = getattr(value, name)
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package
