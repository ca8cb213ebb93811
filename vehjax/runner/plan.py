"""A study's plan: its checked arguments, the chunks of runs it executes in, the blocking of
runs inside a chunk, its devices and mesh, and the memory checks, all before anything is traced.

::

    p = plan(est, ys, us, x0, P0, theta0, P_theta0, key, return_covariances, progress,
             execution, smooth)            # vehjax.run's arguments (execution: an Execution)
    p.chunk, p.n_chunks, p.block        # runs per jitted call, calls, runs side by side

The arguments are checked by :func:`vehjax.engine.check_arguments` (the one check every entry
point shares) and the options here. Large studies are split into balanced chunks of runs
(:func:`balanced_blocks`; each a multiple of the device count, the last padded), each one jitted
call of the same shapes, so that device memory stays bounded and a long study shows its
progress; the chunk budget, the blocking and whether the study fits at all are
:mod:`vehjax.execution`'s rules, from the estimate of what one run holds
(:func:`per_run_bytes`).
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import jax
import numpy as np
from jax.sharding import Mesh

from .. import engine, smoothing, validation
from ..smoothers import methods
from .. import execution as platform
from ..execution import Execution
from ..filters.base import Estimator
from ..runtime import eager
from .shard import AXIS, check_same_study

__all__ = ["Plan", "plan", "balanced_blocks", "check_progress", "STATE_TEMPORARIES"]

#: A filter step holds temporaries of about this many times its carried state (particles through
#: the model, predicted measurements, resampled copies).
STATE_TEMPORARIES = 16


class Plan(NamedTuple):
    """A checked study and how it executes (:func:`plan`)."""

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
    strategy: platform.Strategy | None = None  # how it executes (vehjax.execution)
    smooth: Any = None  # the Gaussian smoothing method's record (vehjax.smoothers), or None


def balanced_blocks(runs: int, block: int) -> tuple[int, int]:
    """(number of blocks, runs per block) for ``runs`` runs in blocks of at most ``block``:
    as few blocks as that allows, as even as they can be (the chunks of a study and the
    blocks of runs inside a chunk)."""
    n_blocks = -(-runs // block)
    return n_blocks, -(-runs // n_blocks)


def _state_numbers(estimator, x0, P0, th0, Pth0, keys) -> int:
    """How many numbers the filter carries for one run (its state from ``init``), found by
    ``jax.eval_shape`` once per estimator and argument shapes (kept with the compiled studies,
    :func:`vehjax.runtime.eager.cached`: a repeated study does not trace ``init`` again)."""
    def first(a, per_run_ndim):
        return None if a is None else (a[0] if a.ndim == per_run_ndim else a)

    args = (first(x0, 2), first(P0, 3), first(th0, 2), first(Pth0, 3),
            None if keys is None else keys[0])
    sig = tuple(None if a is None else (np.shape(a), str(a.dtype)) for a in args)

    def count():
        state = jax.eval_shape(estimator.init, *args)
        return sum(int(np.prod(a.shape)) for a in jax.tree.leaves(state))

    return eager.cached((estimator,), ("state numbers", sig), count)


def per_run_bytes(estimator, ys, state_numbers: int, return_cov: bool) -> tuple[int, int]:
    """(bytes one run holds on the device: its outputs plus what the filter holds, its state
    from ``init`` times the temporaries of a step; bytes of one run's results on the host)."""
    _, T, _ = ys.shape
    nx, p = estimator.nx, len(estimator.param_names)
    itemsize = np.dtype(ys.dtype).itemsize
    out_bytes = T * itemsize * (nx + p + 4 + (nx * nx + p * p if return_cov else 0))
    state_bytes = 8 * state_numbers  # at most float64 (typed PRNG keys have no numpy dtype)
    return out_bytes + STATE_TEMPORARIES * state_bytes, out_bytes


def check_progress(progress) -> None:
    """ValueError naming ``progress`` unless it is None, True or False."""
    validation.flag("progress", progress, allow_none=True)


def _check_options(return_covariances, progress) -> None:
    """ValueError naming the option unless ``return_covariances`` is a bool and ``progress``
    None or a bool (the fields of :class:`vehjax.execution.Execution` check themselves)."""
    validation.flag("return_covariances", return_covariances)
    check_progress(progress)


def _smooth_method(estimator, smooth):
    """``run``'s ``smooth`` as a Gaussian smoother's record (:mod:`vehjax.smoothers.methods`),
    or None: False/None (filter only), True (the filter's own RTS smoother), a method's name or
    record (RTS, IEKS, IPLS), resolved and checked as :func:`vehjax.smooth` resolves and checks
    its ``method`` (:func:`vehjax.smoothing.check_options`). ValueError naming ``smooth``
    otherwise, and for a particle smoother (run smooths no particle filter's study) and an
    iterated smoother's ``initial`` (one run's start, :func:`vehjax.smooth`'s)."""
    if smooth is None or (isinstance(smooth, (bool, np.bool_)) and not smooth):
        return None
    if not isinstance(smooth, (bool, np.bool_, str) + methods.GAUSSIAN + methods.PARTICLE):
        raise ValueError(f"smooth: expected True, False, one of {smoothing.METHODS} or a record "
                         f"vehjax.smoothers.RTS/IEKS/IPLS(...), got {smooth!r}")
    try:
        rec = methods.record(None if smooth is True else smooth)
        if isinstance(rec, methods.PARTICLE):
            raise ValueError(
                f"{type(rec).__name__} is a particle smoother, which vehjax.run does not run "
                f"(it smooths a study with the Gaussian smoothers RTS, IEKS, IPLS); smooth a "
                f"particle filter's runs one at a time with vehjax.smooth(..., method=...)")
        rec = smoothing.check_options(estimator, rec)
    except ValueError as err:
        raise ValueError(f"smooth: {err}") from None
    if getattr(rec, "initial", None) is not None:
        raise ValueError("smooth.initial: an iterated smoother's start is one run's; vehjax.run "
                         "smooths every run from its filter's own moments: give initial to "
                         "vehjax.smooth, run by run")
    return rec


def plan(estimator, measurements, inputs, x0, P0, theta0, P_theta0, key, return_covariances,
         progress, execution=None, smooth=False) -> Plan:
    """The :class:`Plan` of a study of ``vehjax.run``'s arguments (its one signature; of
    ``execution``, a :class:`vehjax.Execution` or None, the ``compiler_options`` are
    ``run``'s to apply), checked (ValueError naming the argument) before anything is traced;
    under ``jax.distributed`` also checked to be the same in every process
    (:func:`vehjax.runner.shard.check_same_study`)."""
    ys, us, x0, P0, th0, Pth0, keys = engine.check_arguments(
        estimator, measurements, inputs, x0, P0, theta0, P_theta0, key, study=True)
    _check_options(return_covariances, progress)
    ex = validation.record("execution", execution, Execution)
    R, T, _ = ys.shape
    nx = int(estimator.nx)

    method = _smooth_method(estimator, smooth)
    devs = tuple(platform.resolve_devices(ex.devices))
    n_dev = len(devs)
    strat = platform.resolve(ex.strategy, devs[0])
    numbers = _state_numbers(estimator, x0, P0, th0, Pth0, keys)
    run_bytes, result_bytes = per_run_bytes(estimator, ys, numbers, bool(return_covariances))
    if method is not None:  # a smoother keeps the filter's states and its cross-covariances
        run_bytes += 3 * T * 8 * numbers
        result_bytes += T * 8 * nx * nx if return_covariances else 0
    platform.check_fits(run_bytes, R * result_bytes, devs[0])
    block = platform.block_size(strat, numbers)
    chunk_size = ex.chunk_size
    if chunk_size is None:
        chunk_size = platform.chunk_runs(strat, run_bytes, T, numbers)
    # Balance the chunks and make each a multiple of the device count.
    chunk = balanced_blocks(R, int(chunk_size))[1]
    chunk = math.ceil(chunk / n_dev) * n_dev
    n_chunks = math.ceil(R / chunk)
    mesh = Mesh(np.array(devs), (AXIS,)) if n_dev > 1 else None
    spans = mesh is not None and mesh.is_multi_process

    dtype = np.result_type(*(a for a in (ys, us, x0, P0, th0, Pth0) if a is not None))
    arrays = tuple(
        None if a is None else a.astype(dtype, copy=False) for a in (ys, us, x0, P0, th0, Pth0)
    )
    per_run = (True, us.ndim == 3, x0.ndim == 2, P0.ndim == 3)
    per_run += (th0 is not None and th0.ndim == 2, Pth0 is not None and Pth0.ndim == 3)
    p = Plan(
        estimator, arrays, per_run, keys, R, chunk, n_chunks, bool(return_covariances), devs, mesh,
        progress, spans, block, strat, method,
    )
    if spans:
        check_same_study(p)
    return p
