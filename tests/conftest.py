"""Fixtures shared by every test: a data folder, a migrated database, an app, a fleet."""

from __future__ import annotations

import os
import sqlite3
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from jobs import db
from jobs.api.app import create_app
from jobs.fleet import registry
from jobs.run import deliveries
from jobs.settings import AuthMode, Settings
from tests.worker.transports.octoprint_server import OctoPrintServer, running_octoprint
from tests.workers import WorkerProcess, in_process_worker

API_KEY = "test-key-0123456789"

# Every dncq a test starts as a process of its own (a worker, `dncq serve`, a CLI command)
# runs this checkout's code, whichever checkout an editable install of dncq points at.
REPO = Path(__file__).resolve().parent.parent
os.environ["PYTHONPATH"] = os.pathsep.join(
    [str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])])


@pytest.fixture(scope="session")
def migrated_sqlite(tmp_path_factory: pytest.TempPathFactory) -> bytes:
    """The bytes of an empty SQLite database migrated to the newest schema, made once: a
    test's database starts as a copy (the migrations take 50-100 ms, a copy well under 1)."""
    path = tmp_path_factory.mktemp("template") / "dncq.sqlite3"
    url = f"sqlite:///{path}"
    db.upgrade(url)
    db.engine_for(url).dispose()  # its last connection closed: the WAL is folded in
    with sqlite3.connect(path) as conn:
        conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    return path.read_bytes()


@pytest.fixture
def settings(tmp_path: Path, migrated_sqlite: bytes) -> Settings:
    """Settings of a fresh dncq: its own data folder and SQLite database, a known API key."""
    data = tmp_path / "data"
    data.mkdir()
    # No periodic machine checks unless a test asks: they would take machines' slots and
    # connections at moments a test does not choose.
    s = Settings(data_dir=data, api_key=API_KEY, auth=AuthMode.KEY, machine_check_interval_s=0)
    database = data / "dncq.sqlite3"
    fd = os.open(database, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)  # as dncq makes it
    with os.fdopen(fd, "wb") as out:
        out.write(migrated_sqlite)
    db.upgrade(s.resolved_database_url)  # at the newest already: checks, changes nothing
    deliveries.forget()  # what an earlier test's tasks were delivered is not this dncq's
    return s


@pytest.fixture
def add_machines(settings: Settings) -> Callable[..., list[registry.MachineSpec]]:
    """Factory: register machines given as fleet-file entries."""

    def add(*entries: dict[str, Any]) -> list[registry.MachineSpec]:
        with db.session_scope(settings.resolved_database_url) as session:
            return [
                registry.upsert(session=session, machine_in=registry.MachineIn.model_validate(e),
                                data_dir=settings.data_dir)[0]
                for e in entries
            ]

    return add


@pytest.fixture
def client(settings: Settings) -> Iterator[TestClient]:
    """The HTTP API of that dncq, with the API key sent on every request."""
    with TestClient(create_app(settings), headers={"X-Api-Key": API_KEY}) as c:
        yield c


@pytest.fixture
def demo_fleet(settings: Settings) -> None:
    """The demo fleet with its sample programs."""
    from jobs.fleet import demo

    with db.session_scope(settings.resolved_database_url) as session:
        demo.create(session=session, data_dir=settings.data_dir)


# -- the queue: a real Redis and a real Celery worker ------------------------------------


@pytest.fixture(scope="session")
def redis_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Any]:
    """One Redis server for the test session (flushed by each test that uses it)."""
    from tests.servers import redis_server as start

    with start(tmp_path_factory.mktemp("redis")) as server:
        yield server


@pytest.fixture
def queue_settings(settings: Settings, redis_server: Any) -> Settings:
    """Settings of a dncq whose queue is the Redis server, with quick retries for tests."""
    redis_server.flush()
    return settings.model_copy(update={
        "broker_url": redis_server.url, "retry_base_s": 0.1, "retry_max_s": 0.5,
        "reaper_interval_s": 0.2, "redispatch_after_s": 2.0, "lease_ttl_s": 3.0,
        "batch_wait_s": 60.0, "busy_wait_s": 2.0,
    })


@pytest.fixture(scope="module")
def postgres_url() -> Iterator[str]:
    """A PostgreSQL server of the module's own, its schema migrated."""
    from tests.servers import postgres_of_its_own

    with postgres_of_its_own() as server:
        db.upgrade(server.url)
        yield server.url


@pytest.fixture
def celery_worker(queue_settings: Settings) -> Iterator[Any]:
    """An in-process Celery worker (16 threads) on that queue, with its reaper."""
    with in_process_worker(queue_settings) as worker:
        yield worker


@pytest.fixture
def queue_client(queue_settings: Settings, celery_worker: Any) -> Iterator[TestClient]:
    """The HTTP API of a dncq with a running worker behind it."""
    with TestClient(create_app(queue_settings), headers={"X-Api-Key": API_KEY}) as c:
        yield c


@pytest.fixture
def start_worker(tmp_path: Path) -> Iterator[Callable[..., WorkerProcess]]:
    """Factory: start a `dncq worker` process; every one is stopped at teardown."""
    started: list[WorkerProcess] = []

    def start(name: str, settings: Settings, **options: Any) -> WorkerProcess:
        worker = WorkerProcess(name, settings, tmp_path / f"worker-{name}.log", **options)
        started.append(worker)
        return worker

    try:
        yield start
    finally:
        # The test is over and nothing it checked depends on how its workers end: killed,
        # not shut down warm (a gevent worker's warm shutdown takes seconds). Tests of the
        # shutdown itself stop their workers in the test.
        for worker in started:
            worker.kill()
        for worker in started:
            print(f"----- log of worker {worker.name} (pid {worker.pid}) -----\n{worker.log()}")


# -- servers of the transport tests that the mixed-fleet tests use too ---------------------


@pytest.fixture(scope="session")
def octoprint_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[OctoPrintServer]:
    """A real OctoPrint on a loopback port with an admin user and its API key.

    One for the test session, as it takes long to start: the tests that write to it empty it.
    """
    with running_octoprint(tmp_path_factory.mktemp("octoprint")) as server:
        yield server
