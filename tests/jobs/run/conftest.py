"""Fixtures of the recovery tests: a queue on Redis with leases and a reaper that act within
seconds, and Redis running again after a test that stopped it."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

from jobs.settings import Settings


@pytest.fixture
def crash_settings(settings: Settings, redis_server: Any) -> Settings:
    """Redis as the queue; leases that expire and a reaper that looks within seconds."""
    redis_server.flush()
    return settings.model_copy(update={
        "broker_url": redis_server.url, "lease_ttl_s": 2.0, "reaper_interval_s": 0.3,
        "redispatch_after_s": 1.0, "retry_base_s": 0.1, "retry_max_s": 0.5,
    })


@pytest.fixture
def restarted_redis(redis_server: Any) -> Iterator[Any]:
    """The session's Redis, running again after the test whatever the test did to it."""
    try:
        yield redis_server
    finally:
        if redis_server.proc is None:
            redis_server.start()
