"""A worker killed while it holds what an operator sent from the control: the program is
recorded once when a worker listens on the machine again, however late the kill came.

The control is the simulated one on the seed's TCP protocol; the workers are `dncq worker`
processes killed with SIGKILL. The database's write lock, held by the test, keeps the
listener between reading a program and recording it for as long as the test needs.
"""

from __future__ import annotations

import sqlite3
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy import func, select

from jobs.db import session_scope
from jobs.inbox import service as inbox
from jobs.models import Job, MachineCheck, MachineLease
from jobs.requests import record, spool
from jobs.run import leases
from jobs.settings import Settings
from tests.jobs.helpers import wait_until
from tests.jobs.requests.conftest import SEED_REQUEST, request_jobs, wait_for_jobs
from tests.jobs.run.conftest import crash_settings  # noqa: F401
from tests.workers import WorkerProcess
from worker.simulator.control import Control, IoChannel, Mode
from worker.simulator.programs import ProgramStore
from worker.simulator.tcp_server import DncServer

pytestmark = pytest.mark.slow

PROGRAM = b"%\nO1234 (BRACKET)\nG0 X1 Y1\nM30\n%\n"


@pytest.fixture
def dnc_control(crash_settings: Settings, add_machines: Callable[..., Any],  # noqa: F811
                tmp_path: Path) -> Iterator[DncServer]:
    """A Fanuc on the seed's TCP protocol whose operator may send requests."""
    control = Control(ProgramStore(tmp_path / "cnc-dnc", model="Fanuc 0i-F"), mode=Mode.EDIT,
                      io_channel=IoChannel.NETWORK)
    server = DncServer(control, host="127.0.0.1", port=0)
    server.start()
    add_machines({"id": "2001", "name": "DNC-H", "model": "Fanuc 0i-F", "transport": "dnc",
                  "options": {"host": "127.0.0.1", "port": server.port,
                              "poll_interval_s": 0.05},
                  # long enough for the answer to be waiting when the worker is killed
                  "requests": {"enabled": True, "switch_window_s": 60}})
    yield server
    server.close()
    control.close()


def listening(settings: Settings, worker: WorkerProcess) -> None:
    """Wait until the worker listens on machine 2001 and has kept the link's check."""
    worker.wait_for_log("listening on machine 2001")

    def heard() -> bool:  # the link's first check kept: nothing more to write until a program
        with session_scope(settings.resolved_database_url) as session:
            return session.scalar(select(func.count()).where(
                MachineLease.machine_id == "2001",
                MachineLease.group == leases.listen_group("2001"))) == 1 and \
                session.scalar(select(MachineCheck.reachable).where(
                    MachineCheck.machine_id == "2001")) is True
    wait_until(heard, timeout_s=30)


@contextmanager
def database_write_locked(settings: Settings) -> Iterator[None]:
    """Nobody writes to the SQLite database while this lasts (readers go on: WAL)."""
    conn = sqlite3.connect(settings.data_dir / "dncq.sqlite3", isolation_level=None)
    try:
        conn.execute("BEGIN IMMEDIATE")
        yield
        conn.execute("ROLLBACK")
    finally:
        conn.close()


def test_a_program_read_by_a_worker_killed_before_it_was_recorded_is_recorded_once_after(
        crash_settings: Settings, dnc_control: DncServer,  # noqa: F811
        start_worker: Callable[..., WorkerProcess]) -> None:
    s = crash_settings
    first = start_worker("a", s)
    listening(s, first)
    with database_write_locked(s):
        dnc_control.punch_text(PROGRAM)
        first.wait_for_log("machine 2001 sent")
        first.kill()  # read from the link and kept on the disk (said once kept), not recorded
    second = start_worker("b", s)

    [job] = wait_for_jobs(s, 1, timeout_s=60)
    assert job["state"] == "succeeded" and job["fileName"] == "1234"
    with session_scope(s.resolved_database_url) as session:
        [item] = inbox.list_items(session=session, machine_id="2001")
        assert item.job_id == job["id"]
    assert spool.pending(s, "2001") == []
    second.wait_for_log("taking up what a lost listener had read (1)")
    assert request_jobs(s, finished=False) == [job]


def test_a_request_recorded_by_a_worker_killed_before_it_answered_is_not_recorded_again(
        crash_settings: Settings, dnc_control: DncServer,  # noqa: F811
        start_worker: Callable[..., WorkerProcess]) -> None:
    s = crash_settings
    first = start_worker("a", s)
    listening(s, first)
    dnc_control.punch_text(SEED_REQUEST)  # answered once the operator presses READ
    wait_until(lambda: request_jobs(s, finished=False), timeout_s=30)
    first.kill()  # recorded, its program still in the spool, the answer not sent
    second = start_worker("b", s)

    second.wait_for_log("taking up what a lost listener had read (1)")
    wait_until(lambda: spool.pending(s, "2001") == [], timeout_s=30)
    [job] = wait_for_jobs(s, 1, timeout_s=60)
    [target] = job["targets"]
    assert job["state"] == "failed" and target["statusMsg"] == record.LISTENER_LOST
    with session_scope(s.resolved_database_url) as session:
        assert session.scalar(select(func.count()).select_from(Job)) == 1


def kept_long_ago(settings: Settings, text: bytes, *, minutes: float) -> None:
    """A program a lost listener read `minutes` ago and could not record, left on the disk."""
    entry = spool.put(settings, "2001", text)
    read_ns = time.time_ns() - int(minutes * 60e9)
    entry.path.rename(entry.path.with_name(f"{read_ns:020d}-{entry.id}{spool.SUFFIX}"))


def test_a_request_kept_longer_than_its_switch_window_is_recorded_but_not_carried_out(
        crash_settings: Settings, dnc_control: DncServer,  # noqa: F811
        start_worker: Callable[..., WorkerProcess]) -> None:
    """An hour-old request would be carried out with nobody at the control to read its
    answer, a delete under whoever works on the machine now; a program that is no request
    goes to the inbox however late it comes."""
    s = crash_settings
    kept_long_ago(s, SEED_REQUEST, minutes=60)  # older than the machine's 60 s window
    kept_long_ago(s, PROGRAM, minutes=59)
    start_worker("a", s).wait_for_log("taking up what a lost listener had read (2)")

    refused, received = wait_for_jobs(s, 2, timeout_s=60)
    [target] = refused["targets"]
    assert refused["state"] == "failed" and target["statusMsg"].startswith(
        "a request read 60 min ago")
    assert "ask again from the control" in target["statusMsg"]
    assert received["state"] == "succeeded" and received["fileName"] == "1234"
    with session_scope(s.resolved_database_url) as session:
        items = {i.job_id: i for i in inbox.list_items(session=session, machine_id="2001")}
        assert items[refused["id"]].reason == target["statusMsg"]  # its text kept there
        assert items[received["id"]].reason == ""
    assert spool.pending(s, "2001") == []
