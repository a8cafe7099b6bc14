"""Backups of machines whose folders nest deep: every path is recorded whole, on PostgreSQL
(which refuses a value longer than its column) as on SQLite."""

from __future__ import annotations

from pathlib import Path

import pytest

from jobs.settings import Settings
from tests.jobs.helpers import mock_file, on_each_database, run_backup


@pytest.fixture(params=["postgresql", "sqlite"])
def settings(request: pytest.FixtureRequest, tmp_path: Path, settings: Settings) -> Settings:
    return on_each_database(request, tmp_path, settings)


def test_a_file_under_folders_1500_characters_deep_is_backed_up_and_recorded_whole(
        queue_client, add_machines, queue_settings):
    deep = "/".join(f"{n:02d}_" + "F" * 96 for n in range(15)) + "/O1000.NC"  # 1509 chars
    add_machines({"id": "deep", "name": "Deep", "model": "Mock"})
    mock_file(queue_settings, "deep", deep, "G0 X1\n")

    backup = run_backup(queue_client, machines={"ids": ["deep"]})

    assert backup["status"] == "complete" and backup["files"] == 1
    manifest = queue_client.get(f"/api/backups/{backup['id']}/manifest").json()
    [recorded] = manifest["files"]
    assert recorded["path"].endswith(deep) and recorded["archivePath"].endswith(deep)
