"""Conformity decisions with a measurement's expanded uncertainty, ISO 14253-1:2017.

For a tolerance ``[lower, upper]`` (either side may be open), a measured value ``y`` and its expanded
uncertainty ``U`` (coverage factor k = 2):

- guard-banded rule (ISO 14253-1's default): *conforms* when ``lower + U <= y <= upper - U`` (the tolerance
  shrunk by U, the acceptance zone); *does not conform* when ``y < lower - U`` or ``y > upper + U`` (outside the
  tolerance widened by U, the rejection zone); otherwise *cannot decide*. When ``2U >= upper - lower`` the
  acceptance zone is empty (at most one point) and conformity cannot be proven at all: the result says so and
  never answers *conforms*.
- simple acceptance (ILAC-G8:09/2019, guard band w = 0): decided by ``y`` alone against the tolerance; never
  *cannot decide*. It has to be asked for by name, and the result carries it (and what the guard-banded rule
  would have said) so that no report shows a simple-acceptance decision as an ISO 14253-1 one.

Unit-agnostic (use metres throughout, as the rest of :mod:`lrms`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

from lrms.errors import LrmsError


class ConformityError(LrmsError):
    """Bad input to a conformity decision. ``field`` names the offending argument."""

    def __init__(self, message: str, field: str) -> None:
        super().__init__(message)
        self.field = field


class DecisionRule(StrEnum):
    """How the uncertainty enters the decision."""

    GUARD_BANDED = "iso14253-1"  #: ISO 14253-1:2017 default: guard bands of width U
    SIMPLE_ACCEPTANCE = "simple-acceptance"  #: ILAC-G8:09/2019 simple acceptance: y alone, no guard band


class Decision(StrEnum):
    CONFORMS = "conforms"
    DOES_NOT_CONFORM = "does not conform"
    CANNOT_DECIDE = "cannot decide"


@dataclass(frozen=True)
class ConformityResult:
    """A decision and the zones it was taken with.

    ``acceptance`` is the closed interval where the rule answers *conforms* (``None`` when empty; an open side is
    ``None`` inside the pair); values below
    ``rejection_below`` or above ``rejection_above`` answer *does not conform*. ``margin_lower = y - lower``,
    ``margin_upper = upper - y`` (positive inside the tolerance); ``margin_in_u`` is the smaller margin in units of
    U (>= 1 inside the acceptance zone under guard bands; ``None`` when U = 0).
    """

    decision: Decision
    rule: DecisionRule
    value: float
    expanded_uncertainty: float
    lower: float | None
    upper: float | None
    acceptance: tuple[float | None, float | None] | None
    rejection_below: float | None
    rejection_above: float | None
    margin_lower: float | None
    margin_upper: float | None
    margin_in_u: float | None
    #: 2U >= tolerance width: no measurement with this U can prove conformity
    uncertainty_too_large: bool
    #: 2U / (upper - lower) for a two-sided tolerance
    uncertainty_to_tolerance: float | None
    #: the guard-banded decision, for comparison (equal to ``decision`` under the guard-banded rule)
    guard_banded_decision: Decision
    note: str


def _finite(x: float, field: str) -> float:
    v = float(x)
    if not math.isfinite(v):
        raise ConformityError(f"{field}: must be a finite number, got {x}", field)
    return v


def _guard_banded(y: float, u: float, lo: float | None, hi: float | None, too_large: bool) -> Decision:
    if (lo is not None and y < lo - u) or (hi is not None and y > hi + u):
        return Decision.DOES_NOT_CONFORM
    inside = (lo is None or y >= lo + u) and (hi is None or y <= hi - u)
    return Decision.CONFORMS if inside and not too_large else Decision.CANNOT_DECIDE


def decide(
    value: float,
    expanded_uncertainty: float,
    lower: float | None = None,
    upper: float | None = None,
    rule: DecisionRule = DecisionRule.GUARD_BANDED,
) -> ConformityResult:
    """Decide whether ``value`` (with expanded uncertainty ``U``, k = 2) conforms to ``[lower, upper]``."""
    y = _finite(value, "value")
    u = _finite(expanded_uncertainty, "expanded_uncertainty")
    if u < 0:
        raise ConformityError(f"expanded_uncertainty: must be >= 0, got {u}", "expanded_uncertainty")
    lo = None if lower is None else _finite(lower, "lower")
    hi = None if upper is None else _finite(upper, "upper")
    if lo is None and hi is None:
        raise ConformityError("tolerance: give a lower limit, an upper limit, or both", "tolerance")
    if lo is not None and hi is not None and not lo < hi:
        raise ConformityError(f"tolerance: lower limit {lo} must be below the upper limit {hi}", "lower")
    try:
        rule = DecisionRule(rule)
    except ValueError:
        raise ConformityError(
            f"rule: unknown decision rule {rule!r}; known: {', '.join(r.value for r in DecisionRule)}", "rule"
        ) from None

    width = None if lo is None or hi is None else hi - lo
    too_large = width is not None and 2 * u >= width
    guard = _guard_banded(y, u, lo, hi, too_large)
    m_lo = None if lo is None else y - lo
    m_hi = None if hi is None else hi - y
    margins = [m for m in (m_lo, m_hi) if m is not None]
    margin_in_u = min(margins) / u if u > 0 else None
    ratio = None if width is None else 2 * u / width

    if rule is DecisionRule.GUARD_BANDED:
        decision = guard
        acc_lo = None if lo is None else lo + u
        acc_hi = None if hi is None else hi - u
        acceptance = None if too_large else (acc_lo, acc_hi)
        rej_lo = None if lo is None else lo - u
        rej_hi = None if hi is None else hi + u
        note = "ISO 14253-1:2017 guard bands of width U (k = 2)"
        if too_large:
            note += f"; 2U = {2 * u:g} >= tolerance width {width:g}: conformity cannot be proven"
    else:
        inside = (lo is None or y >= lo) and (hi is None or y <= hi)
        decision = Decision.CONFORMS if inside else Decision.DOES_NOT_CONFORM
        acceptance = (lo, hi)
        rej_lo, rej_hi = lo, hi
        note = (
            "simple acceptance (ILAC-G8:09/2019, no guard band): decided by the measured value alone; near a limit "
            f"the risk of a wrong decision approaches 50 %; ISO 14253-1 guard bands would say: {guard.value}"
        )
    return ConformityResult(
        decision=decision,
        rule=rule,
        value=y,
        expanded_uncertainty=u,
        lower=lo,
        upper=hi,
        acceptance=acceptance,
        rejection_below=rej_lo,
        rejection_above=rej_hi,
        margin_lower=m_lo,
        margin_upper=m_hi,
        margin_in_u=margin_in_u,
        uncertainty_too_large=too_large,
        uncertainty_to_tolerance=ratio,
        guard_banded_decision=guard,
        note=note,
    )
