"""Drip-feed runs: one row per run of a program on a machine (the run history).

Revision ID: 0007
Revises: 0006
Create Date: 2026-12-01
"""

import sqlalchemy as sa
from alembic import op

revision = "0007"
down_revision = "0006"
branch_labels = None
depends_on = None

TS = sa.DateTime()  # naive UTC; jobs.models.UTCDateTime adds the zone back


def upgrade() -> None:
    op.create_table(
        "runs",
        sa.Column("id", sa.Integer(), primary_key=True, autoincrement=True),
        sa.Column("job_id", sa.String(32), nullable=False, index=True),
        sa.Column("position", sa.Integer(), nullable=False),
        sa.Column("machine_id", sa.String(64), nullable=False),
        sa.Column("program_name", sa.String(255), nullable=False, index=True),
        sa.Column("program_id", sa.String(64), nullable=False),
        sa.Column("state", sa.String(16), nullable=False),
        sa.Column("started_by", sa.String(100), nullable=False),
        sa.Column("created_at", TS, nullable=False),
        sa.Column("started_at", TS, nullable=True),
        sa.Column("ended_at", TS, nullable=True),
        sa.Column("start_line", sa.Integer(), nullable=False),
        sa.Column("restart_from", sa.String(100), nullable=True),
        sa.Column("header", sa.JSON(), nullable=False),
        sa.Column("lines_total", sa.BigInteger(), nullable=False),
        sa.Column("lines_sent", sa.BigInteger(), nullable=False),
        sa.Column("last_line", sa.BigInteger(), nullable=False),
        sa.Column("stop_requested", sa.Boolean(), nullable=False),
        sa.Column("message", sa.String(1000), nullable=True),
        sa.Column("updated_at", TS, nullable=False),
        sa.UniqueConstraint("job_id", "machine_id"),
    )
    op.create_index("ix_runs_machine_started", "runs", ["machine_id", "started_at"])


def downgrade() -> None:
    op.drop_index("ix_runs_machine_started", "runs")
    op.drop_table("runs")
