"""Checking machines without getting in the way of their work.

A check connects to the machine like any operation, so it takes one of the machine's slots:
a machine that allows one connection at a time (most controls, a DNC link) would otherwise
refuse the job, drip-feed or listener that holds it, and the check would call a busy
machine offline. Every check made is kept as the machine's last (jobs.fleet.checks).
"""

from __future__ import annotations

import random
import uuid
from collections.abc import Iterable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

from jobs.db import session_scope
from jobs.errors import ContractError
from jobs.fleet import checks
from jobs.fleet.registry import MachineSpec
from jobs.models import utcnow
from jobs.run import leases
from jobs.run.slot import hand_on, machine_slot
from jobs.settings import Settings

CHECK_THREADS = 16  # machines checked at once


def check_now(settings: Settings, specs: Iterable[MachineSpec]) -> list[dict[str, Any]]:
    """Check the machines as asked (the API, the CLI, the dashboard's button), in order.

    Each waits for one of its slots as a single-machine request does (`busy_wait_s`, a
    listener asked to give the machine up between programs); one still busy then is not
    checked: its answer is its last check, or none, with `busy` true.
    """
    specs = list(specs)
    with ThreadPoolExecutor(max(1, min(CHECK_THREADS, len(specs)))) as pool:
        found = list(pool.map(lambda s: _check_waiting(settings, s), specs))
    checks.record(settings.resolved_database_url, [f for f in found if not f["busy"]])
    return found


def check_idle(settings: Settings, specs: Iterable[MachineSpec], *, every_s: float) -> int:
    """Check the machines that have a slot free now and no check within `every_s`, leaving
    busy ones alone (the periodic checks); how many were checked.

    Every worker sweeps the same due machines, so each check is decided under the machine's
    slot: the last check is read again once the slot is held, and a new one is kept before
    the slot is given back. Two sweeps at once (two workers started together) check each
    machine once; in random order, they rarely want the same machine at the same moment.
    """
    specs = list(specs)
    if not specs:
        return 0
    random.shuffle(specs)
    with ThreadPoolExecutor(min(CHECK_THREADS, len(specs))) as pool:
        return sum(pool.map(lambda s: _check_if_due(settings, s, every_s), specs))


def _check_waiting(settings: Settings, spec: MachineSpec) -> dict[str, Any]:
    try:
        with machine_slot(settings, spec):
            return {**checks.check(spec, data_dir=settings.data_dir), "busy": False}
    except ContractError as exc:  # MACHINE_BUSY: still in use after the wait
        return _busy(settings, spec, f"{int(exc.code)} {exc.status_msg}")


def _check_if_due(settings: Settings, spec: MachineSpec, every_s: float) -> bool:
    """Check the machine if a slot is free and it is still due; whether it was checked."""
    url = settings.resolved_database_url
    holder = leases.acquire(url, machine_id=spec.id, max_concurrent=spec.max_concurrent,
                            group=f"check:{uuid.uuid4().hex}", ttl_s=settings.lease_ttl_s)
    if holder is None:
        return False
    try:
        with session_scope(url) as session:
            last = checks.last(session, spec.id)
        if last is not None and (utcnow() - last["at"]).total_seconds() < every_s:
            return False  # another worker's sweep checked it meanwhile
        with leases.Heartbeat(url, holder=holder, ttl_s=settings.lease_ttl_s):
            found = {**checks.check(spec, data_dir=settings.data_dir), "busy": False}
        checks.record(url, [found])
        return True
    finally:
        leases.release(url, holder=holder)
        hand_on(settings, [spec.id])


def _busy(settings: Settings, spec: MachineSpec, why: str) -> dict[str, Any]:
    """A busy machine's answer: its last check as it was, or nothing known."""
    with session_scope(settings.resolved_database_url) as session:
        last = checks.last(session, spec.id)
    if last is not None:
        checked_at = last.pop("at")
        return {**last, "busy": True, "checked_at": checked_at.isoformat()}
    return {**checks.unchecked(spec), "busy": True, "error": f"busy, not checked now ({why})"}
