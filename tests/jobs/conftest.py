"""Fixtures of the job tests that run `dncq worker` in processes of their own."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from jobs.settings import Settings
from tests.workers import WorkerProcess


@pytest.fixture
def start_worker(tmp_path: Path) -> Iterator[Callable[..., WorkerProcess]]:
    """Factory: start a `dncq worker` process; every one is stopped at teardown."""
    started: list[WorkerProcess] = []

    def start(name: str, settings: Settings, *, concurrency: int = 16,
              pool: str = "threads") -> WorkerProcess:
        worker = WorkerProcess(name, settings, tmp_path / f"worker-{name}.log",
                               concurrency=concurrency, pool=pool)
        started.append(worker)
        return worker

    try:
        yield start
    finally:
        for worker in started:
            worker.stop()
        for worker in started:
            print(f"----- log of worker {worker.name} (pid {worker.pid}) -----\n{worker.log()}")
