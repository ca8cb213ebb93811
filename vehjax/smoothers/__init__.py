"""Smoothers: the backward passes behind :func:`vehjax.smooth`.

One module per family: ``gaussian`` (extended / unscented / cubature RTS, plain and
square-root), ``parallel`` (the associative-scan Kalman filter and RTS smoother),
``iterated`` (IEKS / IPLS), ``particle`` (backward simulation for particle filters),
``marginalized`` (ancestor paths with a per-path RTS for the marginalized PF).
"""
