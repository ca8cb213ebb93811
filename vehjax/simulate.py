"""Truth and noisy measurements for R Monte-Carlo runs in one jitted, vmapped call.

Time convention (shared with :func:`vehjax.run`): ``scenario.x0`` is the state before the first
step; row t of the output holds the state after applying input u_t,

    states[t]       = transition(states[t-1], u_t + steering offset, theta_r) + w_t
    measurements[t] = observe(states[t], u_t + steering offset, theta_r) + bias_t + v_t

with w_t ~ N(0, diag(process_std * noise_scale.process[t])^2) and v_t ~ N(0, diag(meas_std *
noise_scale.meas[t])^2) (:class:`NoiseScale`; biases: :class:`BiasWalk`). The filter is given the *measured* inputs ``sim.inputs`` (without the steering
offset), as a car's estimator would be.

Parameters (:class:`ParamDraw`): ``params.theta`` (the model's, or the one given) must lie in
the model's declared domains (:meth:`vehjax.models.BaseModel.param_domains`; ValueError naming
``params.theta`` and the parameter, before anything is traced); a model without domains is not
checked. The per-run perturbation of ``params.std`` is drawn while tracing and is not checked: a run it pushes outside the domain
shows as ``diverged`` if its states blow up.

Divergence, with the meaning :func:`vehjax.run` gives it (:mod:`vehjax.engine`): a step whose
new state is not finite, or leaves the model's state envelope (``model.state_envelope()``, the
largest plausible magnitude of each state: e.g. 300 m/s for a velocity; finiteness only for a
model without one), is bad, and so is every later step of that run. The run is ``diverged``
(``diverged_at`` its first bad step, -1 for none) and, as ``run`` holds a diverged filter's
outputs, its states, biases and measurements from that step on hold their last good values (the
initial state and bias, and the noise-free measurement of the initial state, when the first
step is bad): the simulation is frozen there, so that nothing non-finite reaches a filter run on
it (a NaN measurement would pass for a missing one). ``Simulation.diverged`` says which runs to
drop.

Measurements that are not finite while the states are: a model whose ``observe`` returns NaN
or +-inf for a finite state (a square root of a negative number, a division by zero) gives
measurements that a filter would take for missing ones (NaN) or refuse (+-inf). Such runs are
flagged in ``Simulation.nonfinite_measurements`` and a warning says how many there are; their
values are left as the model gave them (the states are fine, and the run is not frozen).

Sizes: every array of the study is held at once (the noise draws, then the states, measurements
and biases of all runs), about :func:`study_bytes`; a study that cannot fit in the memory of
the device it runs on (:func:`vehjax.execution.memory_limit`) is refused up front, before
anything is traced or allocated (:func:`check_size`, ValueError naming ``runs`` and the
scenario's steps). A long study (at least ``PROGRESS_RUN_STEPS`` runs x steps) shows a progress
bar over its steps on stderr (:mod:`vehjax.runtime.progress`; ``progress=`` forces it on or off).
"""

from __future__ import annotations

import dataclasses
import itertools
import threading
import warnings
from typing import Any, Callable, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import execution, validation
from .runtime.progress import Progress, text_bar

__all__ = ["Simulation", "simulate", "BiasWalk", "NoiseScale", "ParamDraw", "check_size",
           "study_bytes", "PROGRESS_RUN_STEPS"]

#: a study of at least this many runs x steps shows its progress by default (about ten seconds
#: of a 3-state model on two CPU cores; below it, no bar)
PROGRESS_RUN_STEPS = 5_000_000
_PROGRESS_UPDATES = 100  # the bar moves about this many times over a study


class Simulation(NamedTuple):
    """R simulated runs of one scenario.

    Attributes:
        states: (R, T, nx) true states after each step.
        measurements: (R, T, ny) noisy measurements.
        inputs: (T, nu) measured inputs, shared by all runs.
        theta: (R, np) true parameters of each run.
        biases: (R, T, ny) measurement biases (zeros unless a bias walk was asked for).
        x0: (R, nx) initial states.
        t: (T,) time [s] of each row.
        state_names, input_names, param_names, output_names: the model's names.
        diverged: (R,) bool, the run's state became non-finite or left the model's state
            envelope; its rows from ``diverged_at`` on hold the last good values (module
            docstring).
        diverged_at: (R,) int32, the first step it did, or -1.
        nonfinite_measurements: (R,) bool, the model's ``observe`` gave a NaN or +-inf
            measurement at some step while the run's state was finite (and not diverged): a
            filter would read a NaN as a missing measurement. A warning names how many runs.
    """

    states: jnp.ndarray
    measurements: jnp.ndarray
    inputs: jnp.ndarray
    theta: jnp.ndarray
    biases: jnp.ndarray
    x0: jnp.ndarray
    t: np.ndarray
    state_names: tuple
    input_names: tuple
    param_names: tuple
    output_names: tuple
    diverged: jnp.ndarray | None = None
    diverged_at: jnp.ndarray | None = None
    nonfinite_measurements: jnp.ndarray | None = None

    def to_dict(self) -> dict:
        """Named numpy arrays, e.g. for ``np.savez``; names are stored as string arrays."""
        return {
            "states": np.asarray(self.states),
            "measurements": np.asarray(self.measurements),
            "inputs": np.asarray(self.inputs),
            "theta": np.asarray(self.theta),
            "biases": np.asarray(self.biases),
            "x0": np.asarray(self.x0),
            "t": np.asarray(self.t),
            "state_names": np.array(self.state_names),
            "input_names": np.array(self.input_names),
            "param_names": np.array(self.param_names),
            "output_names": np.array(self.output_names),
            "diverged": np.asarray(self.diverged),
            "diverged_at": np.asarray(self.diverged_at),
            "nonfinite_measurements": np.asarray(self.nonfinite_measurements),
        }

    def save(self, path) -> None:
        """Write the named arrays to an ``.npz`` file."""
        np.savez(path, **self.to_dict())


def _real(name: str, value, nonnegative: bool):
    """The checks of a record's field that need no model (its sizes are checked by
    :func:`simulate`): real and finite (:func:`vehjax.validation.array`), non-negative for a
    std or a scale; ValueError naming it."""
    if value is None or callable(value):
        return
    arr = np.asarray(validation.array(name, value, allow_nan=True), dtype=float)
    if not np.all(np.isfinite(arr)) or (nonnegative and np.any(arr < 0)):
        what = "non-negative, finite" if nonnegative else "finite"
        raise ValueError(f"{name}: expected {what} values, got {arr}")


@dataclasses.dataclass(frozen=True)
class BiasWalk:
    """Random-walk measurement biases, the option ``bias`` of :func:`simulate`:
    ``bias_t = bias_{t-1} + N(0, diag(std)^2)`` from ``bias_0 = initial``, added to the
    measurements (``Simulation.biases``).

    Attributes:
        std: std of the per-step increments, scalar or (ny,), output units per step; None: 0.
        initial: the initial biases, scalar or (ny,), output units; None: 0.
    """

    std: Any = None
    initial: Any = None

    def __post_init__(self):
        _real("bias.std", self.std, True)
        _real("bias.initial", self.initial, False)


@dataclasses.dataclass(frozen=True)
class NoiseScale:
    """Time-varying multipliers of the noise stds, the option ``noise_scale`` of
    :func:`simulate`: the process noise's std at step t is ``process_std * process[t]``, the
    measurement noise's ``meas_std * meas[t]``.

    Attributes:
        process, meas: (T,) non-negative factors, or callables of the time vector t [s] (e.g.
            ``lambda t: np.sin(np.pi * t / 10)`` for paper 001 eq. 31-32); None: 1.
    """

    process: Callable | np.ndarray | None = None
    meas: Callable | np.ndarray | None = None

    def __post_init__(self):
        _real("noise_scale.process", self.process, True)
        _real("noise_scale.meas", self.meas, True)


@dataclasses.dataclass(frozen=True)
class ParamDraw:
    """The runs' true parameters, the option ``params`` of :func:`simulate`:
    ``theta_r = theta * (1 + std * N(0, 1))``.

    Attributes:
        theta: the parameters, (np,) or (R, np); None: ``model.theta``. Must lie in the
            model's declared domains (module docstring).
        std: relative std of a per-run perturbation, scalar or (np,); None: 0.
    """

    theta: Any = None
    std: Any = None

    def __post_init__(self):
        _real("params.theta", self.theta, False)
        _real("params.std", self.std, True)


def _vector(name: str, value, n: int, what: str, allow_none=True):
    """A non-negative finite vector of length n from a scalar or a sequence."""
    if value is None:
        return np.zeros(n)
    arr = np.asarray(validation.array(name, value, allow_nan=True), dtype=float)  # real
    if arr.ndim == 0:
        arr = np.full(n, float(arr))
    if arr.shape != (n,):
        raise ValueError(f"{name}: expected a scalar or shape ({n},) ({what}), got shape {arr.shape}")
    if not np.all(np.isfinite(arr)) or np.any(arr < 0):
        raise ValueError(f"{name}: expected non-negative, finite values, got {arr}")
    return arr


def _scale(name: str, value, t: np.ndarray):
    """A non-negative (T,) std multiplier from None, a callable of t [s], or an array."""
    if value is None:
        return np.ones_like(t)
    arr = np.asarray(validation.array(name, value(t) if callable(value) else value,
                                     allow_nan=True), dtype=float)  # real; finite below
    if arr.ndim == 0:
        arr = np.full_like(t, float(arr))
    if arr.shape != t.shape:
        raise ValueError(f"{name}: expected shape {t.shape} (one factor per step), got {arr.shape}")
    if not np.all(np.isfinite(arr)) or np.any(arr < 0):
        raise ValueError(f"{name}: expected non-negative, finite factors")
    return arr


def _scenario(model, scenario):
    """(inputs (T, nu), x0 (nx,)) of a Scenario, checked against ``model`` by the rules every
    entry point shares (:mod:`vehjax.validation`: real, finite, naming ``scenario.inputs`` or
    ``scenario.x0`` and the first bad index), also for a Scenario built directly."""
    if not all(hasattr(scenario, a) for a in ("inputs", "x0")):
        raise ValueError(f"scenario: expected a vehjax.scenarios.Scenario (inputs, x0), got "
                         f"{type(scenario).__name__}")
    nu, nx = len(model.input_names), len(model.state_names)
    inputs = np.asarray(validation.array("scenario.inputs", scenario.inputs), dtype=float)
    if inputs.ndim != 2 or inputs.shape[1] != nu or inputs.shape[0] == 0:
        raise ValueError(
            f"scenario.inputs: expected shape (T, {nu}) with T >= 1 for {type(model).__name__}'s "
            f"inputs {tuple(model.input_names)}, got {inputs.shape}; build the scenario for "
            f"this model"
        )
    x0 = np.asarray(validation.per_run("scenario.x0", scenario.x0, (nx,),
                                      what=f"{type(model).__name__}'s {nx} states"), dtype=float)
    return inputs, x0


def simulate(
    model,
    scenario,
    runs: int = 1,
    key=None,
    process_std=None,
    meas_std=None,
    *,
    params: ParamDraw | None = None,
    x0_std=None,
    noise_scale: NoiseScale | None = None,
    bias: BiasWalk | None = None,
    steering_offset: float = 0.0,
    progress: bool | None = None,
) -> Simulation:
    """Simulate ``runs`` noisy realisations of ``scenario`` on ``model``.

    Args:
        model: a vehjax model.
        scenario: a :class:`vehjax.scenarios.Scenario` built for this model.
        runs: number of Monte-Carlo runs R (>= 1).
        key: a ``jax.random.key``; the same key gives the same runs. Defaults to key(0).
        process_std: std of the additive process noise per step, scalar or (nx,), state units.
        meas_std: std of the measurement noise, scalar or (ny,), output units.
        params: the true parameters and their per-run perturbation, a :class:`ParamDraw`
            (``theta``, ``std``); None: ``model.theta`` for every run.
        x0_std: std of a per-run perturbation of the initial state, scalar or (nx,).
        noise_scale: time-varying multipliers of the two stds, a :class:`NoiseScale`
            (``process``, ``meas``); None: constant stds.
        bias: random-walk measurement biases, a :class:`BiasWalk` (``std``, ``initial``);
            None: no biases.
        steering_offset: constant offset [rad] added to the true steering input named "delta"
            (paper 004 eq. 4); the returned ``inputs`` are the measured ones without it.
        progress: a progress bar over the steps on stderr: None (default) for a study of at
            least ``PROGRESS_RUN_STEPS`` runs x steps, True always, False never.

    Returns:
        A :class:`Simulation`.

    Raises:
        ValueError: naming the argument (a record's field as ``bias.std``), before anything
            is traced: a bad model, scenario, std, scale, parameter, record or key, and a study whose arrays cannot fit in the device's
            memory (:func:`check_size`, naming ``runs`` and the scenario's steps).

    Warns:
        RuntimeWarning: runs whose measurements are not finite while their states are
            (``Simulation.nonfinite_measurements``).
    """
    validation.model(model)
    if isinstance(runs, bool) or not isinstance(runs, (int, np.integer)) or runs < 1:
        raise ValueError(f"runs: expected an integer >= 1, got {runs!r}")
    runs = int(runs)
    progress = validation.flag("progress", progress, allow_none=True)
    nx, ny, n_par = len(model.state_names), len(model.output_names), len(model.param_names)
    inputs, x0 = _scenario(model, scenario)
    n_steps = inputs.shape[0]
    check_size(model, runs, n_steps)
    t = np.arange(n_steps) * model.dt

    params = validation.record("params", params, ParamDraw)
    noise_scale = validation.record("noise_scale", noise_scale, NoiseScale)
    bias = validation.record("bias", bias, BiasWalk)
    q_std = _vector("process_std", process_std, nx, "one std per state")
    r_std = _vector("meas_std", meas_std, ny, "one std per output")
    p_std = _vector("params.std", params.std, n_par, "a relative std per parameter")
    s_std = _vector("x0_std", x0_std, nx, "one std per state")
    b_std = _vector("bias.std", bias.std, ny, "one std per output")
    b0 = _bias0(bias.initial, ny)
    q_scale = _scale("noise_scale.process", noise_scale.process, t)
    r_scale = _scale("noise_scale.meas", noise_scale.meas, t)
    offset = _input_offset(model, steering_offset)
    theta = params.theta
    base_theta = validation.per_run("params.theta",
                                    np.asarray(model.theta) if theta is None else theta,
                                    (n_par,), runs, f"parameters {tuple(model.param_names)}")
    base_theta = np.asarray(base_theta, dtype=float)
    validation.in_domain("params.theta", base_theta, _declared(model, "param_domains"))
    base_theta = np.broadcast_to(base_theta, (runs, n_par))
    keys = validation.key(jax.random.key(0) if key is None else key, runs)

    dtype = jnp.result_type(float)
    arrays = dict(
        inputs=jnp.asarray(inputs, dtype),
        x0=jnp.asarray(x0, dtype),
        theta=jnp.asarray(base_theta, dtype),
        q=jnp.asarray(q_std[None, :] * q_scale[:, None], dtype),
        r=jnp.asarray(r_std[None, :] * r_scale[:, None], dtype),
        p_std=jnp.asarray(p_std, dtype),
        s_std=jnp.asarray(s_std, dtype),
        b_std=jnp.asarray(b_std, dtype),
        b0=jnp.asarray(b0, dtype),
        offset=jnp.asarray(offset, dtype),
        envelope=jnp.asarray(_envelope(model, nx), dtype),
    )
    show = runs * n_steps >= PROGRESS_RUN_STEPS if progress is None else progress
    states, meas, thetas, biases, x0s, bad_at, bad_y = _execute(model, keys, arrays, show)
    _warn_nonfinite(np.asarray(bad_y), runs)
    return Simulation(
        states=states,
        measurements=meas,
        inputs=arrays["inputs"],
        theta=thetas,
        biases=biases,
        x0=x0s,
        t=t,
        state_names=tuple(model.state_names),
        input_names=tuple(model.input_names),
        param_names=tuple(model.param_names),
        output_names=tuple(model.output_names),
        diverged=bad_at >= 0,
        diverged_at=bad_at,
        nonfinite_measurements=bad_y,
    )


def study_bytes(model, runs: int, steps: int, itemsize: int = 8) -> int:
    """Bytes that :func:`simulate` holds at once for ``runs`` runs of ``steps`` steps of
    ``model`` in floats of ``itemsize`` bytes, about: per run and step the noise draws (nx +
    2 ny numbers) and the states, measurements and biases (nx + 2 ny), each twice (the scan's
    time-major copies and the returned run-major arrays), and the divergence flag; per step the
    shared inputs and noise stds (nu + nx + ny), twice."""
    nx, ny, nu = len(model.state_names), len(model.output_names), len(model.input_names)
    per_run_step = 2 * 2 * (nx + 2 * ny) * itemsize + 2
    return int(runs) * int(steps) * per_run_step + int(steps) * 2 * (nu + nx + ny) * itemsize


def check_size(model, runs: int, steps: int, device=None, *,
               names: str = "runs, scenario") -> None:
    """Refuse a study of ``runs`` runs x ``steps`` steps of ``model`` whose arrays
    (:func:`study_bytes`) cannot fit in the memory of ``device`` (default: JAX's first device,
    where :func:`simulate` runs; :func:`vehjax.execution.memory_limit`): one-line ValueError
    starting with ``names`` (the arguments that set the size), with the estimate and the limit.
    :func:`simulate` checks it before anything is traced or allocated; a caller that builds a
    long scenario can check it before building it (the scenario's steps: its duration over
    ``model.dt``, :func:`vehjax.scenarios.default_steps`)."""
    device = jax.devices()[0] if device is None else device
    itemsize = np.dtype(jnp.result_type(float)).itemsize
    execution.check_memory(
        study_bytes(model, runs, steps, itemsize), device,
        what=f"{names}: {runs} run{'s' if runs != 1 else ''} x {steps} steps of "
             f"{type(model).__name__}",
        advice="use fewer runs or fewer steps (a shorter scenario, or a larger dt)")


def _warn_nonfinite(flags: np.ndarray, runs: int) -> None:
    """The warning for runs whose measurements are not finite while their states are."""
    n = int(np.sum(flags))
    if n:
        first = int(np.argmax(flags))
        warnings.warn(
            f"simulate: model.observe returned NaN or +-inf measurements while the states were "
            f"finite in {n} of {runs} runs (the first: run {first}); a filter reads a NaN "
            f"measurement as a missing one. Simulation.nonfinite_measurements flags them",
            RuntimeWarning, stacklevel=3)


def _declared(model, method: str):
    """The model's ``param_domains()`` / ``state_envelope()``, or None for a model class of the
    user's own that has no such method."""
    fn = getattr(model, method, None)
    return fn() if callable(fn) else None


def _envelope(model, nx: int) -> np.ndarray:
    """(nx,) largest plausible |state|: the model's envelope, +inf where it has none."""
    env = _declared(model, "state_envelope")
    return np.full(nx, np.inf) if env is None else np.asarray(env, dtype=float)


def _bias0(bias0, ny: int) -> np.ndarray:
    """``simulate``'s initial output biases (ny,) from ``bias.initial``: None (zeros), a scalar
    or one per output."""
    b0 = np.asarray(validation.array("bias.initial", 0.0 if bias0 is None else bias0,
                                     allow_nan=True), dtype=float)
    b0 = np.full(ny, float(b0)) if b0.ndim == 0 else b0
    if b0.shape != (ny,) or not np.all(np.isfinite(b0)):
        raise ValueError(f"bias.initial: expected a finite scalar or shape ({ny},), got {b0}")
    return b0


def _input_offset(model, steering_offset) -> np.ndarray:
    """The constant offset (nu,) added to the inputs: ``steering_offset`` [rad] on "delta"."""
    steering_offset = validation.number("steering_offset", steering_offset,
                                        what="a finite number in rad")
    if not np.isfinite(steering_offset):
        raise ValueError(f"steering_offset: expected a finite number in rad, got {steering_offset}")
    offset = np.zeros(len(model.input_names))
    if steering_offset != 0.0:
        if "delta" not in model.input_names:
            raise ValueError(
                f"steering_offset: {type(model).__name__} has no input named 'delta' "
                f"(inputs {tuple(model.input_names)})"
            )
        offset[list(model.input_names).index("delta")] = steering_offset

    return offset


def _inside(x, envelope):
    """Whether a state is finite and within the envelope (|x_i| <= envelope_i)."""
    return jnp.all(jnp.isfinite(x) & (jnp.abs(x) <= envelope))


# ----------------------------------------------------------------------------------------------
# the study: one compiled program, a progress bar for a long one

_BARS: dict[int, Progress] = {}  # the bars of the studies running now, by token
_TOKENS = itertools.count()


def _execute(model, keys, arrays, show: bool):
    """The compiled study, with a progress bar over its steps when ``show``: the program
    reports every ``steps / _PROGRESS_UPDATES`` steps through a host callback (compiled in only
    then) to the bar its token names."""
    if not show:
        return _simulate_jit(model, keys, arrays, None)
    n_steps = arrays["inputs"].shape[0]
    token = next(_TOKENS)
    bar = Progress(n_steps, "vehjax.simulate", True, unit="step", interval=0.5,
                   first_text=_bar_text(0, n_steps))
    _BARS[token] = bar
    try:
        out = _simulate_jit(model, keys, {**arrays, "token": jnp.asarray(token, jnp.int32)},
                            max(1, n_steps // _PROGRESS_UPDATES))
        jax.block_until_ready(out)
        _tick(token, n_steps)
    finally:
        _BARS.pop(token, None)
        bar.close()
    return out


def _bar_text(done: int, total: int) -> str:
    return f"vehjax.simulate [{text_bar(done, total)}] step {done}/{total}"


def _tick(token, done) -> None:
    """Host callback: the study ``token`` has done ``done`` steps."""
    bar = _BARS.get(int(token))
    if bar is not None:
        done = int(done)
        bar.update(done, "", _bar_text(done, bar.total))


def _simulate_jit(model, keys, a, every):
    return _simulate_runs(model, keys, a, every)


def _draws(a, n_steps: int, key, theta_nom):
    """One run's parameters (np,), initial state (nx,) and noise draws (n_steps, nx + 2 ny)."""
    nx, ny = a["x0"].shape[0], a["b0"].shape[0]
    k_par, k_x0, k_noise = jax.random.split(key, 3)
    theta = theta_nom * (1.0 + a["p_std"] * jax.random.normal(k_par, theta_nom.shape))
    x0 = a["x0"] + a["s_std"] * jax.random.normal(k_x0, a["x0"].shape)
    return theta, x0, jax.random.normal(k_noise, (n_steps, nx + 2 * ny))


def _step(model, a, carry, xs, theta):
    """One step of one run (module docstring): the new state, bias and measurement, frozen
    at their last good values once the state is bad; whether the measurement is not finite
    while the state is."""
    nx, ny = a["x0"].shape[0], a["b0"].shape[0]
    x, bias, y_prev, bad, bad_y = carry
    u, q, r, e = xs
    u_true = u + a["offset"]
    x_next = model.transition(x, u_true, theta) + q * e[:nx]
    bias_next = bias + a["b_std"] * e[nx + ny:]
    y = model.observe(x_next, u_true, theta) + bias_next + r * e[nx:nx + ny]
    bad = bad | ~_inside(x_next, a["envelope"])
    bad_y = bad_y | (~bad & ~jnp.all(jnp.isfinite(y)))
    x_next, bias_next, y = (jnp.where(bad, old, new) for old, new in
                            ((x, x_next), (bias, bias_next), (y_prev, y)))
    return (x_next, bias_next, y, bad, bad_y), (x_next, y, bias_next, bad)


def _report(token, i, every: int) -> None:
    """Inside the scan: tell the host every ``every`` steps (step ``i`` counted from 0)."""
    jax.lax.cond((i + 1) % every == 0, lambda: jax.debug.callback(_tick, token, i + 1),
                 lambda: None)


@eqx.filter_jit
def _simulate_runs(model, keys, a, every):
    """Every run side by side (vmapped), stepped through time by one scan; ``every``: steps
    between progress reports, None for none (static)."""
    n_steps, ny = a["inputs"].shape[0], a["b0"].shape[0]
    theta, x0, eps = jax.vmap(lambda k, th: _draws(a, n_steps, k, th))(keys, a["theta"])
    y0 = jax.vmap(lambda x, th: model.observe(x, a["inputs"][0] + a["offset"], th))(x0, theta)
    runs = keys.shape[0]
    carry0 = (x0, jnp.broadcast_to(a["b0"], (runs, ny)), (y0 + a["b0"]).astype(x0.dtype),
              jnp.zeros(runs, bool), jnp.zeros(runs, bool))
    step = jax.vmap(lambda c, xs, th: _step(model, a, c, xs, th), in_axes=(0, (None, None, None, 0), 0))

    def body(carry, xs):
        *per_step, i = xs
        carry, out = step(carry, tuple(per_step), theta)
        if every is not None:
            _report(a["token"], i, every)
        return carry, out

    xs = (a["inputs"], a["q"], a["r"], jnp.swapaxes(eps, 0, 1), jnp.arange(n_steps))
    carry, (states, meas, biases, bad) = jax.lax.scan(body, carry0, xs)
    bad_at = jnp.where(jnp.any(bad, axis=0), jnp.argmax(bad, axis=0), -1).astype(jnp.int32)
    run_major = [jnp.swapaxes(v, 0, 1) for v in (states, meas, biases)]
    return run_major[0], run_major[1], theta, run_major[2], x0, bad_at, carry[4]
