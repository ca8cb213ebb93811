"""The virtual yaw rate's scale: :class:`~vehjax.models.SingleTrackBank` variants for a car whose
rear rolling radii differ (Berntorp & Di Cairano 2018, eq. 10, and its Remark 1).

Eq. 10 reads the yaw rate from the rear wheel speeds, r_virt = (v_rr - v_rl) / l_T. When the
right wheel's rolling radius is (1 + eps) times the left one's, the wheel-speed difference gains
eps vx and r_virt reads r + eps vx / l_T (:func:`virtual_yaw_reading`). The paper takes r_virt as
unbiased; on the shipped comma2k19 RAV4 it is not (eps about -4e-4). This module holds the
models that carry eps:

* :class:`VirtualScaleBank`: SingleTrackBank with eps as a sixth, constant state (affine in
  the output, so the marginalized PF can carry it in each particle's Kalman filter);
* :func:`augmented_model`: Remark 1's "common approach", the planar model augmented with the
  steering offset, the ay and gyro biases and eps as random-walk states (optionally the bank);
* :func:`offset_scale_model`: the planar model with the steering offset and eps as parameters
  (linear in the states given vx, so a Kalman filter's likelihood is exact for it).

Limits: eps is a first-order reading of the radius mismatch (second order in eps dropped); the
rear track :data:`TRACK` is a plausible RAV4 value, not in the log.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from .bank import SingleTrackBank
from .base import Model
from .domains import extended

#: the RAV4's rear track l_T [m] (Comma2k19Drive.measurements' default)
TRACK = 1.61


def virtual_yaw_reading(r, eps, vx, track):
    """Eq. 10's virtual yaw rate from wheels whose rear rolling radii differ by the fraction
    ``eps``: r + eps vx / l_T [rad/s].

    With linear wheel speeds v_rl, v_rr the wheel-speed difference gains eps vx when the right
    radius is (1 + eps) times the left, so (v_rr - v_rl) / l_T reads r + eps vx / l_T. Args:
    r yaw rate [rad/s], eps [-], vx speed [m/s], track l_T [m]; any broadcastable shapes.
    """
    return r + eps * vx / track


class VirtualScaleBank(SingleTrackBank):
    """:class:`~vehjax.models.SingleTrackBank` with the rear rolling-radius mismatch eps [-] as
    a sixth, constant state: x = (vy, r, phi, phi_dot, phi_ddot, eps); the output r_virt is
    :func:`virtual_yaw_reading` (affine in eps, so the marginalized PF can carry eps in each
    particle's Kalman filter beside the bank: learnt online, without forgetting). The rear
    track is :data:`TRACK`. Everything else as SingleTrackBank (domains included); the state
    envelope adds |eps| <= 1 (a radius mismatch of 100 %)."""

    STATE_NAMES = SingleTrackBank.STATE_NAMES + ("eps",)
    STATE_UNITS = SingleTrackBank.STATE_UNITS + ("-",)
    STATE_ENVELOPE = {**SingleTrackBank.STATE_ENVELOPE, "eps": 1.0}

    def derivative(self, x, u, theta):
        return jnp.concatenate([super().derivative(x[:5], u, theta), 0.0 * x[5:]])

    def observe(self, x, u, theta):
        y = super().observe(x[:5], u, theta)
        return y.at[4].set(virtual_yaw_reading(x[1], x[5], u[0], TRACK))

    def bank_noise_gain(self):
        """B_phi on the six states: eps has no process noise."""
        return jnp.concatenate([super().bank_noise_gain(), jnp.zeros(1)])

    def initial_state(self, speed):
        return jnp.zeros(6)


#: Names of the augmented EKF's states (Remark 1 plus eps; the bank ones only with bank=True).
AUG_PLANAR = ("vy", "r", "delta_offset", "ay_bias", "r_bias", "eps")
AUG_BANK = ("phi", "phi_dot", "phi_ddot", "roll_rate_bias")


def augmented_model(model, bank=False):
    """Remark 1's common approach as a :class:`vehjax.models.Model` wrapping SingleTrackBank:
    x = (vy, r, steering offset [rad], ay bias [m/s^2], gyro bias [rad/s], eps [-]) and, with
    ``bank``, (phi, phi_dot, phi_ddot, roll-gyro bias [rad/s]) after them; outputs
    (ay, r, r_virt) and, with ``bank``, roll_rate. r_virt is :func:`virtual_yaw_reading` of the
    state eps (the rolling-radius mismatch as a random-walk state; hold it with a zero prior
    variance to take r_virt as unbiased)."""
    nb = 4 if bank else 0

    def full(x):
        return jnp.concatenate([x[:2], x[6:9] if bank else jnp.zeros(3)])

    def f(x, u, th):
        xn = model.transition(full(x), u.at[1].add(x[2]), th)
        out = [xn[:2], x[2:6]]
        if bank:
            out += [xn[2:5], x[9:10]]
        return jnp.concatenate(out)

    def h(x, u, th):
        y = model.observe(full(x), u.at[1].add(x[2]), th)
        out = [y[0] + x[3], y[1] + x[4], virtual_yaw_reading(x[1], x[5], u[0], TRACK)]
        if bank:
            out.append(y[2] + x[9])
        return jnp.stack(out)

    names = AUG_PLANAR + (AUG_BANK if nb else ())
    units = {"vy": "m/s", "r": "rad/s", "delta_offset": "rad", "ay_bias": "m/s^2",
             "r_bias": "rad/s", "eps": "-", "phi": "rad", "phi_dot": "rad/s",
             "phi_ddot": "rad/s^2", "roll_rate_bias": "rad/s"}
    return Model(f, h, model.dt, names, param_names=model.param_names,
                 input_names=model.input_names,
                 output_names=("ay", "r", "r_virt") + (("roll_rate",) if bank else ()),
                 theta=np.asarray(model.theta), units={k: units[k] for k in names},
                 domains=model.param_domains())


def offset_scale_model(model):
    """The planar single-track model with the steering offset [rad] and the rolling-radius
    mismatch eps [-] as parameters (paper 004's offline reference, sec. 5, ref. [28]).

    A :class:`vehjax.models.Model`: states (vy, r), inputs (vx, delta), parameters
    ``model.param_names`` + (delta_offset, eps), outputs (ay, r, r_virt) with r_virt by
    :func:`virtual_yaw_reading`; sensor biases enter through :func:`vehjax.calibrate.pmmh`'s
    ``bias:`` names. Linear in the states and inputs (given vx), so a Kalman filter's
    likelihood is exact for it. Keeps the model's parameter domains (the two added ones
    unbounded)."""
    n = len(model.param_names)

    def full(x):
        return jnp.concatenate([x, jnp.zeros(3)])

    def f(x, u, th):
        return model.transition(full(x), u.at[1].add(th[n]), th[:n])[:2]

    def h(x, u, th):
        y = model.observe(full(x), u.at[1].add(th[n]), th[:n])
        return jnp.stack([y[0], y[1], virtual_yaw_reading(x[1], th[n + 1], u[0], TRACK)])

    return Model(f, h, model.dt, ("vy", "r"), param_names=model.param_names + ("delta_offset", "eps"),
                 input_names=model.input_names, output_names=("ay", "r", "r_virt"),
                 theta=np.concatenate([np.asarray(model.theta), [0.0, 0.0]]),
                 units={"vy": "m/s", "r": "rad/s"},
                 domains=extended(model.param_domains(), ("delta_offset", "eps")))
