"""How far the queue has got: the newest queue time among the tasks this process was lately
delivered, which tells the reaper a queued target still waiting from a lost one.

The queue is first in, first out. A target queued at T and not started `redispatch_after_s`
later is either waiting behind a backlog (a rollout to 100,000 machines takes minutes to
drain) or its message was lost (Redis restarted without it). A task queued a whole
`redispatch_after_s` after T that was delivered meanwhile means the queue went past T's
message: that one is lost, and the reaper queues it again. If the queue delivered only
tasks queued before or about when T's was, T's message is likely still waiting in it, and
queueing it again would only add a task that finds nothing to do, once per
`redispatch_after_s` for every target of the backlog. A process delivered nothing lately
has no evidence either way, and the reaper keeps to `redispatch_after_s` alone.
"""

from __future__ import annotations

import threading
import time
from datetime import datetime

KEPT_S = 3600  # deliveries are remembered this long, a second at a time

_lock = threading.Lock()
_newest_by_second: dict[int, datetime] = {}  # monotonic second -> newest queue time delivered


def note(queued_at: datetime | None) -> None:
    """A task queued at `queued_at` was delivered to this process and took its target."""
    if queued_at is None:
        return
    second = int(time.monotonic())
    with _lock:
        kept = _newest_by_second.get(second)
        if kept is None:
            for old in [s for s in _newest_by_second if s <= second - KEPT_S]:
                del _newest_by_second[old]
        if kept is None or queued_at > kept:
            _newest_by_second[second] = queued_at


def frontier(window_s: float) -> datetime | None:
    """The newest queue time of a task delivered within the last `window_s`, if any."""
    since = time.monotonic() - window_s
    with _lock:
        recent = [t for s, t in _newest_by_second.items() if s + 1 > since]
    return max(recent, default=None)


def forget() -> None:
    """Drop what was seen (a fresh process; tests)."""
    with _lock:
        _newest_by_second.clear()
