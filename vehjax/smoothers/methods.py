"""The smoothing methods of :func:`vehjax.smooth`, one record each: the option ``method``.

::

    vehjax.smooth(est, ys, us, x0=x0, P0=P0)                                  # the filter's RTS
    vehjax.smooth(est, ys, us, x0=x0, P0=P0, method=IEKS(tol=1e-8, parallel=True))
    vehjax.smooth(pf, ys, us, x0=x0, P0=P0, key=key, method=FFBSi(n_trajectories=200))

Each record holds the options of its method only (an option that does not apply cannot be
given). Gaussian filters (``Estimator.smoother``): :class:`RTS`, :class:`IEKS` (Jacobian
filters), :class:`IPLS` (sigma-point filters). Particle filters (the bootstrap PF, the
marginalized PF): :class:`FFBSi`, :class:`RejectionSampling` (bootstrap PF only),
:class:`AncestorPaths`. A method's name (``"rts"``, ``"ieks"``, ``"ipls"``, ``"ffbsi"``,
``"rejection"``, ``"ancestor"``) stands for its record with the defaults: :func:`record` maps
the one to the other, in this one place (:data:`BY_NAME`).

Fields are checked when a record is made (ValueError naming ``method.<field>``); what depends on
the estimator and the data (the method's family, the shape of ``initial``) by
:func:`vehjax.smooth`.
"""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar

from .. import validation

__all__ = ["RTS", "IEKS", "IPLS", "FFBSi", "RejectionSampling", "AncestorPaths", "BY_NAME",
           "GAUSSIAN", "PARTICLE", "record"]

#: The iterated smoothers' defaults: ``tol`` and ``max_iter`` of :class:`IEKS` / :class:`IPLS`.
TOL, MAX_ITER = 1e-6, 20

_PARALLEL = (False, True, "associative", "doubling")


def _parallel(value):
    if value not in _PARALLEL:
        raise ValueError(f"method.parallel: expected False, True, 'associative' or 'doubling', "
                         f"got {value!r}")
    return value


@dataclasses.dataclass(frozen=True)
class RTS:
    """The filter's own Rauch-Tung-Striebel smoother (extended / unscented / cubature RTS,
    square-root forms in Cholesky factors; :mod:`vehjax.smoothers.gaussian`).

    Attributes:
        parallel: False (sequential), or smooth the filter's own linearisation by the
            parallel-in-time Kalman filter and RTS smoother (:mod:`vehjax.smoothers.parallel`;
            the same numbers to rounding): True or "associative" (``jax.lax.associative_scan``,
            O(T) work; its 2 log2 T copies of the combination compile slowly on XLA:CPU) or
            "doubling" (recursive doubling, O(T log T) work, one copy: compiles in seconds).
    """

    name: ClassVar[str] = "rts"
    parallel: Any = False

    def __post_init__(self):
        object.__setattr__(self, "parallel", _parallel(self.parallel))


@dataclasses.dataclass(frozen=True)
class _Iterated:
    """The options of the iterated smoothers (:mod:`vehjax.smoothers.iterated`).

    Attributes:
        parallel: each pass sequential (False) or parallel in time, as :class:`RTS`'s.
        tol: stop when no smoothed mean moves by more than ``tol`` of its smoothed standard
            deviation in a pass, > 0.
        max_iter: at most this many passes, >= 1; ``converged`` False in the result when they
            did not meet ``tol``.
        initial: the start, (T, n) means (n = nx, or nx + p unconstrained for joint filters)
            with the prior covariance at every step; None: the filter's own filtered means and
            covariances. Its shape is checked by :func:`vehjax.smooth`.
    """

    parallel: Any = False
    tol: float = TOL
    max_iter: int = MAX_ITER
    initial: Any = None

    def __post_init__(self):
        object.__setattr__(self, "parallel", _parallel(self.parallel))
        object.__setattr__(self, "tol", validation.number("method.tol", self.tol, 0.0))
        object.__setattr__(self, "max_iter",
                           validation.integer("method.max_iter", self.max_iter, 1))


@dataclasses.dataclass(frozen=True)
class IEKS(_Iterated):
    """The iterated extended Kalman smoother (Jacobian filters: EKF, joint EKF), started from the
    filter's own moments (or ``initial``); ``loglik`` is that of the model linearised about the
    fixed point, differentiable by implicit differentiation. Fields: ``parallel``, ``tol``,
    ``max_iter``, ``initial`` (:class:`IPLS` has the same)."""

    name: ClassVar[str] = "ieks"


@dataclasses.dataclass(frozen=True)
class IPLS(_Iterated):
    """The iterated posterior linearisation smoother (sigma-point filters: UKF, CKF, joint
    UKF), as :class:`IEKS` with sigma-point linearisations; the same fields."""

    name: ClassVar[str] = "ipls"


@dataclasses.dataclass(frozen=True)
class _Trajectories:
    """What the particle smoothers share: ``n_trajectories``, M >= 1 trajectories to draw."""

    n_trajectories: int = 100

    def __post_init__(self):
        object.__setattr__(self, "n_trajectories", validation.integer(
            "method.n_trajectories", self.n_trajectories, 1))


@dataclasses.dataclass(frozen=True)
class FFBSi(_Trajectories):
    """Backward simulation (forward filtering, backward simulation): the bootstrap PF's
    (:func:`vehjax.smoothers.particle.smooth`) and, Rao-Blackwellised, the marginalized PF's with
    ``kalman_states="linear"`` (:func:`vehjax.smoothers.marginalized.smooth`).

    Attributes:
        n_trajectories: M >= 1 trajectories to draw.
    """

    name: ClassVar[str] = "ffbsi"


@dataclasses.dataclass(frozen=True)
class RejectionSampling(_Trajectories):
    """Backward simulation by rejection sampling, the bootstrap PF's.

    Attributes:
        n_trajectories: M >= 1 trajectories to draw.
        max_tries: proposals per trajectory and step before the exact fallback, >= 1.
    """

    name: ClassVar[str] = "rejection"
    max_tries: int = 10

    def __post_init__(self):
        super().__post_init__()
        object.__setattr__(self, "max_tries",
                           validation.integer("method.max_tries", self.max_tries, 1))


@dataclasses.dataclass(frozen=True)
class AncestorPaths(_Trajectories):
    """The particles' ancestral paths (with a per-path RTS for the marginalized PF, whose
    default this is).

    Attributes:
        n_trajectories: M >= 1 paths to draw.
    """

    name: ClassVar[str] = "ancestor"


#: The Gaussian filters' methods and the particle filters'.
GAUSSIAN = (RTS, IEKS, IPLS)
PARTICLE = (FFBSi, RejectionSampling, AncestorPaths)

#: Each method's name -> its record (the name stands for the record with its defaults).
BY_NAME = {cls.name: cls for cls in GAUSSIAN + PARTICLE}


def record(method):
    """``vehjax.smooth``'s ``method`` as a record: None stays None (the estimator's default), a
    name of :data:`BY_NAME` becomes its record with the defaults, a record stays itself;
    ValueError naming ``method`` otherwise."""
    if method is None or isinstance(method, GAUSSIAN + PARTICLE):
        return method
    if isinstance(method, str) and method in BY_NAME:
        return BY_NAME[method]()
    raise ValueError(f"method: expected None, one of {tuple(BY_NAME)} or a record of "
                     f"vehjax.smoothers ({', '.join(c.__name__ for c in GAUSSIAN + PARTICLE)}), "
                     f"got {method!r}")
