"""Putting work on the Celery queue by task name; the broker and its settings.

The control plane never imports worker tasks: it sends `dncq.run_machine` by name.
"""

from __future__ import annotations

import itertools
import threading
from collections.abc import Iterable
from typing import Any

from celery import Celery
from kombu.exceptions import KombuError
from redis.exceptions import RedisError

from jobs import folders
from jobs.settings import Settings

RUN_MACHINE = "dncq.run_machine"
ASSEMBLE_BACKUP = "dncq.assemble_backup"
SCHEDULE_TICK = "dncq.schedule_tick"
QUEUE = "dncq"
SENT_TOGETHER = 100  # messages per round trip when many are queued at once
SENT_FIRST = 16  # messages in the first round trip, which the workers wait for


def redis_broker(settings: Settings) -> str | None:
    """The broker's URL when it is Redis (`redis://`, `rediss://`); otherwise None."""
    url = settings.broker_url
    return url if url and url.split("://", 1)[0] in ("redis", "rediss") else None


def celery_config(settings: Settings) -> dict[str, Any]:
    """Celery configuration shared by producers and workers."""
    transport: str | None = None
    if settings.broker_url:
        # Every worker slot may queue a task at the same moment (a retry, a job waiting
        # for its machine); kombu's default pool of 10 Redis connections fails the 11th
        # ("Too many connections", seen with a 64-slot gevent worker when acks still went
        # to Redis). The pool only grows to the most commands at once.
        broker = settings.broker_url
        transport_options: dict[str, Any] = {"max_connections": 1024}
        if redis_broker(settings):
            transport = "jobs.run.redis_broker:Transport"  # one client per channel
            # A message a worker received is kept in its memory until acknowledged, not
            # also copied into Redis: that copy cost two Redis round trips and a JSON dump
            # per task, 15-17 % of a busy worker's CPU, and gave a dead worker's messages
            # back only after the visibility timeout, 12 h on. dncq's reaper queues them
            # again from the database long before (docs/jobs.md, "Recovery"); a
            # warm shutdown still puts the messages it had not started back on the queue.
            transport_options["ack_emulation"] = False
    else:
        # Embedded mode: a file-backed queue in the data folder, no server to install.
        folder = (settings.data_dir / "queue").resolve()
        folders.private_dir(folder)
        broker = "filesystem://localhost/"  # a host, or kombu warns it reverts to one
        transport = "jobs.run.file_broker:Transport"  # messages appear only once written whole
        transport_options = {"data_folder_in": str(folder), "data_folder_out": str(folder),
                             "control_folder": str(folder / "control"),
                             "polling_interval": 0.05}
    return {
        "broker_url": broker,
        "broker_transport": transport,
        # For brokers that re-deliver what was not acknowledged in time (not Redis, above):
        # longer than any transfer and any retry countdown, or a task still running is
        # delivered again (dncq's own reaper recovers dead workers much sooner).
        "broker_transport_options": {"visibility_timeout": 12 * 3600, **transport_options},
        "broker_connection_retry_on_startup": True,
        "task_default_queue": QUEUE,
        "task_acks_late": True,  # a task killed mid-way is delivered again ...
        "task_reject_on_worker_lost": True,  # ... also when its worker process dies
        "worker_prefetch_multiplier": 1,  # no worker hoards a fleet's tasks
        "task_ignore_result": True,  # the database, not the result backend, is the record
        # With no result backend, Celery's stand-in keeps no state; without this it builds
        # one per thread, which on a gevent pool means one per task.
        "result_backend_thread_safe": True,
        "worker_hijack_root_logger": False,
        "broker_pool_limit": 16,
    }


BROKER_FAILURES = (KombuError, RedisError, OSError)
"""What sending to an unreachable broker raises (kombu gives up after Celery's publish retries)."""

_PRODUCERS: dict[str, Celery] = {}
_PRODUCERS_LOCK = threading.Lock()


def producer(settings: Settings) -> Celery:
    """A Celery app that only sends tasks, one per broker per process."""
    key = settings.broker_url or str(settings.data_dir.resolve())
    app = _PRODUCERS.get(key)
    if app is None:
        with _PRODUCERS_LOCK:  # the first requests may come at once
            app = _PRODUCERS.get(key)
            if app is None:
                app = Celery("dncq-producer")
                # Configured before it is shared: unconfigured, it sends to Celery's default
                # broker (AMQP on localhost), which refuses the connection.
                app.conf.update(celery_config(settings))
                _PRODUCERS[key] = app
    return app


def enqueue_machine(settings: Settings, job_id: str, machine_id: str,
                    countdown_s: float | None = None) -> None:
    """Queue the run of one job's targets on one machine."""
    producer(settings).send_task(RUN_MACHINE, args=[job_id, machine_id], queue=QUEUE,
                                 countdown=countdown_s)


def enqueue_machines(settings: Settings, runs: Iterable[tuple[str, str]]) -> None:
    """Queue the runs of (job, machine) pairs, in their order, through one producer.

    On Redis, kombu's publish batch sends them `SENT_TOGETHER` at a time in one pipeline:
    one LPUSH per message made the round trips half of what queueing a rollout cost the
    API, and a worker starts on the first ones while the next are sent. A failed
    send raises (kombu's BatchPublishError) without retrying what may have arrived; the
    job is then recovered from the database like any whose queueing was cut short.
    Brokers without batches (the embedded file queue) get one message at a time.
    """
    app = producer(settings)
    pending = iter(runs)
    # The first few go in a round trip of their own, which a worker waits for: the
    # machines start while the rest are made (0.2 ms of the API's CPU each).
    first = list(itertools.islice(pending, SENT_FIRST))
    # The queue is declared with the first message only (Celery's None: the task's queue):
    # kombu declares it once per connection anyway, but binding the queue to the channel
    # to find that out again was about a seventh of what queueing each task cost the API.
    declare: list[Any] | None = None
    with app.producer_or_acquire() as publisher:
        for part, size in ((first, SENT_FIRST), (pending, SENT_TOGETHER)):
            with publisher.batch(max_size=size):
                for job_id, machine_id in part:
                    args = [job_id, machine_id]
                    # The log's form of the arguments, given: two short ids need no safe repr.
                    app.send_task(RUN_MACHINE, args=args, queue=QUEUE, producer=publisher,
                                  argsrepr=repr(args), kwargsrepr="{}", declare=declare)
                    declare = []


def enqueue_assembly(settings: Settings, job_id: str) -> None:
    """Queue the assembly of a finished backup job's ZIP."""
    producer(settings).send_task(ASSEMBLE_BACKUP, args=[job_id], queue=QUEUE)


def broker_status(settings: Settings) -> str:
    """"ok", or why the broker cannot be reached."""
    try:
        with producer(settings).connection_for_write() as conn:
            conn.ensure_connection(max_retries=1, timeout=2)
        return "ok"
    except Exception as exc:  # the message names the failure without any credentials
        return f"error: {type(exc).__name__}"


def workers_answering(settings: Settings, timeout_s: float = 1.0) -> int:
    """How many workers answer a ping within `timeout_s` (distributed mode)."""
    app = producer(settings)
    try:
        return len(app.control.ping(timeout=timeout_s) or [])
    except Exception:  # a pooled connection the broker dropped (it restarted): it is
        return len(app.control.ping(timeout=timeout_s) or [])  # replaced on the next try
