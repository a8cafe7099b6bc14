"""`dncq worker` in processes of their own, for the crash and distributed tests, and a
Celery worker in the test's own process, for the fast ones.

Each worker process gets its settings through `DNCQ_*` environment variables and writes its
output to a log file (the `start_worker` fixture prints it; pytest shows it on failure).
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from jobs.settings import Settings

READY_TIMEOUT_S = 60.0
STOP_TIMEOUT_S = 20.0
TASKS_END_TIMEOUT_S = 30.0  # what an in-process worker's tasks get to end once it stopped


def worker_env(settings: Settings) -> dict[str, str]:
    """The environment that gives a worker process the same settings as `settings`."""
    env = {k: v for k, v in os.environ.items()
           if not k.startswith("DNCQ_")}  # the test's settings, not the shell's
    env.update({
        "PYTHONUNBUFFERED": "1",
        "DNCQ_DATA_DIR": str(settings.data_dir),
        "DNCQ_DATABASE_URL": settings.resolved_database_url,
        "DNCQ_LEASE_TTL_S": str(settings.lease_ttl_s),
        "DNCQ_REAPER_INTERVAL_S": str(settings.reaper_interval_s),
        "DNCQ_REDISPATCH_AFTER_S": str(settings.redispatch_after_s),
        "DNCQ_RETRY_BASE_S": str(settings.retry_base_s),
        "DNCQ_RETRY_MAX_S": str(settings.retry_max_s),
        "DNCQ_MAX_ATTEMPTS": str(settings.max_attempts),
        "DNCQ_CLAIM_AHEAD": str(settings.claim_ahead).lower(),
        "DNCQ_MACHINE_CHECK_INTERVAL_S": str(settings.machine_check_interval_s),
        "DNCQ_REQUEST_SCAN_INTERVAL_S": str(settings.request_scan_interval_s),
    })
    if settings.broker_url:
        env["DNCQ_BROKER_URL"] = settings.broker_url
    return env


POOL_IN_BANNER = {"threads": "thread", "gevent": "gevent"}  # as Celery's start-up banner says


class WorkerProcess:
    """One `dncq worker` process (threads pool unless told) and its log file."""

    def __init__(self, name: str, settings: Settings, log_path: Path, *,
                 concurrency: int = 16, pool: str = "threads", args: Sequence[str] = ()) -> None:
        """`args`: more Celery worker options."""
        self.name, self.log_path = name, log_path
        self.hostname = f"{name}@{socket.gethostname()}"
        # what the worker says at start: its pool as Celery's banner gives it, or a gevent
        # worker's slots (its pool holds twice as many tasks, worker/app.py)
        self.banner = (f"{concurrency} machine operations at once"
                       if pool == "gevent" and settings.claim_ahead
                       else f"concurrency: {concurrency} ({POOL_IN_BANNER[pool]})")
        command = [sys.executable, "-m", "jobs.cli", "worker", "--pool", pool,
                   "--concurrency", str(concurrency), "--loglevel", "INFO", "-n", self.hostname,
                   "--without-mingle", "--without-gossip", *args]
        with open(log_path, "wb") as log:
            self.proc = subprocess.Popen(command, env=worker_env(settings), stdout=log,
                                         stderr=subprocess.STDOUT, cwd=log_path.parent)

    @property
    def pid(self) -> int:
        return self.proc.pid

    @property
    def worker_name(self) -> str:
        """How the process signs its attempts: jobs.run.claims.worker_name, its host and pid."""
        return f"{socket.gethostname()}:{self.pid}"

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")

    def wait_for_log(self, text: str, timeout_s: float = READY_TIMEOUT_S) -> None:
        """Block until `text` shows in the log; fails if the process ends first."""
        deadline = time.monotonic() + timeout_s
        while text not in self.log():
            if self.proc.poll() is not None:
                raise AssertionError(f"worker {self.name} exited ({self.proc.returncode}) "
                                     f"before logging {text!r}")
            if time.monotonic() > deadline:
                raise AssertionError(f"worker {self.name} did not log {text!r} in time")
            time.sleep(0.05)

    def wait_ready(self) -> None:
        """Block until the worker consumes from the queue, running the pool it was asked for."""
        self.wait_for_log(" ready.")
        assert self.banner in self.log(), f"worker {self.name} did not start {self.banner}"

    def kill(self) -> None:
        """SIGKILL: no warm shutdown, no message handed back to the broker."""
        if self.proc.poll() is None:
            os.kill(self.pid, signal.SIGKILL)
        self.proc.wait()

    def stop(self) -> None:
        """Warm shutdown (SIGTERM), then SIGKILL if it does not end in time."""
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                self.kill()


@contextmanager
def in_process_worker(settings: Settings) -> Iterator[Any]:
    """A Celery worker (16 threads) in this process on the settings' queue, with its reaper.

    Celery's test worker stops cold: the tasks it was running go on in its pool's threads,
    into the next test (where they met that test's patches of a transport); they end here.
    """
    from celery.contrib.testing.worker import start_worker

    from worker.app import Reaper, make_celery

    app = make_celery(settings)
    # Redis is asked for the next task with a BRPOP of 1 s, which the worker waits out when it
    # stops: 0.1 s here ends each test's worker in about that.
    app.conf.broker_transport_options = {**app.conf.broker_transport_options,
                                         "polling_interval": 0.1}
    reaper = Reaper(settings)
    worker = None
    try:
        with start_worker(app, pool="threads", concurrency=16, perform_ping_check=False,
                          loglevel="WARNING", shutdown_timeout=30) as worker:
            reaper.start()
            try:
                yield worker
            finally:
                reaper.stop()
    finally:  # however the test (or the worker's stop) ended
        if worker is not None:
            _wait_for_its_tasks(worker)


def _wait_for_its_tasks(worker: Any) -> None:
    threads = worker.pool.executor
    threads.shutdown(wait=False, cancel_futures=True)  # the idle ones end now
    deadline = time.monotonic() + TASKS_END_TIMEOUT_S
    for thread in list(threads._threads):
        thread.join(max(0.0, deadline - time.monotonic()))
        assert not thread.is_alive(), \
            f"a task still runs {TASKS_END_TIMEOUT_S:.0f} s after its worker stopped"
