"""Recorded drives: ``load_comma2k19`` reads a comma2k19 segment (one ships with vehjax) into a
:class:`Drive` on a uniform time grid, with inputs and measurements for
:class:`~vehjax.models.SingleTrackBank`."""

from .comma2k19 import Drive, load_comma2k19

__all__ = ["Drive", "load_comma2k19"]
