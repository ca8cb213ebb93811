"""Paper reproductions, one module or package each, run by ``vehjax reproduce NAME [options]``.

``reporting`` is not a reproduction: it holds what the reports share (markdown tables, report
files, timing). A large reproduction is a package whose study and report are modules of their
own (``dutta2019.study`` and ``dutta2019.report``).

Every module defines ``main(argv: list[str] | None) -> int`` (printed tables, a ``report.md``
that links the figures it saves), ``parser()``, its argparse parser (every option's help
states its default; ``vehjax reproduce --help`` lists them all), and ``PAPER``, one line naming
the paper it reproduces.
"""

from __future__ import annotations

import importlib

#: reproduction name -> module under vehjax.reproduce
REGISTRY = {
    "wang2016": "wang2016",
    "dutta2019": "dutta2019",
    "berntorp2018": "berntorp2018",
    "consistency": "consistency",
    "noise-learning": "noise_learning",
}


def load(name: str):
    """The module that reproduces ``name`` (a key of :data:`REGISTRY`)."""
    if name not in REGISTRY:
        raise ValueError(f"reproduce: unknown paper {name!r}; expected one of {sorted(REGISTRY)}")
    return importlib.import_module(f"{__name__}.{REGISTRY[name]}")
