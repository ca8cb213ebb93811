"""vehjax.runtime.eager: eager calls of filter/smooth run as one compiled program, traced calls inline."""

import jax
import jax.numpy as jnp
import numpy as np

import vehjax as vj
from vehjax.runtime import eager

MODEL = vj.models.Model(
    transition=lambda x, u, th: jnp.array([x[0] + 0.1 * x[1], x[1] - 0.1 * jnp.sin(x[0]) + 0.1 * u[0]]),
    observe=lambda x, u, th: jnp.array([jnp.sin(x[0])]), dt=0.1, state_names=("a", "b"),
    input_names=("u",))


def _data(T=12):
    rng = np.random.default_rng(3)
    ys = rng.normal(size=(T, 1))
    ys[4, 0] = np.nan
    return ys, rng.normal(size=(T, 1))


def test_eager_filter_and_smooth_equal_the_users_jit_and_compile_once():
    ys, us = _data()
    est = vj.filters.ukf(MODEL, np.eye(2) * 0.01, np.eye(1) * 0.1)
    kw = dict(x0=[0.1, 0.0], P0=np.eye(2))
    eagerly = vj.filter(est, ys, us, **kw)
    jitted = jax.jit(lambda y: vj.filter(est, y, us, **kw))(ys)
    for a, b in zip(jax.tree.leaves(eagerly), jax.tree.leaves(jitted)):
        np.testing.assert_allclose(a, b, rtol=1e-13, atol=1e-15)
    sm = vj.smooth(est, ys, us, **kw)
    sm_j = jax.jit(lambda y: vj.smooth(est, y, us, **kw))(ys)
    np.testing.assert_allclose(sm.states, sm_j.states, rtol=1e-13, atol=1e-15)
    # the second eager call with the same estimator reuses the compiled program
    n = len(eager.CACHE)
    vj.filter(est, ys + 0.1, us, **kw)
    assert len(eager.CACHE) == n


def test_traced_arguments_are_traced_inline_and_the_cache_is_bounded(monkeypatch):
    calls = []

    def f(scale, x, *, power):
        calls.append(type(x).__name__)
        return scale.value * x ** power

    class Held:
        value = 3.0

    h = Held()
    assert float(eager.call(f, (h,), {"power": 2}, jnp.asarray(2.0))) == 12.0
    assert float(eager.call(f, (h,), {"power": 2}, jnp.asarray(5.0))) == 75.0
    assert len(calls) == 1  # traced once by the cached jit, not again
    g = jax.grad(lambda x: eager.call(f, (h,), {"power": 2}, x))(2.0)
    assert float(g) == 12.0 and len(calls) == 2  # under grad: inline, not through the cache
    monkeypatch.setattr(eager, "CACHE_SIZE", 3)
    for p in range(6):
        eager.call(f, (h,), {"power": p}, jnp.asarray(1.0))
    assert len(eager.CACHE) == 3
