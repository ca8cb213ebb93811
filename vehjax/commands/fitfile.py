"""``fit.json``: a fitted filter written by ``vehjax fit``, enough to rebuild it with no other
input (``vehjax estimate``).

The file holds the model's specification (its [model] section with every parameter's fitted
value by name), the filter family and its fitted noise (Q, R as matrices, the input noise),
the prior a new drive starts from (x0, P0: the configuration's, not a value fitted to the
first drive; that one is ``x0_fitted`` where [fit] fit_x0 was set), the [drive] section (how a
drive file is read and mapped onto the model) and the [estimate] section, then the fit's
result for the record (values, standard errors, log-likelihood). Numbers are written as
Python's ``repr`` writes them, so they read back to the same float64; a standard error that is
not finite (a quantity the data do not determine, or one on a bound) is written as null.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from . import config
from .setup import BUILDERS, build_model, with_input_noise

__all__ = ["FORMAT", "record", "write", "read", "rebuild"]

#: the file's format tag; a file of another format is refused
FORMAT = "vehjax-fit/1"


def _finite_or_none(v: float):
    return float(v) if math.isfinite(v) else None


def _json(value):
    """``value`` with numpy arrays and tuples as lists (JSON's kinds)."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, dict):
        return {k: _json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


def record(config: dict, family: str, res, x0, P0, drive_path) -> dict:
    """The fit.json content of the TuneResult ``res`` fitted with ``config`` (checked
    sections) and filter ``family``; ``x0``, ``P0`` the prior a new drive starts from."""
    model = res.model
    spec = dict(config["model"], dt=float(model.dt),
                theta={n: float(v) for n, v in zip(model.param_names, np.asarray(model.theta))})
    out = {
        "format": FORMAT,
        "model": spec,
        "filter": {"family": family, "Q": res.Q, "R": res.R, "input_noise": res.input_noise},
        "x0": np.asarray(x0, dtype=float), "P0": np.asarray(P0, dtype=float),
        "drive": config["drive"], "estimate": config["estimate"],
        "states": {"names": model.state_names, "units": model.state_units},
        "result": {
            "drive": str(drive_path), "loglik": float(res.loglik), "converged": bool(res.converged),
            "iterations": int(res.iterations), "values": res.values, "units": res.units,
            "std_errors": {k: _finite_or_none(v) for k, v in res.std_errors.items()},
        },
    }
    if config["fit"].get("fit_x0"):
        out["x0_fitted"] = np.asarray(res.x0, dtype=float)
    return _json(out)


def write(path, content: dict) -> Path:
    path = Path(path)
    path.write_text(json.dumps(content, indent=1, allow_nan=False) + "\n", encoding="utf-8")
    return path


def read(path) -> dict:
    """The content of a fit.json; ValueError naming ``--fit`` for a missing file, one that is
    not JSON, or one of another format."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"--fit: {str(path)!r} is not a file")
    try:
        content = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise ValueError(f"--fit: {str(path)!r} is not a JSON file ({err})") from None
    if not isinstance(content, dict) or content.get("format") != FORMAT:
        raise ValueError(f"--fit: {str(path)!r} is not a fit written by `vehjax fit` (no "
                         f"'format': {FORMAT!r})")
    missing = [k for k in ("model", "filter", "x0", "P0", "drive", "estimate") if k not in content]
    if missing:
        raise ValueError(f"--fit: {str(path)!r} lacks {', '.join(missing)}")
    return content


def rebuild(content: dict, family: str | None = None):
    """(model, estimator, x0, P0) of a fit.json's content: the model rebuilt from its
    specification and fitted parameters, the filter ``family`` (default the fit's) with the
    fitted noise, and the prior a new drive starts from."""
    spec = config.check({"model": content["model"]}, "--fit", ("model",))["model"]
    model = build_model(spec, None)
    f = content["filter"]
    family = family or f["family"]
    if family not in BUILDERS:
        raise ValueError(f"--fit: unknown filter family {family!r}; expected one of "
                         f"{', '.join(BUILDERS)}")
    est = with_input_noise(BUILDERS[family], f["input_noise"])(
        model, np.asarray(f["Q"], dtype=float), np.asarray(f["R"], dtype=float))
    return model, est, np.asarray(content["x0"], dtype=float), np.asarray(content["P0"],
                                                                          dtype=float)
