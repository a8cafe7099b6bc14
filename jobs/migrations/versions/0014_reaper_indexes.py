"""Indexes of what every reaper asks every few seconds: pending targets by when they were
queued, running ones by when their lease runs out (partial: a few among a long history).

Revision ID: 0014
Revises: 0013
Create Date: 2026-12-03
"""

import sqlalchemy as sa
from alembic import op

revision = "0014"
down_revision = "0013"
branch_labels = None
depends_on = None

PENDING_WHERE, RUNNING_WHERE = "state = 'pending'", "state = 'running'"


def upgrade() -> None:
    op.create_index("ix_targets_pending_queued_at", "targets", ["dispatched_at"],
                    postgresql_where=sa.text(PENDING_WHERE), sqlite_where=sa.text(PENDING_WHERE))
    op.create_index("ix_targets_running_lease", "targets", ["lease_until"],
                    postgresql_where=sa.text(RUNNING_WHERE), sqlite_where=sa.text(RUNNING_WHERE))


def downgrade() -> None:
    op.drop_index("ix_targets_running_lease", table_name="targets")
    op.drop_index("ix_targets_pending_queued_at", table_name="targets")
