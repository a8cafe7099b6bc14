"""A job's end, said on Redis by the runner that settled it, heard by whoever waits for it.

A batch request (batchSendFile, batchDeleteFile), and a read asked to wait (`wait_s`),
answers once its job has finished (or its backup's ZIP is registered), and looks for that
in the database between pauses (jobs.api.waiting). On a Redis broker whoever ends a job
(the runner whose transaction settled it, a cancel, the reaper) and the assembler once the
ZIP is registered publish the job's id on the job's own channel after the commit, and a
request listening there looks at once. The database stays the only truth: a message lost,
a Redis that is down and the embedded queue (no Redis at all) are all noticed by a later
look.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import AsyncIterator
from functools import cache
from typing import Any

import redis
import redis.asyncio

from jobs.run import queue
from jobs.settings import Settings

log = logging.getLogger(__name__)

CHANNEL_PREFIX = "dncq:job-ended:"
CONNECT_TIMEOUT_S = 1.0  # a listener that cannot reach Redis by then polls instead


def channel(job_id: str) -> str:
    """The channel the end of this job is said on."""
    return CHANNEL_PREFIX + job_id


def announce(settings: Settings, job_id: str) -> None:
    """Say that the job ended (after the transaction that settled it was committed).

    Never raises: a listener that does not hear it finds the end at its next look.
    """
    url = queue.redis_broker(settings)
    if url is None:
        return
    try:
        _publisher(url).publish(channel(job_id), job_id)
    except redis.RedisError as exc:
        log.debug("could not say that job %s ended: %s", job_id, type(exc).__name__)


@cache
def _publisher(url: str) -> redis.Redis:
    """One client per process and broker (redis-py's pool is safe across threads)."""
    return redis.Redis.from_url(url, socket_connect_timeout=CONNECT_TIMEOUT_S,
                                socket_timeout=CONNECT_TIMEOUT_S)


@contextlib.asynccontextmanager
async def listening(settings: Settings, job_id: str) -> AsyncIterator[Listener]:
    """A listener whose `wait(timeout_s)` returns True as soon as the job's end is said, or
    False when `timeout_s` passed. Listening starts here, before the caller's first look,
    so an end said between that look and the wait is not missed.

    Without Redis, or when it cannot be reached or goes away, `wait` only sleeps, and
    `live` says so.
    """
    url = queue.redis_broker(settings)
    if url is None:
        yield Listener()
        return
    client = redis.asyncio.Redis.from_url(url, socket_connect_timeout=CONNECT_TIMEOUT_S)
    pubsub = client.pubsub(ignore_subscribe_messages=True)
    try:
        try:
            await pubsub.subscribe(channel(job_id))
        except (redis.RedisError, OSError) as exc:
            log.debug("waiting for job %s by looking only: %s", job_id, type(exc).__name__)
            yield Listener()
            return
        yield Listener(pubsub, job_id)
    finally:
        with contextlib.suppress(redis.RedisError, OSError):
            await pubsub.aclose()
        with contextlib.suppress(redis.RedisError, OSError):
            await client.aclose()


class Listener:
    """Hears the job's channel while `live`; without one, or after a failure, it sleeps."""

    def __init__(self, pubsub: Any = None, job_id: str = "") -> None:
        self.pubsub, self.job_id = pubsub, job_id
        self.live = pubsub is not None

    async def wait(self, timeout_s: float) -> bool:
        """True when the end was said within `timeout_s`, False when the time passed."""
        deadline = time.monotonic() + timeout_s
        while (left_s := deadline - time.monotonic()) > 0:
            if not self.live:
                await asyncio.sleep(left_s)
                return False
            try:
                # None also comes back early, for a subscription's own confirmation.
                if await self.pubsub.get_message(timeout=left_s) is not None:
                    return True
            except (redis.RedisError, OSError) as exc:
                log.debug("stopped listening for job %s: %s", self.job_id,
                          type(exc).__name__)
                self.live = False
        return False
