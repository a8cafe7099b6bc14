"""A restore whose worker is killed after it removed the file there and before the backup's
file was written: the retry says what the uninterrupted restore would have said."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from jobs.api.app import create_app
from jobs.settings import Settings
from tests.conftest import API_KEY
from tests.jobs.helpers import mock_file, mock_of, on_machine, run_backup, wait_done, wait_until
from tests.jobs.run.conftest import crash_settings  # noqa: F401
from tests.workers import WorkerProcess
from worker.transports.base import PART_PREFIX

pytestmark = pytest.mark.slow

PROGRAM = b"G1 X1 Y1 F100\n" * 40_000  # 560 kB: seconds at the machine's rate below
WRITE_BYTES_PER_S = 150_000
PUT_BACK = "put back in place of the file there, which is kept with the job"


def test_a_restore_killed_between_removing_the_old_file_and_writing_says_it_put_it_back(
        crash_settings: Settings, add_machines: Callable[..., object],  # noqa: F811
        start_worker: Callable[..., WorkerProcess]) -> None:
    s = crash_settings
    add_machines({"id": "a1", "name": "Lathe", "model": "Mock"})
    mock_file(s, "a1", "P1.nc", PROGRAM.decode())
    first = start_worker("a", s)
    first.wait_ready()
    with TestClient(create_app(s), headers={"X-Api-Key": API_KEY}) as client:
        backup = run_backup(client, machines={"ids": ["a1"]})
        mock_file(s, "a1", "P1.nc", "G0 X100\n")  # changed since the backup
        mock_of(s, "a1").set_options(bytes_per_s=WRITE_BYTES_PER_S)
        job = client.post(f"/api/backups/{backup['id']}/restore",
                          json={"machine": "a1", "path": "P1.nc", "replace": True}).json()
        restored = on_machine(s, "a1", "P1.nc")

        def old_file_gone_and_writing() -> bool:
            return not restored.exists() and any(_part_files(restored.parent))

        wait_until(old_file_gone_and_writing, timeout_s=30)
        first.kill()
        start_worker("b", s)
        [target] = wait_done(client, job["id"], timeout_s=90)["targets"]

    assert [a["errorCode"] for a in target["history"]][-1] == 0
    assert len(target["history"]) == 2  # the killed attempt, then the one that wrote it
    assert (target["errorCode"], target["statusMsg"]) == (0, PUT_BACK)
    assert target["replacedCopy"] is True
    assert restored.read_bytes() == PROGRAM


def _part_files(folder: Path) -> list[Path]:
    return [p for p in folder.iterdir() if p.name.startswith(PART_PREFIX)]
