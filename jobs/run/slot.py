"""A machine's slots for work done outside its jobs: a single-machine request or page, a
backupFiles check, a dry run. The slots are the leases the jobs' runners take, so that a
machine never gets more operations at once than it allows, whoever asks."""

from __future__ import annotations

import contextlib
import uuid
from collections.abc import Iterator, Sequence

from sqlalchemy.orm import Session

from jobs.db import session_scope
from jobs.fleet import door, registry
from jobs.fleet.registry import MachineSpec
from jobs.fleet.rules import MachineFiles
from jobs.run import leases, queue, targets
from jobs.settings import Settings


@contextlib.contextmanager
def machine_slot(settings: Settings, spec: MachineSpec, *, wait_s: float | None = None,
                 reading: bool = False) -> Iterator[None]:
    """One of the machine's `max_concurrent` slots, shared with batch jobs, waiting `wait_s`
    (default `busy_wait_s`) for a busy one, then 20007.

    `reading`: only listings and reads follow. Where those read dncq's own copies
    (`door.reads_held_copies`) no slot is taken: the machine is not touched, and a
    listener on its RS-232 line keeps the line open, since what the operator punches while
    no one listens is lost (a line has no mailbox).
    """
    if reading and door.reads_held_copies(spec):
        yield
        return
    url = settings.resolved_database_url
    try:
        with leases.hold(url, machine_id=spec.id, max_concurrent=spec.max_concurrent,
                         wait_s=settings.busy_wait_s if wait_s is None else wait_s,
                         ttl_s=settings.lease_ttl_s):
            yield
    finally:
        hand_on(settings, [spec.id])


@contextlib.contextmanager
def opened(session: Session, settings: Settings, machine_id: str, *,
           wait_s: float | None = None, reading: bool = False) -> Iterator[MachineFiles]:
    """The machine's files behind its model's rules, holding one of its slots (waiting
    `wait_s` for a busy one, default `busy_wait_s`): a single call of the API or a page.
    `reading`: as `machine_slot`'s."""
    spec = registry.get(session=session, machine_id=machine_id)
    session.commit()  # no read transaction open during the slow machine work
    with machine_slot(settings, spec, wait_s=wait_s, reading=reading), door.open_files(
            spec, data_dir=settings.data_dir) as files:
        yield files


@contextlib.contextmanager
def free_slots(settings: Settings, specs: Sequence[MachineSpec]) -> Iterator[set[str]]:
    """A slot of each of the machines that has one free now, taken together; the ids of
    those held. The others are left to `machine_slot`, which waits for one.

    For a request that asks many machines at once: a slot taken, kept and given back per
    machine was three transactions each (0.14 s more before a backupFiles of 50 machines
    began to answer, docs/performance.md); taken and given back together, two in all.
    """
    url = settings.resolved_database_url
    group = f"api:{uuid.uuid4().hex}"
    with session_scope(url) as session:
        holders = leases.take_many(session, [
            leases.Want(spec.id, spec.max_concurrent, group) for spec in specs],
            ttl_s=settings.lease_ttl_s)
    held = {spec.id: holder for spec, holder in zip(specs, holders, strict=True) if holder}
    with contextlib.ExitStack() as renewed:
        for holder in held.values():
            renewed.enter_context(leases.Heartbeat(url, holder=holder, ttl_s=settings.lease_ttl_s))
        try:
            yield set(held)
        finally:
            with session_scope(url) as session:
                leases.drop_many(session, list(held.values()))
            hand_on(settings, list(held))


def hand_on(settings: Settings, machine_ids: Sequence[str]) -> None:
    """After slots of these machines were given back: a batch that found one busy meanwhile
    (and waits for it) is queued now, in one transaction for them all."""
    if not machine_ids:
        return
    waiting = targets.take_waiting(url=settings.resolved_database_url, machine_ids=machine_ids)
    for machine_id, job_id in zip(machine_ids, waiting, strict=True):
        if job_id:
            queue.enqueue_machine(settings, job_id, machine_id)
