"""The runtime helpers that :mod:`vehjax.execution`'s rules govern: how a program is traced,
compiled and called fast, never what it computes.

Modules:
    eager: a single-run entry point (``vehjax.filter``, ``vehjax.smooth``) compiled as one
        program when called outside ``jit``, and kept in vehjax's one cache of compiled
        programs (also a study's, ``vehjax.run`` with XLA options).
    hoist: a model function split into the part that depends on the state and the part that
        does not (the runs-last step evaluates the second once per step, not per sigma point).
    prng: counter-based random numbers for the particle filters (Threefry-2x32), cheap on CPU in
        float64 mode.
    substitute: any model function run with :mod:`vehjax.lib.elementary`'s vectorisable
        trigonometry, by rewriting its trace.
    progress: one progress bar for the long loops (a study's chunks, a fit's iterations).
"""
