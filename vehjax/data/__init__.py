"""Recorded drives: :class:`Drive` holds your own (from arrays or a CSV, with units, resampled
onto a model's grid); ``load_comma2k19`` reads a comma2k19 segment (one ships with vehjax) into a
:class:`Drive` on a uniform time grid, with inputs and measurements for
:class:`~vehjax.models.SingleTrackBank`."""

from .comma2k19 import Comma2k19Drive, load_comma2k19
from .drive import UNITS, Drive

__all__ = ["Drive", "UNITS", "Comma2k19Drive", "load_comma2k19"]
