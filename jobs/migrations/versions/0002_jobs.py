"""Jobs, their targets and attempts, stored payloads and machine leases.

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-25
"""

import sqlalchemy as sa
from alembic import op

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None

TS = sa.DateTime()  # naive UTC; jobs.models.UTCDateTime adds the zone back


def upgrade() -> None:
    op.create_table(
        "payloads",
        sa.Column("id", sa.String(64), primary_key=True),
        sa.Column("size", sa.BigInteger(), nullable=False),
        sa.Column("data", sa.LargeBinary(), nullable=False),
        sa.Column("created_at", TS, nullable=False),
    )
    op.create_table(
        "jobs",
        sa.Column("id", sa.String(32), primary_key=True),
        sa.Column("kind", sa.String(16), nullable=False),
        sa.Column("state", sa.String(16), nullable=False, index=True),
        sa.Column("options", sa.JSON(), nullable=False),
        sa.Column("payload_id", sa.String(64), sa.ForeignKey("payloads.id"), nullable=True),
        sa.Column("file_name", sa.String(255), nullable=True),
        sa.Column("created_by", sa.String(100), nullable=False),
        sa.Column("created_at", TS, nullable=False, index=True),
        sa.Column("finished_at", TS, nullable=True),
        sa.Column("retry_of", sa.String(32), nullable=True),
    )
    op.create_table(
        "targets",
        sa.Column("id", sa.Integer(), primary_key=True, autoincrement=True),
        sa.Column("job_id", sa.String(32), sa.ForeignKey("jobs.id", ondelete="CASCADE"),
                  nullable=False),
        sa.Column("position", sa.Integer(), nullable=False),
        sa.Column("machine_id", sa.String(64), nullable=False),
        sa.Column("params", sa.JSON(), nullable=False),
        sa.Column("payload_id", sa.String(64), sa.ForeignKey("payloads.id"), nullable=True),
        sa.Column("state", sa.String(16), nullable=False),
        sa.Column("attempts", sa.Integer(), nullable=False),
        sa.Column("error_code", sa.Integer(), nullable=True),
        sa.Column("error_msg", sa.String(500), nullable=True),
        sa.Column("status_msg", sa.String(1000), nullable=True),
        sa.Column("next_attempt_at", TS, nullable=True),
        sa.Column("dispatched_at", TS, nullable=True),
        sa.Column("lease_until", TS, nullable=True),
        sa.Column("started_at", TS, nullable=True),
        sa.Column("finished_at", TS, nullable=True),
        sa.Column("bytes_done", sa.BigInteger(), nullable=False),
        sa.Column("bytes_total", sa.BigInteger(), nullable=True),
        sa.Column("replaced_payload_id", sa.String(64), sa.ForeignKey("payloads.id"),
                  nullable=True),
        sa.Column("claimed_by", sa.String(200), nullable=True),
        sa.Column("interrupted", sa.Boolean(), nullable=False),
        sa.UniqueConstraint("job_id", "position"),
    )
    op.create_index("ix_targets_machine_state", "targets", ["machine_id", "state"])
    op.create_index("ix_targets_job_state", "targets", ["job_id", "state"])
    op.create_table(
        "attempts",
        sa.Column("id", sa.Integer(), primary_key=True, autoincrement=True),
        sa.Column("target_id", sa.Integer(), sa.ForeignKey("targets.id", ondelete="CASCADE"),
                  nullable=False, index=True),
        sa.Column("number", sa.Integer(), nullable=False),
        sa.Column("worker", sa.String(200), nullable=False),
        sa.Column("started_at", TS, nullable=False),
        sa.Column("finished_at", TS, nullable=True),
        sa.Column("error_code", sa.Integer(), nullable=True),
        sa.Column("error_msg", sa.String(1000), nullable=True),
    )
    op.create_table(
        "machine_leases",
        sa.Column("machine_id", sa.String(64), primary_key=True),
        sa.Column("slot", sa.Integer(), primary_key=True),
        sa.Column("group", sa.String(100), nullable=False),
        sa.Column("holder", sa.String(100), nullable=False),
        sa.Column("expires_at", TS, nullable=False),
        sa.UniqueConstraint("machine_id", "group"),
    )


def downgrade() -> None:
    for table in ("machine_leases", "attempts", "targets", "jobs", "payloads"):
        op.drop_table(table)
