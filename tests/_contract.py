"""Properties of the Estimator contract (vehjax.filters.base) that every filter family's tests
check on their own filters.

``assert_batch_equals_step``: what ``vehjax.run`` computes for many runs at once - the
estimator's runs-last ``batch`` step where it has one, else ``jax.vmap`` of ``step`` - equals
``step`` applied run by run (the reference: one jitted per-run step in a Python loop over runs
and steps), leaf by leaf of every StepOutput and of the final states.

The two are different XLA programs (a batched scan against a per-run step), so they agree to a
tolerance, not bit for bit: ``rtol`` 1e-9 for the Gaussian filters (a few float64 rounding
errors through a few steps of small, well-conditioned algebra), :data:`DRAW_RTOL` for filters
that draw random numbers.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def _runs_first(tree):
    return jax.tree.map(lambda a: jnp.moveaxis(a, -1, 0), tree)


def _runs_last(tree):
    return jax.tree.map(lambda a: jnp.moveaxis(a, 0, -1), tree)


#: Relative tolerance between two programs of a filter that draws random numbers (``keys``).
#: vehjax's particle filters draw normals in float32 (:mod:`vehjax.runtime.prng`: Box-Muller with
#: float32 ``log``, ``sqrt`` and polynomial sine and cosine). Two XLA programs may contract
#: that arithmetic's multiply-adds differently or evaluate ``log`` by another routine, so one
#: draw agrees between them to a few float32 ulps (2^-23 = 1.2e-7 relative), not to float64's.
#: The filters' outputs are smooth functions of the draws with gains of order one on the small
#: test problems here (and no resampling decision of them lies within 1e-6 of its threshold):
#: 8 float32 ulps. Measured: 1.1e-9 (the marginalized PF's covariance entry, level 0 with fusion
#: emitters off, AMD EPYC), 3e-8 on a single draw; 1.8e-7 (a bootstrap PF's log-likelihood
#: term, a filter whose scan XLA compiles into one function against one it does not).
DRAW_RTOL = 8 * 2.0**-23


def _assert_trees_close(got, ref, rtol, atol, what, scaled=False):
    g_leaves, g_def = jax.tree.flatten(got)
    r_leaves, r_def = jax.tree.flatten(ref)
    assert g_def == r_def, f"{what}: pytree structure {g_def} != {r_def}"
    for i, (g, r) in enumerate(zip(g_leaves, r_leaves)):
        g, r = np.asarray(g), np.asarray(r)
        assert g.shape == r.shape, f"{what}, leaf {i}: shape {g.shape} != {r.shape}"
        if g.dtype.kind in "biu":
            np.testing.assert_array_equal(g, r, err_msg=f"{what}, leaf {i}")
        else:
            # scaled: an entry near zero (an off-diagonal covariance) carries the error of the
            # leaf's largest entries, so the absolute tolerance is relative to those
            tol = max(atol, rtol * float(np.max(np.abs(r), initial=0.0))) if scaled else atol
            np.testing.assert_allclose(g, r, rtol=rtol, atol=tol, err_msg=f"{what}, leaf {i}")


def assert_batch_equals_step(estimator, ys, us, x0, P0, theta0=None, P_theta0=None, keys=None,
                             rtol=None, atol=1e-12) -> str:
    """Assert that the many-runs form of ``estimator`` equals its ``step`` run by run.

    Args:
        estimator: a :class:`vehjax.filters.Estimator`.
        ys: (R, T, ny) measurements, NaN for missing components.
        us: (T, nu) inputs shared by the runs or (R, T, nu) per run.
        x0, P0: (R, nx) and (nx, nx): each run's prior (P0 shared).
        theta0, P_theta0: (R, p) / (p, p) or None, passed to ``init`` (P_theta0 shared).
        keys: (R,) PRNG keys for a filter that ``needs_key``, else None.
        rtol, atol: tolerances of the floating leaves (integer and bool leaves must be equal);
            ``rtol`` None: 1e-9, or :data:`DRAW_RTOL` with ``keys`` (then ``atol`` is at least
            ``rtol`` times the leaf's largest entry).

    Returns:
        "batch" when the runs-last ``batch`` step was compared, "vmap" when ``vmap(step)``
        was (the estimator has no ``batch``).
    """
    scaled = keys is not None
    if rtol is None:
        rtol = DRAW_RTOL if scaled else 1e-9
    ys, us = jnp.asarray(ys), jnp.asarray(us)
    R, T = ys.shape[:2]
    per_run_u = us.ndim == 3

    def init(r):
        th = None if theta0 is None else jnp.asarray(theta0[r])
        k = None if keys is None else keys[r]
        return estimator.init(jnp.asarray(x0[r]), jnp.asarray(P0), th, P_theta0, k)

    def u_at(r, t):
        return us[r, t] if per_run_u else us[t]

    # the reference: the per-run step, jitted once, run by run and step by step
    one_step = jax.jit(estimator.step)
    ref_states, ref_outs = [], []
    for r in range(R):
        s, outs = init(r), []
        for t in range(T):
            s, o = one_step(s, ys[r, t], u_at(r, t))
            outs.append(o)
        ref_states.append(s)
        ref_outs.append(jax.tree.map(lambda *a: jnp.stack(a), *outs))  # (T, ...)
    ref_state = jax.tree.map(lambda *a: jnp.stack(a), *ref_states)  # (R, ...)
    ref_out = jax.tree.map(lambda *a: jnp.stack(a), *ref_outs)  # (R, T, ...)

    state0 = jax.tree.map(lambda *a: jnp.stack(a), *[init(r) for r in range(R)])
    if estimator.batch is not None:
        form = "batch"
        dtype = jax.tree.leaves(ref_out)[0].dtype
        batch = estimator.batch(per_run_u, dtype, theta0 is None)
        u_rl = jnp.moveaxis(us, 0, -1) if per_run_u else us  # (T, nu, R) or (T, nu)

        @jax.jit
        def many(state0, ys, u_rl):
            def body(s, yu):
                return batch.step(s, *yu)

            s, outs = jax.lax.scan(body, _runs_last(state0),
                                   (jnp.moveaxis(ys, 0, -1), batch.prepare(u_rl)))
            return _runs_first(s), jax.tree.map(lambda a: jnp.moveaxis(a, -1, 0), outs)

        state, out = many(state0, ys, u_rl)
    else:
        form = "vmap"
        step = jax.vmap(estimator.step, in_axes=(0, 0, 0 if per_run_u else None))

        @jax.jit
        def many(state0, ys, us):
            def body(s, t):
                return step(s, ys[:, t], us[:, t] if per_run_u else us[t])

            s, outs = jax.lax.scan(body, state0, jnp.arange(T))
            return s, jax.tree.map(lambda a: jnp.moveaxis(a, 0, 1), outs)  # (R, T, ...)

        state, out = many(state0, ys, us)
    _assert_trees_close(out, ref_out, rtol, atol, f"{estimator.name} {form}: StepOutput", scaled)
    _assert_trees_close(state, ref_state, rtol, atol, f"{estimator.name} {form}: final state",
                        scaled)
    return form
