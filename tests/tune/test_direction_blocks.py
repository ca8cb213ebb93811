"""A forward-mode fit program evaluated a block of directions at a time (the execution seam's
``split_directions``): the same loss, gradient and BHHH matrix as the program that carries
every direction in one call, whichever threads the blocks run on.

References: the program of the same objective compiled with every direction in one call
(``split_directions=False``), and the BHHH matrix from ``jax.jacfwd`` of the per-step
log-likelihoods (the score outer product written out, nothing of vehjax's assembly).
"""

import threading

import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import pytest

import vehjax
from vehjax import execution
from vehjax.models import Model
from vehjax.tune import program
from vehjax.tune.likelihood import prepare

T = 250
CPU = execution.for_platform("cpu")


def _problem(params=("a", "b")):
    rng = np.random.default_rng(4)
    u = np.sin(np.arange(T) / 5.0) + 0.4 * rng.standard_normal(T)
    x, ys = 0.0, []
    for k in range(T):
        x = 0.8 * x + 0.6 * u[k] + 0.1 * rng.standard_normal()
        ys.append(x + 0.2 * rng.standard_normal())
    model = Model(transition=lambda x, u, th: th[0] * x + th[1] * u,
                  observe=lambda x, u, th: x, dt=0.1, state_names=("x",),
                  param_names=("a", "b"), input_names=("u",), output_names=("y",),
                  theta=[0.7, 0.5])
    return prepare(vehjax.filters.ekf, model, np.array([0.02]), np.array([0.05]),
                   np.array(ys)[:, None], u[:, None], x0=np.zeros(1), P0=np.ones(1),
                   params=vehjax.tune.Fitted(params, noise=("Q", "R")))


def test_the_block_rule_follows_the_strategy():
    assert execution.direction_block(CPU._replace(side_by_side=2), 6) == 3
    assert execution.direction_block(CPU._replace(side_by_side=2), 5) == 3
    assert execution.direction_block(CPU._replace(side_by_side=4), 5) == 2
    assert execution.direction_block(CPU._replace(side_by_side=2), 6, beside=True) == 6
    assert execution.direction_block(CPU._replace(side_by_side=1), 6) == 6
    assert execution.direction_block(CPU._replace(side_by_side=2, split_directions=False), 6) == 6
    assert execution.direction_block(execution.for_platform("gpu"), 6) == 6
    with pytest.raises(ValueError, match="split_directions"):
        execution.check_strategy(CPU._replace(split_directions="yes"))


@pytest.mark.parametrize("side", [2, 3])
def test_blocks_give_the_one_call_programs_loss_gradient_and_bhhh(side):
    obj, setup = _problem()
    with execution.using(CPU._replace(side_by_side=side, split_directions=False)):
        whole = program.compiled_loss(obj, setup)
    with execution.using(CPU._replace(side_by_side=side)):
        prog = program.compile_program(obj, setup)
        split = program.compiled_loss(obj, setup, compiled=prog)
        assert prog.block == -(-4 // side)  # a, b, Q, R: blocks of 2 (the last one padded)
        rng = np.random.default_rng(0)
        for _ in range(3):
            f = whole.x0 + 0.2 * rng.standard_normal(whole.x0.shape)
            a, b = whole.vgo(f), split.vgo(f)
            assert b[0] == a[0]  # the filter's own arithmetic, the same in every block
            np.testing.assert_allclose(b[2], a[2], rtol=1e-13, atol=1e-15)
            np.testing.assert_allclose(b[3], a[3], rtol=1e-12, atol=1e-14 * np.abs(a[3]).max())
            np.testing.assert_array_equal(np.asarray(b[1][0]), np.asarray(a[1][0]))
        # several points at once: each point's blocks among the others', the same numbers
        F = [whole.x0 + 0.1 * k for k in range(3)]
        for (va, _, ga), (vb, _, gb) in zip(whole.many(F), split.many(F)):
            assert va == vb
            np.testing.assert_allclose(gb, ga, rtol=1e-13, atol=1e-15)


def test_the_bhhh_matrix_of_blocks_is_the_score_outer_product():
    obj, setup = _problem()
    flat, unravel = jax.flatten_util.ravel_pytree(obj.z0)
    f = np.asarray(flat) + 0.1
    with execution.using(CPU._replace(side_by_side=2)):
        B = program.compiled_loss(obj, setup).vgo(f)[3]
    J = jax.jacfwd(lambda g: setup.per_step(unravel(g), obj.data)[0])(jnp.asarray(f))
    S = np.asarray(J).reshape(-1, f.shape[0])  # (R T, n)
    np.testing.assert_allclose(B, S.T @ S / obj.n_steps, rtol=1e-9,
                               atol=1e-12 * np.abs(B).max())


def test_work_in_flight_takes_a_thread_from_a_points_blocks():
    s = CPU._replace(side_by_side=2)
    assert execution.spare_threads(s) == 2
    go, started = threading.Event(), threading.Event()

    def background():
        started.set()
        go.wait(10)
        return execution.spare_threads(s)

    future = execution.in_thread(background)
    started.wait(10)
    try:
        assert execution.spare_threads(s) == 1
        assert execution.spare_threads(CPU._replace(side_by_side=1)) == 1
    finally:
        go.set()
    assert future.result(10) == 1  # the work counts itself
    assert execution.spare_threads(s) == 2
