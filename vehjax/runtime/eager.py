"""Eager calls of the single-run entry points compiled as one program, and vehjax's one cache
of compiled programs.

:func:`vehjax.filter` and :func:`vehjax.smooth` are pure, traceable functions, and users also
call them outside ``jax.jit``. Called eagerly, JAX dispatches each operation on its own: every
primitive is compiled for its shapes on first use and the time loop as a program of its own, so
a first eager call costs several times the compile of the same call under ``jit`` (on the CPU,
XLA's compile of many small programs dominates). :func:`call` therefore runs the traced function
under ``jax.jit`` when none of its arguments is a tracer, and traces it inline when one is (the
caller's own ``jit``, ``vmap`` or ``grad``): one rule, the same numbers as under the user's jit.

The cache (:func:`cached`, :data:`CACHE`) holds these jitted functions and the studies
``vehjax.run`` compiles ahead of time with XLA options: each entry is keyed by the identities
of the objects it was made for (the estimator; held by the entry, so that an identity is not
reused while the entry lives) and by the values that make it (static options, the argument
shapes); it keeps the ``CACHE_SIZE`` most recently used. A new estimator object is a new
compile, as it is under the user's own ``jax.jit(lambda ...: vehjax.filter(est, ...))``.
"""

from collections import OrderedDict
from functools import partial

import jax

__all__ = ["call", "cached", "CACHE", "CACHE_SIZE"]

CACHE_SIZE = 32
#: key -> (the objects held, the compiled function); the most recently used last.
CACHE: "OrderedDict[tuple, tuple]" = OrderedDict()


def cached(held: tuple, key: tuple, make):
    """What ``make()`` gives for ``(ids of held, *key)`` (a compiled function; or what a study's
    plan finds by tracing, :mod:`vehjax.runner.plan`): the cached one, else ``make()``, kept with
    ``held`` (LRU, at most ``CACHE_SIZE`` entries)."""
    key = (tuple(id(h) for h in held), *key)
    entry = CACHE.get(key)
    if entry is None:
        entry = (held, make())
        CACHE[key] = entry
        while len(CACHE) > CACHE_SIZE:
            CACHE.popitem(last=False)
    else:
        CACHE.move_to_end(key)
    return entry[1]


def _traced(args) -> bool:
    return any(isinstance(a, jax.core.Tracer) for a in jax.tree_util.tree_leaves(args))


def call(fn, held: tuple, static: dict, *args, **kwargs):
    """``fn(*held, *args, **static, **kwargs)``: inline when an argument in ``args`` or
    ``kwargs`` is a tracer, else through a ``jax.jit`` of it cached by ``fn``, the identities of
    the objects in ``held`` (e.g. the estimator) and the values of ``static`` (hashable
    options); ``args`` and ``kwargs`` are its traced arguments (arrays, None, pytrees)."""
    if _traced((args, kwargs)):
        return fn(*held, *args, **static, **kwargs)
    jitted = cached(held, (fn, tuple(sorted(static.items()))),
                    lambda: jax.jit(partial(fn, *held, **static)))
    return jitted(*args, **kwargs)
