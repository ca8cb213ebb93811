"""The marginalized PF's set-up: every check of the builders' arguments (a ValueError naming
the argument, before anything is traced) and the constants the filters are built from
(:class:`Setup`), the model as the steps use it (:class:`ModelFns`), and the start of the
noise statistics (:class:`NiW`). Shared by :func:`~vehjax.filters.marginalized.marginalized_pf`
and :func:`~vehjax.filters.marginalized.marginalized_pf_grid`.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ... import validation
from .. import smc
from .linearise import entry_kinds, linearise

__all__ = ["NiW", "Setup", "ModelFns", "configure", "model_fns", "std_dict"]


class NiW(NamedTuple):
    """The Normal-inverse-Wishart statistics of the noise (paper 004, eq. 17-20): where they
    start and how fast they forget.

    Attributes:
        std0: dict of initial guesses of every unknown std: the noisy input and each sensor, in
            the input's and outputs' units (the paper uses about twice the true values).
            Required.
        mean0: dict of initial offset / bias guesses, same keys (missing ones 0); None: zeros.
        gamma0: initial gamma (1 / kappa) > 0: the prior covariance of the offset and the biases
            is gamma0 times the noise covariance, so 1 says "the offset may be as large as the
            noise std".
        nu0: initial degrees of freedom, > d + 1 (d = 1 + the number of sensors); None: d + 4
            (a light prior, about three samples' worth of std0).
        forgetting: lambda of eq. 20 in (0, 1]; lambda min(nu0, 1 / (1 - lambda)) must exceed
            d + 1 so that the Student-t stays of finite variance.
    """

    std0: Any = None
    mean0: Any = None
    gamma0: float = 1.0
    nu0: float | None = None
    forgetting: float = 0.995


def _std_value(name, value):
    return validation.number(name, value, 0.0, what="a positive, finite standard deviation")


def std_dict(arg, value, required, allowed, unit_hint):
    if not isinstance(value, dict):
        raise ValueError(f"{arg}: expected a dict name -> std, got {value!r}")
    unknown = [k for k in value if k not in allowed]
    if unknown:
        raise ValueError(f"{arg}: unknown name(s) {unknown}; expected names from {tuple(allowed)}")
    missing = [k for k in required if k not in value]
    if missing:
        raise ValueError(f"{arg}: missing initial std for {missing} ({unit_hint})")
    return {k: _std_value(f"{arg}[{k!r}]", v) for k, v in value.items()}


def _affine_deviation(model, states, seed=0, n_points=4):
    """Largest relative deviation of transition and observe from an affine map in the given
    ``states`` over a few random points, extrapolating to 2.5 between two of them; None when no
    point gave finite values. All points in one jitted, vmapped evaluation."""
    rng = np.random.default_rng(seed)
    nx, nu = len(model.state_names), len(model.input_names)
    theta = jnp.asarray(model.theta, float)
    k = len(states)
    a = 2.5
    X = np.repeat(rng.normal(0.0, 0.1, (n_points, 1, nx)), 3, axis=1)
    U = np.repeat(1.0 + 0.1 * rng.normal(size=(n_points, 1, nu)), 3, axis=1)
    z1, z2 = rng.normal(0.0, 0.5, (n_points, k)), rng.normal(0.0, 0.5, (n_points, k))
    Z = np.stack([z1, z2, a * z1 + (1 - a) * z2], axis=1)  # (n_points, 3, k)
    X[:, :, states] = Z

    def both(x, u):
        return jnp.concatenate([jnp.ravel(model.transition(x, u, theta)),
                                jnp.ravel(model.observe(x, u, theta))])

    P = np.asarray(jax.jit(jax.vmap(both))(X.reshape(-1, nx), U.reshape(-1, nu)))
    P = P.reshape(n_points, 3, -1)
    ok = np.all(np.isfinite(P), axis=(1, 2))
    if not ok.any():
        return None
    p1, p2, p3 = P[ok, 0], P[ok, 1], P[ok, 2]
    err = np.abs(p3 - (a * p1 + (1 - a) * p2))
    return float(np.max(err / (1.0 + np.abs(p1) + np.abs(p2) + np.abs(p3))))


def _check_affine(model, li):
    """Raise ValueError naming ``linear_states`` unless transition and observe are affine in
    the linear states at a few random points."""
    if len(li) == 0:
        return
    dev = _affine_deviation(model, li)
    if dev is None:
        raise ValueError(
            "linear_states: could not check that the model is affine in them (transition and "
            "observe gave no finite values at the test points)"
        )
    if dev > 1e-6:
        names = tuple(model.state_names[i] for i in li)
        raise ValueError(
            f"linear_states: the model is not affine in {names} (transition or observe "
            f"deviates by {dev:.3g} relative from an affine map); only states that enter "
            f"linearly can be Rao-Blackwellised"
        )
class Setup(NamedTuple):
    """Everything a marginalized PF fixes when it is built (numpy and Python values, static
    under ``jit``); see :func:`configure`."""

    n_particles: int
    forgetting: float  # lambda of eq. 20
    gamma0: float  # the NiW's initial gamma (1 / kappa)
    nu0: float  # the NiW's initial degrees of freedom
    noise_dim: int  # d, the dimension of v = (w, e)
    n_sensors: int
    n_linear: int  # linear states (Rao-Blackwellised)
    n_sampled: int  # states that are particles
    n_states: int  # the model's states
    n_kalman: int  # the dimension of each particle's Kalman filter
    gaussian_states: bool  # each particle a Gaussian over all states (kalman_states="all")
    sampled_idx: np.ndarray  # the sampled states' indices in the model's state vector
    linear_idx: np.ndarray  # the linear states' indices
    model_order: np.ndarray  # (sampled, linear) order -> model order
    input_idx: int  # the noisy input's index
    linear_noise: np.ndarray  # (n_linear, n_linear) process noise of the linear states
    used_rows: np.ndarray  # the output rows the filter uses (sensors and known-std outputs)
    sensor_rows: list  # sensor j's row among the used rows
    sensor_of_row: dict  # used row -> sensor index
    known_variances: list  # the known variance of each used row (0.0 for sensors)
    param_names: tuple
    theta_prior: np.ndarray
    P_prior: np.ndarray
    n_inputs: int
    n_outputs: int


def _linear_noise(model, Q, li, linear_states) -> np.ndarray:
    """Process covariance of the linear states from ``Q`` (the builder's docstring)."""
    nz = len(li)
    if not nz:
        return np.zeros((0, 0))
    if Q is None:
        raise ValueError(f"Q: required with linear_states {linear_states} "
                         f"(sigma_phi^2 of eq. 3)")
    try:  # real numbers (validation's rule: no bool, string or object), checked below
        q = validation.array("Q", Q, allow_nan=True)
    except ValueError:
        q = np.array(np.nan)
    if q.ndim == 0 and np.isfinite(q) and q >= 0 and hasattr(model, "bank_noise_gain"):
        B = np.asarray(model.bank_noise_gain(), dtype=float)[li]
        return float(q) * np.outer(B, B)
    if q.shape in ((), (nz,)) and np.all(np.isfinite(q)) and np.all(q >= 0):
        return np.diag(np.broadcast_to(q, (nz,)))
    if q.shape == (nz, nz):
        return validation.cov("Q", q, nz, allow_psd=True)
    raise ValueError(f"Q: expected a variance >= 0, {nz} of them or an ({nz}, {nz}) "
                     f"covariance, got {Q!r}")
def _noise_prior(unknown_names, std0, mean0, d):
    """Checked (std0 values, mean0 values, lambda-free priors) of the unknown noise."""
    std0 = std_dict("std0", {} if std0 is None else std0, unknown_names, unknown_names,
                     "input and output units")
    mean0 = validation.keyed("mean0", mean0, unknown_names)
    mean0v = []
    for k in unknown_names:
        try:
            v = float(mean0.get(k, 0.0))
        except (TypeError, ValueError):
            v = float("nan")
        if not np.isfinite(v):
            raise ValueError(f"mean0[{k!r}]: expected a finite number, got {mean0.get(k)!r}")
        mean0v.append(v)
    return np.array([std0[k] for k in unknown_names]), mean0v


def _forgetting(forgetting, gamma0, nu0, d):
    """Checked (lambda, gamma0, nu0): lambda min(nu0, 1 / (1 - lambda)) > d + 1."""
    lam = validation.number("forgetting", forgetting, 0.0, 1.0, high_open=False)
    g0 = validation.number("gamma0", gamma0, 0.0, np.inf)
    nu0 = float(d + 4) if nu0 is None else validation.number("nu0", nu0, d + 1.0, np.inf)
    nu_low = nu0 if lam == 1.0 else min(nu0, 1.0 / (1.0 - lam))
    if not lam * nu_low > d + 1:
        raise ValueError(
            f"forgetting: lambda = {lam} with nu0 = {nu0} lets the degrees of freedom fall to "
            f"{lam * nu_low:.3g} <= d + 1 = {d + 1}, where the Student-t has no variance; use "
            f"lambda > {(d + 1) / (d + 2):.4g} (and nu0 > {(d + 1) / lam:.4g})"
        )
    return lam, g0, nu0


def configure(model, n_particles, noisy_input, sensors, known_std, linear_states,
              Q, niw, kalman_states) -> Setup:
    """Every check of the arguments the two builders share (ValueError naming the argument)
    and the constants the filter is built from."""
    validation.model(model)
    n = smc.check_n_particles(n_particles)
    if kalman_states not in ("linear", "all"):  # before the noise set-up (it computes)
        raise ValueError(f"kalman_states: expected 'linear' or 'all', got {kalman_states!r}")
    niw = validation.record("niw", niw, NiW)  # None: the defaults, no std0
    state_names = tuple(model.state_names)
    input_names = tuple(model.input_names)
    output_names = tuple(model.output_names)
    if not isinstance(noisy_input, str) or noisy_input not in input_names:
        raise ValueError(f"noisy_input: expected one of the model's inputs {input_names}, got "
                         f"{noisy_input!r}")
    sensors = validation.names("sensors", sensors, output_names)
    known = {} if known_std is None else std_dict("known_std", known_std, (), output_names,
                                                  "output units")
    both = [k for k in known if k in sensors]
    if both:
        raise ValueError(f"known_std: {both} are also in sensors (unknown noise); name each "
                         f"output once")
    linear_states = validation.names("linear_states", linear_states, state_names,
                                    allow_empty=True)
    li = np.array([state_names.index(s) for s in linear_states], dtype=int)
    nl = np.array([i for i in range(len(state_names)) if i not in set(li.tolist())], dtype=int)
    if len(nl) == 0:
        raise ValueError("linear_states: at least one state must remain a particle state")
    nz, nx, ny, ns = len(li), len(state_names), len(output_names), len(sensors)
    d = 1 + ns
    Qz = _linear_noise(model, Q, li, linear_states)
    unknown_names = (noisy_input,) + sensors
    std0v, mean0v = _noise_prior(unknown_names, niw.std0, niw.mean0, d)
    lam, g0, nu0 = _forgetting(niw.forgetting, niw.gamma0, niw.nu0, d)
    gauss = kalman_states == "all" and nz > 0
    _check_affine(model, li)

    s_rows = np.array([output_names.index(s) for s in sensors], dtype=int)
    kv = np.zeros(ny)
    for k, v in known.items():
        kv[output_names.index(k)] = v * v
    used = np.zeros(ny, bool)
    used[s_rows] = True
    used[[output_names.index(k) for k in known]] = True
    u_idx = np.flatnonzero(used)
    srow = [int(np.flatnonzero(u_idx == r)[0]) for r in s_rows]
    param_names = (f"{noisy_input}_offset", f"{noisy_input}_std") + tuple(
        f"{s}_bias" for s in sensors) + tuple(f"{s}_std" for s in sensors)
    theta_prior = np.concatenate([[mean0v[0], std0v[0]], mean0v[1:], std0v[1:]])
    iw_var = 1.0 / (2.0 * max(nu0 - d - 3.0, 1.0))  # Var(sigma) / sigma^2 by the delta method
    P_prior = np.diag(np.concatenate([[g0 * std0v[0] ** 2, iw_var * std0v[0] ** 2],
                                      g0 * std0v[1:] ** 2, iw_var * std0v[1:] ** 2]))
    return Setup(
        n_particles=n, forgetting=lam, gamma0=g0, nu0=nu0, noise_dim=d, n_sensors=ns,
        n_linear=nz, n_sampled=len(nl), n_states=nx, n_kalman=nx if gauss else nz,
        gaussian_states=gauss, sampled_idx=nl, linear_idx=li,
        model_order=np.argsort(np.concatenate([nl, li]).astype(int)),
        input_idx=input_names.index(noisy_input), linear_noise=Qz, used_rows=u_idx,
        sensor_rows=srow, sensor_of_row={r: j for j, r in enumerate(srow)},
        known_variances=[float(kv[r]) for r in u_idx], param_names=param_names,
        theta_prior=theta_prior, P_prior=P_prior, n_inputs=len(input_names), n_outputs=ny,
    )


class ModelFns(NamedTuple):
    """The model as the steps use it: ``transition`` and ``observe`` in x's dtype, the
    linearisation at every particle (``linearise_all``, vmapped over the last axis), the kinds of
    its entries (``entry_kinds``: constant, per step or per particle; :func:`entry_kinds`) and
    the model's parameters ``theta``."""

    transition: Callable
    observe: Callable
    linearise_all: Callable
    entry_kinds: Any
    theta: Any


def model_fns(model, s: Setup) -> ModelFns:
    """:class:`ModelFns` of ``model`` for the set-up ``s``."""
    def f(X, u, th):
        return jnp.asarray(model.transition(X, u, th)).astype(X.dtype)

    def h(X, u, th):
        return jnp.asarray(model.observe(X, u, th)).astype(X.dtype)

    lin_all = jax.vmap(
        lambda x, m, u, theta: linearise(f, h, x, m, u, theta, s.sampled_idx, s.linear_idx,
                                         s.input_idx),
        in_axes=(-1, -1, None, None), out_axes=-1,
    )
    mth = jnp.asarray(model.theta)
    kinds = entry_kinds(f, h, mth, s.sampled_idx, s.linear_idx, s.input_idx, s.n_inputs,
                        s.used_rows)
    return ModelFns(f, h, lin_all, kinds, mth)
