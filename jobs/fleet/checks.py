"""Machine checks: one made (connect, list the root, say what the machine can do), and each
machine's last one kept in the database, whoever made it (the API's
`POST /api/machines/check`, the dashboard, a worker's periodic probe; jobs.run.checking
makes them under the machine's lease).

Kept, not held in one process's memory, so that the dashboard of every API process, the
metrics and the CLI say the same thing about which machines answer.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any, Literal

from sqlalchemy import select
from sqlalchemy.orm import Session

from jobs.db import session_scope, upsert_of
from jobs.errors import ContractError, ErrorCode
from jobs.fleet import door, registry
from jobs.fleet.registry import MachineSpec
from jobs.fleet.rules import MachineFiles
from jobs.models import Machine, MachineCheck, utcnow

log = logging.getLogger(__name__)

State = Literal["online", "offline", "unchecked"]


def unchecked(spec: MachineSpec) -> dict[str, Any]:
    """A check's answer before anything is known: what the registry says of the machine,
    every finding None. `check` fills it in; a check made another way (a listener's, a busy
    machine's) starts from it too, so that every answer has the same keys."""
    row = registry.governing_row(spec)
    return {
        "id": spec.id, "name": spec.name, "transport": spec.transport,
        # The model as registered; the contract's table row that governs it when that differs.
        "model": spec.model if row.name == spec.model else f"{spec.model} ({row.name})",
        "can": door.abilities(spec), "reachable": None, "latency_ms": None,
        "programs": None, "error": None,
        "link": None,  # the state of a kept link with a heartbeat, when there is one
        "free_bytes": None}  # where the transport tells it


def check(spec: MachineSpec, *, data_dir: Path) -> dict[str, Any]:
    """Connect to the machine, list its root, and say what it can do; for a transport that
    keeps a link with a heartbeat (`dnc`), whether the heartbeat is answered and its round
    trip (`link`, else None)."""
    found = unchecked(spec)
    started = time.perf_counter()
    try:
        with door.open_files(spec, data_dir=data_dir) as files:
            listing = files.list_program_dir(None, None)
            latency_ms = round((time.perf_counter() - started) * 1000, 1)
            report = files.link_report()
            free = _free_or_none(files)
        found.update(reachable=True, latency_ms=latency_ms,
                     programs=len(listing["programs"]), free_bytes=free)
        if report is not None:
            found["link"] = {"heartbeat": report.heartbeat,
                             "round_trip_ms": report.round_trip_ms, "error": report.error}
    except ContractError as exc:
        found.update(reachable=False, error=f"{int(exc.code)} {exc.status_msg or exc.code.name}")
    except Exception as exc:  # a machine answering nonsense is one bad row, not the end
        log.exception("checking machine %s failed", spec.id)
        found.update(reachable=False,
                     error=f"{int(ErrorCode.INTERNAL_ERROR)} {type(exc).__name__}")
    return found


def _free_or_none(files: MachineFiles) -> int | None:
    """The machine's free space; a machine that answers the listing but not this is not
    unreachable, it does not say."""
    try:
        return files.free_bytes()
    except ContractError:
        return None


def record(url: str, found: Iterable[dict[str, Any]]) -> None:
    """Keep checks (`check`'s answers) as their machines' last ones.

    In one statement that inserts or replaces: a machine checked for the first time by
    two at the same moment (a worker's probe, a listener, `dncq machines check`) keeps
    the later check, where an insert of each failed the second on the key.
    """
    now = utcnow()
    rows = [{"machine_id": check["id"], "checked_at": now,
             "reachable": bool(check["reachable"]), "found": check} for check in found]
    if not rows:
        return
    with session_scope(url) as session:
        statement = upsert_of(session)(MachineCheck)
        session.execute(statement.on_conflict_do_update(
            index_elements=[MachineCheck.machine_id],
            set_={name: statement.excluded[name] for name in ("checked_at", "reachable",
                                                              "found")}), rows)
        # A machine removed since it was checked leaves its row: `latest` reads only the
        # registered ones, and the next check of a machine by that id replaces it.


def noted(spec: MachineSpec, *, reachable: bool, error: str | None,
          by: str) -> dict[str, Any]:
    """A check made by what holds the machine's link (`by`: a listener), shaped as
    `check` answers, without what only a listing tells."""
    return {**unchecked(spec), "reachable": reachable,
            "error": None if reachable else error, "by": by}


def latest(session: Session) -> dict[str, dict[str, Any]]:
    """The last check of every registered machine ever checked, with its time as `at`."""
    rows = session.execute(select(MachineCheck).join(
        Machine, Machine.id == MachineCheck.machine_id)).scalars()
    return {r.machine_id: _view(r) for r in rows}


def last(session: Session, machine_id: str) -> dict[str, Any] | None:
    """The machine's last check, as `latest` gives it; None if never checked."""
    row = session.get(MachineCheck, machine_id)
    return None if row is None else _view(row)


def _view(row: MachineCheck) -> dict[str, Any]:
    return {**row.found, "reachable": row.reachable, "at": row.checked_at}


def state(check: dict[str, Any] | None, *, now: datetime, max_age_s: float | None) -> State:
    """`online` or `offline` by the last check; `unchecked` when there is none or it is older
    than `max_age_s` (None: a check never grows too old)."""
    if check is None:
        return "unchecked"
    if max_age_s is not None and now - check["at"] > timedelta(seconds=max_age_s):
        return "unchecked"
    return "online" if check["reachable"] else "offline"


def due(checks: dict[str, dict[str, Any]], specs: Iterable[MachineSpec], *, every_s: float,
        now: datetime) -> list[MachineSpec]:
    """The machines never checked, or not within `every_s`."""
    return [s for s in specs if s.id not in checks
            or (now - checks[s.id]["at"]).total_seconds() >= every_s]
