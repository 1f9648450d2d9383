"""``lrms recipe import``: store a recipe from its TOML file (a new recipe, or its next version)."""

from __future__ import annotations

import argparse

from service.cli._recipes import add_store_arguments, recipe_store

HELP = "store a recipe from a TOML file in the service's database (new, or its next version)"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", metavar="FILE.toml", help="the recipe (as GET /api/v1/recipes/NAME.toml gives it)")
    add_store_arguments(parser)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from pydantic import ValidationError

    from service.errors import RequestFieldError
    from service.recipes import Recipe, from_toml

    try:
        recipe = from_toml(Path(args.file).read_text(encoding="utf-8"))
    except ValidationError as exc:
        raise RequestFieldError(
            [(tuple(e["loc"]), str(e["msg"]).removeprefix("Value error, ")) for e in exc.errors()]
        ) from None
    with recipe_store(args) as store:
        if not store.exists(recipe.name):
            out = store.create(recipe)
            print(f"{out.name}: created, version {out.version}")
            return 0
        latest = store.latest(recipe.name)
        if Recipe.model_validate(latest.model_dump(include=set(Recipe.model_fields))) == recipe and not latest.retired:
            print(f"{recipe.name}: unchanged, version {latest.version}")
            return 0
        out = store.update(recipe)
        print(f"{out.name}: version {out.version}")
        return 0
