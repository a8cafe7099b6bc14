"""Indexes of what every worker asks every few seconds: pending targets by when they were
queued, running ones by when their lease runs out (partial: a few among a long history),
and the machines with request settings (a few among a fleet).

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
TAKES_REQUESTS = "requests IS NOT NULL AND CAST(requests AS TEXT) != 'null'"


def upgrade() -> None:
    op.create_index("ix_targets_pending_queued_at", "targets", ["dispatched_at"],
                    postgresql_where=sa.text(PENDING_WHERE), sqlite_where=sa.text(PENDING_WHERE))
    op.create_index("ix_targets_running_lease", "targets", ["lease_until"],
                    postgresql_where=sa.text(RUNNING_WHERE), sqlite_where=sa.text(RUNNING_WHERE))
    op.create_index("ix_machines_taking_requests", "machines", ["id"],
                    postgresql_where=sa.text(TAKES_REQUESTS),
                    sqlite_where=sa.text(TAKES_REQUESTS))


def downgrade() -> None:
    op.drop_index("ix_machines_taking_requests", table_name="machines")
    op.drop_index("ix_targets_running_lease", table_name="targets")
    op.drop_index("ix_targets_pending_queued_at", table_name="targets")
