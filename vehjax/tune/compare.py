"""Compare candidate model structures fitted on one drive: :func:`compare`.

Why: two structures can fit a drive about equally well (the same log-likelihood to
a few units, e.g. a single-track model with the data sheet's yaw inertia and one with it
fitted) and still disagree about the state nobody measured (the sideslip). A likelihood alone
does not show that; :func:`compare` puts the information criteria, the held-out likelihood and
the spread of the unmeasured state's estimate side by side and warns where the data cannot
choose but the estimates differ.

Definitions, for fits on the same data:

* k: the number of fitted quantities of a fit (``len(res.values)``: parameters, noise entries,
  a fitted x0's components);
* n: the number of observed measurement components of the fit's data (the finite entries of
  ``measurements``: NaN components are missing and carry no likelihood);
* AIC = 2 k - 2 logL (Akaike 1974), BIC = k ln(n) - 2 logL (Schwarz 1978), logL the fit's
  maximised log-likelihood (``res.loglik``); lower is better;
* the held-out log-likelihood: ``vehjax.filter(res.estimator, ys, us, x0=res.x0, P0=P0)``'s
  on held-out data, the same outputs (higher is better; no free quantity is counted);
* the spread of a state estimate s_t (a state by name, or a function of the state and input),
  on the held-out data where given, else on the fit's: for each pair of fits the RMS over t of
  the difference of their filtered estimates, and for each fit the mean over t of its
  standard deviation, sqrt(g^T P_t g) with g = ds/dx at the filtered mean (exact for a state,
  the delta method for a function).

The warning: for a pair whose information criteria or held-out likelihoods lie within
``margin`` (|dAIC| < margin, or |d held-out logL| < margin; default 10 log-likelihood units,
where AIC's evidence ratio exp(dAIC / 2) passes about 150) while the RMS difference of their
estimates exceeds sqrt(sd_a^2 + sd_b^2) (the difference's standard deviation were the two
estimates independent), :func:`compare` warns and names the pair: the data cannot tell the
structures apart, and they disagree about the state.

Limits: one run (T, ny) of data; the fits' data are checked by recomputing each fit's
log-likelihood on the given data with its x0 and ``P0`` (a ValueError names ``measurements``
where it differs); the spread's standard deviations are the filters' own, which a misfitted
structure can understate.
"""

from __future__ import annotations

import itertools
import math
import warnings
from typing import Callable, Mapping, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..filtering import filter as run_filter
from .result import TuneResult

__all__ = ["compare", "StructureComparison", "MARGIN"]

#: log-likelihood units within which the data do not choose between two structures
MARGIN = 10.0


class StructureComparison(NamedTuple):
    """What :func:`compare` returns (module docstring for the definitions).

    Attributes:
        names: the fits' names, in the given order.
        loglik, k, aic, bic: by name: the fit's log-likelihood, fitted quantities, criteria.
        n: observed measurement components of the fit data.
        held_out_loglik: by name, or None without held-out data.
        state: the compared estimate's label; on: "held_out" or "fit".
        estimates, std: by name, (T,) the filtered estimate and its standard deviation.
        rms_difference: {(a, b): RMS over t of estimates[a] - estimates[b]} for each pair.
        mean_std: by name, the mean over t of ``std``.
        undecided: the pairs the data cannot choose between yet whose estimates differ.
        warnings: the warnings' texts (also issued).
    """

    names: tuple
    loglik: dict
    k: dict
    n: int
    aic: dict
    bic: dict
    held_out_loglik: dict | None
    state: str
    on: str
    estimates: dict
    std: dict
    rms_difference: dict
    mean_std: dict
    undecided: tuple
    warnings: tuple

    def summary(self) -> str:
        """A text table: criteria and spread per fit, pairwise differences, the warnings."""
        best = min(self.aic.values())
        head = (f"structures compared on {self.n} observed measurement components; estimate "
                f"of {self.state} on the {self.on.replace('_', '-')} data")
        lines = [head, f"  {'fit':<16} {'k':>3} {'logL':>12} {'AIC':>12} {'dAIC':>8} "
                       f"{'BIC':>12} {'held-out logL':>14} {'mean sd':>10}"]
        for a in self.names:
            held = "-" if self.held_out_loglik is None else f"{self.held_out_loglik[a]:.6g}"
            lines.append(f"  {a:<16} {self.k[a]:>3} {self.loglik[a]:>12.6g} {self.aic[a]:>12.6g} "
                         f"{self.aic[a] - best:>8.3g} {self.bic[a]:>12.6g} {held:>14} "
                         f"{self.mean_std[a]:>10.3g}")
        for (a, b), d in self.rms_difference.items():
            lines.append(f"  RMS difference {a} - {b}: {d:.3g}")
        lines += [f"  warning: {w}" for w in self.warnings]
        return "\n".join(lines)


def _check_fits(fits) -> dict:
    if not isinstance(fits, Mapping) or len(fits) < 2:
        raise ValueError(f"fits: expected a dict name -> TuneResult of at least two fits, got "
                         f"{type(fits).__name__} of {len(fits) if hasattr(fits, '__len__') else '?'}")
    bad = [str(k) for k, v in fits.items() if not isinstance(v, TuneResult)]
    if bad:
        raise ValueError(f"fits: expected TuneResult values (vehjax.tune.fit's), not for {bad}")
    outputs = {k: tuple(v.model.output_names) for k, v in fits.items()}
    if len(set(outputs.values())) > 1:
        raise ValueError(f"fits: the fits must measure the same outputs, got {outputs}")
    return dict(fits)


def _check_data(arg: str, data, ny: int):
    if not isinstance(data, (tuple, list)) or len(data) != 2:
        raise ValueError(f"{arg}: expected (measurements (T, {ny}), inputs (T, nu))")
    ys, us = np.asarray(data[0], float), None if data[1] is None else np.asarray(data[1], float)
    if ys.ndim != 2 or ys.shape[1] != ny:
        raise ValueError(f"{arg}: expected measurements of shape (T, {ny}) (one run), got "
                         f"{ys.shape}")
    return ys, us


def _estimate_fn(state, model) -> tuple[Callable, str]:
    """(s(x, u) -> scalar, label) for a state name or a function of (x, u)."""
    if callable(state):
        return state, getattr(state, "__name__", "f(x, u)")
    names = tuple(model.state_names)
    if state not in names:
        raise ValueError(f"state: expected a state name of every fit's model (this one has "
                         f"{names}) or a function s(x, u), got {state!r}")
    i = names.index(state)
    return (lambda x, u: x[i]), str(state)


def _spread(fn, out, us):
    """(estimate (T,), its standard deviation (T,)) from a filter's states and covariances."""
    xs, Ps = jnp.asarray(out.states), jnp.asarray(out.covariances)
    u = jnp.zeros((xs.shape[0], 0)) if us is None else jnp.asarray(us)
    value = jax.vmap(fn)(xs, u)
    grad = jax.vmap(jax.grad(fn))(xs, u)
    var = jnp.einsum("ti,tij,tj->t", grad, Ps, grad)
    return np.asarray(value), np.sqrt(np.maximum(np.asarray(var), 0.0))


def _run(res, ys, us, P0):
    return run_filter(res.estimator, ys, us, x0=res.x0, P0=P0)


def _undecided(names, aic, held, rms, sd, margin) -> tuple[tuple, tuple]:
    pairs, texts = [], []
    for a, b in itertools.combinations(names, 2):
        close = abs(aic[a] - aic[b]) < margin or (held is not None and abs(held[a] - held[b])
                                                  < margin)
        limit = math.hypot(sd[a], sd[b])
        if close and rms[(a, b)] > limit:
            pairs.append((a, b))
            why = [f"dAIC {abs(aic[a] - aic[b]):.3g}"] + (
                [] if held is None else [f"d held-out logL {abs(held[a] - held[b]):.3g}"])
            texts.append(f"the data cannot choose between {a!r} and {b!r} ({', '.join(why)}; "
                         f"margin {margin:g}) but their estimates differ by {rms[(a, b)]:.3g} "
                         f"RMS, more than their standard deviations ({sd[a]:.3g}, {sd[b]:.3g})")
    return tuple(pairs), tuple(texts)


def compare(fits, measurements, inputs=None, *, P0, held_out=None, state="vy",
            margin: float = MARGIN, tol: float = 1e-6) -> StructureComparison:
    """Compare fits of candidate structures on one drive (module docstring).

    Args:
        fits: dict name -> :class:`TuneResult`, at least two, fitted on ``measurements``,
            ``inputs`` with the same outputs (states may differ, e.g. a model with biases).
        measurements: (T, ny) the fits' data (one run); inputs: (T, nu) or None.
        P0: the initial covariance the fits used (each fit's own ``x0``, ``res.x0``, is used).
        held_out: (measurements (T2, ny), inputs) of data none of the fits saw, or None.
        state: a state name of every fit's model, or a function ``s(x, u) -> scalar`` of the
            state (nx,) and input (nu,) in jax.numpy (e.g. the sideslip
            ``lambda x, u: jnp.arctan(x[0] / u[1])``).
        margin: log-likelihood units within which the data do not choose (> 0).
        tol: relative tolerance of the check that each fit's log-likelihood is that of the
            given data.

    Returns:
        :class:`StructureComparison`; warns for each undecided pair.
    """
    fits = _check_fits(fits)
    first = next(iter(fits.values()))
    ny = len(first.model.output_names)
    ys, us = _check_data("measurements", (measurements, inputs), ny)
    held = None if held_out is None else _check_data("held_out", held_out, ny)
    if not (isinstance(margin, (int, float)) and margin > 0):
        raise ValueError(f"margin: expected a number > 0, got {margin!r}")
    n = int(np.isfinite(ys).sum())
    ll, k, est, sd, label, held_ll = {}, {}, {}, {}, "", None if held is None else {}
    for name, res in fits.items():
        fn, label = _estimate_fn(state, res.model)
        out = _run(res, ys, us, P0)
        again = float(np.sum(np.asarray(out.loglik)))
        if abs(again - res.loglik) > tol * max(1.0, abs(res.loglik)):
            raise ValueError(f"measurements: fit {name!r} was not fitted on these data with this "
                             f"P0 (its log-likelihood {res.loglik:.6g}, here {again:.6g})")
        if held is not None:
            out = _run(res, *held, P0)
            held_ll[name] = float(np.sum(np.asarray(out.loglik)))
        est[name], sd[name] = _spread(fn, out, us if held is None else held[1])
        ll[name], k[name] = float(res.loglik), len(res.values)
    names = tuple(fits)
    aic = {a: 2.0 * k[a] - 2.0 * ll[a] for a in names}
    bic = {a: k[a] * math.log(max(n, 1)) - 2.0 * ll[a] for a in names}
    rms = {(a, b): float(np.sqrt(np.nanmean((est[a] - est[b]) ** 2)))
           for a, b in itertools.combinations(names, 2)}
    mean_sd = {a: float(np.nanmean(sd[a])) for a in names}
    pairs, texts = _undecided(names, aic, held_ll, rms, mean_sd, margin)
    for t in texts:
        warnings.warn(f"vehjax.tune.compare: {t}", stacklevel=2)
    return StructureComparison(
        names=names, loglik=ll, k=k, n=n, aic=aic, bic=bic, held_out_loglik=held_ll,
        state=label, on="fit" if held is None else "held_out", estimates=est, std=sd,
        rms_difference=rms, mean_std=mean_sd, undecided=pairs, warnings=texts)
