"""A planned study executed chunk by chunk: each chunk's call dispatched before the previous
one's results are fetched, the results brought to host memory (or kept on the device, as the
strategy says) and joined into one :class:`vehjax.RunResult`, with a progress bar per chunk;
and the chunk function compiled ahead of time, with XLA options.

::

    out = execute(plan, fn, progress)            # fn: the jitted chunk function
    compiled = compile_chunks(plan, fn, options, cache=True)
    out = execute(plan, compiled, progress)

``fn(estimator, ys, us, x0, P0, th0, Pth0, keys, return_cov, mesh, block, strategy, smooth)``
computes one chunk (``vehjax.run``'s traced study) and returns its 11 outputs, leading axis the
chunk's runs. A compiled study is kept in vehjax's one cache of compiled programs
(:func:`vehjax.runtime.eager.cached`), keyed by the estimator object, the options and the
argument shapes, as jit's own cache is without options.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..result import RunResult
from ..runtime import eager
from ..runtime.progress import Progress, text_bar
from .plan import Plan
from .shard import chunk_args, chunk_shapes

__all__ = ["call_args", "execute", "compile_chunks"]


def _with_options(plan: Plan, arrays) -> tuple:
    """The chunk function's arguments: the estimator, a chunk's ``arrays`` (or their shapes),
    the plan's options."""
    return (plan.estimator, *arrays, plan.return_cov, plan.mesh, plan.block, plan.strategy,
            plan.smooth)


def call_args(plan: Plan, i: int):
    """(the chunk function's arguments for chunk ``i``, its number of real runs)."""
    args, n = chunk_args(plan, i)
    return _with_options(plan, args), n


def _bar(n_chunks: int, n_runs: int, enabled: bool) -> Progress:
    """The study's progress bar per chunk (:mod:`vehjax.runtime.progress`)."""
    return Progress(n_chunks, "vehjax.run", enabled, unit="chunk",
                    bar_format="{desc} [{bar:30}] chunk {n_fmt}/{total_fmt}{postfix}, "
                               "{elapsed}",  # tqdm puts ", " before a postfix
                    postfix=f"0/{n_runs} runs", first_text=_bar_text(0, n_chunks, 0, n_runs))


def _bar_text(chunks: int, n_chunks: int, runs: int, n_runs: int) -> str:
    return (f"vehjax.run [{text_bar(chunks, n_chunks)}] chunk {chunks}/{n_chunks}, "
            f"{runs}/{n_runs} runs")


def execute(plan: Plan, fn, progress) -> RunResult:
    """Every chunk of ``plan`` through ``fn``; the study's :class:`RunResult`. ``progress``:
    None (a bar when there are several chunks), True or False; under ``jax.distributed`` the
    bar shows on process 0 only."""
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
            args, n = call_args(plan, i)
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
    name = plan.estimator.name + ("" if plan.smooth is None
                                  else f" ({plan.smooth.name} smoothed)")
    return RunResult(states, covs, params, pcov, ll, nis, n_obs, div, div_at, name,
                     tuple(plan.estimator.param_names), at_bound=at_b, cross_covariances=cross)


def compile_chunks(plan: Plan, fn, options: dict | None, cache: bool = False):
    """The chunk function ``fn`` (jitted) compiled for ``plan``'s first chunk (all chunks have
    its shapes), with XLA ``options``. ``cache``: reuse (and keep) the compiled study of the
    same estimator object, options and argument shapes (:func:`vehjax.runtime.eager.cached`).
    ValueError naming ``compiler_options`` for an option XLA does not take."""
    def make():
        args, _ = call_args(plan, 0)
        try:
            return fn.lower(*args).compile(compiler_options=options)
        except jax.errors.JaxRuntimeError as err:
            if options and ("compile option" in str(err) or "setting option" in str(err)):
                raise ValueError(f"compiler_options: {err}") from None
            raise

    if not cache:
        return make()
    # the key from the chunk's shapes: nothing placed on a device for a study compiled before
    leaves, tree = jax.tree.flatten(_with_options(plan, chunk_shapes(plan))[1:])
    sig = (tree, tuple((np.shape(a), str(a.dtype)) if hasattr(a, "dtype") else a
                       for a in leaves))
    return eager.cached((plan.estimator,), (fn, tuple(sorted((options or {}).items())), sig),
                        make)
