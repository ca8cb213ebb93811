"""vehjax.runner: the study runner behind vehjax.run and vehjax.compile_run (one signature, one
check of the arguments, one cache of compiled programs)."""

import inspect

import jax
import numpy as np
import pytest

import vehjax as vj
from vehjax import engine
from vehjax.runner import plan, shard
from vehjax.runtime import eager

M = vj.models.KinematicBicycle()
EST = vj.filters.ekf(M, np.eye(M.nx) * 1e-4, np.eye(len(M.output_names)) * 1e-2)


def test_run_and_compile_run_take_one_signature():
    ran = inspect.signature(vj.run).parameters
    compiled = inspect.signature(vj.compile_run).parameters
    assert list(ran.values()) == list(compiled.values())
    # the plan takes the same arguments, less compiler_options
    planned = inspect.signature(plan.plan).parameters
    assert [p for p in ran if p != "compiler_options"] == list(planned)


def test_a_study_and_a_run_are_checked_by_the_one_check():
    ys = np.zeros((3, 5, EST.ny))
    us = np.zeros((5, EST.nu))
    x0, P0 = np.zeros(EST.nx), np.eye(EST.nx)
    one = engine.check_arguments(EST, ys[0], us, x0, P0, None, None, None)
    many = engine.check_arguments(EST, ys, us, x0, P0, None, None, None, study=True)
    assert len(one) == len(many) == 7 and one[-1] is None and many[-1] is None
    for message, call in (("^x0:", lambda s: engine.check_arguments(
            EST, ys if s else ys[0], us, np.zeros(EST.nx + 1), P0, None, None, None, study=s)),
                          ("^key:", lambda s: engine.check_arguments(
            EST, ys if s else ys[0], us, x0, P0, None, None, 0, study=s))):
        for study in (False, True):
            with pytest.raises(ValueError, match=message):
                call(study)
    p = plan.plan(EST, ys, us, x0, P0, None, None, None, False, None, None, None)
    assert (p.R, p.n_chunks) == (3, 1) and shard.digest(p).shape == (8,)


def test_compiled_studies_live_in_the_one_cache():
    ys = np.zeros((2, 4, EST.ny))
    us = np.zeros((4, EST.nu))
    kw = dict(x0=np.zeros(EST.nx), P0=np.eye(EST.nx),
              execution=vj.Execution(compiler_options={"xla_backend_optimization_level": 1}))
    vj.run(EST, ys, us, **kw)
    n = len(eager.CACHE)
    held = [entry[0] for entry in eager.CACHE.values()]
    assert any(h and h[0] is EST for h in held)
    vj.run(EST, ys + 1.0, us, **kw)
    assert len(eager.CACHE) == n


def test_chunk_shapes_are_those_of_every_chunks_arguments():
    """compile_chunks keys a compiled study by shard.chunk_shapes: the shapes and dtypes of
    every chunk's arguments (the last chunk padded), with per-run priors and a key."""
    pf = vj.filters.bootstrap_pf(M, np.eye(M.nx) * 1e-4, np.eye(len(M.output_names)) * 1e-2,
                                 n_particles=8)
    ys = np.zeros((5, 4, EST.ny))
    us = np.zeros((5, 4, EST.nu))
    x0, P0 = np.zeros((5, EST.nx)), np.eye(EST.nx)
    p = plan.plan(pf, ys, us, x0, P0, None, None, jax.random.key(0), False, None,
                  vj.Execution(chunk_size=2))
    assert p.n_chunks == 3
    specs = shard.chunk_shapes(p)
    for i in range(p.n_chunks):
        args, _ = shard.chunk_args(p, i)
        assert [None if a is None else (a.shape, a.dtype) for a in args] == \
            [None if s is None else (s.shape, s.dtype) for s in specs]
    # the filter's carried numbers are found once per estimator and shapes
    n = len(eager.CACHE)
    plan.plan(pf, ys + 1.0, us, x0, P0, None, None, jax.random.key(1), False, None,
              vj.Execution(chunk_size=2))
    assert len(eager.CACHE) == n
