"""``/api/v1/recipes``: versioned part recipes (JSON or TOML), their history and SPC.

Writes (create, new version, retire) need the admin token: a recipe is configuration. A body is
JSON, or TOML with ``Content-Type: application/toml``; either is validated by the same schema
(:class:`service.recipes.Recipe`) and refused with a 422 naming the field.
"""

from __future__ import annotations

import csv
import io
from typing import Annotated, Any, Literal

from fastapi import APIRouter, HTTPException, Path, Query, Request, Response, status
from fastapi.exceptions import RequestValidationError
from pydantic import BaseModel, Field, ValidationError

from lrms.spc import imr_chart
from service.api.core import Service
from service.api.deps import ADMIN, READ, READ_RESPONSES, ServiceDep
from service.api.errors import responses
from service.api.paths import register_path_pattern
from service.errors import RequestFieldError
from service.models import MAX_VERSION, NAME_PATTERN
from service.recipes import Recipe, RecipeOut, from_toml, to_toml
from service.recipestore import PartLink
from service.store import NotFound

# recipe names have no ".", so /recipes/{name}.toml is never taken for /recipes/{name}
register_path_pattern("recipe", NAME_PATTERN)

router = APIRouter(prefix="/recipes", tags=["recipes"], dependencies=READ, responses=READ_RESPONSES)

RecipeName = Annotated[str, Path(pattern=NAME_PATTERN, description="recipe name")]
TOML_TYPES = ("application/toml", "text/toml", "text/x-toml")
#: The most history rows one request returns.
MAX_HISTORY = 10_000

#: The recipe's JSON Schema, inline (its sub-models are components already, through RecipeOut).
_RECIPE_SCHEMA = {
    k: v for k, v in Recipe.model_json_schema(ref_template="#/components/schemas/{model}").items() if k != "$defs"
}
_BODY = {
    "requestBody": {
        "required": True,
        "content": {
            "application/json": {"schema": _RECIPE_SCHEMA},
            "application/toml": {"schema": {"type": "string", "description": "the recipe as TOML"}},
        },
    }
}


async def _recipe_body(request: Request) -> Recipe:
    """The request body as a recipe (JSON, or TOML by its content type); schema errors are 422s
    with their fields under ``body``."""
    raw = await request.body()
    kind = request.headers.get("content-type", "application/json").split(";")[0].strip().lower()
    try:
        if kind in TOML_TYPES:
            try:
                text = raw.decode("utf-8")
            except UnicodeDecodeError:
                raise RequestFieldError([(("body",), "the TOML body is not UTF-8")]) from None
            return from_toml(text)
        return Recipe.model_validate_json(raw)
    except ValidationError as exc:
        raise RequestValidationError(
            [{**e, "loc": ("body", *e["loc"])} for e in exc.errors(include_url=False, include_input=False)]
        ) from None
    except RequestFieldError as exc:
        raise exc.under("body") from None


@router.get("", response_model=list[RecipeOut], responses=responses(422))
def list_recipes(
    service: ServiceDep, include_retired: Annotated[bool, Query(description="also retired recipes")] = False
) -> list[RecipeOut]:
    """The latest version of every recipe, by name."""
    return service.recipes.list_recipes(include_retired)


@router.post(
    "",
    status_code=status.HTTP_201_CREATED,
    response_model=RecipeOut,
    dependencies=ADMIN,
    responses=responses(401, 403, 409, 413, 422),
    openapi_extra=_BODY,
)
async def create_recipe(request: Request, response: Response, service: ServiceDep) -> RecipeOut:
    """Version 1 of a new recipe (JSON, or TOML with ``Content-Type: application/toml``); 409 if the name exists."""
    recipe = await _recipe_body(request)
    out = service.recipes.create(recipe)
    response.headers["Location"] = f"/api/v1/recipes/{out.name}"
    return out


@router.get(
    "/{name:recipe}.toml",
    response_class=Response,
    responses={200: {"content": {"application/toml": {}}}, **responses(404, 422)},
)
def export_recipe(
    name: RecipeName, service: ServiceDep, version: Annotated[int | None, Query(ge=1, le=MAX_VERSION)] = None
) -> Response:
    """The recipe (latest, or ``?version=``) as TOML: ``POST`` it back, or ``lrms recipe import`` it."""
    r = service.recipes.latest(name) if version is None else service.recipes.version(name, version)
    return Response(
        to_toml(r, r.version),
        media_type="application/toml",
        headers={"Content-Disposition": f'attachment; filename="{name}.toml"'},
    )


@router.get("/{name:recipe}", response_model=RecipeOut, responses=responses(404, 422))
def get_recipe(name: RecipeName, service: ServiceDep) -> RecipeOut:
    """The latest version (a retired recipe too: ``retired`` says so)."""
    return service.recipes.latest(name)


@router.get("/{name:recipe}/versions", response_model=list[RecipeOut], responses=responses(404, 422))
def list_versions(name: RecipeName, service: ServiceDep) -> list[RecipeOut]:
    """Every version, oldest first."""
    return [service.recipes.version(name, v) for v in service.recipes.versions(name)]


@router.get("/{name:recipe}/versions/{version}", response_model=RecipeOut, responses=responses(404, 422))
def get_version(
    name: RecipeName, version: Annotated[int, Path(ge=1, le=MAX_VERSION)], service: ServiceDep
) -> RecipeOut:
    return service.recipes.version(name, version)


@router.put(
    "/{name:recipe}",
    response_model=RecipeOut,
    dependencies=ADMIN,
    responses=responses(401, 403, 404, 409, 413, 422),
    openapi_extra=_BODY,
)
async def update_recipe(name: RecipeName, request: Request, service: ServiceDep) -> RecipeOut:
    """A new version (the body is the whole recipe; its ``name`` must be the path's). A retired
    recipe is in use again."""
    recipe = await _recipe_body(request)
    if recipe.name != name:
        raise RequestFieldError([(("body", "name"), f"the body's name {recipe.name!r} is not the path's {name!r}")])
    return service.recipes.update(recipe)


@router.delete(
    "/{name:recipe}", response_model=RecipeOut, dependencies=ADMIN, responses=responses(401, 403, 404, 413, 422)
)
def retire_recipe(name: RecipeName, service: ServiceDep) -> RecipeOut:
    """Retire the recipe: its versions and history stay readable; new parts of it are refused (422)."""
    return service.recipes.retire(name)


# ------------------------------------------------------------------------------------------ history


class HistoryRow(BaseModel):
    """One part measured with the recipe. Values are null until the measurement is done."""

    measurement_id: str
    created_at: float
    finished_at: float | None
    state: str
    recipe_version: int
    part_id: str
    operator: str | None
    outcome: str | None = Field(description="conforms, does_not_conform or cannot_decide")
    value_m: float | None = Field(description="the decided value (at 20 °C for a hot part)")
    diameter_measured_m: float | None
    diameter_20c_m: float | None
    part_temperature_c: float | None
    expanded_m: float | None
    lsl_m: float | None
    usl_m: float | None
    nominal_range_excess_m: float | None = Field(
        default=None,
        description="the fit is outside the recipe's nominal diameter range (options.nominal_diameter_m) within 3 of"
        " its u: the diameter minus the nearer bound (m); its outcome is then never 'conforms'",
    )


HISTORY_COLUMNS = tuple(HistoryRow.model_fields)


def _history(service: Service, name: str, version: int | None, limit: int) -> list[HistoryRow]:
    service.recipes.latest(name)  # 404 for an unknown recipe
    rows = []
    for link in service.recipes.history(name, version, limit):
        try:
            m = service.store.get(link.measurement_id)
        except NotFound:  # removed from the measurement store
            continue
        rows.append(_row(link, m.state, m.finished_at, m.result))
    return rows


def _row(link: PartLink, state: str, finished_at: float | None, result: dict[str, Any] | None) -> HistoryRow:
    dec = (result or {}).get("decision") or {}
    thermal = (result or {}).get("thermal") or {}
    return HistoryRow(
        measurement_id=link.measurement_id,
        created_at=link.created_at,
        finished_at=finished_at,
        state=state,
        recipe_version=link.version,
        part_id=link.part_id,
        operator=link.operator,
        outcome=dec.get("outcome"),
        value_m=dec.get("value_m"),
        diameter_measured_m=(result or {}).get("diameter_m"),
        diameter_20c_m=thermal.get("diameter_20c_m"),
        part_temperature_c=thermal.get("part_temperature_c"),
        expanded_m=dec.get("expanded_m"),
        lsl_m=dec.get("lsl_m"),
        usl_m=dec.get("usl_m"),
        nominal_range_excess_m=(result or {}).get("diameter_range_excess_m"),
    )


def _csv(rows: list[HistoryRow], name: str) -> Response:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(HISTORY_COLUMNS)
    for r in rows:
        w.writerow(["" if v is None else repr(v) if isinstance(v, float) else v for v in r.model_dump().values()])
    return Response(
        buf.getvalue(),
        media_type="text/csv",
        headers={"Content-Disposition": f'attachment; filename="{name}-history.csv"'},
    )


Version = Annotated[int | None, Query(ge=1, le=MAX_VERSION, description="only parts measured with this version")]
Limit = Annotated[int, Query(ge=1, le=MAX_HISTORY, description="the newest this many")]


@router.get(
    "/{name:recipe}/history",
    response_model=list[HistoryRow],
    responses={200: {"content": {"text/csv": {}}}, **responses(404, 422)},
)
def history(
    name: RecipeName,
    service: ServiceDep,
    version: Version = None,
    limit: Limit = 1000,
    format: Annotated[Literal["json", "csv"], Query(description="json (default) or csv")] = "json",
) -> Any:
    """The recipe's parts, oldest first, with their decisions (every state; values null until done)."""
    rows = _history(service, name, version, limit)
    return _csv(rows, name) if format == "csv" else rows


@router.get(
    "/{name:recipe}/history.csv",
    response_class=Response,
    responses={200: {"content": {"text/csv": {}}}, **responses(404, 422)},
)
def history_csv(name: RecipeName, service: ServiceDep, version: Version = None, limit: Limit = 1000) -> Response:
    """The history as CSV (columns as the JSON's fields; empty cells for nulls)."""
    return _csv(_history(service, name, version, limit), name)


# ---------------------------------------------------------------------------------------------- SPC


class SpcPoint(BaseModel):
    measurement_id: str
    part_id: str
    finished_at: float | None
    value_m: float
    moving_range_m: float | None = Field(description="|x_i - x_(i-1)|; null for the first point")
    beyond_limits: bool
    mr_beyond_limit: bool
    run_of_eight: bool
    flagged: bool


class Capability(BaseModel):
    lsl_m: float | None
    usl_m: float | None
    cp: float | None
    cpk: float | None
    pp: float | None
    ppk: float | None


class SpcOut(BaseModel):
    """Individuals / moving-range chart of the decided values (lrms.spc), with capability against the
    tolerance of ``tolerance_version``."""

    recipe: str
    version: int | None = Field(description="only parts of this version; null: every version")
    tolerance_version: int = Field(description="the recipe version whose tolerance gives LSL / USL")
    n: int
    mean_m: float
    sigma_within_m: float = Field(description="MR-bar / d2")
    sigma_overall_m: float = Field(description="sample standard deviation (n - 1)")
    i_ucl_m: float
    i_lcl_m: float
    mr_bar_m: float
    mr_ucl_m: float
    mr_lcl_m: float
    rules: list[str]
    capability: Capability
    points: list[SpcPoint]


@router.get("/{name:recipe}/spc", response_model=SpcOut, responses=responses(404, 409, 422))
def spc(name: RecipeName, service: ServiceDep, version: Version = None, limit: Limit = 1000) -> SpcOut:
    """I-MR limits, flags and Cp / Cpk / Pp / Ppk of the done parts' decided values, in time order.
    The tolerance is the latest version's (or ``?version=``'s). 409 with fewer than 2 done parts."""
    rows = [r for r in _history(service, name, version, limit) if r.state == "done" and r.value_m is not None]
    if len(rows) < 2:
        raise HTTPException(409, f"recipe {name!r} has {len(rows)} measured part(s): a control chart needs 2")
    rows.sort(key=lambda r: (r.finished_at or r.created_at, r.created_at))
    recipe = service.recipes.latest(name) if version is None else service.recipes.version(name, version)
    tol = recipe.tolerances.diameter
    chart = imr_chart([r.value_m for r in rows if r.value_m is not None], tol.lsl, tol.usl)
    cap = chart.capability
    assert cap is not None  # a recipe's tolerance has at least one limit
    flagged = chart.flagged
    return SpcOut(
        recipe=name,
        version=version,
        tolerance_version=recipe.version,
        n=chart.n,
        mean_m=chart.mean,
        sigma_within_m=chart.sigma_within,
        sigma_overall_m=chart.sigma_overall,
        i_ucl_m=chart.i_ucl,
        i_lcl_m=chart.i_lcl,
        mr_bar_m=chart.mr_bar,
        mr_ucl_m=chart.mr_ucl,
        mr_lcl_m=chart.mr_lcl,
        rules=list(chart.rules),
        capability=Capability(lsl_m=cap.lsl, usl_m=cap.usl, cp=cap.cp, cpk=cap.cpk, pp=cap.pp, ppk=cap.ppk),
        points=[
            SpcPoint(
                measurement_id=r.measurement_id,
                part_id=r.part_id,
                finished_at=r.finished_at,
                value_m=float(r.value_m or 0.0),
                moving_range_m=None if i == 0 else float(chart.moving_ranges[i - 1]),
                beyond_limits=bool(chart.beyond_limits[i]),
                mr_beyond_limit=bool(chart.mr_beyond_limit[i]),
                run_of_eight=bool(chart.run_of_eight[i]),
                flagged=bool(flagged[i]),
            )
            for i, r in enumerate(rows)
        ],
    )
