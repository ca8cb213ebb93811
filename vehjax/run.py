"""Run a whole Monte-Carlo study in one call: ``lax.scan`` over time, ``vmap`` over runs.

::

    out = vehjax.run(est, measurements, inputs, x0=x0, P0=P0, key=jax.random.key(0))
    out.states          # (R, T, nx)
    out.diverged        # (R,) bool

Time convention (the papers' order): ``x0``/``P0`` describe the state before the first step;
step ``t`` predicts with ``inputs[..., t, :]``, then updates with ``measurements[:, t, :]``, so
``out.states[:, t]`` is the filtered estimate after the ``t``-th measurement.

Each run is :func:`vehjax.filter`'s traced logic (``vehjax.engine.one_run``), vmapped over
the runs of a chunk. Estimators with a runs-last ``batch`` form (EKF, UKF and CKF on models with at
most 8 states and outputs, :mod:`vehjax.filters.runs_last`) are not vmapped where the execution
strategy says so: one scan runs the batched step with the runs axis last, and what the model
computes from the inputs alone is computed once for the whole input sequence before the time
loop (:mod:`vehjax.runtime.hoist`); results agree to rounding.

How a study executes on its platform (chunk budget, blocking of runs inside a chunk, runs-last
or vmapped step, XLA options, trigonometric substitutes, results to the host) is decided in one
place, :mod:`vehjax.execution`, from the device the study runs on; ``strategy=`` overrides it.
This module holds no platform rule.

A NaN measurement component is missing; ``run`` passes it to the filter untouched and the filter
skips that component's update. Every filter treats any non-finite component as missing; ``run``
refuses +-inf in the measurements with a ValueError, since it is more likely a fault than a gap.

Divergence (as in :mod:`vehjax.filtering`): a run whose mean is not finite, whose covariance is
not finite and positive definite (also the parameter estimate and its covariance, for filters
that estimate parameters), or whose log-likelihood or NIS is not finite, is flagged ``diverged``
at that step. From then on its outputs hold the last good estimate (the prior ``x0``/``P0`` if it
diverged at the first step), its ``nis`` is NaN, its ``n_obs`` 0 and its ``loglik`` stops
accumulating. A particle filter that re-initialises (``StepOutput.reinit``) flags the run but
keeps going. The other runs are not touched.

Estimates on a bound (as in :mod:`vehjax.engine`): a run of a filter with parameter domains
(``Estimator.bounds``) whose estimate of some parameter lies on a finite bound (within
``engine.AT_BOUND_RTOL`` of the bound's scale) on more than ``engine.AT_BOUND_FRACTION`` of
its steps is flagged ``at_bound``; it is neither frozen nor ``diverged``.

Large studies are split into chunks of runs, each one jitted call (one compilation per chunk
shape; the last chunk is padded); results come back to host memory chunk by chunk, so device
memory stays bounded. When several JAX devices are visible the runs of each chunk are sharded over
them (``jax.shard_map`` over a 1-D mesh, no communication between devices; across processes see
below).

What is reproducible. Bit for bit: the same call (data, key, chunking, devices, strategy and
XLA options) on the same machine. To rounding: another chunking, blocking, sharding or number of
processes changes which runs XLA computes together and how it vectorises them, so the last bits
of a result can change; a Gaussian filter's results then agree to a few float64 rounding errors
amplified by the problem's conditioning. A particle filter draws its normals in float32
(:mod:`vehjax.runtime.prng`), whose last float32 bit can change likewise (relative 1e-7), and where a
resampling decision turns on it the run continues as another, equally valid Monte-Carlo
realisation: particle results agree statistically, and to about 1e-6 relative only while no
decision flips. Per-run keys do not depend on chunking (run r gets ``split(key, R)[r]``).

Past one machine (multi-controller JAX): after ``jax.distributed.initialize`` in every process,
``run`` called in every process with the same arguments (the SPMD convention: the same data,
key, ``chunk_size`` and ``devices``) shards each chunk's runs over the devices of all processes
(``jax.devices()``, the global mesh) and returns the whole :class:`RunResult`, all R runs, in
every process, equal to a one-process run up to rounding (as above)::

    # on each of N hosts (or N local processes), process_id = 0 .. N-1
    jax.distributed.initialize(coordinator_address="host0:1234", num_processes=N,
                               process_id=process_id)   # before any other JAX call
    out = vehjax.run(est, measurements, inputs, x0=x0, P0=P0, key=jax.random.key(0))
    if jax.process_index() == 0:
        out.to_npz("study.npz")                         # every process holds all of out

Every process holds the full host arrays; it places on its own devices only the runs they
compute (``jax.make_array_from_callback``). Each chunk's results are all-gathered over the mesh
inside the jitted call (so every device, and every process, holds the chunk's outputs) and come
back to host memory in every process. Chunks, the padding of the last one and the device order
are computed from the arguments alone, hence the same in every process; before the first chunk
``run`` checks this with one small all-gather of a hash of the arguments and raises ValueError
in every process when they differ (a process that does not call ``run``, or fails before that
check, leaves the others waiting). Processes may have different numbers of local devices. On
CPU the processes exchange data through gloo (``jax_cpu_collectives_implementation``, JAX's
default); ``jax_num_cpu_devices`` gives a process several CPU devices. ``devices=False`` makes
every process run the whole study alone on its first local device, without communication; a
sequence of devices is either all the calling process's (a local study, as with one process)
or includes devices of every process. The progress bar shows on process 0 only.

Compile and execution time can be measured apart with :func:`compile_run`::

    t0 = time.perf_counter(); prepared = vehjax.compile_run(est, ys, us, x0=x0, P0=P0)
    t1 = time.perf_counter(); out = prepared()            # executes only; call again to repeat
    t2 = time.perf_counter()                              # compile: t1 - t0, run: t2 - t1
"""

from __future__ import annotations

import hashlib
import math
import time
from functools import partial
from typing import Any, NamedTuple, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from . import engine, execution, smoothing, validation
from .engine import FilterResult
from .filters import runs_last
from .filters.base import Estimator
from .runtime.progress import Progress, text_bar
from .result import RunResult

__all__ = ["RunResult", "CompiledRun", "run", "compile_run", "Strategy"]

Strategy = execution.Strategy

_AXIS = "runs"
# A filter step holds temporaries of about this many times its carried state (particles through
# the model, predicted measurements, resampled copies).
_STATE_TEMPORARIES = 16


# ----------------------------------------------------------------------------------------------
# Traced part: the per-run logic is vehjax.filtering's; here only the batching


def _scan(body, carry0, xs, pre):
    """``lax.scan(body, carry0, (xs, pre))``."""
    return jax.lax.scan(body, carry0, (xs, pre))


def _scan_prefetched(body, carry0, xs, pre):
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


def _runs_last_study(estimator: Estimator, return_cov: bool, prefetch: bool, per_run, ys, us, x0,
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
    scan = _scan_prefetched if batch.prefetch and prefetch else _scan
    _, per_step = scan(body, state0, y_t, batch.prepare(u_t))
    if predictions:
        per_step, pred = per_step
        means, covs = per_step[0], per_step[1]
    per_step = jax.tree.map(lambda a: jnp.moveaxis(a, -1, 0), per_step)  # (C, T, ...)
    filt = jax.vmap(partial(engine.finish, bounds=estimator.bounds))(per_step, held0)
    return (filt, state0, means, covs, pred) if predictions else filt


def _vmapped_study(estimator, return_cov, per_run, block, *args):
    """`engine.one_run` over the runs (leading axis of the per-run arguments), in
    blocks of ``block`` runs vmapped side by side (all at once when ``block`` is None)."""
    one = partial(engine.one_run, estimator, return_cov)
    side_by_side = jax.vmap(one, in_axes=tuple(0 if r else None for r in per_run))
    return _blocked(side_by_side, per_run, block, args)


def balanced_blocks(runs: int, block: int) -> tuple[int, int]:
    """(number of blocks, runs per block) for ``runs`` runs in blocks of at most ``block``:
    as few blocks as that allows, as even as they can be (the chunks of a study and the
    blocks of runs inside a chunk)."""
    n_blocks = -(-runs // block)
    return n_blocks, -(-runs // n_blocks)


def _blocked(side_by_side, per_run, block, args):
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


def _smoothed_study(estimator, method, return_cov, per_run, block, strategy, *args):
    """:func:`vehjax.smoothing.smooth_one_run` over the runs (in blocks as the vmapped study),
    as the study's outputs; ``cross`` (C, T-1, nx, nx) the lag-one cross-covariances. The
    filter's own RTS of a filter with a runs-last form, where the strategy uses that form,
    runs forward and backward with the runs axis last instead
    (:func:`vehjax.smoothing._smooth_runs_last`): the same numbers to rounding, several times
    faster on the CPU (``vehjax bench smooth``)."""
    def as_result(sm):
        f = sm.filtered
        div_at = jnp.where(f.diverged, f.diverged_at, jnp.where(sm.diverged, 0, -1))
        return FilterResult(sm.states, sm.covariances if return_cov else None, sm.params,
                            sm.params_cov if return_cov else None, sm.loglik, f.nis, f.n_obs,
                            sm.diverged, div_at.astype(f.diverged_at.dtype), f.at_bound), \
            (sm.cross_covariances if return_cov else None)

    if (method == "rts" and execution.runs_last_for(strategy, args[0].shape[0])
            and estimator.batch is not None and not estimator.smoother.sqrt):
        filt, state0, means, covs, pred = _runs_last_study(
            estimator, True, strategy.prefetch_inputs, per_run, *args, predictions=True)
        return as_result(smoothing._smooth_runs_last(estimator, filt, state0, means, covs, pred))

    def one(*a):
        return as_result(smoothing.smooth_one_run(estimator, *a, method=method))

    return _blocked(jax.vmap(one, in_axes=tuple(0 if r else None for r in per_run)), per_run,
                    block, args)


@eqx.filter_jit
def _study(estimator, ys, us, x0, P0, th0, Pth0, keys, return_cov, mesh, block, strategy,
           smooth=None):
    """A chunk of runs: ys (C, T, ny); the others per run (leading C) or shared, by rank. The
    vmapped form computes ``block`` runs side by side at a time (all when None, or when the
    chunk, or a device's share of it, has no more). Traced under ``strategy``
    (:func:`vehjax.execution.using`), which also says whether the runs-last step is used."""
    with execution.using(strategy):
        return _study_traced(estimator, ys, us, x0, P0, th0, Pth0, keys, return_cov, mesh,
                             block, strategy, smooth)


def _study_traced(estimator, ys, us, x0, P0, th0, Pth0, keys, return_cov, mesh, block,
                  strategy, smooth):
    per_run = (
        True,
        us.ndim == 3,
        x0.ndim == 2,
        P0.ndim == 3,
        th0 is not None and th0.ndim == 2,
        Pth0 is not None and Pth0.ndim == 3,
        keys is not None,
    )

    def f(*args):
        cross = None
        if smooth is not None:
            res, cross = _smoothed_study(estimator, smooth, return_cov, per_run, block,
                                         strategy, *args)
        elif execution.runs_last_for(strategy, args[0].shape[0]) and estimator.batch is not None:
            res = _runs_last_study(estimator, return_cov, strategy.prefetch_inputs, per_run,
                                   *args)
        else:
            res = _vmapped_study(estimator, return_cov, per_run, block, *args)
        return (res.states, res.covariances, res.params, res.params_cov,
                jnp.sum(res.loglik, axis=1), res.nis, res.n_obs, res.diverged, res.diverged_at,
                res.at_bound, cross)

    if mesh is not None:
        f = jax.shard_map(
            f,
            mesh=mesh,
            in_specs=tuple(PartitionSpec(_AXIS) if r else PartitionSpec() for r in per_run),
            out_specs=PartitionSpec(_AXIS),
            check_vma=False,  # no collectives; shared inputs are replicated constants
        )
    out = f(ys, us, x0, P0, th0, Pth0, keys)
    if mesh is not None and mesh.is_multi_process:
        # Multi-controller: replicate the chunk's results on every device (one all-gather), so
        # that every process holds all of them and can bring them to host memory.
        out = jax.lax.with_sharding_constraint(out, NamedSharding(mesh, PartitionSpec()))
    return out


# ----------------------------------------------------------------------------------------------
# Validation (before anything is traced)


def _state_numbers(estimator, x0, P0, th0, Pth0, keys) -> int:
    """How many numbers the filter carries for one run (its state from ``init``)."""
    def first(a, per_run_ndim):
        return None if a is None else (a[0] if a.ndim == per_run_ndim else a)

    state = jax.eval_shape(
        estimator.init, first(x0, 2), first(P0, 3), first(th0, 2), first(Pth0, 3),
        None if keys is None else keys[0],
    )
    return sum(int(np.prod(a.shape)) for a in jax.tree.leaves(state))


def _per_run_bytes(estimator, ys, state_numbers: int, return_cov: bool) -> tuple[int, int]:
    """(bytes one run holds on the device: its outputs plus what the filter holds, its state
    from ``init`` times the temporaries of a step; bytes of one run's results on the host)."""
    _, T, _ = ys.shape
    nx, p = estimator.nx, len(estimator.param_names)
    itemsize = np.dtype(ys.dtype).itemsize
    out_bytes = T * itemsize * (nx + p + 4 + (nx * nx + p * p if return_cov else 0))
    state_bytes = 8 * state_numbers  # at most float64 (typed PRNG keys have no numpy dtype)
    return out_bytes + _STATE_TEMPORARIES * state_bytes, out_bytes


class _Plan(NamedTuple):
    estimator: Estimator
    arrays: tuple  # ys, us, x0, P0, th0, Pth0 (numpy or None)
    per_run: tuple  # which of arrays have a leading run axis
    keys: Any  # jax array of per-run keys (R,) or None
    R: int
    chunk: int
    n_chunks: int
    return_cov: bool
    devices: tuple
    mesh: Any
    progress: bool | None
    spans_processes: bool = False  # the mesh holds other processes' devices (jax.distributed)
    block: int | None = None  # runs vmapped side by side inside a chunk (None: all)
    strategy: execution.Strategy | None = None  # how it executes (vehjax.execution)
    smooth: str | None = None  # the smoothing method (vehjax.smoothing.METHODS), or None


def _checked_data(estimator, measurements, inputs, x0, P0, theta0, P_theta0, key):
    """A study's estimator, data, prior, initial parameters and key checked (before anything is
    traced): (ys, us, x0, P0, th0, Pth0, keys) as arrays, keys split per run or None."""
    if not isinstance(estimator, Estimator):
        raise ValueError(
            f"estimator: expected a vehjax.filters.Estimator, got {type(estimator).__name__}"
        )
    nx = int(estimator.nx)
    if nx < 1:
        raise ValueError(f"estimator: nx must be >= 1, got {estimator.nx}")

    # the checks every entry point shares (vehjax.validation): real arrays, NaN measurements
    # missing, +-inf and every other non-finite value refused naming the first bad index
    ys, us = validation.data(measurements, inputs, estimator.ny, estimator.nu, "many")
    R = ys.shape[0]
    x0, P0 = validation.prior(nx, x0, P0, runs=R)
    th0, Pth0 = engine.initial_parameters(estimator, theta0, P_theta0, runs=R)

    if estimator.needs_key and key is None:
        raise ValueError(
            f"key: estimator {estimator.name!r} draws random numbers; pass key=jax.random.key(...)"
        )
    keys = None if key is None else validation.key(key, R)
    return ys, us, x0, P0, th0, Pth0, keys


def _check_progress(progress) -> None:
    """ValueError naming ``progress`` unless it is None, True or False."""
    validation.flag("progress", progress, allow_none=True)


def _check_options(return_covariances, progress, chunk_size) -> None:
    """ValueError naming the option unless ``return_covariances`` is a bool, ``progress`` None
    or a bool and ``chunk_size`` None or an integer >= 1."""
    validation.flag("return_covariances", return_covariances)
    _check_progress(progress)
    if chunk_size is not None and (
        isinstance(chunk_size, (bool, np.bool_))
        or not isinstance(chunk_size, (int, np.integer))
        or chunk_size < 1
    ):
        raise ValueError(f"chunk_size: expected None or an integer >= 1, got {chunk_size!r}")


def _plan(
    estimator,
    measurements,
    inputs,
    x0,
    P0,
    theta0,
    P_theta0,
    key,
    return_covariances,
    chunk_size,
    progress,
    devices,
    strategy=None,
    smooth=False,
) -> _Plan:
    ys, us, x0, P0, th0, Pth0, keys = _checked_data(estimator, measurements, inputs, x0, P0,
                                                    theta0, P_theta0, key)
    _check_options(return_covariances, progress, chunk_size)
    R, T, _ = ys.shape
    nx = int(estimator.nx)

    method = _smooth_method(estimator, smooth)
    devs = tuple(execution.resolve_devices(devices))
    if len(set(devs)) != len(devs):  # a mesh of repeated devices fails deep inside JAX
        raise ValueError(f"devices: expected each device at most once, got {list(devs)}")
    n_dev = len(devs)
    strat = execution.resolve(strategy, devs[0])
    numbers = _state_numbers(estimator, x0, P0, th0, Pth0, keys)
    per_run_bytes, result_bytes = _per_run_bytes(estimator, ys, numbers, bool(return_covariances))
    if method is not None:  # a smoother keeps the filter's states and its cross-covariances
        per_run_bytes += 3 * T * 8 * numbers
        result_bytes += T * 8 * nx * nx if return_covariances else 0
    execution.check_fits(per_run_bytes, R * result_bytes, devs[0])
    block = execution.block_size(strat, numbers)
    if chunk_size is None:
        chunk_size = execution.chunk_runs(strat, per_run_bytes, T, numbers)
    # Balance the chunks and make each a multiple of the device count.
    chunk = balanced_blocks(R, int(chunk_size))[1]
    chunk = math.ceil(chunk / n_dev) * n_dev
    n_chunks = math.ceil(R / chunk)
    mesh = Mesh(np.array(devs), (_AXIS,)) if n_dev > 1 else None
    spans = mesh is not None and mesh.is_multi_process

    dtype = np.result_type(*(a for a in (ys, us, x0, P0, th0, Pth0) if a is not None))
    arrays = tuple(
        None if a is None else a.astype(dtype, copy=False) for a in (ys, us, x0, P0, th0, Pth0)
    )
    per_run = (True, us.ndim == 3, x0.ndim == 2, P0.ndim == 3)
    per_run += (th0 is not None and th0.ndim == 2, Pth0 is not None and Pth0.ndim == 3)
    plan = _Plan(
        estimator, arrays, per_run, keys, R, chunk, n_chunks, bool(return_covariances), devs, mesh,
        progress, spans, block, strat, method,
    )
    if spans:
        _check_same_study(plan)
    return plan


def _smooth_method(estimator, smooth) -> str | None:
    """``run``'s ``smooth``: False/None (filter only), True (the filter's own RTS smoother) or
    a method of :data:`vehjax.smoothing.METHODS`; ValueError naming ``smooth`` otherwise."""
    if smooth is None or (isinstance(smooth, (bool, np.bool_)) and not smooth):
        return None
    if not isinstance(smooth, (bool, np.bool_, str)):
        raise ValueError(f"smooth: expected True, False or one of {smoothing.METHODS}, got "
                         f"{smooth!r}")
    try:
        return smoothing.check_options(estimator, None if smooth is True else smooth)[0]
    except ValueError as err:
        raise ValueError(f"smooth: {err}") from None


def _digest(plan: _Plan) -> np.ndarray:
    """What must be equal in every process of a multi-process study (shapes, chunking, devices,
    the data and the keys; of the estimator only its name and sizes), hashed: 8 uint32 words."""
    h = hashlib.sha256(str(plan.estimator.name).encode())
    nums = [plan.R, plan.chunk, plan.n_chunks, plan.return_cov, plan.estimator.nx,
            len(plan.estimator.param_names), *(d.id for d in plan.devices)]
    h.update(np.array(nums, np.int64).tobytes())
    data = list(plan.arrays)
    if plan.keys is not None:
        data.append(np.asarray(jax.random.key_data(plan.keys)))
    for a in data:
        if a is None:
            h.update(b"None")
            continue
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(memoryview(a).cast("B"))
    return np.frombuffer(h.digest(), np.uint32)


def _check_same_study(plan: _Plan) -> None:
    """Every process must call ``run`` with the same arguments (SPMD); a process whose chunks
    differ would wait for the others forever, one whose data differ would be silently mixed.

    Each device of the mesh gets its process's digest; one all-gather brings all to every
    process.
    """
    mine = _digest(plan)
    n = len(plan.devices)
    digests = jax.make_array_from_callback(
        (n, mine.size), NamedSharding(plan.mesh, PartitionSpec(_AXIS)),
        lambda index: np.broadcast_to(mine, (n, mine.size))[index],
    )
    every = np.asarray(_replicate(digests, NamedSharding(plan.mesh, PartitionSpec())))
    if not np.all(every == mine[None]):
        raise ValueError(
            f"vehjax.run under jax.distributed ({jax.process_count()} processes): every process "
            f"must call it with the same arguments (measurements, inputs, x0, P0, theta0, "
            f"P_theta0, key, chunk_size, return_covariances, devices); process "
            f"{jax.process_index()} found them to differ between processes"
        )


@partial(jax.jit, static_argnums=1)
def _replicate(a, sharding):
    return jax.lax.with_sharding_constraint(a, sharding)


# ----------------------------------------------------------------------------------------------
# Execution


def _global_array(a, sharding):
    """A global array over the processes' devices from ``a``, which every process holds whole:
    each process places the slices of its own devices."""
    return jax.make_array_from_callback(a.shape, sharding, lambda index: a[index])


def _chunk_args(plan: _Plan, i: int):
    """Device-placed arguments of chunk ``i`` (padded with copies of the last run)."""
    start, stop = i * plan.chunk, min((i + 1) * plan.chunk, plan.R)
    # a full chunk is a slice (a view, no copy); the last one is padded with its last run
    idx = (slice(start, stop) if stop - start == plan.chunk
           else np.minimum(np.arange(start, start + plan.chunk), stop - 1))
    if plan.spans_processes:
        split = NamedSharding(plan.mesh, PartitionSpec(_AXIS))
        whole = NamedSharding(plan.mesh, PartitionSpec())
        args = [
            None if a is None else _global_array(a[idx] if r else a, split if r else whole)
            for a, r in zip(plan.arrays, plan.per_run)
        ]
        keys = None if plan.keys is None else _global_array(plan.keys[idx], split)
        return (*args, keys), stop - start
    if plan.mesh is not None:
        split = NamedSharding(plan.mesh, PartitionSpec(_AXIS))
        whole = NamedSharding(plan.mesh, PartitionSpec())
    else:
        split = whole = plan.devices[0]
    args = []
    for a, r in zip(plan.arrays, plan.per_run):
        if a is None:
            args.append(None)
        else:
            args.append(jax.device_put(a[idx] if r else a, split if r else whole))
    keys = None if plan.keys is None else jax.device_put(plan.keys[idx], split)
    return (*args, keys), stop - start


def _call_args(plan: _Plan, i: int):
    args, n = _chunk_args(plan, i)
    return (plan.estimator, *args, plan.return_cov, plan.mesh, plan.block, plan.strategy,
            plan.smooth), n


def _bar(n_chunks: int, n_runs: int, enabled: bool) -> Progress:
    """The study's progress bar per chunk (:mod:`vehjax.runtime.progress`)."""
    return Progress(n_chunks, "vehjax.run", enabled, unit="chunk",
                    bar_format="{desc} [{bar:30}] chunk {n_fmt}/{total_fmt}{postfix}, "
                               "{elapsed}",  # tqdm puts ", " before a postfix
                    postfix=f"0/{n_runs} runs", first_text=_bar_text(0, n_chunks, 0, n_runs))


def _bar_text(chunks: int, n_chunks: int, runs: int, n_runs: int) -> str:
    return (f"vehjax.run [{text_bar(chunks, n_chunks)}] chunk {chunks}/{n_chunks}, "
            f"{runs}/{n_runs} runs")


def _execute(plan: _Plan, fn, progress) -> RunResult:
    show = plan.n_chunks > 1 if progress is None else bool(progress)
    if show and jax.process_count() > 1:
        show = jax.process_index() == 0  # one bar, process 0's
    bar = _bar(plan.n_chunks, plan.R, show)
    to_host = plan.strategy is None or plan.strategy.results_to_host
    parts = []
    pending = None  # (device outputs, n valid); the next chunk is dispatched before fetching
    done = 0
    for i in range(plan.n_chunks + 1):
        nxt = None
        if i < plan.n_chunks:
            args, n = _call_args(plan, i)
            nxt = (fn(*args), n)
        if pending is not None:
            out, n = pending
            parts.append(tuple(None if a is None else (np.asarray(a)[:n] if to_host else a[:n])
                               for a in out))
            done += n
            bar.update(len(parts), f"{done}/{plan.R} runs",
                       _bar_text(len(parts), plan.n_chunks, done, plan.R))
        pending = nxt

    def cat(k):  # np.array copies: writable results, device buffers released
        if parts[0][k] is None:
            return None
        if not to_host:  # stays on the device (strategy.results_to_host False)
            return parts[0][k] if len(parts) == 1 else jnp.concatenate([q[k] for q in parts])
        return np.array(parts[0][k]) if len(parts) == 1 else np.concatenate([q[k] for q in parts])

    states, covs, params, pcov, ll, nis, n_obs, div, div_at, at_b, cross = (cat(k)
                                                                              for k in range(11))
    name = plan.estimator.name + ("" if plan.smooth is None else f" ({plan.smooth} smoothed)")
    return RunResult(states, covs, params, pcov, ll, nis, n_obs, div, div_at, name,
                     tuple(plan.estimator.param_names), at_bound=at_b, cross_covariances=cross)


def run(
    estimator: Estimator,
    measurements,
    inputs,
    *,
    x0,
    P0,
    theta0=None,
    P_theta0=None,
    key=None,
    return_covariances: bool = False,
    chunk_size: int | None = None,
    progress: bool | None = None,
    devices: Sequence | bool | None = None,
    compiler_options: dict | None = None,
    strategy: execution.Strategy | str | None = None,
    smooth: bool | str = False,
) -> RunResult:
    """Run ``estimator`` over R runs of T steps in one jitted call per chunk of runs.

    Args:
        estimator: a :class:`vehjax.filters.Estimator`.
        measurements: (R, T, ny); NaN components are missing (every filter skips them); +-inf
            is refused. A single run is (1, T, ny), or use :func:`vehjax.filter`: 2-D arrays
            are refused rather than guessed.
        inputs: (T, nu) shared by all runs, or (R, T, nu); None when the model has no inputs.
        x0: state before the first step, (nx,) shared or (R, nx) per run.
        P0: its covariance, (nx, nx) or (R, nx, nx), symmetric positive definite, or (nx,)
            variances (as Q and R in the builders).
        theta0: initial parameter estimate, (p,) or (R, p), for filters that estimate
            ``estimator.param_names``; for a state-only filter built on a model (its
            ``n_theta``), (np,) or (R, np) replaces the model's parameters.
        P_theta0: its covariance, (p, p) or (R, p, p).
        key: PRNG key, required when ``estimator.needs_key``; run r gets
            ``jax.random.split(key, R)[r]``.
        return_covariances: also return ``covariances`` and ``params_cov`` (R*T*nx*nx numbers).
        chunk_size: at most this many runs per jitted call, rounded up to a multiple of the
            device count (chunks are balanced and the last is padded to the common size).
            Default: as many as keep a chunk's outputs and the filters' working memory (their
            state from ``init`` times the temporaries of a step, so particles and sigma points
            count) near 512 MiB, and its work near 2e9 state numbers x steps, so that a long
            study runs in several chunks and shows its progress.
        progress: progress bar per chunk (tqdm's, which renders in Jupyter, when installed;
            else a text line on stderr); default shown when there are several chunks.
        devices: None shards runs over all ``jax.devices()``; False uses the default device only;
            or a sequence of devices. Under ``jax.distributed`` (see the module docstring):
            None shards over the devices of all processes and returns all runs in every
            process; False runs the whole study in each process on its first local device; a
            sequence is all this process's devices, or includes devices of every process and
            is the same in every process.
        compiler_options: XLA options for compiling this study, e.g.
            ``{"xla_backend_optimization_level": 1}``, on top of the strategy's own (these
            override them name by name). A compiled study is reused by the next call with the
            same estimator object, options and shapes. Level 1 helps a particle filter on
            :class:`~vehjax.models.SevenDOF` on CPU, whose step LLVM at level 3 takes over 10
            minutes to compile (``vehjax reproduce consistency`` passes it).
        strategy: how the study executes on its platform (:mod:`vehjax.execution`: chunk
            budget, blocking of runs, runs-last step, XLA options, trigonometric substitutes,
            results on the host or the device): None for the rules of the platform of the
            first device used, ``"cpu"``/``"gpu"``/``"tpu"`` for that platform's, or a
            :class:`vehjax.execution.Strategy`. Results do not depend on it beyond rounding.
        smooth: False (filter), True (each run smoothed by the filter's own RTS smoother,
            :func:`vehjax.smooth`), or ``"rts"``, ``"ieks"``, ``"ipls"``: then ``states``,
            ``covariances``, ``params`` and ``params_cov`` are the smoothed ones, ``loglik``
            the filter's (the linearised model's for the iterated smoothers), ``nis`` and
            ``n_obs`` the filter's, ``cross_covariances`` Cov(x_t, x_t+1 | y_1:T) (with
            ``return_covariances``), and a run whose filter or smoother fails is ``diverged``
            (``diverged_at`` 0 when only the smoother failed). Gaussian filters with a smoother
            (``Estimator.smoother``); particle smoothers run one run at a time
            (:func:`vehjax.smooth`).

    Returns:
        :class:`RunResult` of numpy arrays (jax arrays on the device when the strategy's
        ``results_to_host`` is False). All inputs are cast to their common floating dtype
        (pass every array as float32 for a single-precision study).

    Raises:
        ValueError: naming the argument, for wrong shapes, non-finite inputs/x0/P0, a P0 that is
            not symmetric positive definite, a missing key or theta0, a theta0 outside the
            estimator's parameter domains (``Estimator.bounds``) or, for a state-only
            filter, the model's (``Estimator.theta_domains``), compiler_options that are
            not a dict of option names to values, an unknown strategy, a ``smooth`` the
            estimator has no smoother for, a study whose one run
            cannot fit the device's memory or whose results cannot fit the host's (with the
            estimate and the limit), before anything is traced; options XLA does not take,
            when the study is compiled;
            under ``jax.distributed``, in every process, when the processes' arguments differ.

    Under ``jax.distributed`` call it in every process with the same arguments::

        jax.distributed.initialize(coordinator_address, num_processes, process_id)
        out = vehjax.run(est, ys, us, x0=x0, P0=P0, key=jax.random.key(0))  # all runs, each
    """
    execution.check_options(compiler_options)
    plan = _plan(
        estimator, measurements, inputs, x0, P0, theta0, P_theta0, key, return_covariances,
        chunk_size, progress, devices, strategy, smooth,
    )
    options = execution.compiler_options(plan.strategy, estimator.workload, compiler_options)
    if options is None:
        return _execute(plan, _study, progress)
    return _execute(plan, _compile(plan, options, cache=True), progress)


_COMPILED: dict = {}  # (estimator id, options, signature) -> (estimator, compiled study)
_COMPILED_MAX = 16


def _compile(plan: _Plan, options: dict | None, cache: bool = False):
    """The study's chunk function compiled for ``plan``'s first chunk (all chunks have its
    shapes), with XLA ``options``. ``cache``: reuse (and keep) the compiled study of the same
    estimator object, options and argument shapes, as jit's cache does without options."""
    args, _ = _call_args(plan, 0)
    leaves, tree = jax.tree.flatten(args[1:])
    sig = (tree, tuple((np.shape(a), str(a.dtype)) if hasattr(a, "dtype") else a
                       for a in leaves))
    key = (id(plan.estimator), tuple(sorted((options or {}).items())), sig)
    hit = _COMPILED.get(key) if cache else None
    if hit is not None and hit[0] is plan.estimator:
        return hit[1]
    try:
        compiled = _study.lower(*args).compile(compiler_options=options)
    except jax.errors.JaxRuntimeError as err:
        if options and ("compile option" in str(err) or "setting option" in str(err)):
            raise ValueError(f"compiler_options: {err}") from None
        raise
    if cache:
        if len(_COMPILED) >= _COMPILED_MAX:
            _COMPILED.pop(next(iter(_COMPILED)))
        _COMPILED[key] = (plan.estimator, compiled)
    return compiled


class CompiledRun:
    """A study whose chunk function is compiled ahead of time; call it to execute.

    A call's time covers the whole study as ``run`` does it: moving each chunk's data to the
    device, executing, and bringing the results back to host memory.

    Attributes:
        compile_seconds: wall time spent tracing, lowering and compiling, s.
        chunk_size: runs per compiled call; n_chunks: number of calls per execution.
    """

    def __init__(self, plan: _Plan, compiled, compile_seconds: float):
        self._plan, self._compiled = plan, compiled
        self.compile_seconds = compile_seconds
        self.chunk_size, self.n_chunks = plan.chunk, plan.n_chunks

    def __call__(self, *args, progress: bool | None = None) -> RunResult:
        """Execute the whole study (all chunks) and return its :class:`RunResult`.

        The study is the one compiled, with its own data: new measurements need a new
        :func:`compile_run` (or :func:`run`). ``progress``: keyword only, None (as compiled),
        True or False."""
        if args:
            raise TypeError(
                "CompiledRun: a compiled study runs with the data it was compiled with and takes "
                f"no positional arguments (got {len(args)}); for new measurements call "
                "vehjax.compile_run(...) or vehjax.run(...) again; progress is keyword-only")
        _check_progress(progress)
        progress = self._plan.progress if progress is None else progress
        return _execute(self._plan, self._compiled, progress)


def compile_run(
    estimator: Estimator,
    measurements,
    inputs,
    *,
    x0,
    P0,
    theta0=None,
    P_theta0=None,
    key=None,
    return_covariances: bool = False,
    chunk_size: int | None = None,
    progress: bool | None = None,
    devices: Sequence | bool | None = None,
    compiler_options: dict | None = None,
    strategy: execution.Strategy | str | None = None,
    smooth: bool | str = False,
) -> CompiledRun:
    """Validate and compile a study without running it, for timing compilation apart.

    Same arguments as :func:`run`. ``compile_run(...)()`` returns what ``run(...)`` returns,
    under ``jax.distributed`` too: call both in every process with the same arguments. The
    prepared study holds its own copy of the arrays: calling it again repeats the same study.
    """
    execution.check_options(compiler_options)
    plan = _plan(
        estimator, measurements, inputs, x0, P0, theta0, P_theta0, key, return_covariances,
        chunk_size, progress, devices, strategy, smooth,
    )
    options = execution.compiler_options(plan.strategy, estimator.workload, compiler_options)
    # its own copy of the data: "call again to repeat" repeats this study, whatever the
    # caller writes into its arrays afterwards
    plan = plan._replace(arrays=tuple(None if a is None else np.array(a, copy=True)
                                      for a in plan.arrays))
    t0 = time.perf_counter()
    compiled = _compile(plan, options)
    return CompiledRun(plan, compiled, time.perf_counter() - t0)
