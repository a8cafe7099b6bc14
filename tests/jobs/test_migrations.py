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


def test_going_back_before_0016_and_up_again_keeps_every_attempt_and_schedule_run(
        database_url: str) -> None:
    # Dropping 0016's and 0017's columns rebuilt targets and schedules on SQLite; dropping
    # the old table deleted, by its foreign keys' ON DELETE CASCADE, every row below it.
    with db.engine_for(database_url).begin() as conn:
        conn.execute(text(
            "INSERT INTO jobs (id, kind, state, options, created_by, created_at)"
            " VALUES ('j1', 'send', 'done', '{}', 'me', CURRENT_TIMESTAMP)"))
        conn.execute(text(
            "INSERT INTO targets (id, job_id, position, machine_id, params, state, attempts,"
            " bytes_done, interrupted) VALUES (1, 'j1', 0, 'm1', '{}', 'done', 1, 0, false)"))
        conn.execute(text(
            "INSERT INTO attempts (target_id, number, worker, started_at)"
            " VALUES (1, 1, 'w', CURRENT_TIMESTAMP)"))
        conn.execute(text(
            "INSERT INTO schedules (name, cron, timezone, machines, retention, notify, enabled,"
            " created_at) VALUES ('nightly', '0 2 * * *', 'UTC', '[]', '', '{}', true,"
            " CURRENT_TIMESTAMP)"))
        conn.execute(text(
            "INSERT INTO schedule_runs (schedule_name, fire_at, created_at)"
            " VALUES ('nightly', CURRENT_TIMESTAMP, CURRENT_TIMESTAMP)"))

    def kept() -> tuple[int, int]:
        with db.engine_for(database_url).connect() as conn:
            return (conn.execute(text("SELECT count(*) FROM attempts")).scalar_one(),
                    conn.execute(text("SELECT count(*) FROM schedule_runs")).scalar_one())

    command.downgrade(db.alembic_config(database_url), "0015")
    assert kept() == (1, 1)
    db.upgrade(database_url)
    assert kept() == (1, 1)


def test_schedule_runs_whose_backup_was_registered_before_0019_owe_no_alert_again(
        database_url: str) -> None:
    command.downgrade(db.alembic_config(database_url), "0018")
    with db.engine_for(database_url).begin() as conn:
        conn.execute(text(
            "INSERT INTO schedules (name, cron, timezone, machines, retention, notify, enabled,"
            " created_at) VALUES ('before-0019', '0 2 * * *', 'UTC', '[]', '', '{}', true,"
            " CURRENT_TIMESTAMP)"))
        for night, job_id in enumerate(("stored", "running")):
            conn.execute(text(
                "INSERT INTO schedule_runs (schedule_name, fire_at, job_id, created_at)"
                " VALUES ('before-0019', :fire, :job, CURRENT_TIMESTAMP)"),
                {"fire": f"2026-11-2{night} 01:00:00", "job": job_id})
        conn.execute(text(
            "INSERT INTO backups (id, job_id, name, status, size, sha256, created_at)"
            " VALUES ('before-0019', 'stored', 'before-0019.zip', 'COMPLETE', 0, '',"
            " CURRENT_TIMESTAMP)"))

    db.upgrade(database_url)

    with db.engine_for(database_url).connect() as conn:
        owed = dict(conn.execute(text(
            "SELECT job_id, followed_up_at IS NULL FROM schedule_runs"
            " WHERE schedule_name = 'before-0019'")).all())
    assert owed == {"stored": False, "running": True}
