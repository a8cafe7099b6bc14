"""The embedded mode's file queue: a message is taken only once it is written whole."""

from __future__ import annotations

import threading

from kombu import Connection

from jobs.queue import producer
from jobs.settings import Settings

MESSAGES = 3000


def test_a_consumer_polling_while_messages_are_written_gets_every_one_whole(
        settings: Settings) -> None:
    # kombu's own filesystem transport lost about 4% of these (read empty, a JSON error
    # that also stopped the embedded worker of `dncq serve`).
    conf = producer(settings.model_copy(update={"broker_url": None})).conf
    options = {**conf.broker_transport_options, "polling_interval": 0}  # look all the time

    def connection() -> Connection:
        return Connection(conf.broker_url, transport=conf.broker_transport,
                          transport_options=options)

    with connection() as out_conn, connection() as in_conn:
        outbox, inbox = out_conn.SimpleQueue("race"), in_conn.SimpleQueue("race")
        writer = threading.Thread(target=lambda: [
            outbox.put({"n": n, "pad": "G0 X1\n" * 300}) for n in range(MESSAGES)])
        writer.start()
        seen = []
        for _ in range(MESSAGES):
            message = inbox.get(timeout=10)
            seen.append(message.payload["n"])
            message.ack()
        writer.join()

    assert sorted(seen) == list(range(MESSAGES))
    assert not list((settings.data_dir / "queue").glob(".*.part"))  # no half-written leftovers
