"""Exceptions of the numerical core."""

from __future__ import annotations


class LrmsError(ValueError):
    """Base class of errors raised on purpose by :mod:`lrms` (bad input, no model found, ...)."""


class FitError(LrmsError):
    """A model could not be estimated: too few points, degenerate data, or no convergence."""


class NominalDiameterError(FitError):
    """The fitted cylinder's diameter is inconsistent with the request's nominal diameter range:
    outside it by more than its uncertainty can explain (a wrong part or a fit gone astray)."""
