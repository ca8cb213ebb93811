"""The filter settings and the simulated noise of Dutta, Singh & Alam (2019)'s dual state and
parameter estimation of a four-wheel vehicle (``vehjax reproduce dutta2019``), shared by the
reproduction and the Liu-West benchmark (``benchmarks/bench_liu_west_bias.py``).

* :data:`KINEMATIC_SETTINGS`, :data:`DYNAMIC_SETTINGS`: section III as printed, in vehjax's
  naming (the paper follows Thrun et al.: its R is the process noise and its Q the measurement
  noise; here Q is the process noise, R the measurement noise); diagonals of P0, P_theta0, Q,
  Q_theta and R, per step at dt = 0.02 s.
* The simulation (:func:`simulate_runs`): the paper's "simulation noise N(0, 0.1)" read as
  measurement noise of std :data:`SIM_STD` = 0.1 on every measured component and process noise
  of 0.1 per square-root second (0.1 sqrt(dt) per step).
* :func:`matched_settings`: the covariances a user who knows the sensors would set: Q and R
  those of the simulation, Q_theta = (:data:`Q_THETA_REL` |truth|)^2 per step and P_theta0 the
  variance of the uniform box the initial guesses are drawn from.

Limits: the paper does not give the sampling period; these are readings of it, the
reproduction's module docstring says which and why.
"""

from __future__ import annotations

import numpy as np

from ..simulate import simulate

__all__ = ["SIM_STD", "Q_THETA_REL", "KINEMATIC_SETTINGS", "DYNAMIC_SETTINGS",
           "matched_settings", "simulate_runs"]

#: std of the simulated measurement noise, and of the process noise per square-root second
SIM_STD = 0.1
#: matched settings: the parameters' random-walk std per step, relative to the truth
Q_THETA_REL = 1e-3

# Section III, in vehjax's naming (Q process, R measurement); diagonals.
KINEMATIC_SETTINGS = dict(
    P0=(1.0, 1.0, 0.2, 2.0),
    P_theta0=(3.0, 3.0),
    Q=(0.5**2, 0.5**2, 0.2**2, 1.0**2),
    Q_theta=(1.25**2, 1.25**2),
    R=(1.0**2, 1.0**2, 1.5**2, 0.1**2),
)
DYNAMIC_SETTINGS = dict(
    P0=(1.0, 1.0, 0.2),
    P_theta0=(200.0, 2.0e4, 1.5e4),
    Q=(1.2**2, 1.2**2, 0.45**2),
    Q_theta=(20.0**2, 175.0**2, 150.0**2),
    R=(0.2**2, 0.2**2, 0.15**2),
)


def matched_settings(paper: dict, model, truth, box) -> dict:
    """The "matched" settings: Q, R of the simulation, small Q_theta, P_theta0 of the box.

    ``paper``: the paper's settings (its P0 is kept); ``truth`` (p,): the true values of the
    estimated parameters; ``box`` (p, 2): the low and high ends of the uniform box the initial
    guesses are drawn from. Returns a dict of diagonals like ``paper``'s."""
    nx, ny, dt = len(model.state_names), len(model.output_names), model.dt
    width = np.diff(np.asarray(box, float), axis=1)[:, 0]
    return dict(
        P0=paper["P0"],
        P_theta0=tuple(width**2 / 12.0),
        Q=(SIM_STD**2 * dt,) * nx,
        Q_theta=tuple((Q_THETA_REL * np.abs(truth)) ** 2),
        R=(SIM_STD**2,) * ny,
    )


def simulate_runs(model, scn, runs: int, key):
    """``runs`` noisy runs of ``scn`` on ``model`` (its ``theta`` is the truth): process noise of
    :data:`SIM_STD` per square-root second and measurement noise of std :data:`SIM_STD` on
    every component (:func:`vehjax.simulate`)."""
    return simulate(model, scn, runs=runs, key=key, process_std=SIM_STD * np.sqrt(model.dt),
                    meas_std=SIM_STD)
