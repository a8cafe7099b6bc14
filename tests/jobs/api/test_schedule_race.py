"""Runs, deletes and re-creates of one schedule at the same time: each request gets a clear answer.

Threads send the requests to the API served on loopback over a real database (SQLite and
PostgreSQL); a run of a schedule removed meanwhile is a 404, never a 500, and queues nothing.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from typing import Any

import httpx
import pytest
from sqlalchemy import func, select

from jobs import db
from jobs.api.app import create_app
from jobs.fleet import registry
from jobs.models import Job, ScheduleRun
from jobs.settings import Settings
from tests.conftest import API_KEY
from tests.live_server import LiveServer, serving

ROUNDS = 25  # requests per thread
THREADS_PER_ACTION = 2
SCHEDULE = {"name": "nightly", "cron": "0 2 * * *", "machines": {"ids": ["m1"]}}
ANSWERS = {"create": {201}, "delete": {204, 404}, "run": {202, 404}}


@pytest.fixture
def live(settings: Settings, database_url: str) -> Iterator[tuple[LiveServer, str]]:
    """The API over `database_url` with one mock machine; yields it and the database URL."""
    raced = settings.model_copy(update={"database_url": database_url})
    with db.session_scope(database_url) as session:
        registry.upsert(session=session, machine_in=registry.MachineIn(
            id="m1", name="Lathe", model="Mock"))
    with serving(create_app(raced)) as server:
        yield server, database_url


def _hammer(url: str, action: str, answers: list[tuple[str, int, Any]]) -> None:
    with httpx.Client(base_url=url, headers={"X-Api-Key": API_KEY}, timeout=60) as client:
        for _ in range(ROUNDS):
            if action == "create":
                response = client.post("/api/schedules", json=SCHEDULE)
            elif action == "delete":
                response = client.delete("/api/schedules/nightly")
            else:
                response = client.post("/api/schedules/nightly/run")
            body = response.json() if response.content else None
            answers.append((action, response.status_code, body))


def test_run_delete_and_create_at_once_each_get_a_clear_answer(live):
    server, url = live
    answers: list[tuple[str, int, Any]] = []
    threads = [threading.Thread(target=_hammer, args=(server.url, action, answers))
               for action in ANSWERS for _ in range(THREADS_PER_ACTION)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()

    unclear = [(a, status, body) for a, status, body in answers if status not in ANSWERS[a]]
    assert unclear == []
    assert all(body["errorCode"] == 158 for _, status, body in answers if status == 404)
    assert len(answers) == ROUNDS * THREADS_PER_ACTION * len(ANSWERS)


def _job_ids(url: str) -> set[str]:
    with db.session_scope(url) as session:
        return set(session.scalars(select(Job.id)))


def test_a_run_answered_404_queues_no_backup(live):
    server, url = live
    before = _job_ids(url)  # the PostgreSQL server is the module's: earlier tests' jobs stay
    answers: list[tuple[str, int, Any]] = []
    threads = [threading.Thread(target=_hammer, args=(server.url, action, answers))
               for action in ANSWERS for _ in range(THREADS_PER_ACTION)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()

    started = {body["job"] for action, status, body in answers
               if action == "run" and status == 202}
    with db.session_scope(url) as session:
        orphan_runs = session.scalar(select(func.count()).select_from(ScheduleRun).where(
            ScheduleRun.job_id.is_(None)))
    assert _job_ids(url) - before == started
    assert orphan_runs == 0
