"""Baseline: the schema the SQLite store created before migrations (commit 03908b3).

It also adopts a file written by that code, which has the tables but no ``alembic_version``: what
exists is kept, only what is missing is created (``raw_truncated`` was added by that code itself to
files older than the column).

Revision ID: 0001
Revises:
Create Date: 2026-11-24
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects.sqlite import REAL

revision = "0001"
down_revision: str | None = None
branch_labels: str | None = None
depends_on: str | None = None

#: REAL as the first store declared it on SQLite; an 8-byte float elsewhere.
Double = sa.Float().with_variant(REAL(), "sqlite")


def upgrade() -> None:
    insp = sa.inspect(op.get_bind())
    tables = set(insp.get_table_names())
    if "measurements" not in tables:
        op.create_table(
            "measurements",
            sa.Column("id", sa.Text, primary_key=True),
            sa.Column("seq", sa.Integer, nullable=False),
            sa.Column("created_at", Double, nullable=False),
            sa.Column("started_at", Double),
            sa.Column("finished_at", Double),
            sa.Column("state", sa.Text, nullable=False),
            sa.Column("request", sa.Text, nullable=False),
            sa.Column("progress", Double, nullable=False, server_default="0"),
            sa.Column("message", sa.Text, nullable=False, server_default=""),
            sa.Column("result", sa.Text),
            sa.Column("error", sa.Text),
            sa.Column("raw_path", sa.Text),
            sa.Column("cloud_path", sa.Text),
            sa.Column("schedule_id", sa.Text),
            sa.Column("raw_truncated", sa.Integer, nullable=False, server_default="0"),
        )
    elif "raw_truncated" not in {c["name"] for c in insp.get_columns("measurements")}:
        op.add_column("measurements", sa.Column("raw_truncated", sa.Integer, nullable=False, server_default="0"))
    if "measurements_state" not in {i["name"] for i in sa.inspect(op.get_bind()).get_indexes("measurements")}:
        op.create_index("measurements_state", "measurements", ["state", "seq"])
    if "schedules" not in tables:
        op.create_table(
            "schedules",
            sa.Column("id", sa.Text, primary_key=True),
            sa.Column("created_at", Double, nullable=False),
            sa.Column("name", sa.Text, nullable=False, server_default=""),
            sa.Column("cron", sa.Text),
            sa.Column("interval_s", Double),
            sa.Column("template", sa.Text, nullable=False),
            sa.Column("enabled", sa.Integer, nullable=False, server_default="1"),
            sa.Column("next_run", Double),
            sa.Column("last_run", Double),
            sa.Column("last_measurement_id", sa.Text),
        )


def downgrade() -> None:
    op.drop_table("schedules")
    op.drop_index("measurements_state", "measurements")
    op.drop_table("measurements")
