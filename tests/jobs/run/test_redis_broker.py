"""The Redis transport dncq selects: one client per channel, a fresh one after a new pool;
and the worker's one (disabled) result backend."""

from __future__ import annotations

import threading
from typing import Any

from jobs.run.queue import QUEUE, celery_config, producer
from jobs.run.redis_broker import Channel
from jobs.settings import Settings
from worker.app import make_celery


def test_a_redis_broker_url_selects_the_shared_client_transport(settings: Settings) -> None:
    redis_conf = celery_config(settings.model_copy(update={"broker_url": "redis://h:1/0"}))
    embedded_conf = celery_config(settings.model_copy(update={"broker_url": None}))

    assert redis_conf["broker_transport"] == "jobs.run.redis_broker:Transport"
    assert embedded_conf["broker_transport"] == "jobs.run.file_broker:Transport"


def test_commands_share_one_client_and_tasks_still_flow(queue_settings: Settings) -> None:
    app = producer(queue_settings)
    with app.connection_for_write() as conn:
        channel = conn.default_channel
        assert isinstance(channel, Channel)
        with channel.conn_or_acquire() as first, channel.conn_or_acquire() as second:
            assert first is second
        old_pool = channel.pool
        channel._pool = None  # what closing the channel's pools does
        with channel.conn_or_acquire() as after:
            assert after is not first
            assert after.connection_pool is channel.pool is not old_pool

        app.send_task("dncq.test.nothing", args=["a"], queue=QUEUE)
        app.send_task("dncq.test.nothing", args=["b"], queue=QUEUE)
        got: list[Any] = []
        while (message := channel.basic_get(QUEUE)) is not None:
            got.append(message.headers["argsrepr"])
            message.ack()
        with channel.conn_or_acquire() as client:
            assert client.hlen(channel.unacked_key) == 0  # acked through the shared client
    assert got == ["['a']", "['b']"]


def test_the_worker_builds_one_result_backend_for_all_its_tasks(settings: Settings) -> None:
    # Celery builds a backend per thread unless told it is thread-safe; a gevent pool runs
    # every task on a new greenlet, so that would be a backend per task.
    app = make_celery(settings)
    first = app.backend  # what the worker's tracer reads at start
    seen: list[Any] = []
    threads = [threading.Thread(target=lambda: seen.append(app.backend)) for _ in range(3)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()

    assert len(seen) == 3
    assert all(backend is first for backend in seen)
