"""Paper reproductions, one module each, run by ``vehjax reproduce NAME [options]``.

The modules with a leading underscore are not reproductions: ``_report`` holds what the reports
share (markdown tables, report files, timing) and ``_dutta2019_report`` dutta2019's tables,
figures and CLI, so that each paper's module shows its study first.

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
