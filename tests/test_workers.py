"""The in-process Celery worker of the fast tests."""

from __future__ import annotations

import contextlib
from typing import Any

import pytest
from fastapi.testclient import TestClient

from jobs.api.app import create_app
from tests.conftest import API_KEY
from tests.jobs.helpers import wait_until
from tests.workers import in_process_worker


class _TestFailed(Exception):
    pass


@pytest.mark.parametrize("test_fails", [False, True])
def test_an_in_process_worker_stopped_mid_job_leaves_none_of_its_tasks_running(
        queue_settings, add_machines, test_fails: bool):
    # A task left running wrote to its machine in the next test, and took a call that test
    # counted on its own transport; a test that failed must not leave one either.
    add_machines({"id": "slow", "name": "Slow", "model": "Mock",
                  "options": {"latency_ms": 500}})
    pool_threads: list[Any] = []
    with contextlib.suppress(_TestFailed), in_process_worker(queue_settings) as worker, \
            TestClient(create_app(queue_settings), headers={"X-Api-Key": API_KEY}) as client:
        job_id = client.post("/api/jobs", json={
            "kind": "send", "content": "G0 X0\nM30\n",
            "targets": [{"machineID": "slow", "fileName": f"P{i}.nc"} for i in range(3)],
        }).json()["id"]
        wait_until(lambda: client.get(f"/api/jobs/{job_id}").json()["counts"]["running"])
        pool_threads = list(worker.pool.executor._threads)
        if test_fails:
            raise _TestFailed

    assert pool_threads and [t.name for t in pool_threads if t.is_alive()] == []
