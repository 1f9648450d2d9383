"""Recipes (part types): what to measure, how, and what the part must be.

A :class:`Recipe` names the target model, the nominal dimensions with their tolerances, the sweep,
region of interest and fit options of a measurement, the material (for the correction of a hot
part to 20 °C, :mod:`lrms.thermal`) and the decision rule (:mod:`lrms.conformity`). Recipes are
stored versioned by :mod:`service.recipestore`; this module holds the schema, its TOML form and
the expansion of a part's measurement request (:func:`expand_request`).

Tolerances are a nominal value and deviations: ``320.0 +1.5/-0.5 mm`` is ``nominal_m = 0.320``,
``upper_m = 0.0015``, ``lower_m = -0.0005``. Either deviation may be left out (a one-sided
tolerance); both out is refused.
"""

from __future__ import annotations

import math
import tomllib
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from lrms.conformity import DecisionRule
from lrms.thermal import MATERIALS
from service.errors import RequestFieldError
from service.models import NAME_PATTERN, RECIPE_FIELDS, FitOptions, MeasurementRequest, RoiSpec, SweepSpec


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class Tolerance(_Strict):
    """A nominal length and its limit deviations (m): ``LSL = nominal + lower``, ``USL = nominal + upper``."""

    nominal_m: float = Field(gt=0.0, le=100.0)
    lower_m: float | None = Field(default=None, ge=-100.0, le=100.0, description="lower deviation (m), e.g. -0.0005")
    upper_m: float | None = Field(default=None, ge=-100.0, le=100.0, description="upper deviation (m), e.g. 0.0015")

    @model_validator(mode="after")
    def _limits(self) -> Tolerance:
        if self.lower_m is None and self.upper_m is None:
            raise ValueError("give lower_m, upper_m or both (the deviations from nominal_m)")
        if self.lower_m is not None and self.upper_m is not None and not self.lower_m < self.upper_m:
            raise ValueError(f"lower_m ({self.lower_m:g}) must be below upper_m ({self.upper_m:g})")
        return self

    @property
    def lsl(self) -> float | None:
        return None if self.lower_m is None else self.nominal_m + self.lower_m

    @property
    def usl(self) -> float | None:
        return None if self.upper_m is None else self.nominal_m + self.upper_m


class AngleTolerance(_Strict):
    """A nominal angle and its limit deviations (deg)."""

    nominal_deg: float = Field(gt=0.0, le=180.0)
    lower_deg: float | None = Field(default=None, ge=-180.0, le=180.0)
    upper_deg: float | None = Field(default=None, ge=-180.0, le=180.0)

    @model_validator(mode="after")
    def _limits(self) -> AngleTolerance:
        if self.lower_deg is None and self.upper_deg is None:
            raise ValueError("give lower_deg, upper_deg or both (the deviations from nominal_deg)")
        if self.lower_deg is not None and self.upper_deg is not None and not self.lower_deg < self.upper_deg:
            raise ValueError(f"lower_deg ({self.lower_deg:g}) must be below upper_deg ({self.upper_deg:g})")
        return self


class Tolerances(_Strict):
    """``diameter`` (cylinder: the part's diameter; elbow: the pipe diameter D), and for elbows the
    bend radius ``bend_radius`` (A) and the bend angle."""

    diameter: Tolerance
    bend_radius: Tolerance | None = None
    bend_angle: AngleTolerance | None = None


class Recipe(_Strict):
    """A part type. Every change is stored as a new version (:mod:`service.recipestore`)."""

    name: str = Field(pattern=NAME_PATTERN, description="letters, digits, '_' and '-', at most 64")
    description: str = Field(default="", max_length=2000)
    target: Literal["cylinder", "elbow"]
    tolerances: Tolerances
    material: str | None = Field(
        default=None,
        description=f"thermal-expansion table for hot parts (lrms.thermal): one of {', '.join(sorted(MATERIALS))}",
    )
    decision_rule: DecisionRule = Field(
        default=DecisionRule.GUARD_BANDED,
        description="'iso14253-1' (guard bands of U, the default) or 'simple-acceptance' (must be named)",
    )
    sweep: SweepSpec = Field(default_factory=SweepSpec)
    roi: RoiSpec | None = None
    options: FitOptions = Field(default_factory=FitOptions)

    @field_validator("material")
    @classmethod
    def _known_material(cls, v: str | None) -> str | None:
        if v is not None and v not in MATERIALS:
            raise ValueError(f"unknown material {v!r}; known: {', '.join(sorted(MATERIALS))}")
        return v

    @model_validator(mode="after")
    def _consistent(self) -> Recipe:
        if self.target == "cylinder" and (self.tolerances.bend_radius or self.tolerances.bend_angle):
            raise ValueError("tolerances bend_radius and bend_angle apply to target 'elbow' only")
        # the measurement the recipe makes must be a valid request (options that fit the target)
        try:
            MeasurementRequest(target=self.target, sweep=self.sweep, roi=self.roi, options=self.options)
        except ValidationError as exc:
            raise ValueError("; ".join(str(e["msg"]).removeprefix("Value error, ") for e in exc.errors())) from None
        return self

    def request(self) -> MeasurementRequest:
        """The free-form measurement this recipe makes."""
        return MeasurementRequest(target=self.target, sweep=self.sweep, roi=self.roi, options=self.options)


class RecipeOut(Recipe):
    """A stored version of a recipe."""

    version: int = Field(ge=1)
    created_at: float = Field(description="when this version was stored (Unix time, s)")
    retired: bool = Field(description="the recipe is retired: readable, but parts of it can no longer be measured")


def expand_request(req: MeasurementRequest, recipe: Recipe, version: int) -> MeasurementRequest:
    """The stored form of a part's measurement: the recipe's target, sweep, roi and options, the
    recipe's name and ``version``, and the part fields of ``req``. Explicit measurement fields
    beside a recipe are refused (:class:`RequestFieldError`): a recipe's result must follow from the
    recipe version it names, so nothing overrides it."""
    given = [f for f in RECIPE_FIELDS if f in req.model_fields_set]
    if given:
        raise RequestFieldError(
            [((f,), f"{f} comes from recipe {recipe.name!r}; change the recipe (a new version) instead") for f in given]
        )
    if req.part_temperature_c is not None:
        if recipe.material is None:
            raise RequestFieldError(
                [(("part_temperature_c",), f"recipe {recipe.name!r} names no material: a hot part cannot be corrected")]
            )
        table = MATERIALS[recipe.material]
        t = req.part_temperature_c
        if not (table.t_min_c <= t <= table.t_max_c):
            raise RequestFieldError(
                [
                    (
                        ("part_temperature_c",),
                        f"{t:g} °C is outside the range of material {recipe.material!r} "
                        f"({table.t_min_c:g} .. {table.t_max_c:g} °C)",
                    )
                ]
            )
    return MeasurementRequest(
        target=recipe.target,
        sweep=recipe.sweep,
        roi=recipe.roi,
        options=recipe.options,
        recipe=recipe.name,
        recipe_version=version,
        part_id=req.part_id,
        part_temperature_c=req.part_temperature_c,
        temperature_uncertainty_c=req.temperature_uncertainty_c,
        operator=req.operator,
    )


# ---------------------------------------------------------------------------------------------- TOML


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            raise ValueError("TOML export: non-finite number")
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n") + '"'
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"TOML export: cannot write {type(v).__name__}")


def _toml_table(prefix: str, data: dict[str, Any], out: list[str]) -> None:
    scalars = {k: v for k, v in data.items() if v is not None and not isinstance(v, dict)}
    tables = {k: v for k, v in data.items() if isinstance(v, dict)}
    if prefix and (scalars or not tables):
        out.append(f"\n[{prefix}]")
    out.extend(f"{k} = {_toml_value(v)}" for k, v in scalars.items())
    for k, v in tables.items():
        _toml_table(f"{prefix}.{k}" if prefix else k, v, out)


def to_toml(recipe: Recipe, version: int | None = None) -> str:
    """The recipe as a TOML document (unset options left out; ``version`` as a comment)."""
    data = recipe.model_dump(mode="json", exclude_none=True, include=set(Recipe.model_fields))
    head = [f"# lrms recipe {recipe.name}" + (f", version {version}" if version is not None else "")]
    _toml_table("", data, head)
    return "\n".join(head) + "\n"


def from_toml(text: str) -> Recipe:
    """A recipe from its TOML form; a syntax error is a :class:`RequestFieldError` at ``("toml",)``,
    a schema error is pydantic's :class:`ValidationError` (both are 422s in the API)."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise RequestFieldError([(("toml",), f"not valid TOML: {exc}")]) from None
    return Recipe.model_validate(data)
