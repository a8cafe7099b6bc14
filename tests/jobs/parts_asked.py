"""What dncq asked of its parts while a block ran: the SQL statements run on any database
of this process, and the connections its Redis broker took."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import redis
from sqlalchemy import event
from sqlalchemy.engine import Engine

from tests.servers import RedisServer


@dataclass
class PartsAsked:
    """Filled in as the block runs; `broker_connections` once it has ended."""

    statements: list[str] = field(default_factory=list)
    broker_connections: int = 0


def _connections_taken(client: redis.Redis) -> int:
    return int(client.info("stats")["total_connections_received"])


@contextlib.contextmanager
def parts_asked(broker: RedisServer) -> Iterator[PartsAsked]:
    """Count what the block asks: statements seen by SQLAlchemy (the API served in this
    process), connections `broker` accepted (its own count, less this one's)."""
    asked = PartsAsked()

    def seen(_conn: Any, _cursor: Any, statement: str, *_: Any) -> None:
        asked.statements.append(statement)

    counter = redis.Redis.from_url(broker.url)  # one connection, taken before the count
    before = _connections_taken(counter)
    event.listen(Engine, "before_cursor_execute", seen)
    try:
        yield asked
    finally:
        event.remove(Engine, "before_cursor_execute", seen)
        asked.broker_connections = _connections_taken(counter) - before
        counter.close()
