"""``vehjax.smooth``: one run forward-backward, pure and traceable (``jax.jit``, ``jax.vmap``,
``jax.grad``), and the traced functions that ``vehjax.run`` builds on: :func:`smooth_one_run`
(one run) and :func:`smooth_runs_last` (a batch of runs with the runs axis last).

::

    sm = vehjax.smooth(est, ys, us, x0=x0, P0=P0)                  # ys (T, ny), us (T, nu)
    sm.states, sm.covariances, sm.cross_covariances, sm.loglik.sum()
    sm = vehjax.smooth(est, ys, us, x0=x0, P0=P0,
                       method=vehjax.smoothers.IEKS(parallel=True))

The method is a record of :mod:`vehjax.smoothers.methods`, holding that method's options
only, or its name (``"rts"``, ``"ieks"``, ...) for the record with the defaults.

Time convention of :mod:`vehjax.filtering`: x0/P0 describe the state before the first step;
``states[t]`` is the smoothed estimate after step t (predict with ``inputs[t]``, update with
``measurements[t]``); ``cross_covariances[t]`` is Cov(x_t, x_{t+1} | y_1:T).

Methods, for a Gaussian filter (one with ``Estimator.smoother``: EKF, UKF, CKF, their
square-root forms, joint EKF/UKF):

* ``None`` / :class:`~vehjax.smoothers.RTS` (``"rts"``): the filter's own RTS: extended RTS for the EKF, unscented / cubature RTS
  (Särkkä 2008) for the UKF / CKF, in Cholesky factors throughout for the square-root forms
  (:mod:`vehjax.smoothers.gaussian`). With ``RTS(parallel=True)`` the filter's own linearisation
  (about its filtered and predicted moments) is smoothed by the parallel-in-time Kalman filter
  and RTS smoother (:mod:`vehjax.smoothers.parallel`): the same numbers, to rounding; the
  forward filter that provides the linearisation is still sequential.
* :class:`~vehjax.smoothers.IEKS` (``"ieks"``: EKF, joint EKF) / :class:`~vehjax.smoothers.IPLS`
  (``"ipls"``: sigma-point filters): the iterated smoothers of
  :mod:`vehjax.smoothers.iterated`, started from the filter's own means and covariances (or
  ``initial``), each pass sequential or (``parallel``) parallel in time; ``loglik`` is
  that of the model linearised about the fixed point, differentiable by implicit
  differentiation. The square-root filters' iterated and parallel passes run on covariances.

Joint filters: the parameters are states of the augmented model and are smoothed with them
(``params``, ``params_cov`` in physical units by the filter's own map and delta method). Dual
filters have no smoother: their two filters never form the joint Gaussian of state and
parameters that a Gaussian smoother needs (a ValueError naming ``estimator``).

Particle filters (``Estimator.particle_transition``, the bootstrap PF) go to
:func:`vehjax.smoothers.particle.smooth` (backward simulation): ``method`` None /
:class:`~vehjax.smoothers.FFBSi`, :class:`~vehjax.smoothers.RejectionSampling` or
:class:`~vehjax.smoothers.AncestorPaths`, each with its ``n_trajectories`` M.
The marginalized PF (``Estimator.rao_blackwell``) goes to
:func:`vehjax.smoothers.marginalized.smooth` likewise: ``method`` None / ``AncestorPaths``
(ancestor paths with a per-path RTS) or ``FFBSi`` (Rao-Blackwellised backward simulation,
``kalman_states="linear"``).

NaN measurement components are missing (skipped), as in the filters. Divergence: a run whose
filter diverged (:mod:`vehjax.filtering`) or whose smoothed moments are not finite and positive
definite is ``diverged``; it reports the filter's (held) estimates with zero cross-covariances,
so that one bad run never puts NaN into a study.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from . import validation
from .runtime import eager
from .engine import FilterResult, check_arguments, finish, output_ok, scan_body, start
from .lib.entrywise import chol_sym
from .lib.linalg import is_pd, sym
from .filters.base import Estimator
from .smoothers import gaussian as _gauss
from .smoothers import iterated as _iter
from .smoothers import marginalized as _marginalized
from .smoothers import methods as _methods
from .smoothers import particle as _particle

__all__ = ["SmoothResult", "smooth", "smooth_one_run", "smooth_runs_last", "check_options",
           "one_run_options", "METHODS"]

#: The Gaussian smoothing methods' names (module docstring; :mod:`vehjax.smoothers.methods`).
METHODS = tuple(cls.name for cls in _methods.GAUSSIAN)


class SmoothResult(NamedTuple):
    """One run smoothed (a leading runs axis under ``vmap``).

    Attributes:
        states: smoothed means, (T, nx).
        covariances: their covariances, (T, nx, nx).
        cross_covariances: Cov(x_t, x_{t+1} | y_1:T), (T-1, nx, nx).
        params: smoothed parameters (joint filters), (T, p), physical units; p = 0 otherwise.
        params_cov: their covariances, (T, p, p).
        loglik: log p(y_t | y_1:t-1) per step, (T,): the filter's (``"rts"``), or the Kalman
            filter's on the model linearised about the fixed point (``"ieks"``/``"ipls"``);
            the filter's held values on a diverged run.
        diverged: bool scalar (module docstring).
        iterations: int32 scalar, passes of an iterated smoother (0 for ``"rts"``).
        converged: bool scalar, the iterated smoother met its tolerance (True for ``"rts"``).
        filtered: the forward filter's :class:`vehjax.filtering.FilterResult`.
    """

    states: jnp.ndarray
    covariances: jnp.ndarray
    cross_covariances: jnp.ndarray
    params: jnp.ndarray
    params_cov: jnp.ndarray
    loglik: jnp.ndarray
    diverged: jnp.ndarray
    iterations: jnp.ndarray
    converged: jnp.ndarray
    filtered: FilterResult


# ----------------------------------------------------------------------------------------------
# the traced core


def forward(estimator: Estimator, y, u, x0, P0, th0, Pth0, key):
    """The filter over one run, keeping its states: (states at t = 0..T stacked, FilterResult)."""
    p = len(estimator.param_names)
    state0, held0 = start(estimator, y, u, x0, P0, th0, Pth0, key)
    inner = scan_body(estimator.step, lambda out: output_ok(out, p), True)

    def body(state, yu):
        new, per_step = inner(state, yu)
        return new, (new, per_step)

    _, (states, per_step) = jax.lax.scan(body, state0, (y, u))
    states = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a[None], b]), state0, states)
    return states, finish(per_step, held0, estimator.bounds)


def _report(spec, M, P, cross, nx):
    """(states, covariances, cross, params, params_cov) of smoothed moments at t = 1..T."""
    M, P, cross = M[1:], P[1:], cross[1:]
    if spec.report is None:
        p0 = jnp.zeros((M.shape[0], 0), M.dtype)
        return M, P, cross, p0, jnp.zeros((M.shape[0], 0, 0), M.dtype)
    x, Px, th, Pth = jax.vmap(spec.report)(M, P)
    return x, Px, cross[:, :nx, :nx], th, Pth


def _iterated(spec, states, y, u, parallel, tol, max_iter, initial):
    """(M, P, cross, loglik (T+1,), passes, converged) of IEKS / IPLS (module docstring),
    started from the filtered moments or ``initial``."""
    m, S, aux = jax.vmap(spec.split)(states)
    aux = jax.tree_util.tree_map(lambda a: a[:-1], aux)
    P = sym(S @ jnp.swapaxes(S, -1, -2)) if spec.sqrt else S
    ny = y.shape[1]
    ys = jnp.concatenate([jnp.full((1, ny), jnp.nan, y.dtype), y])
    if initial is None:
        M0, P0s = m, P
    else:
        M0 = jnp.concatenate([m[:1], jnp.asarray(initial, m.dtype)])
        P0s = jnp.broadcast_to(P[:1], P.shape)

    def phi(z, args):
        us, ax, yy, x_0, P_0 = args
        mod = _gauss.linearize(spec, z[0], z[1], us, ax, x_0, P_0, ny)
        return _iter.linear_pass(mod, yy, parallel)

    args = (u, aux, ys, m[0], P[0])
    T1 = m.shape[0]
    z0 = (M0, P0s, jnp.zeros((T1 - 1,) + P.shape[1:], P.dtype), jnp.zeros((T1,), P.dtype))
    (M, Ps, cross, ll), k, delta = _iter.fixed_point(phi, z0, args, tol, max_iter)
    return M, Ps, cross, ll, k, delta <= tol


def _rts(spec, states, y, u, parallel):
    """(M, P, cross, loglik (T+1,) or None) of the filter's own RTS, sequential or parallel."""
    if not parallel:
        M, P, cross = _gauss.backward(spec, states, u)
        return M, P, cross, None
    ny = y.shape[1]
    ys = jnp.concatenate([jnp.full((1, ny), jnp.nan, y.dtype), y])
    mod = _gauss.linearize_filtered(spec, states, u, ny)
    return _iter.linear_pass(mod, ys, parallel)


def smooth_one_run(estimator: Estimator, y, u, x0, P0, th0=None, Pth0=None, key=None, *,
                   method: str = "rts", parallel=False, tol: float = 1e-6,
                   max_iter: int = 20, initial=None) -> SmoothResult:
    """One run smoothed, traced, without validation (what ``vehjax.run(..., smooth=True)``
    vmaps): y (T, ny) with NaN missing, u (T, nu), x0 (nx,), P0 (nx, nx), th0/Pth0 as for
    :func:`vehjax.filter`; ``method`` one of :data:`METHODS` (not None), ``parallel``, ``tol``,
    ``max_iter``, ``initial`` the fields of :func:`smooth`'s method record, checked beforehand
    (:func:`check_options`). Gaussian filters only (``estimator.smoother`` set)."""
    spec = estimator.smoother
    states, filt = forward(estimator, y, u, x0, P0, th0, Pth0, key)
    if method == "rts":
        M, P, cross, ll = _rts(spec, states, y, u, parallel)
        k, conv = jnp.zeros((), jnp.int32), jnp.ones((), bool)
    else:
        M, P, cross, ll, k, conv = _iterated(spec, states, y, u, parallel, tol, max_iter,
                                             initial)
    return _result(spec, estimator.nx, filt, M, P, cross, ll, k, conv)


def _result(spec, nx: int, filt: FilterResult, M, P, cross, ll=None, k=None, conv=None,
            good=None) -> SmoothResult:
    """One run's :class:`SmoothResult` from the smoothed moments at t = 0..T (M (T+1, n),
    P (T+1, n, n), cross (T, n, n)), the forward filter's result ``filt``, the linearised
    model's log-likelihood ``ll`` (T+1,) or None (the filter's), ``k``/``conv`` of an iterated
    smoother (None: 0 passes, converged): the report in physical units and the divergence rule
    of the module docstring; ``good`` (bool scalar) that rule's test of the smoothed moments
    when the caller has made it (:func:`_good_runs_last`), None to make it here."""
    if k is None:
        k, conv = jnp.zeros((), jnp.int32), jnp.ones((), bool)
    loglik = filt.loglik if ll is None else ll[1:]
    xs, Px, cross, th, Pth = _report(spec, M, P, cross, nx)
    if good is None:
        good = (jnp.all(jnp.isfinite(xs)) & jnp.all(is_pd(Px)) & jnp.all(jnp.isfinite(cross))
                & jnp.all(jnp.isfinite(loglik)) & jnp.all(jnp.isfinite(th)))
        if th.shape[-1]:
            good = good & jnp.all(is_pd(Pth))
    bad = filt.diverged | ~good
    held_P = filt.covariances
    return SmoothResult(
        states=jnp.where(bad, filt.states, xs),
        covariances=jnp.where(bad, held_P, Px),
        cross_covariances=jnp.where(bad, 0.0, cross),
        params=jnp.where(bad, filt.params, th),
        params_cov=jnp.where(bad, filt.params_cov, Pth),
        loglik=jnp.where(bad, filt.loglik, loglik),
        diverged=bad,
        iterations=k,
        converged=conv,
        filtered=filt,
    )


def smooth_runs_last(estimator: Estimator, filt: FilterResult, state0, means, covs,
                      pred) -> SmoothResult:
    """The filter's own RTS over a batch of runs whose forward pass ran with the runs-last step
    and kept its predictions (``Estimator.batch``'s ``smooth_step``; what
    ``vehjax.run(..., smooth=True)`` does where the platform's strategy uses that step): the
    backward pass runs-last too, from the forward pass's predictions
    (:func:`vehjax.smoothers.gaussian.backward_predicted`), and the layout turns runs-first
    once, at the end. The same numbers as ``jax.vmap(smooth_one_run)`` to rounding.

    Args:
        estimator: a Gaussian filter with a plain-covariance smoother and a runs-last form.
        filt: the forward filter's :class:`~vehjax.filtering.FilterResult`, leading runs axis R.
        state0: the filter's init states of the runs (``estimator.init``), runs axis last.
        means, covs: the forward pass's filtered means (T, nx, R) and covariances
            (T, nx, nx, R), before any divergence hold (such runs are reported held anyway).
        pred: the forward pass's :class:`vehjax.filters.runs_last.Prediction` of every step,
            leading T.

    Returns:
        :class:`SmoothResult` with a leading runs axis R.
    """
    spec = estimator.smoother
    m0, P0, _ = jax.vmap(spec.split, in_axes=-1, out_axes=-1)(state0)
    m = jnp.concatenate([m0[None], means.astype(m0.dtype)])
    P = jnp.concatenate([P0[None], covs.astype(P0.dtype)])
    M, Ps, cross = _gauss.backward_predicted(m, P, pred.mean, pred.cov, pred.cross)
    good = None
    if spec.report is None:  # the divergence test runs-last too (state-only filters)
        good = _good_runs_last(M[1:], Ps[1:], cross[1:]) & jnp.all(
            jnp.isfinite(filt.loglik), axis=1)

    def first(a):
        return jnp.moveaxis(a, -1, 0)

    return jax.vmap(lambda f, a, b, c, ok: _result(spec, estimator.nx, f, a, b, c, good=ok),
                    in_axes=(0, 0, 0, 0, None if good is None else 0))(
        filt, first(M), first(Ps), first(cross), good)


def _good_runs_last(M, P, cross):
    """The divergence rule's test of smoothed moments (:func:`_result`), for a batch of runs
    with the runs axis last, entry by entry: whether every mean M (T, n, R) and
    cross-covariance (T-1, n, n, R) is finite and every covariance P (T, n, n, R) finite and
    positive definite (its Cholesky factor finite); (R,) bool."""
    n = P.shape[1]
    L = chol_sym([[P[:, i, j] for j in range(n)] for i in range(n)])
    # a NaN pivot makes every later column NaN (chol_entries), the last pivot included
    pd = jnp.all(jnp.isfinite(L[n - 1][n - 1]), axis=0) if n else True
    return (jnp.all(jnp.isfinite(M), axis=(0, 1)) & jnp.all(jnp.isfinite(P), axis=(0, 1, 2))
            & pd & jnp.all(jnp.isfinite(cross), axis=(0, 1, 2)))


# ----------------------------------------------------------------------------------------------
# the public single-run function


#: The iterated smoothers' defaults: ``tol`` and ``max_iter`` of :class:`~vehjax.smoothers.IEKS`.
TOL, MAX_ITER = _methods.TOL, _methods.MAX_ITER


def check_options(estimator: Estimator, method=None):
    """The Gaussian smoothing method checked before tracing: its record
    (:mod:`vehjax.smoothers.methods`: :class:`~vehjax.smoothers.methods.RTS`, ``IEKS`` or
    ``IPLS``), None or a name standing for the record with its defaults (None: the filter's
    own RTS). ValueError naming ``estimator`` (no smoother) or ``method`` (unknown, a particle
    smoother's, or IEKS for a sigma-point filter / IPLS for a Jacobian one)."""
    if not isinstance(estimator, Estimator):
        raise ValueError(
            f"estimator: expected a vehjax.filters.Estimator, got {type(estimator).__name__}")
    spec = estimator.smoother
    if spec is None:
        raise ValueError(
            f"estimator: {estimator.name!r} has no smoother; vehjax.smooth smooths the EKF, "
            f"UKF, CKF (plain and square-root), the joint EKF/UKF, the bootstrap PF without "
            f"input noise and the paper's marginalized PF (marginalized_pf; dual filters and "
            f"marginalized_pf_grid do not form the joint Gaussian or paths a smoother needs)")
    rec = _methods.record(method)
    rec = _methods.RTS() if rec is None else rec
    if isinstance(rec, _methods.PARTICLE):
        raise ValueError(f"method: {type(rec).__name__} applies to particle filters only; "
                         f"{estimator.name!r} is a Gaussian filter, whose smoothers are RTS, "
                         f"IEKS and IPLS")
    if rec.name == "ieks" and not spec.taylor:
        raise ValueError(f"method: 'ieks' iterates Jacobian linearisations; {estimator.name!r} "
                         f"linearises by sigma points, use method='ipls'")
    if rec.name == "ipls" and spec.taylor:
        raise ValueError(f"method: 'ipls' iterates sigma-point linearisations; "
                         f"{estimator.name!r} linearises by Jacobians, use method='ieks'")
    return rec


def one_run_options(rec) -> dict:
    """:func:`smooth_one_run`'s keywords of a Gaussian method's record (checked:
    :func:`check_options`) but ``initial``: its name, ``parallel``, ``tol`` and ``max_iter``
    (the iterated smoothers'; RTS takes neither), as :func:`smooth` and ``vehjax.run(...,
    smooth=)`` both pass them."""
    return dict(method=rec.name, parallel=rec.parallel, tol=getattr(rec, "tol", TOL),
                max_iter=getattr(rec, "max_iter", MAX_ITER))


def _particle_method(estimator: Estimator, method) -> dict:
    """A particle filter's smoothing method as the particle smoother's keyword arguments
    (``method``, ``n_trajectories``, ``max_tries``); {} for None (its default). ValueError
    naming ``method`` for a Gaussian smoother's record, which it would not run."""
    rec = _methods.record(method)
    if rec is None:
        return {}
    if isinstance(rec, _methods.GAUSSIAN):
        raise ValueError(
            f"method: {type(rec).__name__} is one of the Gaussian smoothers; {estimator.name!r} "
            f"is a particle filter, whose smoother takes FFBSi, RejectionSampling or "
            f"AncestorPaths (vehjax.smoothers)")
    return dict(method=rec.name, **dataclasses.asdict(rec))


def smooth(estimator: Estimator, measurements, inputs=None, *, x0, P0, theta0=None,
           P_theta0=None, key=None, method=None) -> SmoothResult:
    """Smooth one run of T steps (module docstring for the methods).

    Pure and traceable (``jax.jit`` with the method static, ``jax.vmap`` over runs,
    ``jax.grad`` of ``smooth(...).loglik.sum()`` with the estimator built inside).

    Args:
        estimator: a :class:`vehjax.filters.Estimator` with a smoother (``Estimator.smoother``)
            or a particle filter with ``particle_transition``.
        measurements: (T, ny); NaN (or +-inf) components are missing.
        inputs: (T, nu); None when the model has no inputs.
        x0, P0: state before the first step, (nx,), and its covariance (nx, nx) or (nx,).
        theta0, P_theta0, key: as for :func:`vehjax.filter`.
        method: a record of :mod:`vehjax.smoothers.methods`, with that method's options, or
            its name for the record with the defaults; None: the filter's own. Gaussian
            filters: :class:`~vehjax.smoothers.RTS` (None, ``"rts"``; ``parallel``),
            :class:`~vehjax.smoothers.IEKS` (``"ieks"``, Jacobian filters) or
            :class:`~vehjax.smoothers.IPLS` (``"ipls"``, sigma-point filters), the iterated
            ones with ``parallel``, ``tol``, ``max_iter``, ``initial``. The bootstrap PF
            (:func:`vehjax.smoothers.particle.smooth`): :class:`~vehjax.smoothers.FFBSi`
            (None, ``"ffbsi"``), :class:`~vehjax.smoothers.RejectionSampling`
            (``"rejection"``) or :class:`~vehjax.smoothers.AncestorPaths` (``"ancestor"``);
            the marginalized PF (:func:`vehjax.smoothers.marginalized.smooth`): AncestorPaths
            (None) or FFBSi.

    Returns:
        :class:`SmoothResult`; for particle filters what the particle smoother returns.

    Raises:
        ValueError: naming the argument: a filter without a smoother (``estimator``), an
            unknown or unsuitable ``method`` (a Gaussian smoother for a particle filter, a
            particle smoother for a Gaussian one), ``method.initial`` of the wrong shape (the
            records check their other fields when made, ``method.tol: ...``), and every shape
            error of :func:`vehjax.filter`.
    """
    ys, us, x0, P0, th0, Pth0, _ = check_arguments(estimator, measurements, inputs, x0, P0,
                                                    theta0, P_theta0, key)
    if estimator.smoother is None:  # the particle smoothers, or none at all
        if estimator.particle_transition is None and estimator.rao_blackwell is None:
            check_options(estimator)  # no smoother: say so, whatever the method
        opts = _particle_method(estimator, method)
        if estimator.particle_transition is not None:
            if theta0 is not None:
                opts["theta0"] = theta0
            return _particle.smooth(estimator, measurements, inputs, x0=x0, P0=P0, key=key,
                                    **opts)
        opts.setdefault("method", None)
        opts.pop("max_tries", None)  # "rejection" is the bootstrap PF's: refused by name there
        return _marginalized.smooth(estimator, measurements, inputs, x0=x0, P0=P0, key=key,
                                    theta0=theta0, **opts)
    rec = check_options(estimator, method)
    T = np.shape(ys)[0]
    initial = getattr(rec, "initial", None)
    if initial is not None:
        n = estimator.nx + len(estimator.param_names)
        if np.shape(initial) != (T, n):
            raise ValueError(f"method.initial: expected shape ({T}, {n}), got "
                             f"{np.shape(initial)}")
    ys, us = jnp.asarray(ys), jnp.asarray(us)
    # called eagerly: compiled as one program (vehjax.runtime.eager); under a trace: inline
    return eager.call(smooth_one_run, (estimator,), one_run_options(rec), ys, us,
                      jnp.asarray(x0), jnp.asarray(P0), th0, Pth0, key, initial=initial)
