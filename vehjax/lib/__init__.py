"""vehjax's mathematics layer: pure functions on arrays, one concept a module.

The modules here validate nothing (their callers check arguments before anything is traced),
know no platform (no execution strategy, no device rules) and import nothing of vehjax from
above them: filters, fitting and calibration are built on them, never the other way round.

Modules:
    transforms: maps between bounded parameters and unconstrained coordinates (the ``bounds=``
        of tune, dual and Liu-West, and the priors of calibrate).
    square_root: a square root L L^T = A of a constant or traced covariance.
    gaussian: the Gaussian log-density of a residual's observed components, once.
    whiteness: autocorrelations with missing samples, the Ljung-Box statistic, chi-square
        survival (innovation checks of :mod:`vehjax.tune.innovations`).
    elementary: vectorisable sin, cos, tan, arctan and arctan2 (arithmetic only, so XLA:CPU
        fuses them) for writing fast vehicle models: ``from vehjax.lib.elementary import sin``.
"""
