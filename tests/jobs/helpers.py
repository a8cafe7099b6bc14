"""Helpers of the queue tests: waiting for jobs, the mock machines' files, running a backup."""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from sqlalchemy import event, text
from sqlalchemy.orm import Session

from jobs import db, service
from jobs.fleet import registry
from jobs.models import JobKind, Run, RunState
from jobs.run import targets
from jobs.settings import Settings
from worker.transports.mock import MockOptions, MockTransport


def wait_until(condition: Any, timeout_s: float = 30.0,
               describe: Callable[[], Any] | None = None) -> None:
    """Poll until `condition()` is true (a wait for an event, not a timing assert).

    `describe()` says what was there instead when the wait ends without it."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError("condition not met in time"
                                 + (f": {describe()}" if describe is not None else ""))
        time.sleep(0.05)


def at_once(*calls: Callable[[], Any], timeout_s: float = 60.0) -> list[Any]:
    """Run the calls on threads of their own, started together; their results in order."""
    results: list[Any] = [None] * len(calls)

    def run(n: int) -> None:
        results[n] = calls[n]()

    threads = [threading.Thread(target=run, args=(n,)) for n in range(len(calls))]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout_s)
    return results


def while_another_writes(url: str, first: Callable[[Any], Any],
                         second: Callable[[], Any]) -> dict[str, Any]:
    """`first(session)` in a transaction left open while `second()` runs on a thread of its
    own, meeting it; once the first has committed, what the second returned (`result`) or
    raised (`error`)."""
    other: dict[str, Any] = {}

    def run_second() -> None:
        try:
            other["result"] = second()
        except Exception as exc:  # noqa: BLE001 - the caller asserts on it
            other["error"] = exc

    thread = threading.Thread(target=run_second)
    with db.session_scope(url) as session:
        first(session)
        with _waiting_for(session) as waits:
            thread.start()
            # The second meets the first, not committed yet: a loaded host may keep its
            # thread from running for a second and more, so it is waited for, not timed.
            wait_until(lambda: waits() or not thread.is_alive(),
                       describe=lambda: "the second neither waited for the first nor ended")
    thread.join(30)
    assert not thread.is_alive()
    return other


_WRITES = ("INSERT", "UPDATE", "DELETE", "REPLACE")


@contextlib.contextmanager
def _waiting_for(holder: Session) -> Iterator[Callable[[], bool]]:
    """A check of whether another connection now waits for what `holder`'s open
    transaction holds: on PostgreSQL a backend waiting for a lock; on SQLite a write
    statement of another connection not returned (the holder has the one write lock)."""
    engine = holder.get_bind().engine
    if engine.dialect.name == "postgresql":
        def lock_waited() -> bool:
            with engine.connect() as conn:
                return bool(conn.execute(text(
                    "SELECT count(*) FROM pg_stat_activity WHERE wait_event_type = 'Lock'"
                    " AND datname = current_database()")).scalar())

        yield lock_waited
        return
    mine = holder.connection().connection.dbapi_connection
    writing: set[int] = set()  # the ids of the other connections in a write statement

    def began(conn: Any, _cursor: Any, statement: str, *_: Any) -> None:
        if conn.connection.dbapi_connection is not mine and \
                statement.lstrip().upper().startswith(_WRITES):
            writing.add(id(conn))

    def ended(conn: Any, *_: Any) -> None:
        writing.discard(id(conn))

    event.listen(engine, "before_cursor_execute", began)
    event.listen(engine, "after_cursor_execute", ended)
    try:
        yield lambda: bool(writing)
    finally:
        event.remove(engine, "before_cursor_execute", began)
        event.remove(engine, "after_cursor_execute", ended)


def wait_done(client: Any, job_id: str, timeout_s: float = 60.0) -> dict[str, Any]:
    """The job once every target is final."""
    def finished() -> bool:
        counts = client.get(f"/api/jobs/{job_id}").json()["counts"]
        return counts["pending"] == 0 and counts["running"] == 0

    wait_until(finished, timeout_s)
    return client.get(f"/api/jobs/{job_id}").json()


def mock_of(settings: Any, machine_id: str) -> MockTransport:
    """The mock machine's storage and shared state, as a test sees it."""
    return MockTransport(MockOptions(), folder=settings.data_dir / "mock" / machine_id)


def mock_file(settings: Any, machine_id: str, path: str, text: str) -> None:
    """Put a file with `text` straight into the mock machine's storage."""
    target = settings.data_dir / "mock" / machine_id / "files" / path
    target.parent.mkdir(parents=True, exist_ok=True)
    target.write_text(text)


def on_machine(settings: Any, machine_id: str, name: str) -> Path:
    """Where the mock machine keeps `name` (its folder made if the machine was never used)."""
    path = settings.data_dir / "mock" / machine_id / "files" / name
    path.parent.mkdir(parents=True, exist_ok=True)
    return path


def run_backup(client: Any, **request: Any) -> dict[str, Any]:
    """Submit a backup job, wait for it and for its ZIP; the backup as the API shows it."""
    job = client.post("/api/jobs", json={"kind": "backup", **request}).json()
    wait_done(client, job["id"])

    def registered() -> list[dict[str, Any]]:
        return [b for b in client.get("/api/backups").json() if b["job"] == job["id"]]

    wait_until(lambda: bool(registered()))
    return registered()[0]


def ended_run(job_id: str, machine_id: str, program_name: str, state: RunState,
              ended: Any, *, lines: int = 1) -> Run:
    """A drip-feed run's record as it stands once ended, every line sent: what the
    program's print record (OctoPrint's `prints`, the library's runs) counts."""
    return Run(job_id=job_id, position=0, machine_id=machine_id, program_name=program_name,
               program_id="0" * 64, state=state, started_by="test", created_at=ended,
               started_at=ended, ended_at=ended, start_line=1, header=[], lines_total=lines,
               lines_sent=lines, last_line=lines, stop_requested=False, updated_at=ended)


def on_each_database(request: Any, tmp_path: Path, settings: Settings) -> Settings:
    """`settings` of a module whose tests run on SQLite and again on PostgreSQL (the
    module's server), as its `settings` fixture with params `["postgresql", "sqlite"]`."""
    if request.param == "sqlite":
        return settings
    data = tmp_path / "pg-data"
    data.mkdir()
    return settings.model_copy(update={
        "data_dir": data, "database_url": request.getfixturevalue("postgres_url")})


def one_delete_started(settings: Settings) -> tuple[str, Any]:
    """A delete job with one target on one machine (m1), its target claimed by a runner:
    the job's id and what `targets.begin` gave."""
    with db.session_scope(settings.resolved_database_url) as session:
        registry.upsert(session=session, machine_in=registry.MachineIn.model_validate(
            {"id": "m1", "name": "M1", "model": "Mock"}), data_dir=settings.data_dir)
        job_id = service.create(session=session, kind=JobKind.DELETE, targets=[
            service.TargetIn(machineID="m1", fileName="O1.NC")]).id
    started = targets.begin(settings=settings, job_id=job_id, machine_id="m1")
    assert started.work is not None
    return job_id, started
