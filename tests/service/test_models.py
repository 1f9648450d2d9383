"""Request validation of the elbow fit options (the REST API answers these errors with 422)."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from service.models import MeasurementRequest


def test_elbow_options_are_accepted_for_an_elbow() -> None:
    req = MeasurementRequest.model_validate(
        {"target": "elbow", "options": {"degree_deg": 45, "ratio": 1.5, "flange": True}}
    )
    assert req.options.degree_deg == 45 and req.options.ratio == 1.5 and req.options.flange


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"degree_deg": 0}, "greater than or equal to 1"),
        ({"degree_deg": 200}, "less than or equal to 180"),
        ({"ratio": 0.3}, "greater than or equal to 0.5"),
        ({"flange": "maybe"}, "valid boolean"),
        ({"degree": 90}, "Extra inputs are not permitted"),
    ],
)
def test_bad_elbow_options_are_refused_with_the_reason(options: dict[str, object], message: str) -> None:
    with pytest.raises(ValidationError, match=message):
        MeasurementRequest.model_validate({"target": "elbow", "options": options})


def test_elbow_options_on_a_cylinder_are_refused() -> None:
    with pytest.raises(ValidationError, match="apply to target 'elbow' only"):
        MeasurementRequest.model_validate({"target": "cylinder", "options": {"ratio": 1.0}})
