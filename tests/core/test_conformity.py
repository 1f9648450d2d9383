"""ISO 14253-1 conformity decisions: every zone and its boundaries, one-sided tolerances, simple acceptance."""

from __future__ import annotations

import math

import pytest

from lrms.conformity import ConformityError, Decision, DecisionRule, decide
from lrms.errors import LrmsError

# 320 +1.5 / -0.5 (mm here; the module is unit-agnostic), U = 0.25: binary-exact numbers, so boundaries are exact
LO, HI, U = 319.5, 321.5, 0.25
C, N, CD = Decision.CONFORMS, Decision.DOES_NOT_CONFORM, Decision.CANNOT_DECIDE


@pytest.mark.parametrize(
    ("y", "expected"),
    [
        (320.0, C),
        (319.75, C),  # = lower + U: inside the acceptance zone (closed)
        (321.25, C),  # = upper - U
        (319.7, CD),
        (319.5, CD),  # on the limit
        (319.25, CD),  # = lower - U: not yet the rejection zone
        (319.2, N),
        (321.3, CD),
        (321.75, CD),  # = upper + U
        (321.8, N),
    ],
)
def test_guard_banded_zones(y: float, expected: Decision) -> None:
    r = decide(y, U, LO, HI)
    assert r.decision is expected and r.guard_banded_decision is expected
    assert r.rule is DecisionRule.GUARD_BANDED
    assert r.acceptance == (319.75, 321.25)
    assert (r.rejection_below, r.rejection_above) == (319.25, 321.75)
    assert "14253-1" in r.note


def test_margins_and_ratio() -> None:
    r = decide(320.0, U, LO, HI)
    assert (r.margin_lower, r.margin_upper) == (0.5, 1.5)
    assert r.margin_in_u == 2.0  # 0.5 / 0.25
    assert r.uncertainty_to_tolerance == 0.25  # 2 * 0.25 / 2.0
    assert not r.uncertainty_too_large
    outside = decide(319.0, U, LO, HI)
    assert outside.margin_lower == -0.5 and outside.margin_in_u == -2.0
    assert decide(320.0, 0.0, LO, HI).margin_in_u is None


def test_simple_acceptance_must_be_named_and_says_so() -> None:
    r = decide(319.6, U, LO, HI, rule=DecisionRule.SIMPLE_ACCEPTANCE)
    assert r.decision is C and r.guard_banded_decision is CD
    assert r.rule is DecisionRule.SIMPLE_ACCEPTANCE and "simple acceptance" in r.note and "cannot decide" in r.note
    assert r.acceptance == (LO, HI) and (r.rejection_below, r.rejection_above) == (LO, HI)
    assert decide(319.4, U, LO, HI, rule=DecisionRule.SIMPLE_ACCEPTANCE).decision is N
    assert decide(321.5, U, LO, HI, rule=DecisionRule("simple-acceptance")).decision is C  # the limit belongs to it
    # the default is the guard-banded rule
    assert decide(319.6, U, LO, HI).decision is CD


@pytest.mark.parametrize(
    ("y", "lower", "upper", "expected"),
    [
        (400.0, LO, None, C),
        (319.75, LO, None, C),
        (319.6, LO, None, CD),
        (319.0, LO, None, N),
        (-1e9, None, HI, C),
        (321.6, None, HI, CD),
        (322.0, None, HI, N),
    ],
)
def test_one_sided(y: float, lower: float | None, upper: float | None, expected: Decision) -> None:
    r = decide(y, U, lower, upper)
    assert r.decision is expected
    assert r.uncertainty_to_tolerance is None and not r.uncertainty_too_large
    assert r.acceptance == ((319.75, None) if upper is None else (None, 321.25))


def test_uncertainty_as_large_as_the_tolerance_never_conforms() -> None:
    r = decide(0.5, 0.5, 0.0, 1.0)  # 2U = width: the acceptance zone is one point
    assert r.uncertainty_too_large and r.acceptance is None and r.decision is CD
    assert "cannot be proven" in r.note and r.uncertainty_to_tolerance == 1.0
    assert decide(-0.6, 0.5, 0.0, 1.0).decision is N
    assert decide(0.5, 0.6, 0.0, 1.0).decision is CD
    # simple acceptance still answers, and still reports the flag
    s = decide(0.5, 0.6, 0.0, 1.0, rule=DecisionRule.SIMPLE_ACCEPTANCE)
    assert s.decision is C and s.uncertainty_too_large


@pytest.mark.parametrize(
    ("args", "field", "match"),
    [
        ((320.0, U, 321.0, 320.0), "lower", "below the upper"),
        ((320.0, U, 320.0, 320.0), "lower", "below the upper"),
        ((320.0, -0.1, LO, HI), "expanded_uncertainty", ">= 0"),
        ((math.nan, U, LO, HI), "value", "finite"),
        ((320.0, math.inf, LO, HI), "expanded_uncertainty", "finite"),
        ((320.0, U, None, None), "tolerance", "lower limit"),
    ],
)
def test_bad_input(args: tuple[float, float, float | None, float | None], field: str, match: str) -> None:
    with pytest.raises(ConformityError, match=match) as info:
        decide(*args)
    assert info.value.field == field and isinstance(info.value, LrmsError)


def test_unknown_rule() -> None:
    with pytest.raises(ConformityError, match="simple-acceptance") as info:
        decide(320.0, U, LO, HI, rule="lenient")  # type: ignore[arg-type]
    assert info.value.field == "rule"
