"""A database lost while a listener hears its machine: what the operator sends meanwhile is
heard and kept on the disk, and the same listener records it, once, when the database
answers again.

The database is a PostgreSQL server of the test's own, stopped and started again; the
control is the simulated one on the seed's TCP protocol.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from sqlalchemy import func, select

from jobs import db
from jobs.fleet import registry
from jobs.models import Job
from jobs.requests import spool
from jobs.settings import Settings
from tests.jobs.helpers import wait_until
from tests.jobs.requests.conftest import wait_for_jobs
from tests.servers import PostgresServer, postgres_of_its_own
from worker.listener import Listeners
from worker.simulator.control import Control, IoChannel, Mode
from worker.simulator.programs import ProgramStore
from worker.simulator.tcp_server import DncServer

FIRST = b"%\nO1234 (BRACKET)\nG0 X1 Y1\nM30\n%\n"
SECOND = b"%\nO1235 (PLATE)\nG0 X2 Y2\nM30\n%\n"


@pytest.fixture
def on_postgres(settings: Settings) -> Iterator[tuple[Settings, PostgresServer]]:
    """The test's dncq on a PostgreSQL server the test may stop and start."""
    with postgres_of_its_own() as server:
        s = settings.model_copy(update={"database_url": server.url, "lease_ttl_s": 6.0})
        db.upgrade(s.resolved_database_url)
        yield s, server


@pytest.fixture
def heard_control(on_postgres: tuple[Settings, PostgresServer],
                  tmp_path: Path) -> Iterator[tuple[DncServer, Listeners]]:
    """A Fanuc on the seed's TCP protocol whose operator may send requests; dncq listening."""
    s, _ = on_postgres
    control = Control(ProgramStore(tmp_path / "cnc-dnc", model="Fanuc 0i-F"), mode=Mode.EDIT,
                      io_channel=IoChannel.NETWORK)
    server = DncServer(control, host="127.0.0.1", port=0)
    server.start()
    with db.session_scope(s.resolved_database_url) as session:
        registry.upsert(session=session, data_dir=s.data_dir, machine_in=registry.MachineIn(
            id="2001", name="DNC-H", model="Fanuc 0i-F", transport="dnc",
            options={"host": "127.0.0.1", "port": server.port, "poll_interval_s": 0.05},
            requests={"enabled": True}))
    listeners = Listeners(s)
    listeners.tick()
    wait_until(lambda: listeners.hearing("2001"))
    yield server, listeners
    listeners.stop()
    server.close()
    control.close()


def jobs_recorded(settings: Settings) -> int:
    with db.session_scope(settings.resolved_database_url) as session:
        return session.scalar(select(func.count()).select_from(Job)) or 0


def test_programs_sent_while_the_database_was_lost_are_recorded_by_the_same_listener_after(
        on_postgres: tuple[Settings, PostgresServer],
        heard_control: tuple[DncServer, Listeners]) -> None:
    # The listener that kept them never tried again: they waited on the disk until the
    # machine's next listener, which starts only once this one has ended.
    s, database = on_postgres
    control, listeners = heard_control
    database.stop()
    control.punch_text(FIRST)
    wait_until(lambda: len(spool.pending(s, "2001")) == 1)
    control.punch_text(SECOND)  # heard while the first waits for the database
    wait_until(lambda: len(spool.pending(s, "2001")) == 2)

    database.start()  # no listener is started again: the one that kept them records them

    first, second = wait_for_jobs(s, 2, timeout_s=60)
    assert (first["fileName"], second["fileName"]) == ("1234", "1235")
    assert first["state"] == second["state"] == "succeeded"
    assert spool.pending(s, "2001") == []
    assert listeners.hearing("2001")
    assert jobs_recorded(s) == 2  # each once
