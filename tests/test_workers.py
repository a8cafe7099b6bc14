"""The in-process Celery worker of the fast tests."""

from __future__ import annotations

from fastapi.testclient import TestClient

from jobs.api.app import create_app
from tests.conftest import API_KEY
from tests.jobs.helpers import wait_until
from tests.workers import in_process_worker


def test_an_in_process_worker_stopped_mid_job_leaves_none_of_its_tasks_running(
        queue_settings, add_machines):
    # A task left running wrote to its machine in the next test, and took a call that test
    # counted on its own transport.
    add_machines({"id": "slow", "name": "Slow", "model": "Mock",
                  "options": {"latency_ms": 500}})
    with in_process_worker(queue_settings) as worker, \
            TestClient(create_app(queue_settings), headers={"X-Api-Key": API_KEY}) as client:
        job_id = client.post("/api/jobs", json={
            "kind": "send", "content": "G0 X0\nM30\n",
            "targets": [{"machineID": "slow", "fileName": f"P{i}.nc"} for i in range(3)],
        }).json()["id"]
        wait_until(lambda: client.get(f"/api/jobs/{job_id}").json()["counts"]["running"])
        pool_threads = list(worker.pool.executor._threads)

    assert [t.name for t in pool_threads if t.is_alive()] == []
