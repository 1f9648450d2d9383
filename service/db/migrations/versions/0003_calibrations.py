"""Rig calibrations (issue 12): the ``calibrations`` table of :mod:`service.calstore`.

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-24
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0003"
down_revision: str | None = "0002"
branch_labels: str | None = None
depends_on: str | None = None


def upgrade() -> None:
    op.create_table(
        "calibrations",
        sa.Column("id", sa.String(32), primary_key=True),
        sa.Column("seq", sa.Integer, nullable=False),
        sa.Column("created", sa.String(40), nullable=False),
        sa.Column("name", sa.String(200), nullable=False),
        sa.Column("comment", sa.Text, nullable=False),
        sa.Column("rig_id", sa.String(200), nullable=True),
        sa.Column("result", sa.Text, nullable=False),
        sa.Column("active", sa.Boolean, nullable=False),
    )
    op.create_index("calibrations_seq", "calibrations", ["seq"])
    op.create_index("calibrations_rig", "calibrations", ["rig_id", "seq"])


def downgrade() -> None:
    op.drop_index("calibrations_rig", "calibrations")
    op.drop_index("calibrations_seq", "calibrations")
    op.drop_table("calibrations")
