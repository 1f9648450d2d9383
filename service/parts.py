"""A part's result: the recipe it was measured with, the correction of a hot part to 20 °C and the
conformity decision (the numerics are :mod:`lrms.thermal` and :mod:`lrms.conformity`).

:func:`part_result` adds three keys to a fit's result (docs/service.md, "Recipes and parts")::

    part      {recipe, recipe_version, part_id, operator}
    thermal   {material, part_temperature_c, temperature_uncertainty_c, diameter_measured_m,
               diameter_20c_m, u_thermal_m, budget: [rows]}          (None without a temperature)
    decision  {rule, outcome, value_m, lsl_m, usl_m, expanded_m, k, acceptance_zone_m: [lo, hi], note}

The decided value is the diameter (cylinder: the part's; elbow: the pipe's D), at 20 °C when a
temperature was given. Its expanded uncertainty combines the measurement's budget (every row
times ``dD20/dD_T = 1/(1+e)``) with the thermal rows, root-sum-square, ``U = k u_c`` with the
measurement budget's ``k``. An elbow's budget is its fit's standard deviation of D alone.

:func:`with_parts` wraps a measurement function so that every recipe measurement's result gets them.
"""

from __future__ import annotations

import math
from typing import Any

from lrms.budget import BudgetRow
from lrms.conformity import Decision, DecisionRule, decide
from lrms.thermal import thermal_correction
from service.errors import ServiceError
from service.jobs import JobContext, MeasureFn
from service.recipes import Recipe
from service.recipestore import RecipeStore

OUTCOMES = {
    Decision.CONFORMS: "conforms",
    Decision.DOES_NOT_CONFORM: "does_not_conform",
    Decision.CANNOT_DECIDE: "cannot_decide",
}
#: The coverage factor of an elbow's decision (its fit gives a standard deviation only).
ELBOW_K = 2.0


def _measurement_rows(result: dict[str, Any]) -> tuple[list[dict[str, Any]], float]:
    """The measured diameter's budget rows and coverage factor."""
    unc = result.get("uncertainty")
    if isinstance(unc, dict) and "budget" in unc:
        return list(unc["budget"]), float(unc["k"])
    sigma = result.get("sigma", {}).get("D_m")
    if sigma is None:
        raise ServiceError("the result has no uncertainty of its diameter: no conformity decision is possible")
    row = BudgetRow.of("fit (type A)", "A", float(sigma), "m", 1.0, "normal", "the elbow fit's standard deviation of D")
    return [row.to_dict()], ELBOW_K


def part_result(result: dict[str, Any], request_part: dict[str, Any], recipe: Recipe, version: int) -> dict[str, Any]:
    """``{"part", "thermal", "decision"}`` for a fit's ``result`` of a part of ``recipe`` (version
    ``version``); ``request_part``: the request's ``part_id``, ``operator``, ``part_temperature_c``,
    ``temperature_uncertainty_c``."""
    d = float(result["diameter_m"])
    rows, k = _measurement_rows(result)
    temperature = request_part.get("part_temperature_c")
    thermal: dict[str, Any] | None = None
    scale = 1.0
    thermal_rows: list[dict[str, Any]] = []
    value = d
    if temperature is not None:
        if recipe.material is None:
            raise ServiceError(f"recipe {recipe.name!r} version {version} names no material for a hot part")
        u_t = float(request_part.get("temperature_uncertainty_c") or 0.0)
        tc = thermal_correction(d, float(temperature), u_t, recipe.material)
        scale = tc.scale
        thermal_rows = [r.to_dict() for r in tc.rows]
        value = tc.d20_m
        thermal = {
            "material": tc.material,
            "part_temperature_c": tc.temperature_c,
            "temperature_uncertainty_c": tc.u_temperature_k,
            "diameter_measured_m": d,
            "diameter_20c_m": tc.d20_m,
            "u_thermal_m": tc.u_thermal_m,
            "budget": thermal_rows,
        }
    u_c = math.sqrt(sum((scale * float(r["u_m"])) ** 2 for r in rows) + sum(float(r["u_m"]) ** 2 for r in thermal_rows))
    expanded = k * u_c
    tol = recipe.tolerances.diameter
    lsl, usl = tol.lsl, tol.usl
    rule = DecisionRule(recipe.decision_rule)
    c = decide(value, expanded, lsl, usl, rule)
    if rule is DecisionRule.GUARD_BANDED:
        zone = [None if lsl is None else lsl + expanded, None if usl is None else usl - expanded]
    else:
        zone = [lsl, usl]
    what = "diameter at 20 °C" if thermal is not None else "measured diameter"
    note = f"{what}; U = {k:g} u_c of the measurement budget" + (" and the thermal rows" if thermal else "")
    note += f"; {c.note}"
    if c.uncertainty_too_large:
        note += " (the acceptance zone is empty: its lower end is above its upper end)"
    return {
        "part": {
            "recipe": recipe.name,
            "recipe_version": int(version),
            "part_id": str(request_part["part_id"]),
            "operator": request_part.get("operator"),
        },
        "thermal": thermal,
        "decision": {
            "rule": rule.value,
            "outcome": OUTCOMES[c.decision],
            "value_m": value,
            "lsl_m": lsl,
            "usl_m": usl,
            "expanded_m": expanded,
            "k": k,
            "acceptance_zone_m": zone,
            "note": note,
        },
    }


def with_parts(measure: MeasureFn, recipes: RecipeStore) -> MeasureFn:
    """``measure`` followed, for a recipe measurement, by :func:`part_result` on its result (with the
    recipe version the request pinned when it was queued)."""

    def run(ctx: JobContext) -> dict[str, Any]:
        result = measure(ctx)
        req = ctx.request
        if req.recipe is None:
            return result
        if req.recipe_version is None:
            raise ServiceError("a recipe measurement without its recipe version (queued by an older service?)")
        ctx.info["partial_result"] = result  # kept if the decision fails
        recipe = recipes.version(req.recipe, req.recipe_version)
        part = req.model_dump(include={"part_id", "operator", "part_temperature_c", "temperature_uncertainty_c"})
        return {**result, **part_result(result, part, recipe, req.recipe_version)}

    return run
