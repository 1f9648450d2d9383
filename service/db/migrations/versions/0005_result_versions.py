"""Result versions (issue 14): ``result_versions`` and ``reprocess_calibrations`` of
:mod:`service.versionstore` (``lrms reprocess``).

Revision ID: 0005
Revises: 0004
Create Date: 2026-11-24
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects.sqlite import REAL

revision = "0005"
down_revision: str | None = "0004"
branch_labels: str | None = None
depends_on: str | None = None

Double = sa.Float().with_variant(REAL(), "sqlite")


def upgrade() -> None:
    op.create_table(
        "result_versions",
        sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
        sa.Column("measurement_id", sa.String(64), nullable=False),
        sa.Column("version", sa.Integer, nullable=False),
        sa.Column("created_at", Double, nullable=False),
        sa.Column("software_version", sa.String(64), nullable=False),
        sa.Column("calibration_id", sa.String(64), nullable=False),
        sa.Column("raw_sha256", sa.String(64), nullable=False),
        sa.Column("result", sa.JSON, nullable=False),
        sa.UniqueConstraint("measurement_id", "version", name="result_versions_number"),
        sa.UniqueConstraint(
            "measurement_id", "raw_sha256", "calibration_id", "software_version", name="result_versions_inputs"
        ),
    )
    op.create_index("result_versions_measurement", "result_versions", ["measurement_id"])
    op.create_table(
        "reprocess_calibrations",
        sa.Column("id", sa.String(64), primary_key=True),
        sa.Column("created_at", Double, nullable=False),
        sa.Column("source", sa.String(1024), nullable=False),
        sa.Column("calibration", sa.JSON, nullable=False),
    )


def downgrade() -> None:
    op.drop_table("reprocess_calibrations")
    op.drop_index("result_versions_measurement", "result_versions")
    op.drop_table("result_versions")
