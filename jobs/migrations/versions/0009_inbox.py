"""The inbox: programs machines sent that were not requests, held for review.

Revision ID: 0009
Revises: 0008
Create Date: 2026-12-15
"""

import sqlalchemy as sa
from alembic import op

revision = "0009"
down_revision = "0008"
branch_labels = None
depends_on = None

TS = sa.DateTime()  # naive UTC; jobs.models.UTCDateTime adds the zone back


def upgrade() -> None:
    op.create_table(
        "inbox_items",
        sa.Column("id", sa.Integer(), primary_key=True, autoincrement=True),
        sa.Column("machine_id", sa.String(64), nullable=False),
        sa.Column("received_at", TS, nullable=False, index=True),
        sa.Column("name", sa.String(255), nullable=False),
        sa.Column("program_number", sa.String(64), nullable=True),
        sa.Column("comment", sa.String(255), nullable=True),
        sa.Column("folder", sa.String(500), nullable=False),
        sa.Column("sha256", sa.String(64), nullable=False, index=True),
        sa.Column("size", sa.BigInteger(), nullable=False),
        sa.Column("state", sa.String(16), nullable=False),
        sa.Column("reason", sa.String(1000), nullable=False),
        sa.Column("job_id", sa.String(32), nullable=True),
        sa.Column("decided_by", sa.String(100), nullable=True),
        sa.Column("decided_at", TS, nullable=True),
        sa.Column("library_version", sa.Integer(), nullable=True),
    )
    op.create_index("ix_inbox_items_machine_state", "inbox_items", ["machine_id", "state"])


def downgrade() -> None:
    op.drop_index("ix_inbox_items_machine_state", "inbox_items")
    op.drop_table("inbox_items")
