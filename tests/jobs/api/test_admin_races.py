"""Admin requests about one schedule or machine at the same time: each gets a clear answer.

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
from jobs.backup_models import ScheduleRun
from jobs.fleet import registry
from jobs.models import Job
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
            id="m1", name="Lathe", model="Mock"), data_dir=settings.data_dir)
    with serving(create_app(raced)) as server:
        yield server, database_url


REQUESTS = {
    "create": ("POST", "/api/schedules", SCHEDULE),
    "delete": ("DELETE", "/api/schedules/nightly", None),
    "run": ("POST", "/api/schedules/nightly/run", None),
    "add machine": ("POST", "/api/machines", {"id": "m2", "name": "A", "model": "Mock"}),
    "put machine": ("PUT", "/api/machines/m2", {"id": "m2", "name": "B", "model": "Mock"}),
    "delete machine": ("DELETE", "/api/machines/m2", None),
}
MACHINE_ANSWERS = {"add machine": {201, 409}, "put machine": {200, 409},
                   "delete machine": {204, 404}}


def _hammer(url: str, action: str, answers: list[tuple[str, int, Any]]) -> None:
    method, path, body = REQUESTS[action]
    with httpx.Client(base_url=url, headers={"X-Api-Key": API_KEY}, timeout=60) as client:
        for _ in range(ROUNDS):
            try:
                response = client.request(method, path, json=body)
                answers.append((action, response.status_code,
                                response.json() if response.content else None))
            except Exception as exc:  # said in the test's failure, not lost with the thread
                answers.append((action, 0, repr(exc)))


def _race(url: str, actions: dict[str, set[int]]) -> list[tuple[str, int, Any]]:
    """Every action's requests sent at once from threads of their own; their answers."""
    answers: list[tuple[str, int, Any]] = []
    threads = [threading.Thread(target=_hammer, args=(url, action, answers))
               for action in actions for _ in range(THREADS_PER_ACTION)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert len(answers) == ROUNDS * THREADS_PER_ACTION * len(actions)
    return answers


def test_run_delete_and_create_at_once_each_get_a_clear_answer(live):
    server, _ = live

    answers = _race(server.url, ANSWERS)

    unclear = [(a, status, body) for a, status, body in answers if status not in ANSWERS[a]]
    assert unclear == []
    assert all(body["errorCode"] == 158 for _, status, body in answers if status == 404)


def _job_ids(url: str) -> set[str]:
    with db.session_scope(url) as session:
        return set(session.scalars(select(Job.id)))


def test_a_run_answered_404_queues_no_backup(live):
    server, url = live
    before = _job_ids(url)  # the PostgreSQL server is the module's: earlier tests' jobs stay

    answers = _race(server.url, ANSWERS)

    started = {body["job"] for action, status, body in answers
               if action == "run" and status == 202}
    with db.session_scope(url) as session:
        orphan_runs = session.scalar(select(func.count()).select_from(ScheduleRun).where(
            ScheduleRun.job_id.is_(None)))
    assert _job_ids(url) - before == started
    assert orphan_runs == 0


def test_add_put_and_delete_of_one_machine_at_once_each_get_a_clear_answer(live):
    server, _ = live

    answers = _race(server.url, MACHINE_ANSWERS)

    unclear = [(a, status, body) for a, status, body in answers
               if status not in MACHINE_ANSWERS[a]]
    assert unclear == []
    assert all(body["errorCode"] == 10003 for a, status, body in answers if status == 404)
