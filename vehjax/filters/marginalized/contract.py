"""What the paper's marginalized PF declares for smoothing over its particles
(``Estimator.rao_blackwell``): the public contract :mod:`vehjax.smoothers.marginalized` reads.
A smoother needs nothing else of the filter's set-up."""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import numpy as np

__all__ = ["LinearStep", "RBTransition"]


class LinearStep(NamedTuple):
    """What recomputes one step of a particle's Kalman filter of the linear states and of its
    noise statistics (``kalman_states="linear"``, sec. 3.4 and eq. 18-20).

    Attributes:
        transition, observe: the model's f(x, u, theta) and h(x, u, theta), in x's dtype.
        sampled_idx: the sampled states' indices in the model's state vector.
        linear_idx: the linear states' indices.
        input_idx: the noisy input's index in u.
        used_rows: the output rows the filter uses (sensors and known-std outputs).
        sensor_rows: sensor j's row among the used rows.
        known_variances: the known noise variance of each used row (0.0 for sensors).
        linear_noise: (n_z, n_z) the linear states' process noise.
        forgetting: lambda of eq. 20.
        noise_dim: d, the dimension of v = (w, e).
    """

    transition: Callable
    observe: Callable
    sampled_idx: np.ndarray
    linear_idx: np.ndarray
    input_idx: int
    used_rows: np.ndarray
    sensor_rows: list
    known_variances: list
    linear_noise: np.ndarray
    forgetting: float
    noise_dim: int


class RBTransition(NamedTuple):
    """What the marginalized PF declares for smoothing over its particles
    (``Estimator.rao_blackwell``, :mod:`vehjax.smoothers.marginalized`).

    Attributes:
        predict: ``predict(x, z, P, w, u, theta) -> (m_pred, P_pred, C)``: one particle's
            Gaussian prediction over (sampled, linear) states from its means x (n_xs,), z
            (n_z,), covariance P (n_k, n_k) and offset draw w with input u
            (:func:`vehjax.filters.marginalized.kalman.joint_prediction`); meaningful when
            ``gauss``.
        theta: the model parameters the filter runs with.
        order: (nx,) index array, (sampled, linear) order -> model order.
        nz: number of linear states.
        gauss: the particles carry a Gaussian over all states (``kalman_states="all"`` with
            linear states).
        linear: :class:`LinearStep`, from which the smoother recomputes a step's Kalman filter
            of the linear states with ``kalman_states="linear"``; None: not declared.
    """

    predict: Callable
    theta: Any
    order: np.ndarray
    nz: int
    gauss: bool
    linear: LinearStep | None = None
