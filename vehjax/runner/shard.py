"""A study's chunks placed on its devices: the runs of a chunk sharded over a 1-D mesh, across
processes under ``jax.distributed``, and the digest by which the processes check that they run
the same study.

::

    args, n = chunk_args(plan, i)     # chunk i's arguments on the plan's devices, n real runs
    check_same_study(plan)            # ValueError in every process when their arguments differ

One device: each chunk's arrays go to it. Several: the runs axis of every per-run array is
split over ``plan.mesh`` (axis :data:`AXIS`), the shared arrays replicated; no communication
between devices.

Past one machine (multi-controller JAX): every process holds the full host arrays and places on
its own devices only the runs they compute (``jax.make_array_from_callback``). Each chunk's
results are all-gathered over the mesh inside the jitted call, so that every process holds them
and brings them to host memory. Chunks, the padding of the last one and the device order are
computed from the arguments alone, hence the same in every process; before the first chunk
:func:`check_same_study` checks this with one small all-gather of a hash of the arguments
(:func:`digest`) and raises ValueError in every process when they differ (a process that does
not call ``run``, or fails before that check, leaves the others waiting). Processes may have
different numbers of local devices. On CPU the processes exchange data through gloo
(``jax_cpu_collectives_implementation``, JAX's default); ``jax_num_cpu_devices`` gives a
process several CPU devices.
"""

from __future__ import annotations

import hashlib
from functools import partial

import jax
import numpy as np
from jax.sharding import NamedSharding, PartitionSpec

__all__ = ["AXIS", "digest", "check_same_study", "chunk_args"]

#: The mesh axis the runs are sharded over.
AXIS = "runs"


def digest(plan) -> np.ndarray:
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


def check_same_study(plan) -> None:
    """Every process must call ``run`` with the same arguments (SPMD); a process whose chunks
    differ would wait for the others forever, one whose data differ would be silently mixed.

    Each device of the mesh gets its process's digest; one all-gather brings all to every
    process.
    """
    mine = digest(plan)
    n = len(plan.devices)
    digests = jax.make_array_from_callback(
        (n, mine.size), NamedSharding(plan.mesh, PartitionSpec(AXIS)),
        lambda index: np.broadcast_to(mine, (n, mine.size))[index],
    )
    every = np.asarray(_replicate(digests, NamedSharding(plan.mesh, PartitionSpec())))
    if not np.all(every == mine[None]):
        raise ValueError(
            f"vehjax.run under jax.distributed ({jax.process_count()} processes): every process "
            f"must call it with the same arguments (measurements, inputs, x0, P0, theta0, "
            f"P_theta0, key, return_covariances, execution); process "
            f"{jax.process_index()} found them to differ between processes"
        )


@partial(jax.jit, static_argnums=1)
def _replicate(a, sharding):
    return jax.lax.with_sharding_constraint(a, sharding)


def _global_array(a, sharding):
    """A global array over the processes' devices from ``a``, which every process holds whole:
    each process places the slices of its own devices."""
    return jax.make_array_from_callback(a.shape, sharding, lambda index: a[index])


def chunk_shapes(plan):
    """What :func:`chunk_args` gives for every chunk, as ``jax.ShapeDtypeStruct`` (nothing placed
    on a device): ((ys, us, x0, P0, th0, Pth0, keys) shapes and dtypes)."""
    def spec(a, per_run):
        shape = (plan.chunk,) + a.shape[1:] if per_run else a.shape
        return jax.ShapeDtypeStruct(shape, a.dtype)

    args = [None if a is None else spec(a, r) for a, r in zip(plan.arrays, plan.per_run)]
    return (*args, None if plan.keys is None else spec(plan.keys, True))


def chunk_args(plan, i: int):
    """Device-placed arguments of chunk ``i`` (padded with copies of the last run):
    ((ys, us, x0, P0, th0, Pth0, keys), number of real runs)."""
    start, stop = i * plan.chunk, min((i + 1) * plan.chunk, plan.R)
    # a full chunk is a slice (a view, no copy); the last one is padded with its last run
    idx = (slice(start, stop) if stop - start == plan.chunk
           else np.minimum(np.arange(start, start + plan.chunk), stop - 1))
    if plan.spans_processes:
        split = NamedSharding(plan.mesh, PartitionSpec(AXIS))
        whole = NamedSharding(plan.mesh, PartitionSpec())
        args = [
            None if a is None else _global_array(a[idx] if r else a, split if r else whole)
            for a, r in zip(plan.arrays, plan.per_run)
        ]
        keys = None if plan.keys is None else _global_array(plan.keys[idx], split)
        return (*args, keys), stop - start
    if plan.mesh is not None:
        split = NamedSharding(plan.mesh, PartitionSpec(AXIS))
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
