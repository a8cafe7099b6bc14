"""A job's end said on Redis wakes the batch request waiting for it; without Redis, or
when Redis is gone, the request still finds the end by looking."""

from __future__ import annotations

import asyncio
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from jobs.api.routes import batch
from jobs.run import job_ends
from jobs.settings import Settings
from tests.servers import RedisServer, free_port

PROGRAM = "G21 G90\nG0 X0 Y0\nM30\n"


async def _wait_once(settings: Settings, job_id: str, timeout_s: float,
                     said: str | None = None, say_after_s: float = 0.2) -> tuple[bool, float]:
    """Listen for `job_id`, have `said` announced from a thread, and wait once."""
    async with job_ends.listening(settings, job_id) as wait:
        if said is not None:
            threading.Timer(say_after_s, job_ends.announce, (settings, said)).start()
        started = time.monotonic()
        told = await wait(timeout_s)
        return told, time.monotonic() - started


def test_an_end_said_on_redis_ends_the_wait(queue_settings: Settings) -> None:
    told, waited_s = asyncio.run(_wait_once(queue_settings, "j1", 30.0, said="j1"))
    assert told
    assert waited_s < 15  # woken by the message, not by the end of the 30 s wait


def test_the_end_of_another_job_does_not_end_the_wait(queue_settings: Settings) -> None:
    told, waited_s = asyncio.run(_wait_once(queue_settings, "j1", 0.5, said="j2",
                                            say_after_s=0.05))
    assert not told
    assert waited_s >= 0.5


def test_without_redis_the_wait_sleeps_and_saying_is_a_no_op(settings: Settings) -> None:
    assert settings.broker_url is None  # the embedded queue
    job_ends.announce(settings, "j1")
    told, waited_s = asyncio.run(_wait_once(settings, "j1", 0.2))
    assert not told
    assert waited_s >= 0.2


def test_a_redis_that_cannot_be_reached_leaves_the_wait_to_sleep(settings: Settings) -> None:
    nowhere = settings.model_copy(update={"broker_url": f"redis://127.0.0.1:{free_port()}/0"})
    job_ends.announce(nowhere, "j1")  # says nothing, raises nothing
    told, waited_s = asyncio.run(_wait_once(nowhere, "j1", 0.2))
    assert not told
    assert waited_s >= 0.2


def test_a_redis_that_goes_away_while_listened_to_leaves_the_wait_to_sleep(
        settings: Settings, tmp_path: Path) -> None:
    server = RedisServer(tmp_path)
    server.start()
    own = settings.model_copy(update={"broker_url": server.url})

    async def scenario() -> list[tuple[bool, float]]:
        async with job_ends.listening(own, "j1") as wait:
            server.kill()
            waits = []
            for _ in range(2):  # the first notices the loss, the second only sleeps
                started = time.monotonic()
                told = await wait(0.3)
                waits.append((told, time.monotonic() - started))
            return waits

    try:
        waits = asyncio.run(scenario())
    finally:
        server.kill()
    assert [told for told, _ in waits] == [False, False]
    assert all(waited_s >= 0.3 for _, waited_s in waits)


def test_a_batch_request_answers_when_the_worker_says_its_job_ended(
        queue_client: Any, add_machines: Any, queue_settings: Settings,
        monkeypatch: pytest.MonkeyPatch) -> None:
    # Pauses of a minute between looks: only the worker's message can end the wait sooner.
    monkeypatch.setattr(batch, "POLL_MIN_S", 60.0)
    monkeypatch.setattr(batch, "POLL_MAX_S", 60.0)
    add_machines(*[{"id": f"e{i}", "name": f"E{i}", "model": "Mock",
                    "options": {"latency_ms": 300}} for i in range(3)])
    started = time.monotonic()
    response = queue_client.post("/api/cnc/batchSendFile", json={
        "content": PROGRAM,
        "targets": [{"machineID": f"e{i}", "fileName": "P.nc"} for i in range(3)]})
    answered_s = time.monotonic() - started
    assert response.status_code == 200
    assert [r["errorCode"] for r in response.json()] == [0, 0, 0]  # final, not "running"
    assert answered_s < 30
