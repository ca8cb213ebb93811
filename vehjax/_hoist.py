"""Split a model function into the part that depends on the state and the part that does not.

A vehicle model evaluated at many points (sigma points, particles) with one input vector per
step computes some things from the input and the parameters alone: sin and cos of the steering
angle, the longitudinal tyre forces from the wheel slips. ``vmap`` leaves them unbatched, but
XLA on CPU fuses such scalar chains into every elementwise kernel that uses them and so
recomputes them for each point and each output component, a third to four fifths of a 3-DOF
model's time. :func:`split` traces the function once and partitions its equations: those that
need the state go to ``late``, all others to ``early``, whose results (the residuals) ``late``
takes as arguments. The caller evaluates ``early`` once per input vector (for a filter, over
the whole input sequence before the time loop) and ``late`` at every point.

The two functions compute exactly what the original does, operation for operation.
"""

from __future__ import annotations

from typing import Callable, NamedTuple, Sequence

import jax
from jax.extend.core import ClosedJaxpr, DebugInfo, Jaxpr, Var, jaxpr_as_fun


class Split(NamedTuple):
    """``fn(*args)`` as ``late(*late_args, *early(*early_args))``.

    Attributes:
        early: function of the arguments not marked ``late``, in order; returns a tuple of
            residual arrays.
        late: function of the arguments marked ``late``, in order, then the residuals; returns
            what ``fn`` returns.
        n_residuals: length of ``early``'s tuple (0 when nothing can be computed early).
    """

    early: Callable
    late: Callable
    n_residuals: int


def split(fn: Callable, args: Sequence, late: Sequence[bool]) -> Split:
    """Partition ``fn``'s computation by whether it depends on the arguments marked ``late``.

    Args:
        fn: a pure function of arrays (each argument one array), returning a pytree of arrays.
        args: example arguments (arrays or ``jax.ShapeDtypeStruct``), which fix shapes and
            dtypes.
        late: one flag per argument: True for the arguments that vary from point to point.

    A function with side effects is kept whole in ``late`` (``early`` then returns the
    early arguments unchanged), so the split never changes what is computed or how often.
    """
    late = tuple(bool(f) for f in late)
    if len(late) != len(args):
        raise ValueError(f"late: expected {len(args)} flags, got {len(late)}")
    closed, out_shape = jax.make_jaxpr(fn, return_shape=True)(*args)
    jaxpr, consts = closed.jaxpr, closed.consts
    out_tree = jax.tree.structure(out_shape)
    late_in = [v for v, f in zip(jaxpr.invars, late) if f]
    early_in = [v for v, f in zip(jaxpr.invars, late) if not f]

    if jaxpr.effects or any(e.effects for e in jaxpr.eqns):
        early_eqns, late_eqns, residuals = [], list(jaxpr.eqns), list(early_in)
    else:
        depends = set(late_in)
        early_eqns, late_eqns = [], []
        for eqn in jaxpr.eqns:
            if any(isinstance(v, Var) and v in depends for v in eqn.invars):
                late_eqns.append(eqn)
                depends.update(eqn.outvars)
            else:
                early_eqns.append(eqn)
        # Residuals: values computed early (or early arguments) that the late part reads.
        # Constants stay constants of the late part, so that XLA can fold them.
        consts_set = set(jaxpr.constvars)
        residuals, seen = [], set()
        reads = [v for e in late_eqns for v in e.invars] + list(jaxpr.outvars)
        for v in reads:
            if isinstance(v, Var) and v not in depends and v not in consts_set and v not in seen:
                residuals.append(v)
                seen.add(v)

    info = jaxpr.debug_info

    def debug(name):
        return DebugInfo(info.traced_for, f"{info.func_src_info} ({name})", None, None)

    early_jaxpr = Jaxpr(jaxpr.constvars, early_in, residuals, early_eqns,
                        debug_info=debug("early"))
    late_jaxpr = Jaxpr(jaxpr.constvars, late_in + residuals, jaxpr.outvars, late_eqns,
                       debug_info=debug("late"))
    early_fn = jaxpr_as_fun(ClosedJaxpr(early_jaxpr, consts))
    late_flat = jaxpr_as_fun(ClosedJaxpr(late_jaxpr, consts))

    def late_fn(*a):
        return jax.tree.unflatten(out_tree, late_flat(*a))

    return Split(lambda *a: tuple(early_fn(*a)), late_fn, len(residuals))

