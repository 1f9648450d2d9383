"""Versioned recipes and the link of each part's measurement to its recipe, in SQL (SQLAlchemy Core).

Three tables of the result store's schema (:mod:`service.db.schema`, created by migration 0004):

* ``recipes``: one row per recipe name: its latest version, whether it is retired;
* ``recipe_versions``: every version ever stored, ``(name, version)`` and the recipe as JSON.
  A change is a new version; old versions stay readable, so a result names the version it used;
* ``recipe_measurements``: measurement id -> recipe name, version, part id, operator, time: the
  history of a recipe (:meth:`RecipeStore.history`) without reading the measurement store's tables.

:class:`RecipeStore` takes the result store's :class:`sqlalchemy.Engine` (:attr:`service.store.Store.engine`:
SQLite or PostgreSQL, shared by the rigs of a plant); its writes are write transactions of that
database (:func:`service.db.tx.write_transaction`), so a recipe and its version 1 are stored
together or not at all, and two rigs storing a new version at once get versions n+1 and n+2.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass

import sqlalchemy as sa
from sqlalchemy.exc import IntegrityError

from service.db import schema
from service.db.tx import write_transaction
from service.recipes import Recipe, RecipeOut
from service.store import NotFound, StoreError

RECIPES = schema.recipes
RECIPE_VERSIONS = schema.recipe_versions
RECIPE_MEASUREMENTS = schema.recipe_measurements


class RecipeNotFound(NotFound):
    """No recipe (or no such version) of that name (404)."""


class RecipeConflict(StoreError):
    """The recipe exists already, or changed at the same time (409)."""


@dataclass(frozen=True)
class PartLink:
    """One part's measurement of a recipe."""

    measurement_id: str
    recipe: str
    version: int
    part_id: str
    operator: str | None
    created_at: float


class RecipeStore:
    """Recipes with their versions, and the recipe measurements of parts."""

    def __init__(self, engine: sa.Engine) -> None:
        self.engine = engine

    def close(self) -> None:
        self.engine.dispose()

    # -- recipes --------------------------------------------------------------------------
    def create(self, recipe: Recipe) -> RecipeOut:
        """Version 1 of a new recipe; :class:`RecipeConflict` if the name exists (retired or not)."""
        now = time.time()
        try:
            with write_transaction(self.engine) as conn:
                conn.execute(RECIPES.insert().values(name=recipe.name, latest_version=1, retired=False, created_at=now))
                conn.execute(
                    RECIPE_VERSIONS.insert().values(name=recipe.name, version=1, created_at=now, body=_body(recipe))
                )
        except IntegrityError:
            raise RecipeConflict(
                f"recipe {recipe.name!r} exists already: PUT /api/v1/recipes/{recipe.name} stores a new version"
            ) from None
        return self.version(recipe.name, 1)

    def update(self, recipe: Recipe) -> RecipeOut:
        """A new version of an existing recipe (a retired one is in use again)."""
        now = time.time()
        try:
            with write_transaction(self.engine) as conn:
                row = conn.execute(sa.select(RECIPES.c.latest_version).where(RECIPES.c.name == recipe.name)).first()
                if row is None:
                    raise RecipeNotFound(f"no recipe {recipe.name!r}: POST /api/v1/recipes creates it")
                v = int(row[0]) + 1
                conn.execute(
                    RECIPE_VERSIONS.insert().values(name=recipe.name, version=v, created_at=now, body=_body(recipe))
                )
                conn.execute(
                    RECIPES.update()
                    .where(RECIPES.c.name == recipe.name)
                    .values(latest_version=v, retired=False, retired_at=None)
                )
        except IntegrityError:
            raise RecipeConflict(
                f"recipe {recipe.name!r} was changed at the same time; read it and try again"
            ) from None
        return self.version(recipe.name, v)

    def retire(self, name: str) -> RecipeOut:
        """Mark a recipe retired: its versions stay readable, new parts of it are refused."""
        with write_transaction(self.engine) as conn:
            n = conn.execute(
                RECIPES.update().where(RECIPES.c.name == name).values(retired=True, retired_at=time.time())
            ).rowcount
        if n == 0:
            raise RecipeNotFound(f"no recipe {name!r}")
        return self.latest(name)

    def latest(self, name: str) -> RecipeOut:
        with self.engine.connect() as conn:
            row = conn.execute(sa.select(RECIPES.c.latest_version).where(RECIPES.c.name == name)).first()
        if row is None:
            raise RecipeNotFound(f"no recipe {name!r}")
        return self.version(name, int(row[0]))

    def version(self, name: str, version: int) -> RecipeOut:
        q = (
            sa.select(RECIPE_VERSIONS.c.body, RECIPE_VERSIONS.c.created_at, RECIPES.c.retired)
            .join(RECIPES, RECIPES.c.name == RECIPE_VERSIONS.c.name)
            .where(RECIPE_VERSIONS.c.name == name, RECIPE_VERSIONS.c.version == version)
        )
        with self.engine.connect() as conn:
            row = conn.execute(q).first()
        if row is None:
            if self.exists(name):
                raise RecipeNotFound(f"recipe {name!r} has no version {version}")
            raise RecipeNotFound(f"no recipe {name!r}")
        return RecipeOut.model_validate(
            {**json.loads(row.body), "version": version, "created_at": row.created_at, "retired": bool(row.retired)}
        )

    def exists(self, name: str) -> bool:
        with self.engine.connect() as conn:
            return conn.execute(sa.select(RECIPES.c.name).where(RECIPES.c.name == name)).first() is not None

    def versions(self, name: str) -> list[int]:
        with self.engine.connect() as conn:
            rows = conn.execute(
                sa.select(RECIPE_VERSIONS.c.version)
                .where(RECIPE_VERSIONS.c.name == name)
                .order_by(RECIPE_VERSIONS.c.version)
            ).all()
        if not rows:
            raise RecipeNotFound(f"no recipe {name!r}")
        return [int(r[0]) for r in rows]

    def list_recipes(self, include_retired: bool = False) -> list[RecipeOut]:
        """The latest version of every recipe, by name."""
        q = sa.select(RECIPES.c.name, RECIPES.c.latest_version).order_by(RECIPES.c.name)
        if not include_retired:
            q = q.where(RECIPES.c.retired.is_(False))
        with self.engine.connect() as conn:
            rows = conn.execute(q).all()
        return [self.version(r.name, int(r.latest_version)) for r in rows]

    # -- parts ----------------------------------------------------------------------------
    def link(self, measurement_id: str, recipe: str, version: int, part_id: str, operator: str | None) -> None:
        """Record that ``measurement_id`` measured part ``part_id`` of ``recipe`` version ``version``."""
        with write_transaction(self.engine) as conn:
            conn.execute(
                RECIPE_MEASUREMENTS.insert().values(
                    measurement_id=measurement_id,
                    recipe=recipe,
                    version=version,
                    part_id=part_id,
                    operator=operator,
                    created_at=time.time(),
                )
            )

    def history(self, recipe: str, version: int | None = None, limit: int = 1000) -> list[PartLink]:
        """The recipe's part measurements, oldest first (the newest ``limit``)."""
        q = sa.select(RECIPE_MEASUREMENTS).where(RECIPE_MEASUREMENTS.c.recipe == recipe)
        if version is not None:
            q = q.where(RECIPE_MEASUREMENTS.c.version == version)
        q = q.order_by(RECIPE_MEASUREMENTS.c.created_at.desc(), RECIPE_MEASUREMENTS.c.measurement_id).limit(limit)
        with self.engine.connect() as conn:
            rows = conn.execute(q).all()
        return [
            PartLink(r.measurement_id, r.recipe, int(r.version), r.part_id, r.operator, float(r.created_at))
            for r in reversed(rows)
        ]


def _body(recipe: Recipe) -> str:
    return json.dumps(recipe.model_dump(mode="json", include=set(Recipe.model_fields)))
