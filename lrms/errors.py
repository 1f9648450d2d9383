"""Exceptions of the numerical core."""

from __future__ import annotations


class LrmsError(ValueError):
    """Base class of errors raised on purpose by :mod:`lrms` (bad input, no model found, ...)."""


class FitError(LrmsError):
    """A model could not be estimated: too few points, degenerate data, or no convergence."""
