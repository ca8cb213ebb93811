"""The execution seam: every decision that depends on the platform (CPU, GPU, TPU), in one place.

A study's :class:`Strategy` says how :func:`vehjax.run` executes it: how many runs go in one
compiled call (chunk), whether runs inside a chunk go through in cache-sized blocks, whether a
filter's runs-last batched step is used, which XLA options the study is compiled with, whether a
model's trigonometry is replaced by vectorisable substitutes, and whether results come back to
host memory per chunk. ``run`` and ``compile_run`` pick the strategy of the device the study
runs on (:func:`for_device`); :class:`Execution`'s ``strategy`` overrides it (a
:class:`Strategy`, or a platform name: ``"cpu"``, ``"gpu"``, ``"tpu"``)::

    out = vehjax.run(est, ys, us, x0=x0, P0=P0,
                     execution=vehjax.Execution(strategy="gpu"))          # GPU rules anywhere
    s = vehjax.execution.for_platform("cpu")._replace(block_numbers=None)  # CPU, no blocking
    out = vehjax.run(est, ys, us, x0=x0, P0=P0, execution=vehjax.Execution(strategy=s))

:class:`Execution` holds every platform knob of a study (``chunk_size``, ``devices``,
``compiler_options``, ``strategy``), the one ``execution=`` option of ``run`` and
``compile_run``.

Nothing else in vehjax reads the platform: filters, models and the rest of ``run`` describe
their work (an estimator's :attr:`~vehjax.filters.Estimator.workload`, its optional runs-last
``batch`` form, a model built with ``fast_math``) and this module decides what that means on
each platform. The one exception is traced code outside ``run`` (:func:`vehjax.filter` under a
user's ``jax.jit``): it follows :func:`current`, the strategy of JAX's default backend.

The rules, with the reason and measurement behind each, are in ``docs/execution.md``. In short,
on CPU: each scan compiled into one function (XLA's small-while-loop limit raised when vehjax
is imported, ``vehjax.SMALL_LOOP_BYTES``: a process-wide XLA flag, the one rule not in this
module, since it must be set before JAX starts); runs vmapped in cache-sized blocks
(``block_numbers``); chunks of at most 512 MiB and 2e9 carried numbers x steps (``chunk_bytes``,
``chunk_work``); XLA:CPU's elemental emitter for the small-dense filters
(``elemental_emitter``); vectorisable trigonometry for ``fast_math`` models
(``substitute_elementary``); a fit's independent work on several threads (``side_by_side``),
a point's forward-mode directions among them too (``split_directions``); a
model's integrator sub-steps as a loop (``rolled_substeps``); the runs-last batched step
(``runs_last``) except for a chunk of one run (:func:`runs_last_for`); a live filter's sample
step on a synchronous CPU client, in the calling thread (:func:`live_device`). On
GPU (and TPU, unmeasured): no blocking, no CPU XLA options, substitutes off, the runs-last step
on, chunks of a quarter of the device's memory, one thing at a time in a fit. ``vehjax bench
all``, ``particle``, ``device`` and ``marginalized`` measure them.

Random numbers are the same on every platform by design: the particle filters hash counters
with Threefry-2x32 (:mod:`vehjax.runtime.prng`), several times cheaper than ``jax.random`` in float64
on CPU, and the same draws everywhere, so that a strategy changes timings, never results beyond
rounding (``tests/test_execution.py`` holds every family's GPU strategy, forced on the CPU, to
its CPU strategy's results).

Memory: :func:`memory_limit` is the device's memory (GPU/TPU) or the host's physical memory
(CPU); ``run`` refuses up front a study whose one-run working set, or whose results on the
host, cannot fit (:func:`check_fits`); ``simulate``, which holds all its runs at once, one
whose arrays cannot (:func:`check_memory`).
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import os
import threading
from concurrent.futures import Future, ThreadPoolExecutor
from functools import lru_cache
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["Execution", "Strategy", "for_platform", "for_device", "current", "using", "resolve",
           "compiler_options", "check_options", "block_size", "memory_limit", "check_fits", "check_memory",
           "resolve_devices", "WORKLOADS", "in_thread",
           "live_device"]

#: What an estimator may declare its step to be (``Estimator.workload``).
WORKLOADS = ("default", "small_dense", "particles")

_CPU_CHUNK_BYTES = 512 * 2**20
_CPU_CHUNK_WORK = 2e9
_CPU_BLOCK_NUMBERS = 65536
_MIN_BLOCK = 4  # fewer runs side by side lose more to per-step overheads than caches give
_DEVICE_CHUNK_FRACTION = 0.25
_DEVICE_CHUNK_FALLBACK = 4 * 2**30  # a device that reports no memory limit


class Strategy(NamedTuple):
    """How a study is executed on one platform (every field a plain, hashable value).

    Attributes:
        platform: "cpu", "gpu" or "tpu": the rules it was made from (informative).
        chunk_bytes: bytes of device memory a chunk's outputs and working set may take.
        chunk_work: at most this many carried numbers x steps per chunk (so that a long study
            shows progress); None: no limit.
        block_numbers: runs inside a chunk go through in blocks of about this many carried
            numbers (``lax.map`` over blocks of vmapped runs); None: all runs side by side.
        runs_last: use an estimator's runs-last ``batch`` step where it declares one.
        elemental_emitter: compile ``small_dense`` estimators with XLA:CPU's elemental emitter.
        substitute_elementary: evaluate ``fast_math`` models with the vectorisable
            trigonometric substitutes (:mod:`vehjax.runtime.substitute`).
        results_to_host: bring each chunk's results to host memory (numpy) as it finishes;
            False keeps them on the device (``RunResult`` of jax arrays, one device).
        prefetch_inputs: hand a runs-last step its prepared inputs through the scan's carry
            where the filter's ``Batch.prefetch`` asks for it (a CPU measurement: XLA:CPU fuses
            a slice of a scanned-over array into every kernel that reads it); False: never.
        side_by_side: independent pieces of a fit's work done at once on this many host
            threads (:mod:`vehjax.tune`: the gradients of a Hessian by differences, the
            compile of the next stage's program beside the current stage's evaluations); 1:
            one after the other.
        rolled_substeps: a model's integrator sub-steps (:func:`vehjax.models.base.integrate`,
            more than one per sample) as a loop, not written out: on XLA:CPU the one-run step
            of a fit's program then compiles in half the time and runs about a third faster
            (the single-track model's two RK4 sub-steps; ``benchmarks/results``); the same
            arithmetic, rounded apart by a few ulps.
        batched_hessian_steps: a fit of at least this many run-steps (R T) in forward mode
            computes its Hessian's 2 n difference gradients in one program vmapped over the
            points (a second compile; :mod:`vehjax.tune.program`); None: never, the n forward
            differences as ``side_by_side`` evaluations instead. None on XLA:CPU, where the
            fused filter step is bound by arithmetic: 12 points batched cost 10.6 evaluations of
            one (the brush fit's program, 20,000 steps; ``benchmarks/results``); 50,000 on a
            GPU/TPU, where a point's scan leaves the device mostly idle (not measured there).
        split_directions: a forward-mode evaluation of a fit's program carries its n tangent
            directions in ``side_by_side`` blocks evaluated at once on as many threads
            (:func:`direction_block`), each block repeating the filter's own arithmetic; False:
            all n in one call. On XLA:CPU a call costs about a + b m for m directions with a
            the filter's own share (the brush fit's program, 20,000 steps: 226 ms for its 6
            directions, two blocks of 3 at once 130 ms; ``benchmarks/results``).
    """

    platform: str
    chunk_bytes: int
    chunk_work: float | None
    block_numbers: int | None
    runs_last: bool
    elemental_emitter: bool
    substitute_elementary: bool
    results_to_host: bool = True
    prefetch_inputs: bool = True
    side_by_side: int = 1
    rolled_substeps: bool = False
    batched_hessian_steps: int | None = 50000
    split_directions: bool = False


@dataclasses.dataclass(frozen=True)
class Execution:
    """Where and how a study of :func:`vehjax.run` / :func:`vehjax.compile_run` executes, the
    option ``execution`` of both: the platform knobs, which change timings and memory, never
    results beyond rounding (module docstring of :mod:`vehjax.run`, "What is reproducible").

    Attributes:
        chunk_size: at most this many runs per jitted call, rounded up to a multiple of the
            device count (chunks are balanced and the last is padded to the common size).
            None: as many as keep a chunk's outputs and the filters' working memory (their
            state from ``init`` times the temporaries of a step, so particles and sigma points
            count) within the strategy's budget (on CPU near 512 MiB, and its work near 2e9
            state numbers x steps), so that a long study runs in several chunks and shows its
            progress.
        devices: None shards runs over all ``jax.devices()``; False uses the default device
            only; or a sequence of jax devices, each at most once. Under ``jax.distributed``:
            None shards over the devices of all processes and returns all runs in every
            process; False runs the whole study in each process on its first local device; a
            sequence is all this process's devices, or includes devices of every process and
            is the same in every process.
        compiler_options: XLA options for compiling the study, a dict of option names (str) to
            str, bool, int or float values, e.g. ``{"xla_backend_optimization_level": 1}``, on
            top of the strategy's own (these override them name by name). A compiled study is
            reused by the next call with the same estimator object, options and shapes. Level 1
            helps a particle filter on :class:`~vehjax.models.SevenDOF` on CPU, whose step LLVM
            at level 3 takes over 10 minutes to compile. Options XLA does not take are refused
            when the study is compiled.
        strategy: how the study executes on its platform (chunk budget, blocking of runs,
            runs-last step, XLA options, trigonometric substitutes, results on the host or the
            device): None for the rules of the platform of the first device used,
            ``"cpu"``/``"gpu"``/``"tpu"`` for that platform's, or a :class:`Strategy`.

    Raises:
        ValueError: naming the field (``execution.chunk_size: ...``), when made: a chunk_size
            that is not None or an integer >= 1, devices that are not None, False or a
            sequence of distinct jax devices, compiler_options that are not such a dict, a
            strategy that is not None, a platform name or a valid :class:`Strategy`.
    """

    chunk_size: int | None = None
    devices: Any = None
    compiler_options: dict | None = None
    strategy: Strategy | str | None = None

    def __post_init__(self):
        _named(check_chunk_size, self.chunk_size)
        if self.devices is not None:
            _named(resolve_devices, self.devices)
        _named(check_options, self.compiler_options)
        _named(check_strategy, self.strategy)


def _named(check, value):
    """``check(value)``, its ValueError naming the field of :class:`Execution`."""
    try:
        return check(value)
    except ValueError as err:
        raise ValueError(f"execution.{err}") from None


def check_chunk_size(chunk_size) -> None:
    """ValueError naming ``chunk_size`` unless it is None or an integer >= 1."""
    if chunk_size is not None and (
        isinstance(chunk_size, (bool, np.bool_))
        or not isinstance(chunk_size, (int, np.integer))
        or chunk_size < 1
    ):
        raise ValueError(f"chunk_size: expected None or an integer >= 1, got {chunk_size!r}")


def for_platform(platform: str, device_memory: int | None = None) -> Strategy:
    """The strategy of a platform ("cpu", "gpu"/"cuda"/"rocm", "tpu"); ``device_memory`` in
    bytes sets a GPU/TPU chunk budget (default: a fallback of 4 GiB a chunk)."""
    name = str(platform).lower()
    if name == "cpu":
        return Strategy("cpu", _CPU_CHUNK_BYTES, _CPU_CHUNK_WORK, _CPU_BLOCK_NUMBERS,
                        runs_last=True, elemental_emitter=True, substitute_elementary=True,
                        side_by_side=os.cpu_count() or 1, rolled_substeps=True,
                        batched_hessian_steps=None, split_directions=True)
    if name in ("gpu", "cuda", "rocm", "tpu"):
        budget = (_DEVICE_CHUNK_FALLBACK if device_memory is None
                  else int(_DEVICE_CHUNK_FRACTION * device_memory))
        return Strategy("tpu" if name == "tpu" else "gpu", budget, None, None, runs_last=True,
                        elemental_emitter=False, substitute_elementary=False,
                        prefetch_inputs=False)
    raise ValueError(f"strategy: unknown platform {platform!r}; expected 'cpu', 'gpu' or 'tpu'")


def for_device(device) -> Strategy:
    """The strategy for a jax device: its platform's rules, chunk budget from its memory."""
    return for_platform(device.platform, None if device.platform == "cpu"
                        else _device_memory(device))


def _device_memory(device) -> int | None:
    try:
        stats = device.memory_stats()
    except Exception:  # some backends do not report memory
        return None
    return int(stats["bytes_limit"]) if stats and "bytes_limit" in stats else None


def memory_limit(device) -> int | None:
    """Bytes a study may hold on ``device``: the device's memory limit (GPU/TPU), the host's
    physical memory (CPU); None when unknown."""
    if device.platform != "cpu":
        return _device_memory(device)
    return host_memory()


def host_memory() -> int | None:
    """The host's physical memory in bytes (None when the OS does not say)."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return None


def resolve_devices(devices) -> list:
    """The devices a study runs on: ``devices`` of :func:`vehjax.run` (None or True: every
    device, the global mesh under ``jax.distributed``; False: this process's first device; or
    a sequence of devices, all this process's or including every process's). ValueError naming
    ``devices`` otherwise."""
    if devices is None or devices is True:
        return list(jax.devices())
    if devices is False:
        # jax.devices()[0] belongs to process 0; under jax.distributed each process uses its own
        return [jax.devices()[0] if jax.process_count() == 1 else jax.local_devices()[0]]
    try:
        if isinstance(devices, (str, bytes)):  # not read as a sequence of its characters
            raise TypeError
        devices = list(devices)
    except TypeError:
        raise ValueError(
            f"devices: expected None (all devices), False (one device) or a sequence of "
            f"jax devices, got {devices!r}"
        ) from None
    if not devices or not all(isinstance(d, jax.Device) for d in devices):
        raise ValueError(f"devices: expected a non-empty sequence of jax devices, got {devices!r}")
    if len(set(devices)) != len(devices):  # a mesh of repeated devices fails deep inside JAX
        raise ValueError(f"devices: expected each device at most once, got {devices}")
    owners = {d.process_index for d in devices}
    if owners != {jax.process_index()} and owners != set(range(jax.process_count())):
        raise ValueError(
            f"devices: under jax.distributed the devices must be either all this process's "
            f"(jax.local_devices()) or include devices of every process "
            f"({jax.process_count()}); got devices of processes {sorted(owners)}"
        )
    return devices


def check_fits(per_run_bytes: int, results_bytes: int, device) -> None:
    """Refuse a study that cannot fit: ``per_run_bytes`` (one run's outputs and working set,
    the smallest chunk) against the device's memory, ``results_bytes`` (all runs' results)
    against the host's. Raises ValueError with the estimate and the limit."""
    limit = memory_limit(device)
    if limit is not None and per_run_bytes > limit:
        raise ValueError(
            f"study too large for {device.platform} device {device.id}: one run needs about "
            f"{per_run_bytes / 2**30:.1f} GiB (outputs plus the filter's working set, e.g. its "
            f"particles) and the device has {limit / 2**30:.1f} GiB; use fewer particles or "
            f"steps, or split the run")
    host = host_memory()
    if host is not None and results_bytes > host:
        raise ValueError(
            f"study too large: its results need about {results_bytes / 2**30:.1f} GiB of host "
            f"memory and the host has {host / 2**30:.1f} GiB; use fewer runs or steps, or "
            f"return_covariances=False")


def check_memory(needed_bytes: int, device, what: str, advice: str) -> None:
    """Refuse a job that must hold ``needed_bytes`` at once on ``device`` (all its arrays and
    working set) when they exceed :func:`memory_limit`: one-line ValueError "{what} need about
    N GiB of memory and the <platform> device <id> has M GiB; {advice}". ``what`` names the
    arguments that set the size (e.g. "runs, scenario: 100 runs x 1000 steps"). Nothing is
    refused when the limit is unknown."""
    limit = memory_limit(device)
    if limit is not None and needed_bytes > limit:
        raise ValueError(f"{what} need about {_size(needed_bytes)} of memory and the "
                         f"{device.platform} device {device.id} has {_size(limit)}; {advice}")


def _size(n_bytes: float) -> str:
    """'3.2 GiB', '12.5 TiB': bytes in binary units."""
    if n_bytes >= 2**40:
        return f"{n_bytes / 2**40:.1f} TiB"
    return f"{n_bytes / 2**30:.1f} GiB"


def check_strategy(strategy) -> None:
    """ValueError naming ``strategy`` unless it is None, a platform name or a valid
    :class:`Strategy` (what :func:`resolve` takes)."""
    if strategy is None:
        return
    if isinstance(strategy, Strategy):
        _check(strategy)
    elif isinstance(strategy, str):
        for_platform(strategy)
    else:
        raise ValueError(f"strategy: expected None, 'cpu', 'gpu', 'tpu' or a "
                         f"vehjax.execution.Strategy, got {strategy!r}")


def resolve(strategy, device) -> Strategy:
    """``strategy`` as given to ``run``: None (``device``'s), a platform name, or a Strategy."""
    check_strategy(strategy)
    if strategy is None:
        return for_device(device)
    if isinstance(strategy, Strategy):
        return strategy
    return for_platform(strategy, None if strategy.lower() == "cpu"
                        else _device_memory(device) if device.platform != "cpu" else None)


def _check(s: Strategy) -> None:
    def positive(name, v, allow_none):
        if v is None and allow_none:
            return
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0 or v != v:
            raise ValueError(f"strategy: {name} must be a positive number"
                             f"{' or None' if allow_none else ''}, got {v!r}")
    positive("chunk_bytes", s.chunk_bytes, False)
    positive("chunk_work", s.chunk_work, True)
    positive("block_numbers", s.block_numbers, True)
    positive("batched_hessian_steps", s.batched_hessian_steps, True)
    if isinstance(s.side_by_side, bool) or not isinstance(s.side_by_side, int) or \
            s.side_by_side < 1:
        raise ValueError(f"strategy: side_by_side must be an int >= 1, got {s.side_by_side!r}")
    for name in ("runs_last", "elemental_emitter", "substitute_elementary", "results_to_host",
                 "prefetch_inputs", "rolled_substeps", "split_directions"):
        if not isinstance(getattr(s, name), bool):
            raise ValueError(f"strategy: {name} must be True or False, got "
                             f"{getattr(s, name)!r}")


# ----------------------------------------------------------------------------------------------
# the strategy in force while a study is traced


_ACTIVE: contextvars.ContextVar[Strategy | None] = contextvars.ContextVar("vehjax_strategy",
                                                                          default=None)


def current() -> Strategy:
    """The strategy in force: the one ``run`` traces a study under, else that of JAX's default
    backend (for :func:`vehjax.filter` and the filters under a user's own ``jit``)."""
    s = _ACTIVE.get()
    return s if s is not None else _default(jax.default_backend())


@lru_cache(maxsize=None)
def _default(backend: str) -> Strategy:
    return for_platform(backend)


@contextlib.contextmanager
def using(strategy: Strategy):
    """Trace under ``strategy`` (what :func:`current` returns inside)."""
    token = _ACTIVE.set(strategy)
    try:
        yield strategy
    finally:
        _ACTIVE.reset(token)


# ----------------------------------------------------------------------------------------------
# decisions


def block_size(strategy: Strategy, numbers: int) -> int | None:
    """Runs vmapped side by side inside a chunk for a filter carrying ``numbers`` numbers a run;
    None: all of them (no blocking)."""
    if strategy.block_numbers is None:
        return None
    return max(_MIN_BLOCK, int(strategy.block_numbers) // max(int(numbers), 1))


def runs_last_for(strategy: Strategy, runs: int) -> bool:
    """Whether a chunk of ``runs`` runs takes an estimator's runs-last step under ``strategy``:
    where the strategy says so and the chunk holds more than one run (one run goes by the
    per-run step, as :func:`vehjax.filter`)."""
    return bool(strategy.runs_last) and int(runs) > 1


def direction_block(strategy: Strategy, n: int, beside: bool = False) -> int:
    """Tangent directions per call of a forward-mode fit program over ``n`` of them: all n, or
    with ``split_directions`` ceil(n / side_by_side), the calls then made at once on
    ``side_by_side`` threads. ``beside``: the program is evaluated while a fit's next program
    compiles in another thread (:func:`in_thread`): all n, since its blocks would wait for a
    core and each repeats the filter's own arithmetic (the nested linear fit of
    ``benchmarks/bench_fit_limit.py``: 89 ms an evaluation in two blocks, 70 ms in one)."""
    n = max(int(n), 1)
    if beside or not strategy.split_directions or strategy.side_by_side < 2:
        return n
    return -(-n // strategy.side_by_side)


def chunk_runs(strategy: Strategy, per_run_bytes: int, steps: int, numbers: int) -> int:
    """Runs per chunk: the memory budget over one run's bytes, and the work budget."""
    by_memory = int(strategy.chunk_bytes // max(per_run_bytes, 1))
    if strategy.chunk_work is None:
        return max(1, by_memory)
    by_work = int(strategy.chunk_work // (steps * max(numbers, 1)))
    return max(1, min(by_memory, by_work))


def compiler_options(strategy: Strategy, workload: str, user: dict | None = None) -> dict | None:
    """XLA options for compiling a study of an estimator with ``workload`` under ``strategy``,
    updated by the caller's ``user`` options (name by name); None when empty. Options this XLA
    does not know are dropped from the strategy's (they are measured choices, not needs)."""
    own = {}
    if strategy.elemental_emitter and workload == "small_dense":
        own["xla_cpu_use_fusion_emitters"] = False
    own = {k: v for k, v in own.items() if _xla_knows(k, v)}
    check_options(user)
    return {**own, **(user or {})} or None


def check_options(user) -> None:
    """A caller's ``compiler_options``: None or a dict of option names (str) to str, bool, int
    or float values; ValueError naming the argument otherwise (checked before any tracing)."""
    if user is None:
        return
    if not isinstance(user, dict) or not all(isinstance(k, str) for k in user):
        raise ValueError(f"compiler_options: expected a dict of XLA option names (str) to "
                         f"values, got {user!r}")
    bad = [k for k, v in user.items() if not isinstance(v, (str, bool, int, float))]
    if bad:
        raise ValueError(f"compiler_options: values must be str, bool, int or float; {bad} are "
                         f"not")


@lru_cache(maxsize=None)
def _xla_knows(name: str, value) -> bool:
    """Whether this XLA (on the default backend) takes the compile option."""
    try:
        jax.jit(lambda x: x).lower(jnp.zeros(())).compile(compiler_options={name: value})
    except jax.errors.JaxRuntimeError:
        return False
    return True


def live_device():
    """The device a live filter's sample step runs on (:class:`vehjax.Online`).

    A live loop waits for every sample's result, so a thread hand-over is pure latency. JAX's
    CPU backend hands a computation of over 1000 flops (XLA's cost analysis) to a worker
    thread unless its dispatch is synchronous (``jax_cpu_enable_async_dispatch``), and that
    hand-over costs an erratic 4-65 us on a shared 2-core machine against a UKF step's 10 us
    (``benchmarks/results``). So where JAX's default backend is the CPU with asynchronous
    dispatch, the step runs on the device of a second CPU client of this process, made once
    and synchronous: XLA:CPU runs its computations in the calling thread, and the rest of the
    process keeps JAX's default. Otherwise (a GPU or TPU backend, or synchronous dispatch
    already, or a jaxlib without ``xla_client.make_cpu_client``): JAX's default device.
    """
    if jax.default_backend() == "cpu" and jax.config.read("jax_cpu_enable_async_dispatch"):
        device = _calling_thread_cpu()
        if device is not None:
            return device
    return jax.local_devices()[0]


@lru_cache(maxsize=1)
def _calling_thread_cpu():
    """The device of a synchronous CPU client of this process (made on first use), or None."""
    try:
        from jaxlib import xla_client
        return xla_client.make_cpu_client(asynchronous=False, num_devices=1).local_devices()[0]
    except (ImportError, AttributeError, TypeError, RuntimeError):
        return None


_BACKGROUND = {"in_flight": 0}  # work started by in_thread and not yet done
_BACKGROUND_LOCK = threading.Lock()


def _counted(fn, *args, **kwargs):
    """``fn(*args, **kwargs)``, counted in flight (:func:`spare_threads`) while it runs."""
    with _BACKGROUND_LOCK:
        _BACKGROUND["in_flight"] += 1
    try:
        return fn(*args, **kwargs)
    finally:
        with _BACKGROUND_LOCK:
            _BACKGROUND["in_flight"] -= 1


def in_thread(fn, *args, **kwargs) -> Future:
    """``fn(*args, **kwargs)`` started in a second host thread, in a copy of this one's context
    (the strategy in force, :func:`using`): a future. The work that ``side_by_side`` lets run
    beside the caller's (a fit's next program compiled while it fits); the thread ends with
    its work, counted in flight until then (:func:`spare_threads`)."""
    pool = ThreadPoolExecutor(1)
    future = pool.submit(contextvars.copy_context().run, _counted, fn, *args, **kwargs)
    pool.shutdown(wait=False)
    return future


def spare_threads(strategy: Strategy) -> int:
    """The host threads a fit's evaluation may take now: ``side_by_side`` less the work
    :func:`in_thread` has in flight, at least 1 (a point's blocks of directions,
    ``split_directions``, go one after another while a program compiles beside)."""
    with _BACKGROUND_LOCK:
        busy = _BACKGROUND["in_flight"]
    return max(1, strategy.side_by_side - busy)
