"""A chunk's runs computed side by side, traced: ``vmap`` of the one-run engine (in blocks of
runs, one block after the other), the runs-last batched step of the estimators that have one,
and the smoothed forms of both.

::

    res = vmapped_study(est, return_cov, per_run, block, ys, us, x0, P0, th0, Pth0, keys)
    res = runs_last_study(est, return_cov, prefetch, per_run, ys, us, x0, P0, th0, Pth0, keys)
    res, cross = smoothed_study(est, method, return_cov, per_run, block, strategy, *args)

Each returns what ``jax.vmap(vehjax.engine.one_run)`` over the chunk's runs returns (a
:class:`vehjax.engine.FilterResult` with a leading runs axis), to rounding. ``per_run`` says
which arguments have a leading runs axis (the others are shared). The runs-last form
(:mod:`vehjax.filters.runs_last`) scans the batched step once with the runs axis last, what the
model computes from the inputs alone computed before the time loop; which form a chunk takes is
:mod:`vehjax.execution`'s rule (``runs_last_for``), applied by ``vehjax.run``'s chunk function.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp

from .. import engine, execution, smoothing
from ..engine import FilterResult
from ..filters import runs_last
from ..filters.base import Estimator
from ..smoothers.methods import RTS
from .plan import balanced_blocks

__all__ = ["scan", "scan_prefetched", "runs_last_study", "vmapped_study", "blocked",
           "smoothed_study"]


def scan(body, carry0, xs, pre):
    """``lax.scan(body, carry0, (xs, pre))``."""
    return jax.lax.scan(body, carry0, (xs, pre))


def scan_prefetched(body, carry0, xs, pre):
    """``lax.scan(body, carry0, (xs, pre))``, except that ``pre[t]`` reaches the body through
    the carry: it is read at the end of step t - 1 (of the first step, before the loop).

    XLA on CPU fuses a slice of a scanned-over array into every kernel that reads it; a carried
    value is a plain buffer. Which is faster depends on the step (``runs_last.Batch.prefetch``).
    """
    T = jax.tree.leaves(xs)[0].shape[0]
    if T == 0 or not jax.tree.leaves(pre):
        return jax.lax.scan(body, carry0, (xs, pre))

    def at(t):
        return jax.tree.map(lambda a: jax.lax.dynamic_index_in_dim(a, t, keepdims=False), pre)

    def loop(carry, x):
        inner, pre_t = carry
        x_t, t_next = x
        inner, out = body(inner, (x_t, pre_t))
        return (inner, at(jnp.minimum(t_next, T - 1))), out

    (carry, _), outs = jax.lax.scan(loop, (carry0, at(0)), (xs, jnp.arange(1, T + 1)))
    return carry, outs


def runs_last_study(estimator: Estimator, return_cov: bool, prefetch: bool, per_run, ys, us, x0,
                     P0, th0, Pth0, keys, predictions: bool = False):
    """What ``vmap(engine.one_run)`` computes, for an estimator with a runs-last ``batch``
    form: one scan over time of the batched step, every array with the runs axis last (see
    :mod:`vehjax.filters.runs_last`); the same per-run bookkeeping (``engine.finish``).

    With ``predictions`` (static; what the runs-last smoother needs, ``return_cov`` then True)
    the scan runs the step's ``smooth_step`` instead and the result is
    ``(FilterResult, state0, means, covs, prediction)``: the init states (runs-last
    GaussianState), the filtered means (T, nx, R) and covariances (T, nx, nx, R) and every
    step's :class:`vehjax.filters.runs_last.Prediction` stacked (leading T), all runs last.
    Without it only the FilterResult, and the scan is the filter's alone."""
    p = len(estimator.param_names)
    per_run_u = us.ndim == 3
    start = jax.vmap(
        partial(engine.start, estimator), in_axes=tuple(0 if r else None for r in per_run)
    )
    state0, held0 = start(ys, us, x0, P0, th0, Pth0, keys)
    batch = estimator.batch(per_run_u, held0[0].dtype, th0 is None)
    state0 = jax.tree.map(lambda a: jnp.moveaxis(a, 0, -1), state0)

    ok = partial(engine.output_ok, p=p, pd=runs_last.runs_pd,
                 all_finite=runs_last.all_finite)
    if predictions:
        if batch.smooth_step is None:
            raise ValueError(f"estimator: {estimator.name!r}'s runs-last step has no smooth_step")

        def body(state, yu):
            kept = []  # the step's Prediction, passed around filtering's bookkeeping

            def step(s, y, prepared):
                s, (out, pred) = batch.smooth_step(s, y, prepared)
                kept.append(pred)
                return s, out

            state, per_step = engine.scan_body(step, ok, return_cov)(state, yu)
            return state, (per_step, kept[0])
    else:
        body = engine.scan_body(batch.step, ok, return_cov)

    y_t = jnp.moveaxis(ys, 0, -1)  # (T, ny, C)
    u_t = jnp.moveaxis(us, 0, -1) if per_run_u else us  # (T, nu, C) or (T, nu)
    # the prepared inputs go through the carry where the filter and the platform say so
    over_time = scan_prefetched if batch.prefetch and prefetch else scan
    _, per_step = over_time(body, state0, y_t, batch.prepare(u_t))
    if predictions:
        per_step, pred = per_step
        means, covs = per_step[0], per_step[1]
    per_step = jax.tree.map(lambda a: jnp.moveaxis(a, -1, 0), per_step)  # (C, T, ...)
    filt = jax.vmap(partial(engine.finish, bounds=estimator.bounds))(per_step, held0)
    return (filt, state0, means, covs, pred) if predictions else filt


def vmapped_study(estimator, return_cov, per_run, block, *args):
    """`engine.one_run` over the runs (leading axis of the per-run arguments), in
    blocks of ``block`` runs vmapped side by side (all at once when ``block`` is None). A
    chunk of one run is computed unbatched (:func:`one_run_study`)."""
    one = partial(engine.one_run, estimator, return_cov)
    if args[0].shape[0] == 1:
        return one_run_study(one, per_run, args)
    side_by_side = jax.vmap(one, in_axes=tuple(0 if r else None for r in per_run))
    return blocked(side_by_side, per_run, block, args)


def one_run_study(one, per_run, args):
    """``one`` (the one-run engine) on a chunk of one run: the per-run arguments' runs axis
    dropped, the outputs given it back. The program is then :func:`vehjax.filter`'s: a
    vmap over a runs axis of length 1 compiles its small matrix products as batched ones,
    which XLA:CPU runs slower (Dynamic3DOF EKF, 20,000 steps: 1.44 against 0.91 us a step,
    ``benchmarks/bench_floor.py --model 3dof``)."""
    res = one(*(a[0] if r else a for a, r in zip(args, per_run)))
    return jax.tree.map(lambda a: a[None], res)


def blocked(side_by_side, per_run, block, args):
    """``side_by_side(*args)`` (vmapped over the runs, the leading axis of the per-run
    arguments) in blocks of at most ``block`` runs, one block after the other (``lax.map``);
    all at once when ``block`` is None or covers the chunk. The blocks are balanced
    (:func:`balanced_blocks`, as the chunks are): 20 runs at a block of 19 go as two blocks of
    10, not 19 and 1 padded to 19, which computed 38 runs for 20."""
    C = args[0].shape[0]
    if block is None or block >= C:
        return side_by_side(*args)
    n_blocks, block = balanced_blocks(C, block)
    pad = n_blocks * block - C  # < n_blocks: the last block is filled with copies of the last run

    def blocked(a):
        a = jnp.concatenate([a, jnp.repeat(a[-1:], pad, axis=0)]) if pad else a
        return a.reshape((n_blocks, block) + a.shape[1:])

    def one_block(mapped):
        it = iter(mapped)
        return side_by_side(*(next(it) if r else a for a, r in zip(args, per_run)))

    res = jax.lax.map(one_block, [blocked(a) for a, r in zip(args, per_run) if r])
    return jax.tree.map(lambda a: a.reshape((n_blocks * block,) + a.shape[2:])[:C], res)


def smoothed_study(estimator, method, return_cov, per_run, block, strategy, *args):
    """:func:`vehjax.smoothing.smooth_one_run` over the runs (in blocks as the vmapped study),
    as the study's outputs; ``cross`` (C, T-1, nx, nx) the lag-one cross-covariances.
    ``method``: a Gaussian method's record (RTS, IEKS, IPLS, checked; its options passed as
    :func:`vehjax.smooth` passes them, :func:`vehjax.smoothing.one_run_options`). The
    filter's own sequential RTS (``RTS()``) of a filter with a runs-last form, where the
    strategy uses that form,
    runs forward and backward with the runs axis last instead
    (:func:`vehjax.smoothing.smooth_runs_last`): the same numbers to rounding, several times
    faster on the CPU (``vehjax bench smooth``)."""
    def as_result(sm):
        f = sm.filtered
        div_at = jnp.where(f.diverged, f.diverged_at, jnp.where(sm.diverged, 0, -1))
        return FilterResult(sm.states, sm.covariances if return_cov else None, sm.params,
                            sm.params_cov if return_cov else None, sm.loglik, f.nis, f.n_obs,
                            sm.diverged, div_at.astype(f.diverged_at.dtype), f.at_bound), \
            (sm.cross_covariances if return_cov else None)

    if (method == RTS() and execution.runs_last_for(strategy, args[0].shape[0])
            and estimator.batch is not None and not estimator.smoother.sqrt):
        filt, state0, means, covs, pred = runs_last_study(
            estimator, True, strategy.prefetch_inputs, per_run, *args, predictions=True)
        return as_result(smoothing.smooth_runs_last(estimator, filt, state0, means, covs, pred))

    def one(*a):
        return as_result(smoothing.smooth_one_run(estimator, *a,
                                                  **smoothing.one_run_options(method)))

    return blocked(jax.vmap(one, in_axes=tuple(0 if r else None for r in per_run)), per_run,
                    block, args)
