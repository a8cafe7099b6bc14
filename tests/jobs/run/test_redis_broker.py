"""The Redis transport dncq selects: one client per channel, a fresh one after a new pool,
channels that still close after Redis restarted; and the worker's one (disabled) result
backend."""

from __future__ import annotations

import socket
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import redis
from kombu import Connection, Exchange, Queue

from jobs.run import redis_broker
from jobs.run.queue import QUEUE, celery_config, producer
from jobs.run.redis_broker import Channel
from jobs.settings import Settings
from tests.servers import RedisServer
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
    assert got == ["['a']", "['b']"]


def test_a_received_message_lives_in_the_worker_until_acked_and_goes_back_at_a_close(
        queue_settings: Settings) -> None:
    # No copy in Redis's unacked hash (kombu's acknowledgement emulation is off: dncq's
    # reaper recovers what a dead worker took); a warm shutdown closes the channel, which
    # must put what was received and not acknowledged back on the queue.
    app = producer(queue_settings)
    with app.connection_for_write() as conn:
        channel = conn.default_channel
        app.send_task("dncq.test.nothing", args=["kept"], queue=QUEUE)
        message = channel.basic_get(QUEUE)
        assert message is not None
        with channel.conn_or_acquire() as client:
            assert client.llen(QUEUE) == 0
            assert not client.exists(channel.unacked_key, channel.unacked_index_key)
        channel.close()

        back = conn.channel().basic_get(QUEUE)
        assert back is not None
        assert back.headers["argsrepr"] == "['kept']"
        back.ack()


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


@pytest.fixture
def restartable_redis(tmp_path: Path) -> Iterator[RedisServer]:
    """A Redis of the test's own that keeps every write in its append-only file."""
    server = RedisServer(tmp_path, appendonly=True)
    server.start()
    try:
        yield server
    finally:
        server.kill()


def test_channels_left_open_by_an_outage_close_and_restore_their_messages_after_a_restart(
        restartable_redis: RedisServer) -> None:
    # What Celery's consumer does when Redis goes away: it collects the connection, whose
    # first failing channel close leaves the others open, and closes those later. Here with
    # kombu's acknowledgement emulation (its default), whose close restores through Redis
    # and so fails; dncq turns it off, but the channel must not depend on that.
    queue = Queue("q", Exchange("q"), "q")
    conn = Connection(restartable_redis.url, transport="jobs.run.redis_broker:Transport")
    with conn.Producer() as publisher:
        for i in range(3):
            publisher.publish({"i": i}, exchange=queue.exchange, routing_key="q",
                              declare=[queue])
    channels = [conn.channel() for _ in range(3)]
    for channel in channels:
        assert channel.basic_get("q", no_ack=False) is not None  # delivered, not acked
    restartable_redis.kill()
    conn.collect(socket_timeout=1)
    left_open = [channel for channel in channels if not channel.closed]
    assert left_open, "collect closed every channel: nothing left to close after the restart"
    restartable_redis.start()

    for channel in left_open:
        channel.close()  # kombu's own channel raises AttributeError here

    with Connection(restartable_redis.url) as fresh, fresh.SimpleQueue("q") as back:
        assert back.qsize() == len(left_open)  # their unacknowledged messages queued again


def test_messages_that_cannot_go_back_to_a_redis_that_is_gone_leave_a_warning_not_a_dump(
        restartable_redis: RedisServer, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        caplog: pytest.LogCaptureFixture) -> None:
    # kombu logged an ERROR and wrote the messages into a file in /tmp at every restart of
    # Redis, for targets the reaper recovers from the database anyway.
    import tempfile

    dumps = tmp_path / "tmp"
    dumps.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(dumps))  # where kombu's dump would go
    queue = _published(restartable_redis.url, 3)
    conn = _connection(restartable_redis.url)
    channel = conn.channel()
    with conn.Consumer([queue], channel=channel, callbacks=[lambda *_: None],
                       prefetch_count=3):
        conn.drain_events(timeout=5)  # three taken, none acknowledged
        restartable_redis.kill()
        with caplog.at_level("WARNING"):
            channel.qos.restore_unacked_once()

    assert not list(dumps.iterdir())
    assert [r.levelname for r in caplog.records] == ["WARNING"]
    assert "3 messages taken from the broker could not go back" in caplog.records[0].message
    conn.release()


def test_batched_publishes_reach_redis_together_at_the_block_end(
        queue_settings: Settings) -> None:
    # kombu batches through the channel's own client: dncq's channel must keep that working.
    app = producer(queue_settings)
    with app.producer_or_acquire() as publisher, \
            publisher.channel.conn_or_acquire() as client:
        with publisher.batch():
            app.send_task("dncq.test.nothing", args=["first"], queue=QUEUE, producer=publisher)
            app.send_task("dncq.test.nothing", args=["second"], queue=QUEUE, producer=publisher)
            assert client.llen(QUEUE) == 0  # gathered, not sent
        assert client.llen(QUEUE) == 2

        with pytest.raises(RuntimeError), publisher.batch():
            app.send_task("dncq.test.nothing", args=["dropped"], queue=QUEUE,
                          producer=publisher)
            raise RuntimeError("the caller failed half-way")
        app.send_task("dncq.test.nothing", args=["after"], queue=QUEUE, producer=publisher)
        got = []
        while (message := publisher.channel.basic_get(QUEUE)) is not None:
            got.append(message.headers["argsrepr"])
            message.ack()
    assert got == ["['first']", "['second']", "['after']"]  # a failed block sent nothing


def test_many_runs_are_queued_in_their_order_a_few_first_then_a_hundred_a_round_trip(
        queue_settings: Settings, monkeypatch: pytest.MonkeyPatch) -> None:
    from kombu.transport.redis import PublishBatch

    from jobs.run import queue

    runs = [("job-a", f"m{i:03d}") for i in range(250)]
    sent_together: list[int] = []
    flush = PublishBatch.flush

    def counted(self: PublishBatch) -> None:
        if self._buffered:
            sent_together.append(self._buffered)
        flush(self)

    monkeypatch.setattr(PublishBatch, "flush", counted)
    queue.enqueue_machines(queue_settings, runs)

    assert sent_together == [16, 100, 100, 34]
    app = producer(queue_settings)
    with app.connection_for_write() as conn:
        got = []
        while (message := conn.default_channel.basic_get(QUEUE)) is not None:
            assert message.headers["task"] == queue.RUN_MACHINE
            got.append(tuple(message.decode()[0]))
            message.ack()
    assert got == runs


def _connection(url: str) -> Connection:
    """A kombu connection as dncq's workers make it: its transport, no ack emulation."""
    return Connection(url, transport="jobs.run.redis_broker:Transport",
                      transport_options={"ack_emulation": False})


def _published(url: str, count: int) -> Queue:
    queue = Queue("q", Exchange("q"), "q")
    with _connection(url) as conn, conn.Producer() as publisher:
        for i in range(count):
            publisher.publish({"i": i}, exchange=queue.exchange, routing_key="q",
                              declare=[queue])
    return queue


def _waiting(url: str) -> list[int]:
    """Empty the list: the messages left in it, in the order a consumer takes them."""
    with _connection(url) as conn:
        channel = conn.channel()
        left = []
        while (message := channel.basic_get("q", no_ack=True)) is not None:
            left.append(message.decode()["i"])
    return left


def test_one_poll_takes_what_waits_up_to_the_consumers_prefetch_window_in_order(
        redis_server: RedisServer) -> None:
    redis_server.flush()
    queue = _published(redis_server.url, 12)
    got: list[int] = []
    with _connection(redis_server.url) as conn, \
            conn.Consumer([queue], callbacks=[lambda body, _: got.append(body["i"])],
                          prefetch_count=5):
        conn.drain_events(timeout=5)  # one BRPOP answered

        assert got == [0, 1, 2, 3, 4]  # one by the BRPOP, four more in one RPOP
        assert _waiting(redis_server.url) == list(range(5, 12))


def test_a_worker_takes_no_more_than_its_pool_can_start_and_wakes_when_a_task_ends(
        redis_server: RedisServer, monkeypatch: pytest.MonkeyPatch) -> None:
    # Its prefetch window is twice its pool. Taken beyond the pool (in bulk, or by a poll
    # made while it was full), a message waited in this worker while another worker had
    # room: a 50-machine backup on two workers now and then took a whole round more
    # (docs/performance.md).
    monkeypatch.setattr(redis_broker, "_pool_size", None)
    monkeypatch.setattr(redis_broker, "_slots", None)
    monkeypatch.setattr(redis_broker, "FULL_POOL_WAIT_S", 60.0)  # only a task's end wakes it
    redis_broker.take_in_bulk_up_to(4)
    redis_server.flush()
    queue = _published(redis_server.url, 12)
    got: list[Any] = []
    with _connection(redis_server.url) as conn, \
            conn.Consumer([queue], callbacks=[lambda body, message: got.append(message)],
                          prefetch_count=8):
        conn.drain_events(timeout=5)
        assert [m.decode()["i"] for m in got] == [0, 1, 2, 3]  # the BRPOP's, three more

        with pytest.raises(socket.timeout):
            conn.drain_events(timeout=0.5)  # the pool is full: nothing taken
        assert redis.Redis.from_url(redis_server.url).llen("q") == 8  # there for another

        threading.Timer(0.2, got.pop(0).ack).start()  # a task ends while the consumer waits
        conn.drain_events(timeout=10)
        assert [m.decode()["i"] for m in got] == [1, 2, 3, 4]  # the BRPOP's alone
        assert _waiting(redis_server.url) == list(range(5, 12))


def test_a_worker_with_every_slot_busy_leaves_the_queue_to_one_with_room_first(
        redis_server: RedisServer, monkeypatch: pytest.MonkeyPatch) -> None:
    # A gevent worker's pool is twice its slots: the tasks beyond them claim ahead and wait
    # for a slot. Taken in bulk, or by the first poll, while another worker had slots free,
    # they made a 50-machine backup on two workers of 32 take a whole round more.
    monkeypatch.setattr(redis_broker, "_pool_size", None)  # both set back after the test
    monkeypatch.setattr(redis_broker, "_slots", None)
    monkeypatch.setattr(redis_broker, "CLAIM_AHEAD_WAIT_S", 60.0)  # the poll's own wait only
    redis_broker.take_in_bulk_up_to(8, slots=4)
    redis_server.flush()
    queue = _published(redis_server.url, 12)
    busy: list[int] = []
    with_room: list[int] = []
    with _connection(redis_server.url) as busy_worker, \
            _connection(redis_server.url) as worker_with_room, \
            busy_worker.Consumer([queue], callbacks=[lambda b, _: busy.append(b["i"])],
                                 prefetch_count=8), \
            worker_with_room.Consumer([queue], callbacks=[lambda b, _: with_room.append(b["i"])],
                                      prefetch_count=8):
        busy_worker.drain_events(timeout=5)
        assert busy == [0, 1, 2, 3]  # the BRPOP's and three more: every slot, not the pool

        claiming = threading.Thread(target=busy_worker.drain_events, kwargs={"timeout": 1.0})
        claiming.start()  # every slot busy: it looks again in a while
        worker_with_room.drain_events(timeout=5)
        claiming.join(10)

    assert with_room == [4, 5, 6, 7]
    # What no worker with room took in the meantime, it then claims ahead, up to its pool.
    assert busy == [0, 1, 2, 3, 8, 9, 10, 11]


def test_messages_taken_together_and_not_acknowledged_go_back_when_the_channel_closes(
        redis_server: RedisServer) -> None:
    # A warm shutdown: everything taken, delivered or not yet run, is queued again.
    redis_server.flush()
    queue = _published(redis_server.url, 8)
    got: list[int] = []
    with _connection(redis_server.url) as conn:
        with conn.Consumer([queue], callbacks=[lambda body, _: got.append(body["i"])],
                           prefetch_count=6):
            conn.drain_events(timeout=5)
        conn.default_channel.close()

    assert got == [0, 1, 2, 3, 4, 5]
    assert sorted(_waiting(redis_server.url)) == list(range(8))


def test_a_delivery_that_fails_puts_the_rest_taken_back_first_in_line(
        redis_server: RedisServer) -> None:
    redis_server.flush()
    queue = _published(redis_server.url, 10)
    got: list[int] = []

    def take(body: dict[str, int], _: Any) -> None:
        if body["i"] == 3:
            raise RuntimeError("the consumer failed")
        got.append(body["i"])

    with _connection(redis_server.url) as conn, \
            conn.Consumer([queue], callbacks=[take], prefetch_count=8):
        with pytest.raises(RuntimeError):
            conn.drain_events(timeout=5)

        assert got == [0, 1, 2]
        # 4-7 were taken with 3 and are next again, before 8 and 9
        assert _waiting(redis_server.url) == [4, 5, 6, 7, 8, 9]
