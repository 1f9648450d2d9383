"""Part recipes (issue 13): ``recipes``, ``recipe_versions`` and ``recipe_measurements`` of
:mod:`service.recipestore`.

Revision ID: 0004
Revises: 0003
Create Date: 2026-11-24
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects.sqlite import REAL

revision = "0004"
down_revision: str | None = "0003"
branch_labels: str | None = None
depends_on: str | None = None

Double = sa.Float().with_variant(REAL(), "sqlite")


def upgrade() -> None:
    op.create_table(
        "recipes",
        sa.Column("name", sa.String(64), primary_key=True),
        sa.Column("latest_version", sa.Integer, nullable=False),
        sa.Column("retired", sa.Boolean, nullable=False),
        sa.Column("created_at", Double, nullable=False),
        sa.Column("retired_at", Double, nullable=True),
    )
    op.create_table(
        "recipe_versions",
        sa.Column("name", sa.String(64), primary_key=True),
        sa.Column("version", sa.Integer, primary_key=True),
        sa.Column("created_at", Double, nullable=False),
        sa.Column("body", sa.Text, nullable=False),
        sa.ForeignKeyConstraint(["name"], ["recipes.name"], name="fk_recipe_versions_name_recipes"),
    )
    op.create_table(
        "recipe_measurements",
        sa.Column("measurement_id", sa.String(64), primary_key=True),
        sa.Column("recipe", sa.String(64), nullable=False),
        sa.Column("version", sa.Integer, nullable=False),
        sa.Column("part_id", sa.String(128), nullable=False),
        sa.Column("operator", sa.String(200), nullable=True),
        sa.Column("created_at", Double, nullable=False),
    )
    op.create_index("recipe_measurements_by_recipe", "recipe_measurements", ["recipe", "created_at"])


def downgrade() -> None:
    op.drop_index("recipe_measurements_by_recipe", "recipe_measurements")
    op.drop_table("recipe_measurements")
    op.drop_table("recipe_versions")
    op.drop_table("recipes")
