"""Smoothers: the backward passes behind :func:`vehjax.smooth`.

One module per family: ``gaussian`` (extended / unscented / cubature RTS, plain and
square-root), ``parallel`` (the associative-scan Kalman filter and RTS smoother),
``iterated`` (IEKS / IPLS), ``particle`` (backward simulation for particle filters),
``marginalized`` (ancestor paths with a per-path RTS for the marginalized PF); ``methods``:
the records that name a method and its options for :func:`vehjax.smooth` (``method=``),
importable from here: :class:`RTS`, :class:`IEKS`, :class:`IPLS`, :class:`FFBSi`,
:class:`RejectionSampling`, :class:`AncestorPaths`.
"""

from .methods import IEKS, IPLS, RTS, AncestorPaths, FFBSi, RejectionSampling

__all__ = ["RTS", "IEKS", "IPLS", "FFBSi", "RejectionSampling", "AncestorPaths"]
