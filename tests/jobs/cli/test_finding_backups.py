"""Finding last Tuesday's backup: `dncq backup list` filters, `backup show`, `backup download`,
and `dncq jobs --since/--until`, against a live API and worker."""

from __future__ import annotations

import re
import zipfile
from datetime import UTC, datetime, timedelta

import pytest
from sqlalchemy import update

from jobs import db
from jobs.backup_models import Backup
from jobs.models import Job
from tests.jobs.cli.runner import dncq
from tests.jobs.helpers import on_machine

LAST_TUESDAY = datetime(2026, 11, 24, 2, 0, tzinfo=UTC)


def backup_id_of(output: str) -> str:
    [found] = re.findall(r"Backup ([0-9a-f]{16}):", output)
    return found


@pytest.fixture
def two_backups(live_with_worker, queue_settings) -> tuple[str, str]:
    """m0's backup made last Tuesday, and m1's made now."""
    on_machine(queue_settings, "m0", "P1.nc").write_text("G0 X1\n")
    on_machine(queue_settings, "m0", "sub/P2.nc").write_text("G0 X2\n")
    on_machine(queue_settings, "m1", "Q1.nc").write_text("G0 Y1\n")
    old = backup_id_of(dncq("backup", "run", "--to", "m0").output)
    new = backup_id_of(dncq("backup", "run", "--to", "m1").output)
    with db.session_scope(queue_settings.resolved_database_url) as session:
        session.execute(update(Backup).where(Backup.id == old).values(created_at=LAST_TUESDAY))
    return old, new


def test_backup_list_finds_a_backup_by_its_day_and_its_machine(two_backups):
    old, new = two_backups

    tuesday = dncq("backup", "list", "--since", "2026-11-23", "--until", "2026-11-25")
    of_m1 = dncq("backup", "list", "--machine", "m1")

    assert old in tuesday.output and new not in tuesday.output
    assert new in of_m1.output and old not in of_m1.output


def test_backup_list_of_a_mistyped_machine_is_refused_naming_the_machine_meant(
        elsewhere, add_machines):
    add_machines({"id": "1010", "name": "Lathe", "model": "Mock"})

    result = dncq("backup", "list", "--machine", "1O10")  # a letter O for the 0

    assert result.exit_code == 1
    assert "Invalid MachineID (1O10) (did you mean 1010?)" in " ".join(result.output.split())


def test_backup_list_by_state_shows_only_backups_in_that_state(two_backups):
    old, new = two_backups

    complete = dncq("backup", "list", "--state", "complete")
    failed = dncq("backup", "list", "--state", "failed")

    assert old in complete.output and new in complete.output
    assert old not in failed.output and new not in failed.output


def test_backup_show_draws_the_manifest_as_a_tree_of_folders_and_files(two_backups):
    old, _ = two_backups

    shown = dncq("backup", "show", old)

    assert shown.exit_code == 0, shown.output
    lines = shown.output.splitlines()
    machine = next(i for i, line in enumerate(lines) if "m0 M0: ok" in line)
    folder = next(i for i, line in enumerate(lines) if "sub/" in line)
    nested = next(i for i, line in enumerate(lines) if "P2.nc  6 bytes" in line)
    assert machine < folder < nested
    assert "Q1.nc" not in shown.output
    title = " ".join(" ".join(lines[:machine]).split())  # whole in 80 columns, wrapped
    assert re.search(r"\(complete, 2 files, \d+ bytes, \d{4}-\d\d-\d\d \d\d:\d\d:\d\d \S+\)$",
                     title)


def test_backup_download_saves_the_zip_whole(two_backups, queue_settings, tmp_path):
    old, _ = two_backups

    saved = dncq("backup", "download", old, "-o", str(tmp_path / "tuesday.zip"))
    into_folder = dncq("backup", "download", old, "-o", str(tmp_path))

    assert saved.exit_code == 0, saved.output
    [stored] = [p for p in (queue_settings.data_dir / "backups").glob("*.zip")
                if p.name in into_folder.output]
    assert (tmp_path / "tuesday.zip").read_bytes() == stored.read_bytes()
    assert (tmp_path / stored.name).read_bytes() == stored.read_bytes()
    with zipfile.ZipFile(tmp_path / "tuesday.zip") as archive:
        assert any(n.endswith("/sub/P2.nc") for n in archive.namelist())


def test_backup_download_into_a_folder_not_there_yet_makes_it_and_saves_the_zip_in_it(
        two_backups, queue_settings, tmp_path):
    old, _ = two_backups

    saved = dncq("backup", "download", old, "-o", f"{tmp_path / 'dl'}/")

    assert saved.exit_code == 0, saved.output
    [stored] = [p for p in (queue_settings.data_dir / "backups").glob("*.zip")
                if p.name in saved.output]
    assert [p.name for p in (tmp_path / "dl").iterdir()] == [stored.name]
    assert (tmp_path / "dl" / stored.name).read_bytes() == stored.read_bytes()


def test_backup_download_of_an_unknown_backup_fails_and_saves_nothing(live_with_worker,
                                                                        tmp_path):
    saves = tmp_path / "saves"
    saves.mkdir()
    result = dncq("backup", "download", "0123456789abcdef", "-o", str(saves / "x.zip"))
    into_new = dncq("backup", "download", "0123456789abcdef", "-o", f"{saves / 'new'}/")

    assert result.exit_code == 1 and into_new.exit_code == 1
    assert list(saves.iterdir()) == []


def test_jobs_since_and_until_list_only_the_jobs_of_that_time(two_backups, queue_settings):
    with db.session_scope(queue_settings.resolved_database_url) as session:
        first = session.query(Job).order_by(Job.created_at).first()
        assert first is not None
        first.created_at, first_id = LAST_TUESDAY, first.id
    tomorrow = (datetime.now() + timedelta(days=1)).strftime("%Y-%m-%d")

    tuesday = dncq("jobs", "--since", "2026-11-24", "--until", "2026-11-25")
    later = dncq("jobs", "--since", "2026-11-25 00:00", "--until", tomorrow)

    assert first_id in tuesday.output and len(re.findall(r"backup", tuesday.output)) == 1
    assert first_id not in later.output and "backup" in later.output
