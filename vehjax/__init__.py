"""vehjax: batched, jitted state and parameter estimation for road vehicles.

Importing vehjax switches JAX to float64 (``jax_enable_x64``): estimation accuracy needs it.
Pass float32 arrays to run in single precision.
"""

import jax

jax.config.update("jax_enable_x64", True)

from . import filters, limit_drive, models, scenarios, second_car  # noqa: E402
from . import data, execution, math, metrics, tune  # noqa: E402
from . import calibrate  # noqa: E402
from .filtering import FilterResult, filter  # noqa: E402
from .smoothing import SmoothResult, smooth  # noqa: E402
from .run import CompiledRun, RunResult, compile_run, run  # noqa: E402
from .simulate import Simulation, simulate  # noqa: E402

__version__ = "0.1.0"

__all__ = [
    "filters", "models", "scenarios", "limit_drive", "second_car", "metrics", "data", "math", "tune", "calibrate",
    "execution", "simulate",
    "Simulation",
    "filter", "FilterResult", "smooth", "SmoothResult", "run", "compile_run", "RunResult", "CompiledRun",
]
