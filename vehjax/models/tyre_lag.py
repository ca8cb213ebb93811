"""Single-track model with tyre lag: the axle forces relax to the tyre curve over a relaxation
length.

A tyre does not build its lateral force at once when its slip angle changes: the contact patch
has to roll some distance, the relaxation length sigma [m], before the carcass deflection (and
with it the force) settles. The first-order relaxation-length model of non-steady-state slip
(Pacejka, Tire and Vehicle Dynamics, the chapter on non-steady-state tyre behaviour; Rajamani,
Vehicle Dynamics and Control, on transient tyre forces) makes each axle force a state::

    Ff' = (vx / sigma_f) (F_f(alpha_f) - Ff)
    Fr' = (vx / sigma_r) (F_r(alpha_r) - Fr)

i.e. a first-order lag with the time constant sigma / vx (25 ms at 20 m/s and 0.5 m), towards
the steady-state force of :class:`~vehjax.models.SingleTrack`'s tyre curve (``tyres=``:
``"linear"``, ``"brush"``, ``"pacejka"``, with its slip angles from the state's vy and r). The
body equations are SingleTrack's with the lagged forces::

    m (vy' + vx r) = Ff cos(delta) + Fr         (cos(delta) = 1 for the linear tyres)
    iz r'          = lf Ff cos(delta) - lr Fr
    ay             = (Ff cos(delta) + Fr) / m

States (vy, r, Ff, Fr) [m/s, rad/s, N, N]. As sigma -> 0 the forces follow the curve at once and
the model becomes SingleTrack; in steady state (constant inputs, Ff' = Fr' = 0) it is
SingleTrack's steady state, the forces on the curve.

Stiffness and discretisation. The force modes have rates of about vx / sigma (with the body's
coupling: tests/models/test_tyre_lag.py computes the Jacobian's eigenvalues): 40 1/s at
20 m/s and 0.5 m, 100 1/s at 20 m/s and 0.2 m, 200 1/s at 40 m/s and 0.2 m. RK4's stability
interval on the negative real axis is |lambda h| < 2.78, and its local error is of order
(lambda h)^5 / 120. The default ``substeps`` take RK4 steps of at most 2.5 ms
(ceil(dt / 2.5 ms): 2 at 200 Hz, 4 at 100 Hz), so |lambda h| <= 0.5 for sigma >= 0.2 m up to
40 m/s (local error below 3e-4 relative in the fastest mode, 1e-7 at 20 m/s and 0.5 m). For
shorter relaxation lengths or higher speeds, scale the substeps with vx / sigma; the domain's
lower end (0.01 m) needs h of about 0.1 ms at 40 m/s.
"""

from __future__ import annotations

import math

import jax.numpy as jnp

from .. import validation
from . import domains as dom
from .single_track import SingleTrack, body_forces

#: the longest RK4 substep the default ``substeps`` allow [s]
MAX_SUBSTEP = 0.0025


def default_substeps(dt: float) -> int:
    """ceil(dt / :data:`MAX_SUBSTEP`), at least 1: RK4 steps of at most 2.5 ms (module
    docstring: |lambda h| <= 0.5 for sigma >= 0.2 m up to 40 m/s)."""
    dt = validation.number("dt", dt, 0.0)
    return max(1, math.ceil(dt / MAX_SUBSTEP - 1e-9))


def relaxation(force, steady, vx, sigma):
    """F' = (vx / sigma) (steady - force) [N/s]: first-order relaxation of the force ``force``
    [N] towards the tyre curve's ``steady`` [N] at speed ``vx`` [m/s] over the relaxation length
    ``sigma`` [m]."""
    return vx / sigma * (steady - force)


class SingleTrackLag(SingleTrack):
    """Single-track model with first-order tyre lag (see the module docstring).

    States x = (vy, r, Ff, Fr): lateral velocity of the CoG [m/s], yaw rate [rad/s], front and
        rear axle lateral forces [N] (each in its wheel's frame).
    Inputs u = (delta, vx), outputs y = (ay, r, *references): as :class:`SingleTrack`'s (ay from
        the lagged forces, at the accelerometer's position with ``lever_arm``).
    Parameters theta: :class:`SingleTrack`'s for the tyre curve (``tyres``), then the relaxation
        lengths (sigma_f, sigma_r) [m] (nominal 0.5, 0.5), then (xa, ya) [m] with ``lever_arm``.

    Domains: SingleTrack's, and sigma_f, sigma_r in (0.01, 10) m
    (:data:`vehjax.models.domains.RELAXATION`: car tyres 0.3-1.5 m). State envelope:
    SingleTrack's and |Ff|, |Fr| <= 1e6 N.

    ``nested_model()``: the lagged linear tyres (same states, so :func:`vehjax.tune.fit`'s
    staged start keeps Q0's shape) with this model's body parameters, relaxation lengths, lever
    arm and outputs; None for the linear tyres.

    Args:
        dt: sampling period [s], > 0.
        integrator: ``"rk4"`` (default) or ``"euler"``.
        theta: parameter vector in the order above; None for the nominal values.
        tyres: ``"linear"``, ``"pacejka"`` or ``"brush"``.
        substeps: integration steps per sampling period (int >= 1); None (default):
            :func:`default_substeps` (RK4 steps of at most 2.5 ms; module docstring).
        lever_arm, references: as :class:`SingleTrack`'s.
    """

    STATE_NAMES = ("vy", "r", "Ff", "Fr")
    STATE_UNITS = ("m/s", "rad/s", "N", "N")
    PARAM_DOMAINS = {**SingleTrack.PARAM_DOMAINS, "sigma_f": dom.RELAXATION,
                     "sigma_r": dom.RELAXATION}
    STATE_ENVELOPE = {**SingleTrack.STATE_ENVELOPE, "Ff": dom.FORCE_LIMIT, "Fr": dom.FORCE_LIMIT}
    LAG = True

    def __init__(self, dt: float = 0.01, integrator: str = "rk4", theta=None,
                 tyres: str = "linear", substeps: int | None = None, lever_arm: bool = False,
                 references=()):
        substeps = default_substeps(dt) if substeps is None else substeps
        super().__init__(dt=dt, integrator=integrator, theta=theta, tyres=tyres,
                         substeps=substeps, lever_arm=lever_arm, references=references)

    def body_forces(self, x, u, theta):
        """(Fy [N], Mz [N m]) at the CoG of the lagged axle forces (x[2], x[3])."""
        return body_forces(x[2], x[3], u[0], theta[2], theta[3], self.tyres == "linear")

    def derivative(self, x, u, theta):
        """(vy', r', Ff', Fr') [m/s^2, rad/s^2, N/s, N/s], shape (4,)."""
        ff, fr = self.axle_forces(x, u, theta)          # the curve's, at the state's slips
        k = self.param_names.index("sigma_f")
        lag = [relaxation(x[2], ff, u[1], theta[k]), relaxation(x[3], fr, u[1], theta[k + 1])]
        return jnp.concatenate([super().derivative(x, u, theta), jnp.stack(lag)])

    def steady_forces(self, x, u, theta=None):
        """(vy, r, F_f(alpha_f), F_r(alpha_r)), shape (4,): the state ``x`` (its vy, r) with the
        forces on the tyre curve, e.g. to start from a SingleTrack state."""
        theta = self.theta if theta is None else theta
        return jnp.concatenate([x[:2], jnp.stack(self.axle_forces(x, u, theta))])

    def initial_state(self, speed):
        """Straight driving: zeros (no slip, no force), shape (4,)."""
        return jnp.zeros(4)
