"""The garbage collector of a long-running process (API, worker): the objects made at its
start set aside, young ones collected less often.

Most of a worker's heap is what it imported and set up before its first task (Celery,
kombu, SQLAlchemy's statements, pydantic's models: about 180,000 objects), and none of it
is ever garbage. CPython's collector went through all of it at every full collection:
133 ms each on the development machine, the whole process stalled, ten of them in a
benchmark of 8,000 targets, and 1.7 s of the worker's 18 s of CPU in the collector (the
API: 0.75 of 5.3 s; bench/batch_send.py --machines 2000 --latency-ms 0,
docs/performance.md). Frozen, those objects are left out of every collection; and a task
or a request makes some hundreds of short-lived objects, so the youngest generation is
collected every 10,000 allocations instead of CPython's 700.
"""

from __future__ import annotations

import gc

YOUNG_THRESHOLD = 10_000  # allocations less deallocations between young collections


def settle() -> None:
    """Collect once, set every object alive now aside for good, and collect less often."""
    gc.collect()
    gc.freeze()
    _, middle, old = gc.get_threshold()
    gc.set_threshold(YOUNG_THRESHOLD, middle, old)
