"""Migrations keep the data of a database made by an older dncq."""

from __future__ import annotations

from alembic import command
from sqlalchemy import text

from jobs import db


def test_backups_stored_before_file_counts_were_kept_get_theirs(database_url: str) -> None:
    command.downgrade(db.alembic_config(database_url), "0004")
    with db.engine_for(database_url).begin() as conn:
        conn.execute(text("DELETE FROM backups"))
        for backup_id, files in (("three", 3), ("none", 0)):
            conn.execute(text(
                "INSERT INTO backups (id, name, status, size, sha256, created_at)"
                " VALUES (:id, :id, 'COMPLETE', 0, '', CURRENT_TIMESTAMP)"), {"id": backup_id})
            for k in range(files):
                conn.execute(text(
                    "INSERT INTO backup_files (backup_id, machine_id, path, archive_path, size,"
                    " sha256) VALUES (:b, 'm1', :p, :p, 1, '')"), {"b": backup_id, "p": f"/P{k}"})

    db.upgrade(database_url)

    with db.engine_for(database_url).connect() as conn:
        counts = dict(conn.execute(text("SELECT id, file_count FROM backups")).all())
    assert counts == {"three": 3, "none": 0}
