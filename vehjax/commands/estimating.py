"""``vehjax estimate DRIVE --fit DIR/fit.json --out DIR2 [--smooth]``: a fitted filter (or its
smoother) run over another drive file.

The filter is rebuilt from fit.json (:func:`vehjax.commands.fitfile.rebuild`), the drive read
and mapped with the fit's [drive] section (or another configuration's, ``--config``), and
:func:`vehjax.filter` (or :func:`vehjax.smooth`) run from the fit's prior x0, P0. Writes, in
DIR2:

* ``estimates.csv``: ``t [s]``, then each state's mean ``name [unit]`` and standard deviation
  ``name_std [unit]`` per step of the model's grid, as :meth:`vehjax.data.Drive.from_csv`
  reads them (numbers written as ``repr``: they read back to the same float64; a state whose
  unit :data:`vehjax.data.UNITS` does not know reads with ``units={"name": "-"}``);
* ``estimates.parquet``: the same columns (each field's unit in its metadata), when pyarrow is
  installed (the ``export`` extra); else a one-line note on stderr;
* ``estimates.png``: each state with its +-2 standard deviation band.
"""

from __future__ import annotations

import csv
import sys
from pathlib import Path

import numpy as np

from ..filtering import filter as run_filter
from ..smoothing import smooth as run_smooth
from . import figures, fitfile
from .setup import load_drive, model_label, on_model

__all__ = ["run", "columns", "write_csv", "write_parquet"]


def columns(t, means, stds, names, units) -> dict:
    """``{header: (T,) array}``: ``t [s]``, then per state ``name [unit]`` and
    ``name_std [unit]``."""
    out = {"t [s]": np.asarray(t, dtype=float)}
    for i, (n, u) in enumerate(zip(names, units)):
        out[f"{n} [{u}]"] = means[:, i]
        out[f"{n}_std [{u}]"] = stds[:, i]
    return out


def write_csv(path, cols: dict) -> Path:
    """The columns as CSV, headers ``name [unit]``, numbers as ``repr`` (empty where NaN)."""
    path = Path(path)
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(list(cols))
        for row in np.stack([np.asarray(c, dtype=float) for c in cols.values()], axis=1):
            w.writerow(["" if np.isnan(v) else repr(float(v)) for v in row])
    return path


def write_parquet(path, cols: dict):
    """The columns as Parquet (pyarrow), each field's unit in its metadata (``b"unit"``); the
    path, or None (and a note on stderr) when pyarrow is not installed."""
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        print("vehjax estimate: note: pyarrow is not installed, so no estimates.parquet "
              "(pip install 'vehjax[export]')", file=sys.stderr)
        return None
    fields, arrays = [], []
    for header, values in cols.items():
        unit = header[header.rindex("[") + 1:-1]
        fields.append(pa.field(header, pa.float64(), metadata={"unit": unit}))
        arrays.append(pa.array(np.asarray(values, dtype=float)))
    pq.write_table(pa.Table.from_arrays(arrays, schema=pa.schema(fields)), str(path))
    return Path(path)


def run(drive_path, fit_path, out, config: dict | None = None, smooth: bool | None = None,
        family: str | None = None) -> int:
    """The command's work: the fit read and its filter rebuilt, the drive read and mapped
    (``config``'s [drive] section when given, else the fit's), every check before the run;
    ``smooth`` None: the fit's [estimate] smooth (default False); ``family`` None: the fit's."""
    content = fitfile.read(fit_path)
    section = config["drive"] if config and config.get("drive") else content["drive"]
    if smooth is None:
        smooth = bool(((config or {}).get("estimate") or content["estimate"]).get("smooth",
                                                                                   False))
    drive = load_drive(drive_path, section)
    model, est, x0, P0 = fitfile.rebuild(content, family)
    grid = on_model(drive, model, section)
    what = "smoother" if smooth else "filter"
    print(f"vehjax estimate: running the fitted {est.name} {what} over {len(grid.t)} steps of "
          f"{model.dt:g} s", file=sys.stderr, flush=True)
    run_one = run_smooth if smooth else run_filter
    res = run_one(est, grid.measurements, grid.inputs, x0=x0, P0=P0)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    means = np.asarray(res.states, dtype=float)
    stds = np.sqrt(np.maximum(np.diagonal(np.asarray(res.covariances), axis1=-2, axis2=-1), 0.0))
    cols = columns(grid.t, means, stds, model.state_names, model.state_units)
    written = [write_csv(out / "estimates.csv", cols),
               write_parquet(out / "estimates.parquet", cols),
               figures.estimates(out / "estimates.png", grid.t, means, stds, model.state_names,
                                 model.state_units, f"{model_label(content['model'])}, {est.name} "
                                 f"{what} on {Path(drive_path).name}")]
    for p in written:
        if p is not None:
            print(f"wrote {p}")
    return 0
