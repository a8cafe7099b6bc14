"""The program library: programs, versions, machines' folders; jobs record the version sent.

Revision ID: 0008
Revises: 0007
Create Date: 2026-12-08
"""

import sqlalchemy as sa
from alembic import op

revision = "0008"
down_revision = "0007"
branch_labels = None
depends_on = None

TS = sa.DateTime()  # naive UTC; jobs.models.UTCDateTime adds the zone back


def upgrade() -> None:
    op.create_table(
        "library_programs",
        sa.Column("id", sa.Integer(), primary_key=True, autoincrement=True),
        sa.Column("folder", sa.String(500), nullable=False),
        sa.Column("name", sa.String(255), nullable=False),
        sa.Column("deleted", sa.Boolean(), nullable=False),
        sa.Column("deleted_at", TS, nullable=True),
        sa.Column("created_at", TS, nullable=False),
        sa.UniqueConstraint("folder", "name"),
    )
    op.create_table(
        "library_versions",
        sa.Column("id", sa.Integer(), primary_key=True, autoincrement=True),
        sa.Column("program_id", sa.Integer(),
                  sa.ForeignKey("library_programs.id", ondelete="CASCADE"), nullable=False,
                  index=True),
        sa.Column("number", sa.Integer(), nullable=False),
        sa.Column("sha256", sa.String(64), nullable=False, index=True),
        sa.Column("size", sa.BigInteger(), nullable=False),
        sa.Column("state", sa.String(16), nullable=False),
        sa.Column("note", sa.String(1000), nullable=False),
        sa.Column("source", sa.String(200), nullable=False),
        sa.Column("created_by", sa.String(100), nullable=False),
        sa.Column("created_at", TS, nullable=False),
        sa.Column("decided_by", sa.String(100), nullable=True),
        sa.Column("decided_at", TS, nullable=True),
        sa.UniqueConstraint("program_id", "number"),
    )
    op.create_table(
        "library_assignments",
        sa.Column("machine_id", sa.String(64), primary_key=True),
        sa.Column("folder", sa.String(500), primary_key=True),
        sa.Column("created_at", TS, nullable=False),
    )
    with op.batch_alter_table("jobs") as batch:  # SQLite alters tables by copying
        batch.add_column(sa.Column("library_version_id", sa.Integer(), nullable=True))
        batch.create_index("ix_jobs_library_version_id", ["library_version_id"])


def downgrade() -> None:
    with op.batch_alter_table("jobs") as batch:
        batch.drop_index("ix_jobs_library_version_id")
        batch.drop_column("library_version_id")
    op.drop_table("library_assignments")
    op.drop_table("library_versions")
    op.drop_table("library_programs")
