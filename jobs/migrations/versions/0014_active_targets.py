"""An index of the targets still to run (pending or running), a few among a long history.

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

ACTIVE_WHERE = "state IN ('pending', 'running')"


def upgrade() -> None:
    op.create_index("ix_targets_active", "targets", ["state", "job_id"],
                    postgresql_where=sa.text(ACTIVE_WHERE), sqlite_where=sa.text(ACTIVE_WHERE))


def downgrade() -> None:
    op.drop_index("ix_targets_active", table_name="targets")
