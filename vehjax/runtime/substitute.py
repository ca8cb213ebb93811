"""Run any model function with vehjax's vectorisable sin, cos, tan, arctan and arctan2.

A user's own model written with ``jnp.sin``, ``jnp.cos``, ``jnp.arctan2``... traces to the
``sin``, ``cos``, ``tan``, ``atan``, ``atan2`` primitives, which XLA on CPU evaluates in float64
by one scalar library call per element and does not fuse into vectorised loops (see
:mod:`vehjax.lib.elementary`). :func:`fast_elementary` traces the function once per argument
signature, re-traces its jaxpr through an interpreter that binds every primitive as it is
except those five, which it replaces by the corresponding :mod:`vehjax.lib.elementary` function
(arithmetic and ``where`` only, 1-3 ulp from libm, derivatives by ``custom_jvp``), and
evaluates the rewritten jaxpr. Nested jaxprs are rewritten too: ``jit``/``closed_call`` bodies
are inlined (so that :func:`vehjax.runtime.hoist.split` sees their equations; a ``jit`` with shardings,
layouts, donation or compiler options is rewritten in place instead); ``cond`` branches,
``scan``/``while`` bodies, ``checkpoint`` bodies and the primal function of a user's
``custom_jvp``/``custom_vjp`` are rewritten in place. A user's custom derivative rules are kept
as written, so under differentiation such a function computes with ``jnp``'s functions (within
an ulp or two of the substituted primal). Everything else (``shard_map``, ``pallas_call``...)
is bound untouched.

Only float32 and float64 operands are substituted (float16, bfloat16 and complex keep XLA's
functions), and only where the primitive asks for no particular ``accuracy``. A function whose
trace has effects (callbacks, prints, ordered IO), or that cannot be traced, or that has nothing
to substitute, is called as it is.
"""

from __future__ import annotations

import functools
import warnings
from typing import Any, Callable, NamedTuple

import jax
import numpy as np
from jax import lax
from jax.extend.core import ClosedJaxpr, DropVar, Jaxpr, Literal, jaxpr_as_fun, jaxprs_in_params

from .. import execution
from ..lib import elementary
from .hoist import CALLS, call_body, inlinable_call



def _weak_convert(x, dtype):
    """``x`` as ``dtype`` with JAX's weak type (what a Python scalar operand has), by binding
    the public primitive ``lax.convert_element_type_p``."""
    return lax.convert_element_type_p.bind(x, new_dtype=dtype, weak_type=True, sharding=None)


@functools.cache
def _weak_types_restorable() -> bool:
    """Whether :func:`_weak_convert` works with this JAX (its primitive's parameters): probed
    abstractly on first use, not at import (importing vehjax starts no JAX backend). Without
    it weakly typed operands are not substituted."""
    try:
        jax.eval_shape(lambda a: _weak_convert(a, np.dtype(np.float32)),
                       jax.ShapeDtypeStruct((), np.float32))
        return True
    except TypeError:  # pragma: no cover - the primitive's parameters changed
        return False


_SUBSTITUTES: dict[Any, Callable] = {
    lax.sin_p: elementary.sin,
    lax.cos_p: elementary.cos,
    lax.tan_p: elementary.tan,
    lax.atan_p: elementary.arctan,
    lax.atan2_p: elementary.arctan2,
}
_FLOATS = (np.dtype(np.float32), np.dtype(np.float64))
#: Primitives whose nested jaxprs are rewritten in place (same params otherwise).
_NESTED = frozenset({"cond", "scan", "while", "remat2", "checkpoint", "custom_jvp_call",
                     "custom_vjp_call", "custom_vjp_call_jaxpr"}) | CALLS
_MARK = "_vehjax_fast_elementary"  # on a wrapper: the wrapper itself
_MEMO = "_vehjax_fast_elementary_wrapper"  # on a wrapped function: (its id, its wrapper)
_MAX_ENTRIES = 32


# ---------------------------------------------------------------------------------------------
# the jaxpr rewrite


def _substitutable(eqn) -> bool:
    if eqn.primitive not in _SUBSTITUTES or eqn.params.get("accuracy") is not None:
        return False
    avals = [v.aval for v in eqn.invars] + [v.aval for v in eqn.outvars]
    if not all(getattr(a, "dtype", None) in _FLOATS for a in avals):
        return False
    return _weak_types_restorable() or not any(getattr(a, "weak_type", False) for a in avals)


def _has_work(jaxpr: Jaxpr, memo: dict) -> bool:
    """Whether ``jaxpr`` holds a substitutable primitive, here or in a nested jaxpr we rewrite."""
    key = id(jaxpr)
    if key not in memo:
        memo[key] = False  # recursion guard
        memo[key] = any(
            _substitutable(eqn)
            or (eqn.primitive.name in _NESTED
                and any(_has_work(sub, memo) for sub in jaxprs_in_params(eqn.params)))
            for eqn in jaxpr.eqns
        )
    return memo[key]


def _like(out, aval):
    """``out`` with exactly ``aval``'s dtype and weak type."""
    if out.dtype != aval.dtype:
        out = lax.convert_element_type(out, aval.dtype)
    if getattr(aval, "weak_type", False) and not jax.typeof(out).weak_type:
        out = _weak_convert(out, aval.dtype)
    return out


def _specs(avals):
    return [jax.ShapeDtypeStruct(a.shape, a.dtype, weak_type=getattr(a, "weak_type", False))
            for a in avals]


def _same_types(old, new) -> bool:
    return len(old) == len(new) and all(
        a.shape == b.shape and a.dtype == b.dtype
        and getattr(a, "weak_type", False) == getattr(b, "weak_type", False)
        for a, b in zip(old, new))


def _rewrite_closed(closed: ClosedJaxpr, memo: dict) -> ClosedJaxpr:
    """``closed`` re-traced through the substituting interpreter; ``closed`` itself when there
    is nothing to substitute or the rewrite does not keep the types exactly."""
    key = ("closed", id(closed.jaxpr), tuple(map(id, closed.consts)))
    if key in memo:
        return memo[key][1]
    new = closed
    if _has_work(closed.jaxpr, memo):
        try:
            cand = jax.make_jaxpr(functools.partial(_interpret, closed.jaxpr, closed.consts, memo))(
                *_specs(closed.in_avals))
            if _same_types(closed.out_avals, cand.out_avals) and not cand.jaxpr.effects:
                new = cand
        except Exception:  # a structure we cannot re-trace: leave it as it is
            new = closed
    memo[key] = (closed, new)  # holding ``closed`` keeps the ids in the key from being reused
    return new


def _rewrite_param(value, memo: dict):
    if isinstance(value, ClosedJaxpr):
        return _rewrite_closed(value, memo)
    if isinstance(value, Jaxpr):
        if value.constvars:
            return value
        new = _rewrite_closed(ClosedJaxpr(value, ()), memo)
        return new.jaxpr if not new.consts else value
    if isinstance(value, tuple) and any(isinstance(v, (Jaxpr, ClosedJaxpr)) for v in value):
        return tuple(_rewrite_param(v, memo) for v in value)
    return value


def _apply(eqn, invals, memo: dict):
    prim = eqn.primitive
    if _substitutable(eqn):
        return _like(_SUBSTITUTES[prim](*invals), eqn.outvars[0].aval)
    if prim.name in _NESTED and any(_has_work(j, memo) for j in jaxprs_in_params(eqn.params)):
        if inlinable_call(eqn):
            return _interpret(*call_body(eqn), memo, *invals)
        params = {k: _rewrite_param(v, memo) for k, v in eqn.params.items()}
        return prim.bind(*invals, **prim.get_bind_params(params))
    return prim.bind(*invals, **prim.get_bind_params(eqn.params))


def _interpret(jaxpr: Jaxpr, consts, memo: dict, *args):
    """Evaluate ``jaxpr`` under the current trace, substituting the elementary functions."""
    env: dict = {}

    def read(v):
        return v.val if isinstance(v, Literal) else env[v]

    def write(v, val):
        if not isinstance(v, DropVar):
            env[v] = val

    for v, val in zip(jaxpr.constvars, consts):
        write(v, val)
    for v, val in zip(jaxpr.invars, args):
        write(v, val)
    for eqn in jaxpr.eqns:
        ctx = getattr(eqn, "ctx", None)
        with (ctx.manager if ctx is not None else _nullcontext()):
            out = _apply(eqn, [read(v) for v in eqn.invars], memo)
        if eqn.primitive.multiple_results:
            for v, val in zip(eqn.outvars, out):
                write(v, val)
        else:
            write(eqn.outvars[0], out)
    return [read(v) for v in jaxpr.outvars]


class _nullcontext:
    def __enter__(self):
        return None

    def __exit__(self, *exc):
        return False


def substitute_jaxpr(closed: ClosedJaxpr) -> ClosedJaxpr:
    """``closed`` with every float32/float64 sin, cos, tan, atan, atan2 (nested ones included,
    where rewritable) replaced by :mod:`vehjax.lib.elementary`'s; same input and output types.
    Returns ``closed`` itself when there is nothing to replace or it has effects."""
    if closed.jaxpr.effects:
        return closed
    return _rewrite_closed(closed, {})


# ---------------------------------------------------------------------------------------------
# the function transform


class _Entry(NamedTuple):
    passthrough: bool  # call the original function
    fun: Callable | None  # flat arrays -> flat outputs, under the current trace
    jitted: Callable | None  # the same, compiled, for concrete arguments
    out_tree: Any
    cacheable: bool


_PASS = _Entry(True, None, None, None, True)


def _is_dynamic(leaf) -> bool:
    return isinstance(leaf, (jax.Array, np.ndarray, np.generic, jax.core.Tracer)) or type(leaf) in (
        int, float, complex, bool)


def _build(fn, treedef, leaves, dyn_idx, avals) -> _Entry:
    template = [None if i in dyn_idx else leaf for i, leaf in enumerate(leaves)]

    def flat_fn(*dyn):
        full = list(template)
        for i, v in zip(dyn_idx, dyn):
            full[i] = v
        args, kwargs = jax.tree.unflatten(treedef, full)
        return fn(*args, **kwargs)

    try:
        closed, out_shape = jax.make_jaxpr(flat_fn, return_shape=True)(*_specs(avals))
    except Exception:  # not traceable (Python control flow on values...): call it as it is
        return _PASS
    cacheable = not any(isinstance(c, jax.core.Tracer) for c in closed.consts)
    if closed.jaxpr.effects or not _has_work(closed.jaxpr, {}):
        return _PASS._replace(cacheable=cacheable)
    try:
        new = substitute_jaxpr(closed)
    except Exception as err:  # pragma: no cover - a bug here must not break the user's model
        warnings.warn(f"fast_elementary: rewrite failed ({err!r}); using the function as it is")
        return _PASS._replace(cacheable=cacheable)
    if new is closed:
        return _PASS._replace(cacheable=cacheable)
    fun = jaxpr_as_fun(new)
    jitted = jax.jit(fun) if cacheable and not any(
        isinstance(c, jax.core.Tracer) for c in new.consts) else None
    return _Entry(False, fun, jitted, jax.tree.structure(out_shape), cacheable)


def fast_elementary(fn: Callable) -> Callable:
    """``fn`` evaluated with vehjax's vectorisable sin, cos, tan, arctan, arctan2.

    Args:
        fn: a pure, traceable function of arrays (pytrees of arrays; leaves that are not arrays
            or Python numbers are treated as static and must be hashable to be cached).

    Returns:
        ``fast(*args, **kwargs)``: what ``fn`` returns, same structure, shapes and dtypes, with
        every float32/float64 ``sin``, ``cos``, ``tan``, ``atan``, ``atan2`` primitive of its
        trace computed by :mod:`vehjax.lib.elementary` (within 1-3 ulp of libm, derivatives those
        of the true functions, see there). ``fast`` works under ``jit``, ``vmap``, ``grad`` and
        ``jacfwd``/``jacrev``. The rewritten jaxpr is cached per argument shapes and dtypes;
        called with concrete arrays it runs compiled (``jax.jit``), called with tracers it
        binds its equations into the caller's trace, so :func:`vehjax.runtime.hoist.split` and XLA
        see them as if written out.

    ``fn`` is called as it is (same results, bit for bit) when its trace has effects, when it
    cannot be traced, when it holds nothing to substitute (vehjax's built-in models), or when
    the execution strategy in force says not to substitute on its platform
    (:func:`vehjax.execution.current`; e.g. on a GPU).
    Wrapping is idempotent, and wrapping the same function twice gives the same wrapper.
    """
    if getattr(fn, _MARK, None) is fn:
        return fn
    memo = getattr(fn, _MEMO, None)  # (id of the function it belongs to, its wrapper)
    if isinstance(memo, tuple) and len(memo) == 2 and memo[0] == id(fn):
        return memo[1]
    cache: dict = {}

    @functools.wraps(fn)
    def fast(*args, **kwargs):
        if not execution.current().substitute_elementary:  # the platform's rule
            return fn(*args, **kwargs)
        leaves, treedef = jax.tree.flatten((args, kwargs))
        dyn_idx = tuple(i for i, leaf in enumerate(leaves) if _is_dynamic(leaf))
        avals = tuple(jax.typeof(leaves[i]) for i in dyn_idx)
        statics = tuple(leaf for i, leaf in enumerate(leaves) if i not in dyn_idx)
        key = (treedef, dyn_idx, avals, statics)
        try:
            entry = cache.get(key)
            hashable = True
        except TypeError:
            entry, hashable = None, False
        if entry is None:
            entry = _build(fn, treedef, leaves, dyn_idx, avals)
            if hashable and entry.cacheable:
                if len(cache) >= _MAX_ENTRIES:
                    cache.pop(next(iter(cache)))
                cache[key] = entry
        if entry.passthrough:
            return fn(*args, **kwargs)
        dyn = [leaves[i] for i in dyn_idx]
        if entry.jitted is not None and not any(isinstance(x, jax.core.Tracer) for x in dyn):
            flat = entry.jitted(*dyn)
        else:
            flat = entry.fun(*dyn)
        return jax.tree.unflatten(entry.out_tree, flat)

    setattr(fast, _MARK, fast)
    try:  # a reference cycle fn <-> fast, collected with fn
        setattr(fn, _MEMO, (id(fn), fast))
    except (AttributeError, TypeError):  # a bound method, a builtin: no memo
        pass
    return fast


__all__ = ["fast_elementary", "substitute_jaxpr"]
