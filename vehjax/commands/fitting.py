"""``vehjax fit DRIVE --config car.toml --out DIR``: a model fitted to a drive file by maximum
likelihood (:func:`vehjax.tune.fit`), its report, its fitted filter and its figures.

Writes, in DIR:

* ``report.txt``: the drive, the model and the filter, then the fit's summary
  (:meth:`vehjax.tune.TuneResult.summary`: each value with its unit and standard error, the
  log-likelihood, the score tests of the held values and the innovation checks) and the fit's
  warnings;
* ``fit.json``: the fitted filter (:mod:`vehjax.commands.fitfile`), what ``vehjax estimate``
  runs;
* ``fitted.png``: each output measured against the fitted filter's one-step prediction;
* ``innovations.png``: the innovations with their +-2 sigma band.

The innovations are recomputed from the filtered estimates with the EKF's algebra
(:func:`vehjax.tune.innovations.innovations`): the EKF's own, a first-order approximation of
the UKF's and CKF's.
"""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

import numpy as np

from .. import tune
from ..filtering import filter as run_filter
from ..filters import input_noise as inoise
from ..tune.innovations import innovations, p_text
from ..tune.likelihood import NOISE
from ..tune.options import OPTIMIZERS
from . import figures, fitfile
from .setup import (BUILDERS, build_model, load_drive, model_label, on_model, start_values,
                    with_input_noise)

__all__ = ["run", "fit_options", "fit_keywords"]

#: [fit] keys read as they are (:func:`fit_keywords` maps them to vehjax.tune.fit's records)
_PASSED = ("fit_x0", "start", "compare", "release", "steps", "optimizer", "gtol")
#: the optimiser of a [fit] with steps or gtol but no optimizer name: scoring, the default (every
#: filter of the command is deterministic; L-BFGS beyond 12 fitted coordinates)
_DEFAULT_OPTIMIZER = "scoring"


def _check_starts(model, bounds: dict, floors) -> None:
    """Each bounded parameter's start (its value in ``model``) strictly inside its bounds, as
    vehjax.tune.fit requires; those with a data floor (``floors``) it moves there itself."""
    for k, (lo, hi) in bounds.items():
        v = float(model.theta[model.param_names.index(k)])
        if k not in floors and not lo < v < hi:
            raise ValueError(f"[fit] bounds: {k} starts at {v:g} ([model] theta, else the "
                             f"model's nominal value), not strictly inside [{lo:g}, {hi:g}]; "
                             f"give a start inside with [model] theta")


def fit_options(model, section: dict, floors=()) -> dict:
    """The fit's settings of the [fit] section (but the noise and prior), by their [fit] keys,
    the parameter names and bounds checked against ``model`` (``floors``: the names of the
    parameters with a data floor, ``model.data_floors``); :func:`fit_keywords` makes them
    vehjax.tune.fit's keyword arguments."""
    params = section.get("params", ())
    unknown = [p for p in params if p not in model.param_names]
    if unknown:
        raise ValueError(f"[fit] params: {unknown[0]!r} is not a parameter of the model; its "
                         f"parameters: {', '.join(model.param_names)}")
    bounds = section.get("bounds", {})
    stray = [k for k in bounds if k not in params]
    if stray:
        raise ValueError(f"[fit] bounds: {stray[0]!r} is not among the fitted params "
                         f"({', '.join(params) or 'none'})")
    _check_starts(model, bounds, floors if section.get("start", "data") == "data" else ())
    out = {k: section[k] for k in _PASSED if k in section}
    out.update(params=tuple(params), bounds=dict(bounds) or None,
               noise=tuple(section.get("noise", NOISE)))
    return out


def fit_keywords(options: dict, progress: bool) -> dict:
    """vehjax.tune.fit's keywords ``params``, ``start`` and ``options`` of the settings
    :func:`fit_options` read: the fitted quantities as a :class:`vehjax.tune.Fitted`, the start
    as a :class:`vehjax.tune.Start`, the optimiser's record (its steps and gtol where given, the
    default optimizer's otherwise) in :class:`vehjax.tune.Options`."""
    name = options.get("optimizer")
    limits = {k: options[k] for k in ("steps", "gtol") if k in options}
    optimizer = OPTIMIZERS[name or _DEFAULT_OPTIMIZER](**limits) if limits else name
    return dict(params=tune.Fitted(options["params"], options["noise"],
                                   options.get("fit_x0", False), options["bounds"]),
                start=tune.Start(options.get("start", "data"), options.get("compare", True),
                                 options.get("release", True)),
                options=tune.Options(optimizer=optimizer, progress=progress))


def _say(text: str) -> None:
    print(f"vehjax fit: {text}", file=sys.stderr, flush=True)


def _fit(builder, model, start, grid, options, progress):
    """(TuneResult, its warnings as one-line texts), the warnings also on stderr."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = tune.fit(with_input_noise(builder, start.input_noise), model, start.Q, start.R,
                       grid.measurements, grid.inputs, x0=start.x0, P0=start.P0,
                       **fit_keywords(options, progress))
    texts = [" ".join(str(w.message).split()) for w in caught]
    for t in texts:
        _say(f"warning: {t}")
    return res, texts


def _report(path, drive_path, grid, model, name, family, res, texts) -> Path:
    head = [f"drive: {drive_path} ({len(grid.t)} steps of {model.dt:g} s, t = {grid.t[0]:.6g}.."
            f"{grid.t[-1]:.6g} s)",
            f"model: {name}: states {', '.join(model.state_names)}; outputs "
            f"{', '.join(model.output_names)}",
            f"filter: {family}", ""]
    checks = [f"  {k}: mean NIS {c.nis_mean:.3g} (1 expected), lag-1 autocorrelation "
              f"{c.lag1:+.3f}, Ljung-Box {p_text(c.p_value)} ({c.lags} lags, {c.n} samples)"
              for k, c in res.innovations.items()]
    checks = ["", "innovations of the fitted filter, per output:", *checks] if checks else []
    tail = ["", "warnings:", *[f"  {t}" for t in texts]] if texts else []
    path.write_text("\n".join(head + [res.summary()] + checks + tail) + "\n",
                    encoding="utf-8")
    return path


def _figures(out: Path, grid, model, name, res, P0, family):
    """fitted.png and innovations.png of the fitted filter on the fit's own drive."""
    ys, us = grid.measurements, grid.inputs
    filt = run_filter(res.estimator, ys, us, x0=res.x0, P0=P0)
    Lu = inoise.input_factor(res.input_noise, model.input_names)
    e, S = innovations(res.model, res.Q, res.R, ys[None], us, np.asarray(filt.states)[None],
                       np.asarray(filt.covariances)[None], np.asarray(res.x0, float), P0, Lu)
    names, units = model.output_names, model.output_units
    label = f"{name}, {family.upper()} at the fitted values"
    return (figures.fitted(out / "fitted.png", grid.t, ys, e[0], names, units,
                           f"{label}: measured and one-step predicted outputs"),
            figures.innovations(out / "innovations.png", grid.t, e[0], S[0], names, units,
                                f"{label}: innovations"))


def run(drive_path, config: dict, out, progress: bool = True) -> int:
    """The command's work on checked sections ``config``: every check first (the drive read
    and mapped, the model built, the noise and options checked), then the fit and its files."""
    drive = load_drive(drive_path, config["drive"])
    model = build_model(config["model"], drive.dt)
    grid = on_model(drive, model, config["drive"])
    start = start_values(model, config["fit"])
    options = fit_options(model, config["fit"],
                          tuple(model.data_floors(grid.measurements, grid.inputs)))
    family = config["fit"].get("filter", "ekf")
    fitted = ", ".join(options["params"] + options["noise"]) or "nothing"
    name = model_label(config["model"])
    if progress:
        _say(f"fitting {fitted} of {name} with the {family.upper()} on {len(grid.t)} steps "
             f"of {model.dt:g} s (compiling first)")
    res, texts = _fit(BUILDERS[family], model, start, grid, options, progress)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)  # after the fit: a value it refuses leaves no folder
    P0 = start.P0
    written = [_report(out / "report.txt", drive_path, grid, model, name, family, res, texts),
               fitfile.write(out / "fit.json", fitfile.record(config, family, res, start.x0,
                                                              P0, drive_path)),
               *_figures(out, grid, model, name, res, P0, family)]
    print(res.summary())
    for p in written:
        print(f"wrote {p}")
    return 0
