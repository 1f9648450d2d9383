"""Defaults shared by the rig's config (:mod:`service.config`) and the fits of a file
(:mod:`service.fitting`), in a module of constants only: ``lrms fit FILE`` needs them without
importing pydantic and the config schema (each costs a command-line start tenths of a second)."""

from __future__ import annotations

#: The coverage factor k of seed 003's critical-point interval when a request, the rig's ``[fit]``
#: table or ``lrms fit --k`` gives none: the k-ellipsoids of every point at k = 3 (seed 003).
DEFAULT_K = 3.0
