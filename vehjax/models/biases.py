"""Sensor biases and input offsets as states: a model with one constant state per biased
output (:func:`with_output_biases`) or per offset input (:func:`with_input_offset`).

``with_output_biases(model, ("ay", "roll_rate"))`` returns a :class:`~vehjax.models.Model`
whose state is the model's followed by ``ay_bias``, ``roll_rate_bias`` (in the outputs' units):
the transition keeps them, the observation adds each to its output. Any state filter then
estimates the biases jointly with the state (the EKF/UKF as an augmented state; the
marginalized PF as linear states in its per-particle Kalman filter, where a bias that a
sensor cannot tell apart from a state, e.g. a roll-rate bias from the bank rate, keeps its
correlation with that state: see ``vehjax reproduce consistency``).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .base import Model

__all__ = ["with_output_biases", "with_input_offset", "augmented"]


class _BiasedBank(Model):
    """The same for a model with a bank process-noise gain (eq. 3 of paper 004), kept on the
    model's states and zero on the biases: ``marginalized_pf`` builds its Q from it."""

    gain: tuple = eqx.field(static=True)

    def __init__(self, gain, **kwargs):
        self.gain = gain
        super().__init__(**kwargs)

    def bank_noise_gain(self):
        return jnp.asarray(self.gain)


def with_output_biases(model, outputs) -> Model:
    """``model`` with a constant additive bias state per output in ``outputs``.

    Args:
        model: any vehjax model (built-in or :class:`~vehjax.models.Model`).
        outputs: names in ``model.output_names``, each at most once.

    Returns:
        A :class:`~vehjax.models.Model` with states ``model.state_names`` then
        ``<output>_bias`` per output (unit: the output's), the same inputs, parameters,
        nominal ``theta``, outputs and ``dt`` (and parameter domains); ``transition`` keeps
        the biases, ``observe`` adds them. Initial state and covariance of a filter: the model's, then the biases'
        prior mean and variance. A model with ``bank_noise_gain()`` keeps it (zeros on the
        biases).

    Raises:
        ValueError: ``outputs`` empty, repeated or not outputs of the model.
    """
    names, rows = _picked("outputs", outputs, model.output_names)
    transition, observe = augmented(model.transition, model.observe, len(model.state_names),
                                    bias_rows=rows)
    return _wrapped(model, transition, observe, names, "_bias", _units(model))


def augmented(transition, observe, nx: int, bias_rows=(), offset_cols=()):
    """(transition, observe) on a state z = (x, biases, offsets): the model's ``nx`` states,
    then one additive bias per output row in ``bias_rows`` (y = h(x, u + offset) + b), then
    one additive offset per input column in ``offset_cols`` (the model driven by u + offset);
    the transition keeps the biases and offsets. ``transition``, ``observe``: the model's
    ``(x, u, theta)`` functions. Used by :func:`with_output_biases`, :func:`with_input_offset`
    and the VB filters' ``augment`` (:class:`vehjax.filters.Augmentation`)."""
    b_rows, o_cols = np.asarray(bias_rows, int), np.asarray(offset_cols, int)
    nb, no = len(b_rows), len(o_cols)

    def shifted(z, u):
        return jnp.asarray(u).at[o_cols].add(z[nx + nb:]) if no else u

    def f(z, u, theta):
        return jnp.concatenate([transition(z[:nx], shifted(z, u), theta), z[nx:]])

    def h(z, u, theta):
        y = observe(z[:nx], shifted(z, u), theta)
        return y.at[b_rows].add(z[nx:nx + nb]) if nb else y

    return f, h


def _picked(arg, value, known):
    """(names, their indices in ``known``) of ``value`` (a name or names); ValueError naming
    ``arg`` when empty, repeated or unknown."""
    names = (value,) if isinstance(value, str) else tuple(value)
    known = list(known)
    if not names or len(set(names)) != len(names) or not all(n in known for n in names):
        raise ValueError(f"{arg}: expected distinct names among {tuple(known)}, got {value!r}")
    return names, np.array([known.index(n) for n in names])


def _units(model) -> dict:
    units = {}
    for kind in ("state", "input", "param", "output"):
        names_k = getattr(model, f"{kind}_names")
        units.update(zip(names_k, getattr(model, f"{kind}_units", ("-",) * len(names_k))))
    return units


def _wrapped(model, transition, observe, names, suffix, units) -> Model:
    """The :class:`Model` of ``transition``, ``observe`` with the model's states then
    ``<name><suffix>`` per name (each in that name's unit), the model's inputs, parameters,
    nominal ``theta``, outputs and ``dt``; a model with ``bank_noise_gain()`` keeps it (zeros
    on the added states)."""
    added = tuple(f"{n}{suffix}" for n in names)
    kwargs = dict(
        transition=transition, observe=observe, dt=model.dt,
        state_names=tuple(model.state_names) + added,
        param_names=tuple(model.param_names), input_names=tuple(model.input_names),
        output_names=tuple(model.output_names), theta=model.theta,
        units={k: v for k, v in {**units, **{a: units[n] for a, n in zip(added, names)}}.items()
               if v != "-"},
        fast_math=False,  # the model's own functions are called as they are
        domains=model.param_domains() if hasattr(model, "param_domains") else None,
    )
    if hasattr(model, "bank_noise_gain"):
        gain = np.r_[np.asarray(model.bank_noise_gain(), float), np.zeros(len(names))]
        return _BiasedBank(tuple(float(g) for g in gain), **kwargs)
    return Model(**kwargs)


def with_input_offset(model, inputs) -> Model:
    """``model`` with a constant additive offset state per input in ``inputs``: the model is
    driven by the input reading plus the offset (a steering-angle sensor's offset, paper 004's
    mu_w), u_true = u + offset.

    Args:
        model: any vehjax model (built-in or :class:`~vehjax.models.Model`).
        inputs: names in ``model.input_names``, each at most once.

    Returns:
        A :class:`~vehjax.models.Model` with states ``model.state_names`` then
        ``<input>_offset`` per input (unit: the input's), the same inputs, parameters, nominal
        ``theta``, outputs and ``dt``; ``transition`` and ``observe`` evaluate the model at
        u + offset and ``transition`` keeps the offsets. A model with ``bank_noise_gain()``
        keeps it (zeros on the offsets).

    Raises:
        ValueError: ``inputs`` empty, repeated or not inputs of the model.
    """
    names, cols = _picked("inputs", inputs, model.input_names)
    transition, observe = augmented(model.transition, model.observe, len(model.state_names),
                                    offset_cols=cols)
    return _wrapped(model, transition, observe, names, "_offset", _units(model))
