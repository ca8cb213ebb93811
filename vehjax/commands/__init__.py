"""The command line's work on a user's own drive file: ``vehjax fit`` and ``vehjax estimate``.

:mod:`~vehjax.commands.drive_cli` registers the two commands (light: no JAX at parse time),
:mod:`~vehjax.commands.config` reads and checks their TOML file, :mod:`~vehjax.commands.setup`
turns it into a drive, a model and a filter, :mod:`~vehjax.commands.fitfile` writes and reads
the fitted filter (``fit.json``), :mod:`~vehjax.commands.fitting` and
:mod:`~vehjax.commands.estimating` do the two commands' work, :mod:`~vehjax.commands.figures`
draws their figures.
"""
