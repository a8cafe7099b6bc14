"""A worker killed while it handles a request dropped into a machine's folder: the request
is carried out once, however late the kill came, and a request dropped again is a new one.

The workers are `dncq worker` processes killed with SIGKILL; the request deletes a library
program and then sends one from a second machine, whose slot the test holds, so that the
worker is killed with the delete done and its answers not yet written.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from typing import Any

import pytest
from sqlalchemy import func, select

from jobs.db import session_scope
from jobs.errors import ContractError
from jobs.fleet import door, registry
from jobs.library import service as library
from jobs.models import Job
from jobs.requests import record
from jobs.run import leases
from jobs.settings import Settings
from tests.jobs.helpers import wait_until
from tests.jobs.requests.conftest import DROP_FOLDER, O0010, DropMachine, wait_for_jobs
from tests.jobs.run.conftest import crash_settings  # noqa: F401
from tests.workers import WorkerProcess

pytestmark = pytest.mark.slow

O0020 = b"%\nO0020 (FLANGE)\nG0 X0\nM30\n%\n"
DELETE_THEN_SEND = b"%\nO8888\n(DIR=/VIPROS)\n(DEL=0010)\n(PRG=0020)\n%\n"


@pytest.fixture
def scan_settings(crash_settings: Settings) -> Settings:  # noqa: F811
    """Workers that look into the drop folders every half second."""
    return crash_settings.model_copy(update={"request_scan_interval_s": 0.5})


@pytest.fixture
def machines(scan_settings: Settings, drop_machine: Callable[..., DropMachine],
             add_machines: Callable[..., Any], add_program: Callable[..., None]
             ) -> DropMachine:
    """m1 drops requests; its programs come from the library, then from m2's /NC."""
    add_program("VIPROS", "0010", O0010)
    add_machines({"id": "m2", "name": "Source", "model": "Mock", "transport": "mock"})
    with session_scope(scan_settings.resolved_database_url) as session:
        source = registry.get(session=session, machine_id="m2")
    with door.open_files(source, data_dir=scan_settings.data_dir) as files:
        files.make_dir("NC", "/", None)
        files.make_dir("VIPROS", "/NC", None)
        files.send_chunks(files.ref("0020", "/NC/VIPROS", None), iter([O0020]))
    return drop_machine(sources=["library:", "machine:m2:/NC"])


def drop_settled(settings: Settings, machine: DropMachine, data: bytes) -> float:
    """The control drops the request; written long enough ago to be taken at once. Its
    modification time."""
    machine.drop("O8888", data)
    written = settings.data_dir / "mock" / machine.id / "files" / DROP_FOLDER.strip("/") / "O8888"
    mtime = time.time() - 60
    os.utime(written, (mtime, mtime))
    return mtime


def in_library(settings: Settings, name: str) -> bool:
    with session_scope(settings.resolved_database_url) as session:
        try:
            return library.find(session=session, folder="VIPROS", name=name) is not None
        except ContractError:  # deleted (158)
            return False


def test_a_dropped_request_whose_worker_was_killed_after_it_was_recorded_is_not_run_again(
        scan_settings: Settings, machines: DropMachine,
        start_worker: Callable[..., WorkerProcess]) -> None:
    s, machine = scan_settings, machines
    with leases.hold(s.resolved_database_url, machine_id="m2", max_concurrent=1, wait_s=5,
                     ttl_s=s.lease_ttl_s):
        drop_settled(s, machine, DELETE_THEN_SEND)
        first = start_worker("a", s)
        wait_until(lambda: not in_library(s, "0010"), timeout_s=60)
        first.kill()  # 0010 deleted, waiting for m2; the request still in the drop folder
    assert machine.names() == ["O8888"]
    start_worker("b", s)

    wait_until(lambda: "O8888" not in machine.names(), timeout_s=60)
    # Neither a second delete (NOT FOUND: VIPROS/0010 in O8890) nor a second answer.
    assert machine.names() == []
    [job] = wait_for_jobs(s, 1, timeout_s=60)
    assert job["state"] == "failed"
    assert {t["statusMsg"] for t in job["targets"]} == {record.LISTENER_LOST}
    with session_scope(s.resolved_database_url) as session:
        assert session.scalar(select(func.count()).select_from(Job)) == 1
