"""The embedded mode: the HTTP API and a Celery worker in one process, no server to install.

Tasks still go through Celery, on kombu's file-backed transport in the data folder.
What it cannot do: run workers on other hosts (the queue is a local folder), survive
losing the data folder, or serve more machines at once than `worker_concurrency`.
A hard kill loses the messages this process had taken; the reaper requeues their
targets on the next start, from the database.
"""

from __future__ import annotations

import logging
import threading
import time
import warnings
from typing import Any

import uvicorn
from celery.exceptions import SecurityWarning

from jobs import logs
from jobs.settings import Settings
from worker.app import make_celery

log = logging.getLogger(__name__)


def run(settings: Settings, asgi_app: Any) -> None:
    """Serve `asgi_app` and work the queue until interrupted."""
    # Celery warns a worker run by root against unpickling what any client of the broker
    # sends. Here the queue is a folder of the data folder, which only its owner opens, and
    # takes JSON only: the demo run as root (a container's default) need not alarm anyone.
    # `dncq worker`, a service of its own, keeps the warning. The filter goes in before the
    # API thread starts: FastAPI wraps parts of each request in `warnings.catch_warnings()`,
    # which puts back the filters it found on leaving, and would drop one added meanwhile.
    warnings.filterwarnings("ignore", category=SecurityWarning)
    server = uvicorn.Server(uvicorn.Config(asgi_app, host=settings.host, port=settings.port,
                                           log_level="info",
                                           **logs.uvicorn_options(settings.log_format)))
    api_thread = threading.Thread(target=server.run, name="dncq-api", daemon=True)
    api_thread.start()
    while not server.started and api_thread.is_alive():
        time.sleep(0.05)
    if not server.started:  # uvicorn said why (its address taken): no worker without an API
        raise SystemExit(1)
    celery_app = make_celery(settings)
    worker = celery_app.Worker(
        pool_cls="threads", concurrency=settings.worker_concurrency, loglevel="INFO",
        without_heartbeat=True, without_mingle=True, without_gossip=True, quiet=True,
    )
    try:
        worker.start()  # blocks; Ctrl-C stops it warmly (running targets finish)
    finally:
        server.should_exit = True
        api_thread.join(timeout=10)
