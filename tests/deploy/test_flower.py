"""Flower, as docs/deployment.md runs it (`celery -A worker.app flower`), watching real dncq
workers through the Redis broker: it sees the workers and the tasks a job fans out."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from fastapi.testclient import TestClient

from jobs.api.app import create_app
from jobs.run.queue import RUN_MACHINE
from tests.conftest import API_KEY
from tests.jobs.helpers import wait_done, wait_until
from tests.servers import free_port, stop_process, unavailable
from tests.workers import worker_env


@pytest.fixture
def flower(queue_settings, tmp_path: Path) -> Iterator[str]:
    """Flower on a loopback port, its API open as FLOWER_UNAUTHENTICATED_API allows."""
    if importlib.util.find_spec("flower") is None:
        unavailable("Flower is not installed (a test extra: pip install -e '.[test]')")
    port = free_port()
    env = {**worker_env(queue_settings), "FLOWER_UNAUTHENTICATED_API": "true"}
    log_path = tmp_path / "flower.log"
    with open(log_path, "wb") as log:
        proc = subprocess.Popen(
            [sys.executable, "-m", "celery", "-A", "worker.app", "flower",
             f"--port={port}", "--address=127.0.0.1"],
            env=env, stdout=log, stderr=subprocess.STDOUT, cwd=tmp_path)
    url = f"http://127.0.0.1:{port}"

    def up() -> bool:
        assert proc.poll() is None, log_path.read_text(errors="replace")
        try:
            return httpx.get(f"{url}/healthcheck", timeout=2).text == "OK"
        except httpx.HTTPError:
            return False

    try:
        wait_until(up, timeout_s=30)
        yield url
    finally:
        stop_process(proc, timeout_s=10)


def test_flower_lists_the_workers_and_the_tasks_of_a_job(queue_settings, add_machines,
                                                         start_worker, flower) -> None:
    add_machines(*[{"id": f"m{i}", "name": f"M{i}", "model": "Mock"} for i in range(3)])
    worker = start_worker("w1", queue_settings)
    worker.wait_ready()

    def workers() -> dict:
        answer = httpx.get(f"{flower}/api/workers", params={"refresh": "1"}, timeout=10)
        return answer.json() if answer.status_code == 200 else {}

    wait_until(lambda: worker.hostname in workers(), timeout_s=30)
    # Flower turns the workers' task events on itself; a job sent before that is not seen.
    worker.wait_for_log("Events of group {task} enabled by remote", timeout_s=30)
    with TestClient(create_app(queue_settings), headers={"X-Api-Key": API_KEY}) as api:
        job = api.post("/api/jobs", json={"kind": "send", "content": "%\nO1000\nM30\n%\n",
                                          "targets": [{"machineID": f"m{i}",
                                                       "fileName": "O1000"}
                                                      for i in range(3)]}).json()
        assert wait_done(api, job["id"])["counts"]["succeeded"] == 3

    def tasks() -> list[dict]:
        found = httpx.get(f"{flower}/api/tasks", params={"taskname": RUN_MACHINE},
                          timeout=10).json()
        return [t for t in found.values() if job["id"] in str(t.get("args"))]

    wait_until(lambda: len([t for t in tasks() if t["state"] == "SUCCESS"]) == 3,
               timeout_s=30)
    assert {t["worker"] for t in tasks()} == {worker.hostname}
    assert workers()[worker.hostname]["stats"]["pool"]["max-concurrency"] == 16

