"""A fitted filter run sample by sample: :class:`Online`, for a live stream of measurements.

``Online(estimator, x0, P0)`` starts any :class:`~vehjax.filters.Estimator` (EKF, UKF, CKF,
their square-root forms, the adaptive, dual and joint filters, the particle filters with a
``key``) exactly as :func:`vehjax.filter` does, and ``update(y, u, t)`` takes one sample::

    live = vehjax.Online(est, x0, P0, dt=model.dt)      # key=jax.random.key(0) for a PF
    for t, y, u in stream:                              # y (ny,) NaN missing, or None; u (nu,)
        e = live.update(y, u, t=t)                       # e.mean (nx,), e.cov (nx, nx), e.loglik
    live.save("car.npz")                                 # and later Online.load("car.npz", est)
    live.export("step.jax")                              # the compiled step, for a process
                                                         # without vehjax (jax alone)

The same filter as :func:`vehjax.filter`. Each model step is the estimator's own ``step`` with
the engine's rule for a bad step (:mod:`vehjax.engine`): from the first step whose estimate is
not finite or whose covariance is not positive definite, the reported estimate is the last good
one, ``loglik`` 0, ``nis`` NaN, ``n_obs`` 0 and ``diverged`` True, and the filter state goes on.
So T updates give, sample by sample, what ``vehjax.filter`` gives over the T rows stacked, to
rounding, particle filters with the same key included (the key lives in the state).

Time stamps (multi-rate and irregular streams). The model has a fixed step ``dt`` [s]. Without
a stamp a sample is one model step. With a stamp ``t`` [s] the sample is
``k = round((t - t_filter) / dt)`` model steps, where ``t_filter`` is the filter's clock (the
time of its last step, on the grid ``t_origin + steps * dt``): k - 1 prediction-only steps (all
components missing) and then the step with ``y``. The sample's inputs ``u`` are held over all k
steps, so the sample equals :func:`vehjax.filter` over the data with k - 1 rows of NaN
measurements inserted before it, their inputs the sample's (in vehjax's convention, step t
predicts with ``u_t``: the sample's inputs drive the steps that lead up to it). A stamp is
refused (ValueError naming ``t``) when k < 1 (it goes back, repeats, or comes less than half a
step after the last one), when it lies more than ``max_gap`` seconds after the clock, or when it
is not finite. Stamps are rounded to the grid, so jitter of up to half a step is absorbed and
never accumulates; the clock's origin is ``t0`` (the time of x0, P0) when given, else one model
step before the first stamped sample.

Saved state. :attr:`Online.state` is the whole state, a pytree of arrays
(:class:`OnlineState`); :meth:`Online.save` writes it to one ``np.savez`` file with the clock
and the prior, and :meth:`Online.load` with the same estimator continues from it exactly. The
file's ``state_0`` ... ``state_{n-1}`` are the packed state (:func:`pack`: the leaves of one
dtype concatenated, a few flat buffers) that the exported step takes.

Export. :meth:`Online.export` writes the compiled one-model-step function with ``jax.export``
(StableHLO, serialized): in any process with jax (and ``flatbuffers``) and no vehjax::

    import jax, numpy as np
    jax.config.update("jax_enable_x64", True)      # before anything else: the step is float64
    step = jax.jit(jax.export.deserialize(open("step.jax", "rb").read()).call)
    saved = np.load("car.npz")
    cpu = jax.devices("cpu")[0]                    # the state placed (committed) as the step's
    state = [jax.device_put(saved[f"state_{i}"], cpu)   # outputs are: one compile, not two
             for i in range(int(saved["n_buffers"]))]
    out = step(state, y, u)                        # y (ny,) NaN missing, u (nu,), float64
    state = out["state"]                           # and out["mean"], out["cov"], out["loglik"], ...

The exported function is one model step without the clock: a gap of k steps is k - 1 calls with
an all-NaN ``y`` and then the sample's. Without ``jax_enable_x64`` the loading process would
hand it float32 arrays and the call is refused.

Speed. The step is compiled once, when the filter is built (with the XLA options
:func:`vehjax.run` uses for the estimator's workload, :func:`vehjax.execution.compiler_options`),
and every sample calls that same executable, never retraced: a wrong shape is refused on the
host first. What a sample costs besides the step's arithmetic is the call of a compiled function
from Python, about 15 us on a CPU, growing by about 1.5 us with each array it takes or returns.
So the state stays on the device as a few flat buffers (:class:`Layout`), donated to the step
(updated in place), y and u go to it as one vector (y then u), and the step's outputs come
back as one vector that :meth:`Online.update` splits into numpy views; the checks of y and u
are a few Python-level operations (about 1 us each).
A gap compiles a second function (a loop over prediction steps) on first use.

Dispatch. JAX's CPU backend hands a computation of over 1000 flops (XLA's cost analysis; the
UKF's and the particle filters' steps) to a worker thread, and a loop that waits for every
result would pay the hand-over, several times the step on a shared machine. So on a CPU the
step and its state live on a second, synchronous CPU client (:func:`vehjax.execution.live_device`):
each sample runs in the calling thread; :attr:`Online.state` comes back on JAX's default
device. ``vehjax bench online`` measures the latency under both of JAX's dispatch settings.

Limits: one stream per object (for many cars, :func:`vehjax.run` or ``jax.vmap`` of the step);
the inputs between two stamped samples are not known and are taken to be the later sample's;
the estimator's ``batch`` form is not used (one run).
"""

from __future__ import annotations

import math
from functools import partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from . import execution, validation
from .runtime import eager
from .engine import check_arguments, output_ok, start
from .filters.base import Estimator, StepOutput

__all__ = ["Online", "OnlineEstimate", "OnlineState", "Layout", "layout_of", "pack", "unpack",
           "model_steps", "FORMAT"]

#: The ``format`` entry of a saved file.
FORMAT = "vehjax.online/1"


class OnlineState(NamedTuple):
    """The whole state of an :class:`Online` filter (besides its clock): arrays on the device.

    Attributes:
        filter: the estimator's own state (its ``init``/``step`` pytree).
        mean: the reported estimate, (nx,): the last good step's (the prior x0 before the
            first step).
        cov: its covariance, (nx, nx).
        params: the reported parameter estimate, (p,); (0,) for a state-only filter (NaN before
            the first step when the filter starts from the model's nominal values).
        params_cov: its covariance, (p, p).
        bad: bool scalar: a step was bad (the engine's rule, module docstring); the reported
            estimate is held from then on.
        diverged: bool scalar: a step was bad or the filter re-initialised
            (``StepOutput.reinit``).
    """

    filter: Any
    mean: jnp.ndarray
    cov: jnp.ndarray
    params: jnp.ndarray
    params_cov: jnp.ndarray
    bad: jnp.ndarray
    diverged: jnp.ndarray


class OnlineEstimate(NamedTuple):
    """What :meth:`Online.update` returns for a sample: numpy arrays (read-only views).

    Attributes:
        mean: filtered state estimate, (nx,), in the model's state units.
        cov: its covariance, (nx, nx).
        params: parameter estimate, (p,); (0,) for a state-only filter.
        params_cov: its covariance, (p, p).
        loglik: log p(y_t | y_1:t-1) of the sample's observed components (float; 0 when none
            was observed or the filter diverged).
        nis: normalised innovation squared of the observed components (float; NaN once
            diverged).
        n_obs: number of observed components (int), the degrees of freedom of ``nis``.
        diverged: the filter has diverged or re-initialised at this or an earlier step.
        steps: model steps taken since the prior (int).
        t: time of the estimate [s] on the filter's clock, None without stamps.
    """

    mean: np.ndarray
    cov: np.ndarray
    params: np.ndarray
    params_cov: np.ndarray
    loglik: float
    nis: float
    n_obs: int
    diverged: bool
    steps: int
    t: float | None


class Layout(NamedTuple):
    """How a pytree of arrays packs into a few flat buffers (:func:`pack`): one per dtype, bool
    leaves stored in the floating buffer (as 0 and 1, exact), a typed PRNG key as its key data.

    Attributes:
        treedef: the pytree's structure.
        slots: per leaf ``(buffer, start, shape, dtype, key_impl)``: the buffer it lies in, its
            offset there, its shape and dtype, and for a typed PRNG key its implementation (its
            uint32 key data is stored) or None.
        buffers: per buffer ``(dtype, size)``.
    """

    treedef: Any
    slots: tuple
    buffers: tuple


def _stored(leaf):
    """(dtype, shape, key implementation or None) of a leaf as it is stored."""
    if jax.dtypes.issubdtype(leaf.dtype, jax.dtypes.prng_key):
        data = jax.eval_shape(jax.random.key_data, leaf)
        return np.dtype(data.dtype), tuple(data.shape), jax.random.key_impl(leaf)
    return np.dtype(leaf.dtype), tuple(leaf.shape), None


def layout_of(tree) -> Layout:
    """The :class:`Layout` of a pytree of concrete arrays."""
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    stored = [_stored(leaf) for leaf in leaves]
    floats = [d for d, _, _ in stored if np.issubdtype(d, np.floating)]
    order, sizes, slots = [], {}, []
    for leaf, (dtype, shape, impl) in zip(leaves, stored):
        into = floats[0] if dtype == np.bool_ and floats else dtype
        if into not in sizes:
            order.append(into)
            sizes[into] = 0
        slots.append((order.index(into), sizes[into], shape, dtype, impl))
        sizes[into] += math.prod(shape)
    return Layout(treedef, tuple(slots), tuple((d, sizes[d]) for d in order))


def pack(tree, layout: Layout) -> list:
    """The pytree ``tree`` (of ``layout``'s structure) as ``layout``'s flat buffers: a list of
    1-D arrays, the leaves stored in each raveled and concatenated in order."""
    parts = [[] for _ in layout.buffers]
    for leaf, (b, _, _, _, impl) in zip(jax.tree_util.tree_leaves(tree), layout.slots):
        data = leaf if impl is None else jax.random.key_data(leaf)
        parts[b].append(jnp.ravel(data).astype(layout.buffers[b][0]))
    return [jnp.concatenate(p) for p in parts]


def unpack(buffers, layout: Layout):
    """The pytree that :func:`pack` packed into ``buffers`` (a sequence of 1-D arrays)."""
    leaves = []
    for b, start_at, shape, dtype, impl in layout.slots:
        leaf = jnp.reshape(buffers[b][start_at:start_at + math.prod(shape)], shape)
        leaf = leaf.astype(dtype)
        leaves.append(leaf if impl is None else jax.random.wrap_key_data(leaf, impl=impl))
    return jax.tree_util.tree_unflatten(layout.treedef, leaves)


def initial_state(estimator: Estimator, y, u, x0, P0, th0, Pth0, key) -> OnlineState:
    """The :class:`OnlineState` before the first step, by the engine's :func:`~vehjax.engine.start`
    (which also checks the step's output shapes); y (1, ny), u (1, nu) are read for shapes."""
    state0, (x, P, th, Pth) = start(estimator, y, u, x0, P0, th0, Pth0, key)
    no = jnp.zeros((), bool)
    return OnlineState(state0, x, P, th, Pth, no, no)


def model_step(estimator: Estimator, state: OnlineState, y, u):
    """One model step: the estimator's ``step`` with y (ny,), u (nu,), then the engine's rule
    for a bad step (module docstring). Returns (state, StepOutput as reported)."""
    fstate, out = estimator.step(state.filter, y, u)
    p = len(estimator.param_names)
    bad = state.bad | ~output_ok(out, p=p)

    def held(new, old):
        return jnp.where(bad, old, new.astype(old.dtype))

    mean, cov = held(out.mean, state.mean), held(out.cov, state.cov)
    params, pcov = held(out.params, state.params), held(out.params_cov, state.params_cov)
    diverged = state.diverged | bad | jnp.asarray(out.reinit, bool)
    reported = StepOutput(
        mean=mean, cov=cov, loglik=jnp.where(bad, 0.0, out.loglik).astype(out.loglik.dtype),
        nis=jnp.where(bad, jnp.nan, out.nis), n_obs=jnp.where(bad, 0, out.n_obs),
        params=params, params_cov=pcov, reinit=diverged)
    return OnlineState(fstate, mean, cov, params, pcov, bad, diverged), reported


def predict_steps(estimator: Estimator, state: OnlineState, u, n):
    """``n`` (int32 scalar, may be traced) prediction-only steps (y all NaN) with inputs u."""
    nan_y = jnp.full((estimator.ny,), jnp.nan, state.mean.dtype)
    return jax.lax.fori_loop(0, n, lambda _, s: model_step(estimator, s, nan_y, u)[0], state)


def output_vector(out: StepOutput):
    """The reported outputs as one vector in the mean's dtype: mean (nx), cov (nx * nx),
    params (p), params_cov (p * p), loglik, nis, n_obs, diverged (``reinit`` holds it)."""
    dt = out.mean.dtype
    scalars = jnp.stack([out.loglik.astype(dt), out.nis.astype(dt), out.n_obs.astype(dt),
                         jnp.asarray(out.reinit).astype(dt)])
    return jnp.concatenate([out.mean, out.cov.ravel(), out.params, out.params_cov.ravel(),
                            scalars])


def packed_step(estimator: Estimator, layout: Layout, buffers, yu):
    """The compiled sample step on y and u concatenated, yu (ny + nu,) (one array to hand to
    the device per sample, not two): (buffers, outputs :func:`output_vector`)."""
    ny = estimator.ny
    state, out = model_step(estimator, unpack(buffers, layout), yu[:ny], yu[ny:])
    return pack(state, layout), output_vector(out)


def packed_gap(estimator: Estimator, layout: Layout, buffers, u, n):
    """``n`` prediction-only steps on packed buffers (the steps a stamp's gap adds)."""
    return pack(predict_steps(estimator, unpack(buffers, layout), u, n), layout)


def exported_step(estimator: Estimator, layout: Layout, buffers, y, u) -> dict:
    """The step :meth:`Online.export` writes: packed state buffers (a list), y (ny,), u (nu,)
    -> dict of ``state`` (the new buffers) and the reported outputs by name."""
    state, out = model_step(estimator, unpack(buffers, layout), y, u)
    return {"state": pack(state, layout), "mean": out.mean, "cov": out.cov,
            "params": out.params, "params_cov": out.params_cov, "loglik": out.loglik,
            "nis": out.nis, "n_obs": out.n_obs.astype(jnp.int32), "diverged": out.reinit}


def model_steps(t: float, t_filter: float | None, dt: float, max_gap: float | None) -> int:
    """Model steps of a sample stamped ``t`` [s] on a clock at ``t_filter`` [s] (None: not set,
    one step), by the module docstring's rule; ValueError naming ``t`` when refused."""
    if not math.isfinite(t):
        raise ValueError(f"t: expected a finite time stamp in seconds, got {t!r}")
    if t_filter is None:
        return 1
    gap = t - t_filter
    if max_gap is not None and gap > max_gap:
        raise ValueError(f"t: stamp {t!r} s is {gap!r} s after the filter's clock "
                         f"{t_filter!r} s, more than max_gap = {max_gap!r} s")
    k = round(gap / dt)
    if k < 1:
        raise ValueError(f"t: stamp {t!r} s goes back or repeats: it is {gap!r} s after the "
                         f"filter's clock {t_filter!r} s, less than half a model step "
                         f"dt = {dt!r} s")
    return k


def _vector(arg: str, value, n: int, dtype, missing: bool) -> np.ndarray:
    """A sample's y or u as a (n,) numpy array of ``dtype``, checked by the house rules (NaN
    missing in y, +-inf refused; u finite). A real numpy array takes the fast path (a few
    Python-level checks, about 1 us); anything else goes through :func:`vehjax.validation.array`."""
    if type(value) is np.ndarray and value.dtype.kind in "fiu":
        a = value.astype(dtype, copy=False)
    else:
        a = np.asarray(validation.array(arg, value, missing=missing), dtype=dtype)
    if a.shape != (n,):
        raise ValueError(f"{arg}: expected shape ({n},), got {a.shape}")
    values = a.tolist()
    if missing:
        if any(map(math.isinf, values)):
            validation.array(arg, a, missing=True)
    elif not all(map(math.isfinite, values)):
        validation.array(arg, a)
    return a


def _widths(estimator) -> tuple[int, int]:
    """(ny, nu) of an Estimator; ValueError naming ``estimator`` when it is none or lacks them."""
    if not isinstance(estimator, Estimator):
        raise ValueError(
            f"estimator: expected a vehjax.filters.Estimator, got {type(estimator).__name__}")
    if estimator.ny is None or estimator.nu is None:
        raise ValueError("estimator: Online needs the measurement and input widths; build the "
                         "Estimator with ny= and nu=")
    return estimator.ny, estimator.nu


def _stamp(t) -> float:
    """A time stamp [s] as a float (ValueError naming ``t``; finiteness: :func:`model_steps`)."""
    try:
        return float(t)
    except (TypeError, ValueError):
        raise ValueError(f"t: expected a time stamp in seconds, got {t!r}") from None


def _option(name: str, value):
    """None, or a finite float > 0."""
    return None if value is None else validation.number(name, value, 0.0)


class Online:
    """A filter run sample by sample (module docstring for the rules).

    Args:
        estimator: a :class:`vehjax.filters.Estimator` with ``ny`` and ``nu`` set (every
            builder's are).
        x0: state before the first step, (nx,); its dtype (float64 by default) is the filter's.
        P0: its covariance, (nx, nx) or (nx,) variances.
        theta0, P_theta0: as in :func:`vehjax.filter`.
        key: PRNG key, required when ``estimator.needs_key`` (the particle filters).
        dt: the model's step [s] (``model.dt``), required for time stamps.
        t0: time of x0, P0 [s]; None: one model step before the first stamped sample.
        max_gap: the largest gap [s] between a stamp and the filter's clock; None: no limit.

    Raises:
        ValueError: naming the argument, by :func:`vehjax.filter`'s rules, before tracing.
    """

    def __init__(self, estimator: Estimator, x0, P0, theta0=None, P_theta0=None, key=None, *,
                 dt=None, t0=None, max_gap=None):
        ny, nu = _widths(estimator)
        ys, us, x0, P0, th0, Pth0, _ = check_arguments(
            estimator, np.full((1, ny), np.nan), np.zeros((1, nu)), x0, P0, theta0, P_theta0, key)
        self.estimator = estimator
        self.dt = _option("dt", dt)
        self.max_gap = _option("max_gap", max_gap)
        self._t_origin = None if t0 is None else validation.number("t0", t0)
        self._steps = 0
        self._prior = (x0, P0, th0, Pth0)
        state = eager.call(initial_state, (estimator,), {}, jnp.asarray(ys), jnp.asarray(us),
                           jnp.asarray(x0), jnp.asarray(P0), th0, Pth0, key)
        self._compile(state)

    def _compile(self, state: OnlineState) -> None:
        """Lay out ``state`` and compile the sample step for it (once per filter)."""
        est = self.estimator
        self.layout = layout_of(state)
        self._dtype = np.dtype(state.mean.dtype)
        self._on = jax.sharding.SingleDeviceSharding(execution.live_device())
        self._buffers = self._placed(pack(state, self.layout))
        self._nan_y = np.full((est.ny,), np.nan, self._dtype)
        self._no_u = np.zeros((est.nu,), self._dtype)
        self._options = execution.compiler_options(execution.current(), est.workload)
        yu = self._spec((est.ny + est.nu,), self._dtype)
        specs = [self._spec(b.shape, b.dtype) for b in self._buffers]
        # the state's buffers are donated: the step writes the new state in place
        fn = jax.jit(partial(packed_step, est, self.layout), donate_argnums=0)
        self._step = fn.lower(specs, yu).compile(compiler_options=self._options)
        self._gap = self._unpack = None
        nx, p = est.nx, len(est.param_names)
        self._cuts = (nx, p, nx + nx * nx, nx + nx * nx + p, nx + nx * nx + p + p * p)

    def _spec(self, shape, dtype) -> jax.ShapeDtypeStruct:
        """An argument of the compiled steps: on the live device."""
        return jax.ShapeDtypeStruct(shape, dtype, sharding=self._on)

    def _placed(self, buffers) -> list:
        """State buffers (arrays) on the live device (:func:`vehjax.execution.live_device`)."""
        return [jax.device_put(np.asarray(b), self._on) for b in buffers]

    # ------------------------------------------------------------------------------------------
    # one sample

    def update(self, y=None, u=None, t=None) -> OnlineEstimate:
        """Filter one sample and return its estimate (:class:`OnlineEstimate`, numpy).

        Args:
            y: measurements (ny,), NaN for missing components; None: none (a prediction).
            u: inputs (nu,); None only for a model without inputs.
            t: time stamp [s] or None (one model step); see the module docstring.

        Raises:
            ValueError: naming ``y``, ``u`` or ``t`` (wrong shape, +-inf in y, non-finite u,
                a refused stamp), before anything runs; the filter is then unchanged.
        """
        est = self.estimator
        y = self._nan_y if y is None else _vector("y", y, est.ny, self._dtype, True)
        if u is None:
            if est.nu:
                raise ValueError(f"u: required, shape ({est.nu},) for this model's inputs")
            u = self._no_u
        else:
            u = _vector("u", u, est.nu, self._dtype, False)
        k, origin = 1, self._t_origin
        if t is not None:
            if self.dt is None:
                raise ValueError("t: time stamps need the model's step; pass dt=model.dt to "
                                 "Online")
            t = _stamp(t)
            k = model_steps(t, None if origin is None else origin + self._steps * self.dt,
                            self.dt, self.max_gap)
            if origin is None:  # the clock starts: this sample is one step after the last
                origin = t - (self._steps + 1) * self.dt
        buffers = self._buffers
        if k > 1:
            buffers = self._predict(buffers, u, k - 1)
        buffers, vec = self._step(buffers, np.concatenate((y, u)))
        self._buffers, self._t_origin = buffers, origin
        self._steps += k
        return self._estimate(np.asarray(vec))

    def _predict(self, buffers, u, n: int):
        """``n`` prediction-only steps (compiled on the first gap)."""
        if self._gap is None:
            fn = jax.jit(partial(packed_gap, self.estimator, self.layout), donate_argnums=0)
            specs = [self._spec(b.shape, b.dtype) for b in buffers]
            self._gap = fn.lower(specs, self._spec(u.shape, u.dtype),
                                 self._spec((), np.int32)).compile(
                compiler_options=self._options)
        return self._gap(buffers, u, np.int32(n))

    def _estimate(self, v: np.ndarray) -> OnlineEstimate:
        """The :class:`OnlineEstimate` of :func:`output_vector`'s ``v``: views, Python scalars."""
        nx, p, e1, e2, e3 = self._cuts
        loglik, nis, n_obs, diverged = v[-4:].tolist()
        t = None if self._t_origin is None else self._t_origin + self._steps * self.dt
        return OnlineEstimate(v[:nx], v[nx:e1].reshape(nx, nx), v[e1:e2],
                              v[e2:e3].reshape(p, p), loglik, nis, int(n_obs), diverged != 0.0,
                              self._steps, t)

    # ------------------------------------------------------------------------------------------
    # state, clock

    @property
    def state(self) -> OnlineState:
        """The whole state (:class:`OnlineState`): arrays on the device, a copy (the filter's
        own buffers are reused by the next update)."""
        if self._unpack is None:
            self._unpack = jax.jit(partial(unpack, layout=self.layout))
        return jax.device_put(self._unpack(self._buffers), jax.local_devices()[0])

    @property
    def steps(self) -> int:
        """Model steps taken since the prior."""
        return self._steps

    @property
    def t(self) -> float | None:
        """The filter's clock [s]: time of its last step (of the prior before any), None
        before the first stamp (without ``t0``)."""
        if self._t_origin is None:
            return None
        return self._t_origin + self._steps * self.dt

    def save(self, path) -> None:
        """Write the state, the clock and the prior to ``path`` (one ``np.savez`` file,
        module docstring); :meth:`load` with the same estimator continues from it."""
        x0, P0, th0, Pth0 = self._prior
        none = np.zeros((0,))
        entries = {f"state_{i}": np.asarray(b) for i, b in enumerate(self._buffers)}
        np.savez(path, format=FORMAT, estimator=self.estimator.name,
                 n_buffers=len(self._buffers), x0=x0, P0=P0,
                 theta0=none if th0 is None else th0, P_theta0=none if Pth0 is None else Pth0,
                 has_theta0=th0 is not None, has_P_theta0=Pth0 is not None,
                 dt=np.nan if self.dt is None else self.dt,
                 max_gap=np.nan if self.max_gap is None else self.max_gap,
                 t_origin=np.nan if self._t_origin is None else self._t_origin,
                 steps=self._steps, **entries)

    @classmethod
    def load(cls, path, estimator: Estimator) -> "Online":
        """The filter :meth:`save` wrote to ``path``, continuing with ``estimator`` (the one
        it was saved from, or one built alike). ValueError naming ``path`` when the file is not
        such a file or its state does not fit the estimator."""
        _widths(estimator)
        saved = _read(path)
        if str(saved["estimator"]) != estimator.name:  # refused before anything compiles
            raise ValueError(f"path: {path} holds the state of estimator "
                             f"{str(saved['estimator'])!r}, not of {estimator.name!r}")
        opt = {k: None if np.isnan(saved[k]) else float(saved[k]) for k in ("dt", "max_gap")}
        key = jax.random.key(0) if estimator.needs_key else None  # replaced by the saved state
        th0 = saved["theta0"] if bool(saved["has_theta0"]) else None
        Pth0 = saved["P_theta0"] if bool(saved["has_P_theta0"]) else None
        live = cls(estimator, saved["x0"], saved["P0"], th0, Pth0, key, **opt)
        buffers = [saved[f"state_{i}"] for i in range(int(saved["n_buffers"]))]
        expected = [(np.dtype(d), (n,)) for d, n in live.layout.buffers]
        if [(b.dtype, b.shape) for b in buffers] != expected:
            raise ValueError(f"path: {path} holds the state of estimator "
                             f"{str(saved['estimator'])!r} in buffers "
                             f"{[(str(b.dtype), b.shape) for b in buffers]}; estimator "
                             f"{estimator.name!r} expects {[(str(d), s) for d, s in expected]}")
        live._buffers = live._placed(buffers)
        live._t_origin = None if np.isnan(saved["t_origin"]) else float(saved["t_origin"])
        live._steps = int(saved["steps"])
        return live

    # ------------------------------------------------------------------------------------------
    # export

    def export(self, path, platforms=None):
        """Write the one-model-step function (:func:`exported_step`) with ``jax.export`` to
        ``path`` (module docstring for the loading side) and return its ``jax.export.Exported``.

        ``platforms``: a sequence such as ("cpu", "cuda") to run it on; None: this process's
        default backend. Needs the ``flatbuffers`` package (jax's serialization)."""
        est = self.estimator
        fn = jax.jit(partial(exported_step, est, self.layout))
        specs = [jax.ShapeDtypeStruct(b.shape, b.dtype) for b in self._buffers]
        exp = jax.export.export(fn, platforms=platforms)(
            specs, jax.ShapeDtypeStruct((est.ny,), self._dtype),
            jax.ShapeDtypeStruct((est.nu,), self._dtype))
        try:
            data = exp.serialize()
        except ImportError as err:
            raise ImportError(f"Online.export needs the flatbuffers package (pip install "
                              f"flatbuffers, or vehjax[online]): {err}") from None
        with open(path, "wb") as f:
            f.write(data)
        return exp


def _read(path) -> dict:
    """The entries of a file :meth:`Online.save` wrote (ValueError naming ``path``)."""
    try:
        with np.load(path, allow_pickle=False) as f:
            saved = {k: f[k] for k in f.files}
    except (OSError, ValueError) as err:
        raise ValueError(f"path: cannot read {path} as a saved Online filter ({err})") from None
    if str(saved.get("format", "")) != FORMAT:
        raise ValueError(f"path: {path} is not a saved Online filter (format {FORMAT!r})")
    return saved
