"""What a study returns: :class:`RunResult`, its one-line summary and its export.

``vehjax.run`` returns a :class:`RunResult` of numpy arrays. In a notebook its repr is a short
summary (filter, runs, steps, states, parameters, diverged runs); ``result.summary(truth)`` adds
the RMSE per state when the true states are given; ``result.to_npz(path, model)`` and
``result.to_xarray(model)`` export the arrays with their names and units (the model gives the
state names and units and the units of its own parameters; without one, states are named
``x0, x1, ...`` and units are left empty). xarray is optional (``pip install vehjax[export]``).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import NamedTuple

import numpy as np

from .metrics import rmse

_ARRAYS = ("states", "covariances", "params", "params_cov", "loglik", "nis", "n_obs",
           "diverged", "diverged_at", "at_bound", "cross_covariances")


class RunResult(NamedTuple):
    """Outputs of a study of R runs over T steps (numpy arrays on the host).

    Attributes:
        states: filtered state estimates, (R, T, nx), in the model's state units.
        covariances: their covariances, (R, T, nx, nx); None unless ``return_covariances``.
        params: parameter estimates, (R, T, p); p = 0 for state-only filters.
        params_cov: their covariances, (R, T, p, p); None unless ``return_covariances``.
        loglik: total log-likelihood log p(y_1:T) of the observed components, (R,); for a
            diverged run, the sum over the steps before it diverged.
        nis: normalised innovation squared of the observed components per step, (R, T);
            NaN from the step a run diverged.
        n_obs: number of observed (non-NaN) measurement components per step, (R, T); the
            degrees of freedom of ``nis``. 0 from the step a run diverged.
        diverged: whether the run diverged, (R,) bool.
        diverged_at: index of the step at which it diverged, or -1, (R,) int.
        name: the estimator's name.
        param_names: names of the estimated parameters, (p,) strings (the estimator's).
        at_bound: whether a parameter estimate of the run sat on a bound of its domain for more
            than ``vehjax.filtering.AT_BOUND_FRACTION`` of the steps, (R,) bool (the companion
            of ``diverged``, see :mod:`vehjax.filtering`); None when not computed.
        cross_covariances: a smoothed study's (``vehjax.run(..., smooth=True,
            return_covariances=True)``) lag-one cross-covariances Cov(x_t, x_t+1 | y_1:T),
            (R, T-1, nx, nx); None otherwise.
    (The optional fields come last, so that positional construction without them works.)
    """

    states: np.ndarray
    covariances: np.ndarray | None
    params: np.ndarray
    params_cov: np.ndarray | None
    loglik: np.ndarray
    nis: np.ndarray
    n_obs: np.ndarray
    diverged: np.ndarray
    diverged_at: np.ndarray
    name: str
    param_names: tuple = ()
    at_bound: np.ndarray | None = None
    cross_covariances: np.ndarray | None = None

    def __repr__(self) -> str:
        R, T, nx = np.shape(self.states)
        n_div = int(np.sum(self.diverged))
        parts = [f"{R} runs x {T} steps", f"{nx} states"]
        if self.param_names:
            parts.append(f"parameters ({', '.join(self.param_names)})")
        parts.append(f"{n_div} diverged")
        if self.at_bound is not None and np.any(self.at_bound):
            parts.append(f"{int(np.sum(self.at_bound))} at a parameter bound")
        steps = np.asarray(self.n_obs).astype(bool).sum(axis=1)
        ok = ~np.asarray(self.diverged, bool) & (steps > 0)
        if ok.any():
            per_step = np.mean(np.asarray(self.loglik)[ok] / steps[ok])
            parts.append(f"mean log-likelihood {per_step:.4g} per observed step")
        return f"RunResult({self.name}: {', '.join(parts)})"

    def summary(self, truth=None, model=None) -> str:
        """A few lines: the repr, then (with ``truth``, the true states (R, T, nx) or anything
        that broadcasts to it) the RMSE of each state over the runs that did not diverge, with
        names and units from ``model`` when given."""
        lines = [repr(self)]
        if np.any(self.diverged):
            at = np.asarray(self.diverged_at)[np.asarray(self.diverged, bool)]
            lines.append(f"  diverged runs: {np.flatnonzero(self.diverged).tolist()} "
                         f"(first at step {int(at.min())})")
        if self.at_bound is not None and np.any(self.at_bound):
            lines.append(f"  runs with a parameter on a bound: "
                         f"{np.flatnonzero(self.at_bound).tolist()}")
        if truth is not None:
            keep = ~np.asarray(self.diverged, bool)
            names, units = _state_labels(model, np.shape(self.states)[2])
            err = rmse(self.states, truth, mask=keep)
            lines.append(f"  RMSE over {int(keep.sum())} runs:")
            lines += [f"    {n:<12s} {e:.4g} {u}".rstrip() for n, e, u in zip(names, err, units)]
        return "\n".join(lines)

    def labels(self, model=None) -> dict:
        """Names and units of the states and parameters: ``{"state_names", "state_units",
        "param_names", "param_units"}``, tuples. ``model`` (any vehjax model) gives the state
        names and units and the units of the parameters it owns; others are ``""``."""
        nx = np.shape(self.states)[2]
        state_names, state_units = _state_labels(model, nx)
        units = {} if model is None else dict(zip(model.param_names, model.param_units))
        return {"state_names": state_names, "state_units": state_units,
                "param_names": tuple(self.param_names),
                "param_units": tuple(units.get(n, "") for n in self.param_names)}

    def to_npz(self, path, model=None) -> Path:
        """Save every array, the filter name, and the names and units of :meth:`labels` (as a
        JSON string under ``"labels"``) to a compressed ``.npz``; returns the path.
        ``np.load(path)`` reads it back; absent covariances are not stored."""
        path = Path(path)
        arrays = {k: np.asarray(getattr(self, k)) for k in _ARRAYS if getattr(self, k) is not None}
        meta = dict(self.labels(model), name=self.name)
        np.savez_compressed(path, **arrays, labels=np.asarray(json.dumps(meta)))
        return path if path.suffix == ".npz" else path.with_name(path.name + ".npz")

    def to_xarray(self, model=None, dt: float | None = None):
        """An ``xarray.Dataset`` with dims ``run``, ``time``, ``state`` (and ``state2``,
        ``param``, ``param2`` for covariances and parameters), coordinates named by
        :meth:`labels`, units in each variable's ``attrs``; ``time`` in seconds when ``dt`` (or
        the model's ``dt``) is known, else step indices. Needs xarray."""
        try:
            import xarray as xr
        except ImportError:
            raise ImportError("RunResult.to_xarray needs xarray: pip install 'vehjax[export]' "
                              "(or use to_npz)") from None
        lab = self.labels(model)
        R, T, _ = np.shape(self.states)
        if dt is None and model is not None:
            dt = model.dt
        time = np.arange(T) * float(dt) if dt is not None else np.arange(T)
        coords = {"run": np.arange(R), "time": time, "state": list(lab["state_names"]),
                  "param": list(lab["param_names"])}
        units = lab["state_units"]
        data = {"states": (("run", "time", "state"), self.states, {"units": list(units)}),
                "params": (("run", "time", "param"), self.params,
                           {"units": list(lab["param_units"])}),
                "loglik": (("run",), self.loglik, {"units": "nats"}),
                "nis": (("run", "time"), self.nis, {}),
                "n_obs": (("run", "time"), self.n_obs, {}),
                "diverged": (("run",), self.diverged, {}),
                "diverged_at": (("run",), self.diverged_at, {"units": "step"})}
        if self.at_bound is not None:
            data["at_bound"] = (("run",), self.at_bound, {})
        if self.covariances is not None:
            coords["state2"] = coords["state"]
            data["covariances"] = (("run", "time", "state", "state2"), self.covariances, {})
        if self.params_cov is not None:
            coords["param2"] = coords["param"]
            data["params_cov"] = (("run", "time", "param", "param2"), self.params_cov, {})
        attrs = {"filter": self.name, "time_units": "s" if dt is not None else "step"}
        return xr.Dataset({k: xr.Variable(*v) for k, v in data.items()}, coords=coords,
                          attrs=attrs)


def _state_labels(model, nx: int) -> tuple[tuple, tuple]:
    if model is None or len(model.state_names) != nx:
        return tuple(f"x{i}" for i in range(nx)), ("",) * nx
    return tuple(model.state_names), tuple(model.state_units)
