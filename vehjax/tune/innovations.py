"""Per-output innovation checks: whether each measured output's innovations are as the filter's
model says (unit normalised variance, white), from a filter run's filtered estimates.

A filter's outputs carry only a scalar NIS per step (:class:`vehjax.filters.StepOutput`), so the
one-step predictions are recomputed from the filtered estimates (the first step from the
prior x0, P0), with the EKF's algebra (:func:`vehjax.filters.kalman.linearized_predict`,
:func:`~vehjax.filters.kalman.linearized_measure`)::

    x- = f(x_{t-1|t-1}, u_t),   P- = F P F^T + Q (+ G Sigma_u G^T with input noise),
    y^ = h(x-, u_t),            S = H P- H^T + R,      e = y_t - y^

G = df/du at the filtered mean (as :func:`vehjax.filters.ekf` does,
:mod:`vehjax.filters.input_noise`). For the EKF these are the filter's own innovations
exactly; for the UKF and CKF a first-order approximation of theirs (the sigma-point moments
differ from the linearised ones by the model's curvature over the state's spread, small
where the state is well determined).

For each output i the check (:class:`InnovationCheck`) is the mean of ``e_i^2 / S_ii``
(expected 1; above it the filter is overconfident for that output, below underconfident), the
lag-1 autocorrelation of the normalised innovations ``e_i / sqrt(S_ii)`` and the Ljung-Box
statistic over ``lags`` lags with its p-value (:mod:`vehjax.lib.whiteness`). Missing (NaN)
samples are left out: autocorrelations over the pairs where both samples are present. Several
runs are pooled into one check per output (one mean, the pairs within each run).

"Coloured" (:func:`coloured`): Ljung-Box p below :data:`COLOURED_P` *and* |lag-1
autocorrelation| above :data:`COLOURED_LAG1`. With 10^4 samples the test alone rejects any real
sensor (a lag-1 autocorrelation of 0.03 is already significant), so the size of the
correlation decides.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import validation
from ..engine import FilterResult
from ..filtering import filter as run_filter
from ..filters import input_noise as inoise
from ..filters.kalman import linearized_measure, linearized_predict
from ..lib import whiteness
from ..result import RunResult
from .likelihood import check_data, float_array

__all__ = ["InnovationCheck", "check_innovations", "one_step_predictions", "output_checks",
           "innovations", "fitted_innovations",
           "coloured", "coloured_text", "COLOURED_P", "COLOURED_LAG1"]

#: Ljung-Box p-value below which an output's innovations may be called coloured
COLOURED_P = 1e-3
#: ... and the least |lag-1 autocorrelation| that makes them so: at 0.2 the previous innovation
#: predicts 4 % (0.2^2) of the next one's variance, an error of the model or of the noise's
#: description the filter could use and does not; below it the colouring of real sensors
#: (filtering, quantisation, small lags) is common and harmless for the estimate
COLOURED_LAG1 = 0.2


class InnovationCheck(NamedTuple):
    """One output's innovation check (module docstring).

    Attributes:
        nis_mean: mean of e_i^2 / S_ii over the present samples (expected 1).
        lag1: lag-1 autocorrelation of the normalised innovations (expected 0).
        ljung_box: the Ljung-Box statistic over ``lags`` lags.
        p_value: its chi-square (``lags`` degrees of freedom) survival probability.
        lags: the number of lags.
        n: the number of present samples (all runs together).
    """

    nis_mean: float
    lag1: float
    ljung_box: float
    p_value: float
    lags: int
    n: int


def one_step_predictions(model, Q, R, ys, us, states, covs, x0, P0, Lu=None):
    """The innovations and their covariances of one run recomputed from its filtered estimates
    (module docstring); traceable.

    Args:
        model: the filter's model (its ``theta``).
        Q (nx, nx), R (ny, ny): the noise covariances.
        ys (T, ny): measurements, NaN where missing; us (T, nu) inputs.
        states (T, nx), covs (T, nx, nx): the filtered means and covariances.
        x0 (nx,), P0 (nx, nx): the prior before the first step.
        Lu: (nu, k) factor of the input noise's covariance
            (:func:`vehjax.filters.input_noise.input_factor`) or None.

    Returns:
        (e (T, ny) innovations, NaN where missing; S (T, ny, ny) their covariances).
    """
    theta = jnp.asarray(model.theta)
    xs = jnp.concatenate([jnp.asarray(x0)[None], states[:-1]])
    Ps = jnp.concatenate([jnp.asarray(P0)[None], covs[:-1]])

    def one(x, P, y, u):
        Qd = jnp.asarray(Q, x.dtype)
        if Lu is not None:
            Qd = Qd + inoise.linearized_input_noise(
                lambda v, w: model.transition(v, w, theta), x, u, Lu)
        xp, Pp, _ = linearized_predict(x, P, lambda v: model.transition(v, u, theta), Qd)
        m = linearized_measure(xp, Pp, lambda v: model.observe(v, u, theta), jnp.asarray(R))
        return y - m.y_hat, m.S

    return jax.vmap(one)(xs, Ps, ys, us)


def output_checks(e, S, names, lags=None) -> dict:
    """``{output name: InnovationCheck}`` from innovations ``e`` (R, T, ny) (NaN missing) and
    their covariances ``S`` (R, T, ny, ny), the runs pooled; ``lags`` None:
    :func:`vehjax.lib.whiteness.default_lags` of T."""
    e, S = np.asarray(e, dtype=float), np.asarray(S, dtype=float)
    L = whiteness.default_lags(e.shape[1]) if lags is None else int(lags)
    out = {}
    for i, name in enumerate(names):
        var = np.diagonal(S, axis1=-2, axis2=-1)[..., i]
        with np.errstate(invalid="ignore", divide="ignore"):
            z = np.where(var > 0, e[..., i] / np.sqrt(np.where(var > 0, var, 1.0)), np.nan)
        rho, n = whiteness.autocorrelation(z, L)
        q = whiteness.ljung_box(rho, n)
        nis = float(np.nanmean(z**2)) if n else float("nan")
        out[name] = InnovationCheck(nis, float(rho[0]), q, whiteness.chi2_sf(q, L), L, n)
    return out


def coloured(check: InnovationCheck) -> bool:
    """Whether an output's innovations are coloured (module docstring)."""
    return bool(check.p_value < COLOURED_P and abs(check.lag1) > COLOURED_LAG1)


def p_text(p: float) -> str:
    """A p-value as the report writes it: "p < 1e-16" below that, else "p = 0.0012"."""
    return "p < 1e-16" if p < 1e-16 else f"p = {p:.2g}"


def coloured_text(name: str, check: InnovationCheck) -> str:
    """What the report says of a coloured output."""
    return (f"innovations of {name} are coloured: lag-1 autocorrelation {check.lag1:.2f} "
            f"(Ljung-Box {p_text(check.p_value)}, {check.lags} lags; mean NIS "
            f"{check.nis_mean:.3g})")


def _estimates(states, covariances):
    """(states (R, T, nx), covariances (R, T, nx, nx)) from arrays or a filter's result."""
    if isinstance(states, (FilterResult, RunResult)):
        if covariances is not None:
            raise ValueError("covariances: give them in the result (return_covariances=True) "
                             "or as arrays with the states, not both")
        states, covariances = states.states, states.covariances
        if covariances is None:
            raise ValueError("states: the result has no covariances; run the filter with "
                             "return_covariances=True")
    if covariances is None:
        raise ValueError("covariances: expected the filtered covariances (T, nx, nx) or "
                         "(R, T, nx, nx)")
    xs = float_array("states", states)
    Ps = float_array("covariances", covariances)
    xs = xs[None] if xs.ndim == 2 else xs
    Ps = Ps[None] if Ps.ndim == 3 else Ps
    return xs, Ps


def check_innovations(model, Q, R, measurements, inputs, states, covariances=None, *, x0, P0,
                      input_noise=None, lags=None) -> dict:
    """Per-output innovation checks of a filter run (module docstring), e.g. of a filter one
    did not fit::

        out = vehjax.filter(est, ys, us, x0=x0, P0=P0)          # return_covariances=True
        checks = vehjax.tune.check_innovations(model, Q, R, ys, us, out, x0=x0, P0=P0)
        checks["ay"].lag1, checks["ay"].p_value

    Args:
        model: the filter's model (``model.theta`` its parameters).
        Q (nx, nx) or (nx,), R (ny, ny) or (ny,): the filter's noise covariances.
        measurements: (T, ny) or (R, T, ny), NaN where missing.
        inputs: (T, nu) or (R, T, nu); None for a model without inputs.
        states: the filtered means (T, nx) or (R, T, nx), or the filter's result:
            :func:`vehjax.filter`'s ``FilterResult`` or :func:`vehjax.run`'s ``RunResult``,
            run with ``return_covariances=True``.
        covariances: the filtered covariances (T, nx, nx) or (R, T, nx, nx) with array
            ``states``; None with a result.
        x0, P0: the prior the filter started from ((nx,) or (R, nx); (nx, nx), (nx,) or
            (R, nx, nx)).
        input_noise: the filter's ``input_noise`` (stds by input name or a covariance), or None.
        lags: Ljung-Box lags, >= 1; None: ``min(20, T // 5)``.

    Returns:
        ``{output name: InnovationCheck}``, the runs pooled.

    Raises:
        ValueError: naming the argument: shapes that do not fit, a result without
            covariances, bad noise covariances, lags < 1.
    """
    validation.model(model)
    nx, ny = len(model.state_names), len(model.output_names)
    ys, us, x0a, P0a = check_data(model, measurements, inputs, x0, P0)
    xs, Ps = _estimates(states, covariances)
    n_runs, T = ys.shape[:2]
    if xs.shape != (n_runs, T, nx) or Ps.shape != (n_runs, T, nx, nx):
        raise ValueError(f"states: expected ({n_runs}, {T}, {nx}) means and ({n_runs}, {T}, "
                         f"{nx}, {nx}) covariances for the measurements' {n_runs} run(s) of {T} "
                         f"steps, got {xs.shape} and {Ps.shape}")
    Qa = validation.cov("Q", float_array("Q", Q), nx, allow_psd=True)
    Ra = validation.cov("R", float_array("R", R), ny)
    if lags is not None:
        lags = validation.integer("lags", lags, 1)
    Lu = inoise.input_factor(input_noise, model.input_names)
    e, S = innovations(model, Qa, Ra, ys, us, xs, Ps, x0a, P0a, Lu)
    return output_checks(e, S, model.output_names, lags)


def innovations(model, Q, R, ys, us, xs, Ps, x0, P0, Lu=None):
    """:func:`one_step_predictions` of every run, jitted and vmapped: ys (R, T, ny), us
    (T, nu), (R, T, nu) or None, xs (R, T, nx), Ps (R, T, nx, nx), x0 (nx,) or (R, nx), P0
    (nx, nx) or (R, nx, nx). Returns numpy (e (R, T, ny), S (R, T, ny, ny))."""
    n_runs, T = ys.shape[:2]
    if us is None:
        us = np.zeros((T, 0))
    P0 = np.diag(P0) if P0.ndim == 1 else P0
    axes = (0, None if us.ndim == 2 else 0, 0, 0, 0 if x0.ndim == 2 else None,
            0 if P0.ndim == 3 else None)
    run = jax.jit(jax.vmap(lambda y, u, x, P, a, B: one_step_predictions(
        model, Q, R, y, u, x, P, a, B, Lu), in_axes=axes))
    e, S = run(ys, us, xs, Ps, x0, P0)
    return np.asarray(e), np.asarray(S)


def fitted_innovations(setup):
    """``fn(z, data) -> (e (R, T, ny), S (R, T, ny, ny))``: the filter of a fit's set-up
    (:func:`vehjax.tune.likelihood.prepare`) at its coordinates z run on every run of the fit's
    ``data`` (:func:`vehjax.filter`) and its innovations recomputed
    (:func:`one_step_predictions`); traceable, one program for ``jax.jit``. The fitted values
    are its argument, so a program compiled at a fit's start serves its optimum."""
    at = setup.at

    def fn(z, data):
        ys, us, _, P0, _ = data
        est, model, Q, R, noise, x0 = at(z, data)
        Lu = inoise.input_factor(noise, model.input_names)
        T = ys.shape[1]
        P0 = jnp.diag(P0) if P0.ndim == 1 else P0

        def one(y, u, a, B):
            out = run_filter(est, y, u, x0=a, P0=B)
            uu = jnp.zeros((T, 0), y.dtype) if u is None else u
            return one_step_predictions(model, Q, R, y, uu, out.states, out.covariances, a, B,
                                        Lu)

        axes = (0, None if us is None or us.ndim == 2 else 0, 0 if x0.ndim == 2 else None,
                0 if P0.ndim == 3 else None)
        return jax.vmap(one, in_axes=axes)(ys, us, x0, P0)

    return fn
