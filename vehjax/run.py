"""Run a whole Monte-Carlo study in one call: ``lax.scan`` over time, ``vmap`` over runs.

::

    out = vehjax.run(est, measurements, inputs, x0=x0, P0=P0, key=jax.random.key(0))
    out.states          # (R, T, nx)
    out.diverged        # (R,) bool

Time convention (the papers' order): ``x0``/``P0`` describe the state before the first step;
step ``t`` predicts with ``inputs[..., t, :]``, then updates with ``measurements[:, t, :]``, so
``out.states[:, t]`` is the filtered estimate after the ``t``-th measurement.

Each run is :func:`vehjax.filter`'s traced logic (``vehjax.engine.one_run``), vmapped over the
runs of a chunk, or, for estimators with a runs-last ``batch`` form
(:mod:`vehjax.filters.runs_last`) where the execution strategy says so, one scan of the batched
step with the runs axis last (:mod:`vehjax.runner.batch`); results agree to rounding.

How a study executes on its platform (chunk budget, blocking of runs inside a chunk, runs-last
or vmapped step, XLA options, trigonometric substitutes, results to the host) is decided in one
place, :mod:`vehjax.execution`, from the device the study runs on; ``execution=`` (a
:class:`vehjax.Execution`) overrides it. This module holds no platform rule.

A NaN measurement component is missing; ``run`` passes it to the filter untouched and the filter
skips that component's update. Every filter treats any non-finite component as missing; ``run``
refuses +-inf in the measurements with a ValueError, since it is more likely a fault than a gap.

Divergence (as in :mod:`vehjax.filtering`): a run whose mean is not finite, whose covariance is
not finite and positive definite (also the parameter estimate and its covariance, for filters
that estimate parameters), or whose log-likelihood or NIS is not finite, is flagged ``diverged``
at that step. From then on its outputs hold the last good estimate (the prior ``x0``/``P0`` if it
diverged at the first step), its ``nis`` is NaN, its ``n_obs`` 0 and its ``loglik`` stops
accumulating. A particle filter that re-initialises (``StepOutput.reinit``) flags the run but
keeps going. The other runs are not touched.

Estimates on a bound (as in :mod:`vehjax.engine`): a run of a filter with parameter domains
(``Estimator.bounds``) whose estimate of some parameter lies on a finite bound (within
``engine.AT_BOUND_RTOL`` of the bound's scale) on more than ``engine.AT_BOUND_FRACTION`` of
its steps is flagged ``at_bound``; it is neither frozen nor ``diverged``.

Large studies are split into chunks of runs, each one jitted call (one compilation per chunk
shape; the last chunk is padded); results come back to host memory chunk by chunk, so device
memory stays bounded. When several JAX devices are visible the runs of each chunk are sharded
over them (``jax.shard_map`` over a 1-D mesh, no communication between devices; across
processes see below). That scheduling is :mod:`vehjax.runner`'s; this module holds the entry
points and the chunk function they schedule.

What is reproducible. Bit for bit: the same call (data, key, chunking, devices, strategy and
XLA options) on the same machine. To rounding: another chunking, blocking, sharding or number of
processes changes which runs XLA computes together and how it vectorises them, so the last bits
of a result can change; a Gaussian filter's results then agree to a few float64 rounding errors
amplified by the problem's conditioning. A particle filter draws its normals in float32
(:mod:`vehjax.runtime.prng`), whose last float32 bit can change likewise (relative 1e-7), and where a
resampling decision turns on it the run continues as another, equally valid Monte-Carlo
realisation: particle results agree statistically, and to about 1e-6 relative only while no
decision flips. Per-run keys do not depend on chunking (run r gets ``split(key, R)[r]``).

Past one machine (multi-controller JAX): after ``jax.distributed.initialize`` in every process,
``run`` called in every process with the same arguments (the SPMD convention: the same data,
key and ``execution``) shards each chunk's runs over the devices of all processes
(``jax.devices()``, the global mesh) and returns the whole :class:`RunResult`, all R runs, in
every process, equal to a one-process run up to rounding (as above)::

    # on each of N hosts (or N local processes), process_id = 0 .. N-1
    jax.distributed.initialize(coordinator_address="host0:1234", num_processes=N,
                               process_id=process_id)   # before any other JAX call
    out = vehjax.run(est, measurements, inputs, x0=x0, P0=P0, key=jax.random.key(0))
    if jax.process_index() == 0:
        out.to_npz("study.npz")                         # every process holds all of out

Chunk placement and the check that the processes run the same study (a process that does not
call ``run``, or fails before it, leaves the others waiting): :mod:`vehjax.runner.shard`.
``Execution(devices=False)`` makes every process run the whole study alone on its first local
device; a sequence of devices is all the calling process's (a local study) or includes devices
of every process. The progress bar shows on process 0 only.

Compile and execution time can be measured apart with :func:`compile_run`::

    t0 = time.perf_counter(); prepared = vehjax.compile_run(est, ys, us, x0=x0, P0=P0)
    t1 = time.perf_counter(); out = prepared()            # executes only; call again to repeat
    t2 = time.perf_counter()                              # compile: t1 - t0, run: t2 - t1
"""

from __future__ import annotations

import inspect
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import NamedSharding, PartitionSpec

from . import execution, validation
from .execution import Execution
from .filters.base import Estimator
from .result import RunResult
from .runner import batch
from .runner.execute import compile_chunks, execute
from .runner.plan import Plan, check_progress, plan as _plan
from .runner.shard import AXIS

__all__ = ["RunResult", "CompiledRun", "run", "compile_run", "Execution", "Strategy"]

Strategy = execution.Strategy



@eqx.filter_jit
def _study(estimator, ys, us, x0, P0, th0, Pth0, keys, return_cov, mesh, block, strategy,
           smooth=None):
    """A chunk of runs: ys (C, T, ny); the others per run (leading C) or shared, by rank. The
    vmapped form computes ``block`` runs side by side at a time (all when None, or when the
    chunk, or a device's share of it, has no more). Traced under ``strategy``
    (:func:`vehjax.execution.using`), which also says whether the runs-last step is used."""
    with execution.using(strategy):
        return _study_traced(estimator, ys, us, x0, P0, th0, Pth0, keys, return_cov, mesh,
                             block, strategy, smooth)


def _study_traced(estimator, ys, us, x0, P0, th0, Pth0, keys, return_cov, mesh, block,
                  strategy, smooth):
    per_run = (
        True,
        us.ndim == 3,
        x0.ndim == 2,
        P0.ndim == 3,
        th0 is not None and th0.ndim == 2,
        Pth0 is not None and Pth0.ndim == 3,
        keys is not None,
    )

    def f(*args):
        cross = None
        if smooth is not None:
            res, cross = batch.smoothed_study(estimator, smooth, return_cov, per_run, block,
                                              strategy, *args)
        elif execution.runs_last_for(strategy, args[0].shape[0]) and estimator.batch is not None:
            res = batch.runs_last_study(estimator, return_cov, strategy.prefetch_inputs, per_run,
                                   *args)
        else:
            res = batch.vmapped_study(estimator, return_cov, per_run, block, *args)
        return (res.states, res.covariances, res.params, res.params_cov,
                jnp.sum(res.loglik, axis=1), res.nis, res.n_obs, res.diverged, res.diverged_at,
                res.at_bound, cross)

    if mesh is not None:
        f = jax.shard_map(
            f,
            mesh=mesh,
            in_specs=tuple(PartitionSpec(AXIS) if r else PartitionSpec() for r in per_run),
            out_specs=PartitionSpec(AXIS),
            check_vma=False,  # no collectives; shared inputs are replicated constants
        )
    out = f(ys, us, x0, P0, th0, Pth0, keys)
    if mesh is not None and mesh.is_multi_process:
        # Multi-controller: replicate the chunk's results on every device (one all-gather), so
        # that every process holds all of them and can bring them to host memory.
        out = jax.lax.with_sharding_constraint(out, NamedSharding(mesh, PartitionSpec()))
    return out


def _planned(arguments: dict):
    """(the study's :class:`vehjax.runner.plan.Plan`, its XLA options or None) from the
    arguments of :func:`run` / :func:`compile_run` (their one signature), checked."""
    a = dict(arguments)
    ex = validation.record("execution", a["execution"], Execution)
    plan = _plan(a.pop("estimator"), a.pop("measurements"), a.pop("inputs"), **a)
    return plan, execution.compiler_options(plan.strategy, plan.estimator.workload,
                                            ex.compiler_options)


def run(
    estimator: Estimator,
    measurements,
    inputs,
    *,
    x0,
    P0,
    theta0=None,
    P_theta0=None,
    key=None,
    return_covariances: bool = False,
    progress: bool | None = None,
    execution: Execution | None = None,
    smooth=False,
) -> RunResult:
    """Run ``estimator`` over R runs of T steps in one jitted call per chunk of runs.

    Args:
        estimator: a :class:`vehjax.filters.Estimator`.
        measurements: (R, T, ny); NaN components are missing (every filter skips them); +-inf
            is refused. A single run is (1, T, ny), or use :func:`vehjax.filter`: 2-D arrays
            are refused rather than guessed.
        inputs: (T, nu) shared by all runs, or (R, T, nu); None when the model has no inputs.
        x0: state before the first step, (nx,) shared or (R, nx) per run.
        P0: its covariance, (nx, nx) or (R, nx, nx), symmetric positive definite, or (nx,)
            variances (as Q and R in the builders).
        theta0: initial parameter estimate, (p,) or (R, p), for filters that estimate
            ``estimator.param_names``; for a state-only filter built on a model (its
            ``n_theta``), (np,) or (R, np) replaces the model's parameters.
        P_theta0: its covariance, (p, p) or (R, p, p).
        key: PRNG key, required when ``estimator.needs_key``; run r gets
            ``jax.random.split(key, R)[r]``.
        return_covariances: also return ``covariances`` and ``params_cov`` (R*T*nx*nx numbers).
        progress: progress bar per chunk (tqdm's, which renders in Jupyter, when installed;
            else a text line on stderr); default shown when there are several chunks.
        execution: where and how the study executes, a :class:`vehjax.Execution` (its
            ``chunk_size``, ``devices``, ``compiler_options`` and ``strategy``, the rules of
            :mod:`vehjax.execution`); None: ``Execution()``, every default. Results do not
            depend on it beyond rounding.
        smooth: False (filter), True (each run smoothed by the filter's own RTS smoother,
            :func:`vehjax.smooth`), or a Gaussian smoother as :func:`vehjax.smooth`'s
            ``method`` takes it, its record :class:`vehjax.smoothers.RTS`, ``IEKS`` or ``IPLS``
            (with its options; not ``initial``, one run's start) or its name ``"rts"``,
            ``"ieks"``, ``"ipls"`` (the record with its defaults): then ``states``,
            ``covariances``, ``params`` and ``params_cov`` are the smoothed ones, ``loglik``
            the filter's (the linearised model's for the iterated smoothers), ``nis`` and
            ``n_obs`` the filter's, ``cross_covariances`` Cov(x_t, x_t+1 | y_1:T) (with
            ``return_covariances``), and a run whose filter or smoother fails is ``diverged``
            (``diverged_at`` 0 when only the smoother failed). Gaussian filters with a smoother
            (``Estimator.smoother``); particle smoothers run one run at a time
            (:func:`vehjax.smooth`).

    Returns:
        :class:`RunResult` of numpy arrays (jax arrays on the device when the strategy's
        ``results_to_host`` is False). All inputs are cast to their common floating dtype
        (pass every array as float32 for a single-precision study).

    Raises:
        ValueError: naming the argument, for wrong shapes, non-finite inputs/x0/P0, a P0 that is
            not symmetric positive definite, a missing key or theta0, a theta0 outside the
            estimator's parameter domains (``Estimator.bounds``) or, for a state-only
            filter, the model's (``Estimator.theta_domains``), an ``execution`` that is not
            a :class:`vehjax.Execution` (whose fields check themselves when it is made), a ``smooth`` the
            estimator has no smoother for, a study whose one run
            cannot fit the device's memory or whose results cannot fit the host's (with the
            estimate and the limit), before anything is traced; options XLA does not take,
            when the study is compiled;
            under ``jax.distributed``, in every process, when the processes' arguments differ.

    Under ``jax.distributed`` call it in every process with the same arguments::

        jax.distributed.initialize(coordinator_address, num_processes, process_id)
        out = vehjax.run(est, ys, us, x0=x0, P0=P0, key=jax.random.key(0))  # all runs, each
    """
    plan, options = _planned(locals())
    if options is None:
        return execute(plan, _study, progress)
    return execute(plan, compile_chunks(plan, _study, options, cache=True), progress)


class CompiledRun:
    """A study whose chunk function is compiled ahead of time; call it to execute.

    A call's time covers the whole study as ``run`` does it: moving each chunk's data to the
    device, executing, and bringing the results back to host memory.

    Attributes:
        compile_seconds: wall time spent tracing, lowering and compiling, s.
        chunk_size: runs per compiled call; n_chunks: number of calls per execution.
    """

    def __init__(self, plan: Plan, compiled, compile_seconds: float):
        self._plan, self._compiled = plan, compiled
        self.compile_seconds = compile_seconds
        self.chunk_size, self.n_chunks = plan.chunk, plan.n_chunks

    def __call__(self, *args, progress: bool | None = None) -> RunResult:
        """Execute the whole study (all chunks) and return its :class:`RunResult`.

        The study is the one compiled, with its own data: new measurements need a new
        :func:`compile_run` (or :func:`run`). ``progress``: keyword only, None (as compiled),
        True or False."""
        if args:
            raise TypeError(
                "CompiledRun: a compiled study runs with the data it was compiled with and takes "
                f"no positional arguments (got {len(args)}); for new measurements call "
                "vehjax.compile_run(...) or vehjax.run(...) again; progress is keyword-only")
        check_progress(progress)
        progress = self._plan.progress if progress is None else progress
        return execute(self._plan, self._compiled, progress)


def compile_run(*args, **kwargs) -> CompiledRun:
    """Validate and compile a study without running it, for timing compilation apart.

    Same arguments as :func:`run`. ``compile_run(...)()`` returns what ``run(...)`` returns,
    under ``jax.distributed`` too: call both in every process with the same arguments. The
    prepared study holds its own copy of the arrays: calling it again repeats the same study.
    """
    plan, options = _planned(_arguments(args, kwargs))
    # its own copy of the data: "call again to repeat" repeats this study, whatever the
    # caller writes into its arrays afterwards
    plan = plan._replace(arrays=tuple(None if a is None else np.array(a, copy=True)
                                      for a in plan.arrays))
    t0 = time.perf_counter()
    compiled = compile_chunks(plan, _study, options)
    return CompiledRun(plan, compiled, time.perf_counter() - t0)


_SIGNATURE = inspect.signature(run)


def _arguments(args: tuple, kwargs: dict) -> dict:
    """``compile_run``'s arguments bound to :func:`run`'s one signature, defaults filled in
    (TypeError as a call of ``run`` with them would raise)."""
    try:
        bound = _SIGNATURE.bind(*args, **kwargs)
    except TypeError as err:
        raise TypeError(f"compile_run(): {err}") from None
    bound.apply_defaults()
    return dict(bound.arguments)


compile_run.__signature__ = _SIGNATURE.replace(return_annotation=CompiledRun)
