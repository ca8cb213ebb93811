"""The fitted quantities by name and unit (``"Q[x,x]"`` in m^2, a parameter in its unit, ...),
and the names and natural sizes of the unconstrained coordinates they are fitted in.

The natural size ("scale") of a coordinate makes the curvature comparable across coordinates:
the report (:mod:`vehjax.tune.information`) and the optimisers' steps work in ``z / scale``.
"""

from __future__ import annotations

import numpy as np

from ..models.base import BaseModel

__all__ = ["fitted_quantities", "coordinates", "cov_names"]


def _units(model, attr: str, n: int) -> tuple:
    if isinstance(model, BaseModel):
        return tuple(getattr(model, attr))
    return ("-",) * n


def _sq(u: str) -> str:
    if u == "-":
        return "-"
    return f"{u}^2" if u.isalnum() else f"({u})^2"


def _prod(a: str, b: str) -> str:
    if "-" in (a, b):
        return "-"
    if a == b:
        return _sq(a)
    wrap = (lambda u: u if u.isalnum() else f"({u})")
    return f"{wrap(a)}*{wrap(b)}"


def cov_names(prefix: str, names: tuple, n: int, diag: bool):
    """Names of the (a <= b) entries of a fitted covariance, in the order
    :func:`vehjax.tune.fit` reports them, and of its coordinates (log-diagonal, then the
    Cholesky entries below it)."""
    entries = [(a, b) for a in range(n) for b in range(a, n if not diag else a + 1)]
    values = [f"{prefix}[{names[a]},{names[b]}]" for a, b in entries]
    rows, cols = np.tril_indices(n, -1)
    coords = [f"{prefix}[{names[i]},{names[i]}]" for i in range(n)]
    if not diag:
        coords += [f"{prefix}[{names[c]},{names[r]}]" for r, c in zip(rows, cols)]
    return entries, values, coords


def fitted_quantities(info, model, v):
    """The fitted quantities as ``[(name, unit, value)]`` from the physical values ``v``
    (:attr:`Objective.unpack`'s dict; jax or numpy): covariance entries ``"Q[a,b]"``,
    ``"R[a,b]"`` (variances / covariances, units squared), input-noise stds ``"input[u]"``
    (the input's unit) or covariance entries ``"input[u,w]"``, parameters by name, ``"x0[v]"``
    / ``"x0[r,v]"``. Traceable: the Jacobian of the values by JAX gives the delta method."""
    out = []
    su = _units(model, "state_units", len(model.state_names))
    ou = _units(model, "output_units", len(model.output_names))
    iu = _units(model, "input_units", len(model.input_names))
    for name, diag, cnames, cu in (("Q", info.diagQ, model.state_names, su),
                                   ("R", info.diagR, model.output_names, ou)):
        if name not in info.noise:
            continue
        entries, names, _ = cov_names(name, cnames, len(cnames), diag)
        for (a, b), k in zip(entries, names):
            out.append((k, _sq(cu[a]) if a == b else _prod(cu[a], cu[b]), v[name][a, b]))
    inp = info.input
    if inp is not None:
        names = tuple(model.input_names)
        if inp.cov is None:
            for n in inp.names:
                out.append((f"input[{n}]", iu[names.index(n)], v["input"][n]))
        else:
            entries, keys, _ = cov_names("input", names, len(names), inp.diag)
            for (a, b), k in zip(entries, keys):
                out.append((k, _sq(iu[a]) if a == b else _prod(iu[a], iu[b]), v["input"][a, b]))
    pu = _units(model, "param_units", len(model.param_names))
    for p in info.params:
        j = model.param_names.index(p)
        out.append((p, pu[j], v["theta"][j]))
    if info.fit_x0:
        x0 = v["x0"]
        for idx in np.ndindex(np.shape(x0)):
            comp = model.state_names[idx[-1]]
            k = f"x0[{comp}]" if np.ndim(x0) == 1 else f"x0[{idx[0]},{comp}]"
            out.append((k, su[idx[-1]], x0[idx]))
    return out


def coordinates(info, model, z0):
    """(names (n,), scales (n,)) of the unconstrained coordinates, flattened in
    ``jax.flatten_util.ravel_pytree`` order (dict keys sorted). A scale is the size of a change
    of that coordinate that would be as large as the quantity itself: 1 for log standard
    deviations and log/logit parameter maps, |theta0| for a free parameter, sqrt(A0_rr) for a
    Cholesky entry below the diagonal, the prior standard deviation sqrt(P0_ii) for x0."""
    per = {}
    for name, diag, cnames, A0 in (("Q", info.diagQ, model.state_names, info.Qa),
                                   ("R", info.diagR, model.output_names, info.Ra)):
        if name in z0:
            n = len(cnames)
            _, _, coords = cov_names(name, cnames, n, diag)
            rows, _ = np.tril_indices(n, -1)
            sc = np.ones(n) if diag else np.concatenate([np.ones(n), np.sqrt(np.diag(A0))[rows]])
            per[name] = (coords, sc)
    inp = info.input
    if inp is not None:
        if inp.cov is None:
            per["input"] = ([f"input[{n}]" for n in inp.names], np.ones(len(inp.names)))
        else:
            n = len(inp.names)
            _, _, coords = cov_names("input", inp.names, n, inp.diag)
            L0 = np.exp(inp.z0[:n])  # the starting standard deviations
            rows, _ = np.tril_indices(n, -1)
            per["input"] = (coords, np.ones(n) if inp.diag else np.concatenate(
                [np.ones(n), L0[rows]]))
    if "theta" in z0:
        th = info.theta0[[model.param_names.index(p) for p in info.params]]
        free = np.array([k == "none" for k in info.theta_map.kinds])
        per["theta"] = (list(info.params),
                        np.where(free, np.where(th != 0, np.abs(th), 1.0), 1.0))
    if "x0" in z0:
        P0 = info.P0
        sd = np.sqrt(np.diagonal(P0, axis1=-2, axis2=-1))
        x0 = info.x0
        names, sc = [], []
        for idx in np.ndindex(x0.shape):
            comp = model.state_names[idx[-1]]
            names.append(f"x0[{comp}]" if x0.ndim == 1 else f"x0[{idx[0]},{comp}]")
            sc.append(sd[idx[-1]] if sd.ndim == 1 else sd[idx[0], idx[-1]])
        per["x0"] = (names, np.asarray(sc))
    names, scales = [], []
    for key in sorted(z0):
        names += list(per[key][0])
        scales.append(per[key][1])
    return tuple(names), np.concatenate(scales)
