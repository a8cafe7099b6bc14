"""One of a machine's slots for work done outside its jobs: a single-machine request, a
backupFiles check, a dry run. The slots are the leases the jobs' runners take, so that a
machine never gets more operations at once than it allows, whoever asks."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

from jobs.fleet.registry import MachineSpec
from jobs.run import leases, queue, targets
from jobs.settings import Settings


@contextlib.contextmanager
def machine_slot(settings: Settings, spec: MachineSpec) -> Iterator[None]:
    """One of the machine's `max_concurrent` slots, shared with batch jobs (20007 if busy)."""
    url = settings.resolved_database_url
    try:
        with leases.hold(url, machine_id=spec.id, max_concurrent=spec.max_concurrent,
                         wait_s=settings.busy_wait_s, ttl_s=settings.lease_ttl_s):
            yield
    finally:
        # A batch that found the machine busy meanwhile takes the slot now.
        waiting = targets.take_waiting(url=url, machine_id=spec.id)
        if waiting:
            queue.enqueue_machine(settings, waiting, spec.id)
