"""Plain Celery on the same Redis and pool as dncq's worker: tasks that only sleep.

The reference for bench/batch_send.py: what Celery itself costs on this host when a task
does nothing but wait as long as one target's transfer, with Celery's default settings
(no database, no machine, no lease). The gap between this and dncq's figures is what
dncq's own work adds. The worker is `celery -A bench.plain_celery worker`; each task adds
one to a Redis counter, which the benchmark polls to see the batch finish.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import redis
from celery import Celery

QUEUE = "plain-celery"
COUNTER = "plain-celery:done"
POLL_S = 0.005

app = Celery("plain", broker=os.environ.get("PLAIN_CELERY_BROKER", "redis://127.0.0.1:6379/0"))
app.conf.update(task_ignore_result=True, worker_hijack_root_logger=False,
                task_default_queue=QUEUE)

_client: list[Any] = []


@app.task(name="plain.sleep")
def sleep(ms: float) -> None:
    """Wait `ms` milliseconds, then count one task done."""
    if ms:
        time.sleep(ms / 1000)
    if not _client:
        _client.append(redis.Redis.from_url(app.conf.broker_url))
    _client[0].incr(COUNTER)


@contextlib.contextmanager
def plain_worker(broker_url: str, *, pool: str, concurrency: int, folder: Path,
                 workers: int = 1) -> Iterator[None]:
    """`workers` `celery worker` processes for the sleep tasks, stopped after the block."""
    repo = Path(__file__).resolve().parent.parent
    env = {**os.environ, "PLAIN_CELERY_BROKER": broker_url, "PYTHONPATH": str(repo)}
    procs = []
    for i in range(workers):
        with open(folder / f"plain-celery-{i}.log", "wb") as log:
            procs.append(subprocess.Popen(
                [sys.executable, "-m", "celery", "-A", "bench.plain_celery", "worker", "-P",
                 pool, "-c", str(concurrency), "-Q", QUEUE, "-l", "WARNING", "-n",
                 f"plain{i}@%h", "--without-mingle", "--without-gossip",
                 "--without-heartbeat"],
                env=env, stdout=log, stderr=subprocess.STDOUT, cwd=folder))
    try:
        run_batch(broker_url, tasks=workers, ms=0, timeout_s=60)  # ready once they answer
        yield
    finally:
        for proc in procs:
            proc.terminate()
        for proc in procs:
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def run_batch(broker_url: str, *, tasks: int, ms: float, timeout_s: float = 120) -> float:
    """Send `tasks` sleep tasks and wait until all have run; returns the wall time."""
    app.conf.broker_url = broker_url
    counter = redis.Redis.from_url(broker_url)
    counter.set(COUNTER, 0)
    started = time.perf_counter()
    for _ in range(tasks):
        sleep.apply_async(args=[ms], queue=QUEUE)
    while int(counter.get(COUNTER) or 0) < tasks:
        if time.perf_counter() - started > timeout_s:
            done = int(counter.get(COUNTER) or 0)
            raise TimeoutError(f"plain Celery ran {done} of {tasks} tasks")
        time.sleep(POLL_S)
    return time.perf_counter() - started
