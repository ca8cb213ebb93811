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
"""

import importlib
import importlib.util
import os
import sys
import types
from typing import TYPE_CHECKING

if "jax" in sys.modules:
    sys.modules["jax"].config.update("jax_enable_x64", True)
else:
    os.environ["JAX_ENABLE_X64"] = "1"

if TYPE_CHECKING:  # what static analysers and IDEs see; at run time each loads on first use
    from . import calibrate, data, execution, filters, limit_drive, math, metrics, models, scenarios
    from . import second_car, tune
    from .filtering import FilterResult, filter
    from .online import Online
    from .run import CompiledRun, RunResult, compile_run, run
    from .simulate import Simulation, simulate
    from .smoothing import SmoothResult, smooth

__version__ = "0.1.0"

__all__ = [
    "filters", "models", "scenarios", "limit_drive", "second_car", "metrics", "data", "math", "tune", "calibrate",
    "execution", "simulate",
    "Simulation",
    "filter", "FilterResult", "smooth", "SmoothResult", "run", "compile_run", "RunResult", "CompiledRun",
    "Online",
]

#: the names of ``__all__`` that are not submodules -> the submodule that defines each
_DEFINED_IN = {
    "filter": "filtering", "FilterResult": "filtering", "smooth": "smoothing", "SmoothResult": "smoothing",
    "run": "run", "compile_run": "run", "RunResult": "run", "CompiledRun": "run",
    "simulate": "simulate", "Simulation": "simulate",
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
