"""The study runner behind :func:`vehjax.run` and :func:`vehjax.compile_run`: how a study of R
runs is scheduled, never what one run computes (that is :mod:`vehjax.engine`'s).

::

    p = plan.plan(est, ys, us, x0, P0, theta0, P_theta0, key, return_covariances,
                  progress, execution, smooth)       # checked, before any trace
    out = execute.execute(p, chunk_fn, progress)              # chunk by chunk, a RunResult

Modules:
    plan: a study's checked arguments, its chunks of runs, the blocking inside a chunk, its
        devices and mesh, the memory checks.
    shard: a chunk's arguments placed on the devices (sharded over a 1-D mesh, across
        processes under ``jax.distributed``) and the digest by which the processes check that
        they run the same study.
    batch: a chunk's runs computed side by side, traced: ``vmap`` of the one-run engine in
        blocks, the runs-last batched step, their smoothed forms.
    execute: the chunks executed, their results brought to the host and joined into one
        :class:`vehjax.RunResult` with a progress bar; the chunk function compiled ahead of
        time with XLA options, kept in vehjax's one cache of compiled programs
        (:mod:`vehjax.runtime.eager`).
"""

from . import batch, execute, plan, shard

__all__ = ["plan", "shard", "batch", "execute"]
