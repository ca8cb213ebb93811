"""The marginalized PF's one XLA tactic: materialise a stage of the per-particle algebra.

Why: the particles' algebra is written entry by entry (every matrix entry an (N,) vector), and
XLA on CPU fuses long chains of elementwise producers into every consumer and recomputes them
there (7x the operation count of one step). :func:`stage` passes its arrays through
:func:`vehjax.lib.entrywise.barrier`, a trivial while loop whose trip count XLA cannot know
at compile time, so each stage is computed once. The loop needs an int32 zero that the compiler
cannot see through; best one that is the same for every run of a study, so that the loop stays a
plain loop under ``vmap``: :func:`staged` sets it, from the step's input, for the duration of
one step's trace. Outside :func:`staged` (a function called on its own, e.g. in a test) the zero
comes from the staged arrays themselves. Values are never changed: the body multiplies by one.

The mathematics calls ``stage(...)`` on its intermediate results and takes no token: the tactic
lives here alone.
"""

from __future__ import annotations

import contextlib
import contextvars

import jax.numpy as jnp

from ...lib.entrywise import barrier

__all__ = ["stage", "staged"]

_TOKEN: contextvars.ContextVar = contextvars.ContextVar("vehjax_mpf_stage_token", default=None)


@contextlib.contextmanager
def staged(u):
    """Within: :func:`stage` uses ``u``'s opaque zero (0 unless u[0] is NaN; ``u`` the step's
    input, the same for every run of a study)."""
    token = _TOKEN.set((u[0] != u[0]).astype(jnp.int32))
    try:
        yield
    finally:
        _TOKEN.reset(token)


def stage(tree):
    """The array leaves of ``tree`` materialised (values unchanged; structural constants pass
    through)."""
    return barrier(tree, _TOKEN.get())
