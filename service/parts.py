"""A part's result: the recipe it was measured with, the correction of a hot part to 20 °C and the
conformity decision (the numerics are :mod:`lrms.thermal` and :mod:`lrms.conformity`).

:func:`part_result` adds three keys to a fit's result (docs/service.md, "Recipes and parts")::

    part      {recipe, recipe_version, part_id, operator}
    thermal   {material, part_temperature_c, temperature_uncertainty_c, diameter_measured_m,
               diameter_20c_m, u_thermal_m, budget: [rows]}          (None without a temperature)
    decision  {rule, outcome, value_m, lsl_m, usl_m, expanded_m, k, acceptance_zone_m: [lo, hi],
               nominal_range_excess_m, note,
               characteristics: [{characteristic, unit, value, lsl, usl, expanded, k, acceptance_zone,
                                  outcome, note}]}

The decided value is the diameter (cylinder: the part's; elbow: the pipe's D), at 20 °C when a
temperature was given; ``decision``'s ``value_m`` .. ``acceptance_zone_m`` are the diameter's. An
elbow recipe may also tolerance the bend radius A (corrected to 20 °C as D is, U from the fit's
sigma of A and the thermal rows) and the bend angle; each is decided in ``characteristics``, and
``outcome`` is the worst of them (does not conform, then cannot decide, then conforms). A cylinder
fit flagged outside its request's nominal diameter range (``diameter_range_excess_m`` not None)
never *conforms*: its diameter's outcome is then *cannot decide* at best, the note says why and
``decision.nominal_range_excess_m`` repeats the excess (None otherwise). The
elbow fit holds the bend angle fixed (given, or its start value from the pipe ends), so an angle
tolerance is *cannot decide* until the fit estimates the angle with an uncertainty.

The diameter's expanded uncertainty combines the measurement's budget (every row
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
from service.errors import RequestFieldError, ServiceError
from service.jobs import JobContext, MeasureFn
from service.models import MeasurementRequest
from service.recipes import Recipe, expand_request
from service.recipestore import RecipeStore
from service.store import NotFound

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
    rule = DecisionRule(recipe.decision_rule)
    tol = recipe.tolerances.diameter
    what = "diameter at 20 °C" if thermal is not None else "measured diameter"
    how = f"U = {k:g} u_c of the measurement budget" + (" and the thermal rows" if thermal else "")
    diameter = _characteristic("diameter", "m", value, k * u_c, k, tol.lsl, tol.usl, rule, f"{what}; {how}")
    diameter = _nominal_range_flag(diameter, result)
    characteristics = [diameter, *_elbow_characteristics(result, recipe, request_part, k, rule)]
    outcome = max((c["outcome"] for c in characteristics), key=SEVERITY.__getitem__)
    note = diameter["note"]
    if len(characteristics) > 1:
        note += "; the part's outcome is the worst of " + ", ".join(
            f"{c['characteristic']} ({c['outcome']})" for c in characteristics
        )
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
            "outcome": outcome,
            "value_m": value,
            "lsl_m": tol.lsl,
            "usl_m": tol.usl,
            "expanded_m": diameter["expanded"],
            "k": k,
            "acceptance_zone_m": diameter["acceptance_zone"],
            "nominal_range_excess_m": result.get("diameter_range_excess_m"),
            "note": note,
            "characteristics": characteristics,
        },
    }


#: Outcomes from best to worst: a part's outcome is its worst characteristic's.
SEVERITY = {"conforms": 0, "cannot_decide": 1, "does_not_conform": 2}


def _characteristic(
    name: str,
    unit: str,
    value: float,
    expanded: float | None,
    k: float,
    lsl: float | None,
    usl: float | None,
    rule: DecisionRule,
    how: str,
) -> dict[str, Any]:
    """One toleranced characteristic decided by ``rule``; ``expanded`` None: not measured with an
    uncertainty, so *cannot decide* (``how`` says why)."""
    out: dict[str, Any] = {"characteristic": name, "unit": unit, "value": value, "lsl": lsl, "usl": usl, "k": k}
    if expanded is None:
        return out | {"outcome": "cannot_decide", "expanded": None, "acceptance_zone": None, "note": how}
    c = decide(value, expanded, lsl, usl, rule)
    if rule is DecisionRule.GUARD_BANDED:
        zone = [None if lsl is None else lsl + expanded, None if usl is None else usl - expanded]
    else:
        zone = [lsl, usl]
    note = f"{how}; {c.note}"
    if c.uncertainty_too_large:
        note += " (the acceptance zone is empty: its lower end is above its upper end)"
    return out | {"outcome": OUTCOMES[c.decision], "expanded": expanded, "acceptance_zone": zone, "note": note}


def _nominal_range_flag(diameter: dict[str, Any], result: dict[str, Any]) -> dict[str, Any]:
    """The diameter's decision on a fit flagged outside the request's nominal diameter range
    (``diameter_range_excess_m``: within 3 of its u, :func:`lrms.cylinder.nominal_check`): the
    note says so, and *conforms* becomes *cannot decide*: the fit is of doubtful plausibility (a
    wrong part, or a fit whose family choice it cannot make), so it proves no conformity; a
    *does not conform* stands."""
    excess = result.get("diameter_range_excess_m")
    if excess is None:
        return diameter
    lo, hi = (1e3 * float(x) for x in result["diameter_range_m"])
    flag = (
        f"the fit is outside the nominal diameter range [{lo:.1f}, {hi:.1f}] mm of the request by"
        f" {1e3 * float(excess):+.2f} mm ({float(result['diameter_range_excess_u']):.2f} u of the fit)"
    )
    if diameter["outcome"] == "conforms":
        return diameter | {"outcome": "cannot_decide", "note": f"{diameter['note']}; {flag}: cannot decide"}
    return diameter | {"note": f"{diameter['note']}; {flag}"}


def _elbow_characteristics(
    result: dict[str, Any], recipe: Recipe, request_part: dict[str, Any], k: float, rule: DecisionRule
) -> list[dict[str, Any]]:
    """An elbow's bend radius A (at 20 °C for a hot part: it scales as D does) and bend angle, when
    the recipe tolerances them."""
    out: list[dict[str, Any]] = []
    tol_a, tol_angle = recipe.tolerances.bend_radius, recipe.tolerances.bend_angle
    sigma = result.get("sigma") or {}
    if tol_a is not None:
        if "bend_radius_m" not in result or "A_m" not in sigma:
            raise ServiceError("the result has no bend radius with its uncertainty: the bend radius cannot be decided")
        a = float(result["bend_radius_m"])
        u_fit = float(sigma["A_m"])
        temperature = request_part.get("part_temperature_c")
        how = f"U = {k:g} x the elbow fit's standard deviation of A"
        if temperature is not None:
            assert recipe.material is not None  # checked with the diameter's correction
            u_t = float(request_part.get("temperature_uncertainty_c") or 0.0)
            tc = thermal_correction(a, float(temperature), u_t, recipe.material)
            a, u = tc.d20_m, math.hypot(tc.scale * u_fit, tc.u_thermal_m)
            how = "bend radius at 20 °C; " + how + " and the thermal rows"
        else:
            u = u_fit
            how = "measured bend radius; " + how
        out.append(_characteristic("bend_radius", "m", a, k * u, k, tol_a.lsl, tol_a.usl, rule, how))
    if tol_angle is not None:
        if "degree" not in result:
            raise ServiceError("the result has no bend angle: the bend angle cannot be decided")
        angle = float(result["degree"])
        lo = None if tol_angle.lower_deg is None else tol_angle.nominal_deg + tol_angle.lower_deg
        hi = None if tol_angle.upper_deg is None else tol_angle.nominal_deg + tol_angle.upper_deg
        u_angle = sigma.get("degree_deg")
        if u_angle is None:
            how = (
                f"the elbow fit does not estimate the bend angle: it holds it at {angle:g} deg (the recipe's "
                "options.degree_deg, or the start value from the pipe ends, snapped to 45 or 90 deg within 12 deg), "
                "with no uncertainty, "
                "so its conformity can be neither proved nor disproved"
            )
            out.append(_characteristic("bend_angle", "deg", angle, None, k, lo, hi, rule, how))
        else:
            how = f"bend angle; U = {k:g} x the elbow fit's standard deviation of the angle"
            out.append(_characteristic("bend_angle", "deg", angle, k * float(u_angle), k, lo, hi, rule, how))
    return out


def resolve_part(req: MeasurementRequest, recipes: RecipeStore) -> MeasurementRequest:
    """A part's request with its recipe's measurement filled in and the version pinned
    (:func:`service.recipes.expand_request`): the latest version unless ``recipe_version`` names
    one. :class:`RequestFieldError` (locations relative to the request) for an unknown recipe or
    version, a retired recipe, or fields the recipe supplies."""
    if req.recipe is None:
        raise RequestFieldError([(("recipe",), "not a part's measurement: no recipe named")])
    try:
        recipe = (
            recipes.latest(req.recipe)
            if req.recipe_version is None
            else recipes.version(req.recipe, req.recipe_version)
        )
    except NotFound as exc:
        field = "recipe_version" if req.recipe_version is not None and recipes.exists(req.recipe) else "recipe"
        raise RequestFieldError([((field,), str(exc))]) from None
    if recipe.retired:
        raise RequestFieldError([(("recipe",), f"recipe {req.recipe!r} is retired")])
    return expand_request(req, recipe, recipe.version)


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
